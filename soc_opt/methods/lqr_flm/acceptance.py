"""Step acceptance (docs/math.md §12) and the multiplier it leaves: :func:`judge` and :func:`next_multiplier`.

Every iteration of the sample-based methods samples the current policy ``p_i`` and asks :func:`judge`
for a :class:`Verdict` on that batch against the last accepted policy ``p_a``.  With
``[baseline.acceptance] enabled = true`` (the default) the verdict is the test of §12.1; with
``enabled = false`` it is the paper as written: a judge that accepts every batch and records nothing,
so the iteration (:mod:`soc_opt.methods.lqr_flm.iteration`) has one path.  :func:`next_multiplier`
turns the verdict into the KL-budget multiplier of the step (a :class:`NextMultiplier`): the GPS rule on
an accepted batch (:func:`soc_opt.lqg.adapt_multiplier`, its settings
:class:`~soc_opt.lqg.step_size.StepSizeConfig`), bounded by the ceiling a rejection leaves; the shrunk
multiplier of a rejected one; with ``recover = true`` the multiplier a rejection interrupted, given back
once the model predicts well again (§12.2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, NamedTuple

import numpy as np

from ... import lqg
from ...config import Config, Interval, Options
from ...lqg.step_size import StepSizeConfig

if TYPE_CHECKING:
    from ...models import Rollouts
    from ..state import AcceptedPolicy, IterationRecord

__all__ = ["AcceptanceConfig", "AS_WRITTEN", "Verdict", "NextMultiplier", "judge", "next_multiplier", "acceptance_cost",
           "acceptance_costs", "acceptance_limit", "acceptance_threshold", "rank_worse", "rank_level"]


@dataclass(frozen=True)
class AcceptanceConfig(Config):
    """Step acceptance of the sample-based methods (docs/math.md §12), ``[baseline.acceptance]``.

    enabled:  judge every sampled policy against the last accepted one and return the last accepted
              policy (default).  ``false`` is the paper as written, bit for bit: every step is taken
              and the policy of the last KL step (never sampled) is returned.
    kappa:    standard errors of the cost difference that sampling noise may explain (2.0).
    eps:      relative margin on the accepted cost ``|C_a|`` (0.02).  A policy is accepted iff
              ``C_i <= C_a + kappa sqrt(se_i^2 + se_a^2) + eps |C_a|``.
    shrink:   on a rejection the next step is taken around the last accepted policy with its
              multiplier times ``shrink`` (0.1, the GPS rule's ``factor_min``), floored at
              ``[baseline.step_size] mult_min``.
    cost:     the cost the test reads: "measured" (default; the total cost of the measured states,
              which is all a learner on a real robot observes), "estimated" (the cost of the states the
              learner fits on: the state estimator's, e.g. the kinematic smoother's ``h(E[z | s, a])``,
              computed from the measurements alone; the measured states when the estimator learns on
              them; docs/math.md §12.1) or "true" (the simulator's true states, what the run records;
              identical without sensor noise).
    ceiling:  after a rejection the multiplier is kept below ``ceiling`` times the multiplier of the
              rejected step until a step at that size is accepted (0.5; 1.0 turns it off), so that the
              step-size rule does not grow straight back to the size that just failed.
    hold_when_improved: after an accepted step whose samples improved on the last accepted policy by
              more than ``kappa`` standard errors, the multiplier is not lowered by the GPS rule (whose
              predicted and actual improvements come from fitted models, unreliable under sensor
              noise); off by default.
    actual:   the actual improvement the GPS rule reads on an accepted step: "laplace" (default, §6: the
              new samples' fitted model's expected cost, as the paper) or "samples" (the mean cost of the
              last accepted batch minus the new batch's, on the cost the test reads (``cost``): the
              trust-region ratio's numerator read from the samples the acceptance test already has).
    recover:  step sizes that recover (docs/math.md §12.2; off by default, which is the rule above and the
              paper as written unchanged): a rejection remembers the multiplier the run had before it (the
              largest rejected one since the last recovery, ``RunState.mult_recover``); a later accepted
              step whose actual improvement (the one ``actual`` names) is at least ``recover_ratio`` times a
              positive predicted one gives it back (at most ``[baseline.step_size] mult_max``, never below
              the GPS rule's value) and lifts the ceiling.
    recover_ratio: the actual / predicted improvement from which the model counts as good again and the
              remembered multiplier is given back (0.5; in [0, 1]; read only with ``recover``).
    recover_fraction: the fraction of the remembered multiplier that is given back (1.0: all of it; in
              (0, 1]; read only with ``recover``).  Below 1 a step that failed at a size is not retried at
              that size as soon as one step predicts well (the sawtooth of docs/results/recover_door.md).
    test:     how a batch is compared with the accepted policy's (docs/math.md §12.1): "mean" (default, the
              test above: means through standard errors) or "rank" (distribution-free: rejected when the
              mean rises by more than ``eps |C_a|`` and the samples are stochastically larger by a one-sided
              Mann-Whitney test or have more costs above the accepted batch's largest than chance allows
              (exceedance test), either at the level ``Phi(-kappa) / 2`` (0.011 at ``kappa = 2``);
              :func:`rank_worse`).  Contact tasks have heavy-tailed costs: a few failed rollouts widen the
              standard error until "mean" accepts a batch whose mean cost is several times the reference's,
              and a rank test is not widened by them.
    """

    enabled: bool = True
    kappa: float = 2.0
    eps: float = 0.02
    shrink: float = 0.1
    cost: Literal["measured", "estimated", "true"] = "measured"
    ceiling: float = 0.5
    hold_when_improved: bool = False
    actual: Literal["laplace", "samples"] = "laplace"
    recover: bool = False
    recover_ratio: float = 0.5
    recover_fraction: float = 1.0
    test: Literal["mean", "rank"] = "mean"

    #: records written before ``recover`` existed ran without it (soc_opt.config.IMPLIED_WHEN_ABSENT)
    _implied_when_absent = {"acceptance.recover": (False, {}), "acceptance.recover_ratio": (0.5, {}),
                            "acceptance.test": ("mean", {}), "acceptance.recover_fraction": (1.0, {})}
    _constraints = {
        "kappa": [Interval(0)],
        "eps": [Interval(0)],
        "shrink": [Interval(0, 1, "neither")],
        "cost": [Options(("measured", "estimated", "true"))],
        "ceiling": [Interval(0, 1, "right")],
        "actual": [Options(("laplace", "samples"))],
        "recover_ratio": [Interval(0, 1)],
        "recover_fraction": [Interval(0, 1, "right")],
        "test": [Options(("mean", "rank"))],
    }


#: The paper as written; also what a run record without an acceptance table ran with.
AS_WRITTEN = AcceptanceConfig(enabled=False)


class Verdict(NamedTuple):
    """What :func:`judge` says of one sampled batch.

    accept:    take the step around the sampled policy (else around the last accepted one, §12.2).
    tested:    whether a test was made (False: the paper as written, which tracks no accepted policy and
               has no zero step).
    cost, se:  ``C_i`` and its standard error, on the cost the test reads (NaN untested).
    threshold: the largest ``C_i`` the "mean" test accepts (``inf`` before any policy is accepted, or
               untested; recorded with the "rank" test too).
    costs:     the batch's costs the test read ``(M,)`` (None untested): the reference of the next test
               when the batch is accepted.
    """

    accept: bool
    tested: bool
    cost: float = float("nan")
    se: float = float("nan")
    threshold: float = float("inf")
    costs: np.ndarray | None = None

    def columns(self, accepted_iteration: int) -> dict[str, float]:
        """The history row's acceptance columns (none untested); ``accepted_iteration``: the iteration of
        the accepted policy after this verdict."""
        if not self.tested:
            return {}
        return {"test_cost": self.cost, "test_cost_se": self.se, "accept_threshold": self.threshold,
                "accepted": float(self.accept), "accepted_iteration": float(accepted_iteration)}


def acceptance_limit(cfg: AcceptanceConfig, c_a: float, se_a: float, se: float) -> float:
    """The largest mean cost a batch with standard error ``se`` may have against a reference batch of
    mean ``c_a`` and standard error ``se_a`` (docs/math.md §12.1): ``c_a + kappa sqrt(se^2 + se_a^2) + eps |c_a|``."""
    return c_a + cfg.kappa * float(np.hypot(se, se_a)) + cfg.eps * abs(c_a)


def acceptance_costs(cfg: AcceptanceConfig, rec: IterationRecord, learned: Rollouts | None = None) -> np.ndarray:
    """``(M,)``: the total cost of each rollout of a batch on the cost the acceptance test reads
    (``cfg.cost``: measured, estimated or true states; docs/math.md §12.1).  ``learned``: the batch as the
    learner sees it (:meth:`Estimates.data`), whose costs are the estimated ones; needed with
    ``cost = "estimated"``."""
    if cfg.cost == "estimated":
        if learned is None:
            raise ValueError("acceptance cost 'estimated' needs the batch's estimated states")
        return np.asarray(learned.total_cost(), float)
    return np.asarray(rec.cost if cfg.cost == "true" else rec.cost_measured, float)


def acceptance_cost(cfg: AcceptanceConfig, rec: IterationRecord, learned: Rollouts | None = None) -> tuple[float, float]:
    """``(C_i, se_i)``: the mean of :func:`acceptance_costs` and its standard error."""
    return _mean_se(acceptance_costs(cfg, rec, learned))


def _mean_se(c: np.ndarray) -> tuple[float, float]:
    """The mean of the costs ``c (M,)`` and its standard error (``ddof = 1``; ``inf`` for one cost)."""
    return float(np.mean(c)), float(np.std(c, ddof=1) / np.sqrt(c.size)) if c.size > 1 else float("inf")


def rank_worse(c_ref, c_new, alpha: float, margin: float) -> dict:
    """Are the costs ``c_new (m,)`` worse than ``c_ref (n,)``?  (docs/math.md §12.1 "rank", §12.3.)

    Worse when both hold: the mean rises by more than ``margin |mean(c_ref)|`` (``rise``, relative), and
    one of two one-sided, distribution-free tests is below ``alpha / 2``: the Mann-Whitney U test that
    ``c_new`` is stochastically larger (``p_rank``: a shift of the bulk) or the exceedance test
    (``p_tail``: ``j`` of the ``m`` new costs above the largest reference cost has probability
    ``C(m, j) / C(n + m, j)`` when both come from one distribution: a few catastrophic rollouts).  Both are
    rank tests, so a heavy tail does not widen them as it widens a standard error.

    Returns ``{"ratio", "rise", "p_rank", "p_tail", "exceed", "worse"}``.
    """
    from math import comb

    from scipy import stats

    c_ref, c_new = np.asarray(c_ref, float).ravel(), np.asarray(c_new, float).ravel()
    n, m = c_ref.size, c_new.size
    mean_r, mean_n = float(c_ref.mean()), float(c_new.mean())
    rise = (mean_n - mean_r) / abs(mean_r) if mean_r != 0 else (np.inf if mean_n > 0 else 0.0)
    p_rank = float(stats.mannwhitneyu(c_new, c_ref, alternative="greater").pvalue) if n and m else 1.0
    j = int(np.sum(c_new > c_ref.max())) if n else 0
    p_tail = comb(m, j) / comb(n + m, j)
    return {"ratio": mean_n / mean_r if mean_r != 0 else float("nan"), "rise": float(rise), "p_rank": p_rank,
            "p_tail": float(p_tail), "exceed": j, "worse": bool(rise > margin and min(p_rank, p_tail) < alpha / 2)}


def rank_level(cfg: AcceptanceConfig) -> float:
    """The level of the "rank" test: ``Phi(-kappa)``, the one-sided level of the "mean" test's ``kappa``
    standard errors for normal costs (split between its two rank tests)."""
    from scipy import stats

    return float(stats.norm.sf(cfg.kappa))


def acceptance_threshold(cfg: AcceptanceConfig, se: float, accepted: AcceptedPolicy | None) -> float:
    """:func:`acceptance_limit` against the last accepted policy (``inf`` before any is accepted)."""
    if accepted is None:
        return float("inf")
    return acceptance_limit(cfg, accepted.cost_mean, accepted.cost_se, se)


def judge(cfg: AcceptanceConfig, rec: IterationRecord, learned: Rollouts | None,
          accepted: AcceptedPolicy | None) -> Verdict:
    """The verdict on the batch of ``rec`` (``learned``: the same batch as the learner sees it) against the
    last accepted policy (docs/math.md §12.1): accepted iff ``C_i <= C_a + kappa sqrt(se_i^2 + se_a^2) +
    eps |C_a|``, or with ``cfg.test = "rank"`` iff :func:`rank_worse` does not find it worse than the accepted
    policy's batch (the mean test when the accepted policy carries no costs: a run resumed from a state
    written before the option existed); the first batch is always accepted.  Disabled: every batch is
    accepted, untested."""
    if not cfg.enabled:
        return Verdict(True, False)
    costs = acceptance_costs(cfg, rec, learned)
    c, se = _mean_se(costs)
    threshold = acceptance_threshold(cfg, se, accepted)
    if cfg.test == "rank" and accepted is not None and accepted.costs is not None:
        worse = rank_worse(accepted.costs, costs, rank_level(cfg), cfg.eps)["worse"]
        return Verdict(not worse, True, c, se, threshold, costs)
    return Verdict(bool(c <= threshold), True, c, se, threshold, costs)


class NextMultiplier(NamedTuple):
    """What :func:`next_multiplier` leaves for the step that follows a verdict (docs/math.md §6, §12.2).

    mult:       the multiplier of the KL budget of that step.
    ceiling:    the bound a rejection put on the multiplier (None: ``step_size.mult_max`` only).
    recover_to: the multiplier a rejection interrupted, given back once the model predicts well again
                (``AcceptanceConfig.recover``; None: nothing to give back, always None with ``recover`` off).
    """

    mult: float
    ceiling: float | None
    recover_to: float | None = None


def next_multiplier(step: StepSizeConfig, cfg: AcceptanceConfig, verdict: Verdict, mult: float,
                    ceiling: float | None, improvements: tuple[float, float] | None,
                    accepted: AcceptedPolicy | None, adapt: bool = True,
                    recover_to: float | None = None) -> NextMultiplier:
    """The :class:`NextMultiplier` of the step that follows ``verdict`` (docs/math.md §6, §12.2).

    ``mult``: the multiplier of the step whose batch ``verdict`` judged; ``ceiling``, ``recover_to``: what
    the previous call left (``RunState.mult_ceiling``, ``RunState.mult_recover``).

    Accepted: with ``adapt`` and the previous step's Laplace ``improvements`` (predicted, actual), the GPS
    rule (:func:`soc_opt.lqg.adapt_multiplier`) reads the actual improvement of ``cfg.actual``; with
    ``cfg.hold_when_improved`` a clear improvement on ``accepted`` keeps the multiplier from shrinking; the
    result stays below ``ceiling``, which is lifted once a step at the ceiling is accepted.  Rejected:
    ``mult * cfg.shrink`` floored at ``step.mult_min``, and the ceiling lowered to ``cfg.ceiling * mult``.

    With ``cfg.recover`` a rejection also remembers ``recover_to = min(max(recover_to, mult), step.mult_max)``
    (never above ``mult_max``); an accepted step whose improvements have ``predicted > 0`` and
    ``actual >= cfg.recover_ratio * predicted`` (the actual improvement the rule reads, with or without
    ``adapt``) gives it back: the multiplier is the larger of the rule's value and
    ``cfg.recover_fraction * recover_to``, the ceiling is lifted and nothing is remembered any more; nor is
    it once an accepted step's multiplier is back at ``recover_to`` on its own.  Without ``cfg.recover``
    ``recover_to`` is ignored and None.
    """
    if not cfg.recover or recover_to is None:
        recover_to = None
    else:
        recover_to = min(recover_to, step.mult_max)
    if not verdict.accept:
        new = max(mult * cfg.shrink, step.mult_min)
        if cfg.ceiling < 1.0:
            ceiling = min(ceiling if ceiling is not None else np.inf, cfg.ceiling * mult)
        if cfg.recover:
            recover_to = min(mult if recover_to is None else max(recover_to, mult), step.mult_max)
        return NextMultiplier(new, ceiling, recover_to)
    new = mult
    seen = None
    if improvements is not None:
        predicted, actual = improvements
        seen = actual if cfg.actual == "laplace" or accepted is None else accepted.cost_mean - verdict.cost
    if adapt and improvements is not None:
        new = lqg.adapt_multiplier(new, predicted, seen, step)
        if (cfg.hold_when_improved and accepted is not None
                and verdict.cost < accepted.cost_mean - cfg.kappa * float(np.hypot(verdict.se, accepted.cost_se))):
            new = max(new, mult)  # the samples show a clear improvement: do not shrink
    if recover_to is not None and seen is not None and predicted > 0 and seen >= cfg.recover_ratio * predicted:
        # the model predicts well again: the multiplier the rejection interrupted, without a ceiling
        return NextMultiplier(max(new, cfg.recover_fraction * recover_to), None, None)
    if ceiling is not None:
        if mult >= ceiling * (1.0 - 1e-12):
            ceiling = None  # a step at the ceiling was accepted: the rule may grow again
        else:
            new = min(new, ceiling)
    if recover_to is not None and new >= recover_to:
        recover_to = None  # back at the remembered size on its own: nothing left to give back
    return NextMultiplier(new, ceiling, recover_to)
