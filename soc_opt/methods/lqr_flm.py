"""LQR-FLM, the paper's baseline ("iLQG" in the paper; docs/math.md §7), as a pure step function.

One iteration on an explicit :class:`~soc_opt.methods.state.RunState`:

1. sample ``M`` rollouts of the current policy ``p_i`` on the task;
2. fit linear-Gaussian dynamics (mixture prior + NIW posterior, docs/math.md §2);
3. expand the cost to second order around the sample mean trajectory;
4. adapt the KL budget from predicted vs actual improvement (docs/math.md §6, GPS rule);
5. KL-constrained LQG step against the reference policy -> ``p_{i+1}``.

Noise-aware variants (docs/math.md §10, ``[baseline.noise]``): steps 2–5 call the run's
:class:`~soc_opt.noise.strategy.NoiseStrategy` (state estimates for the prior, corrected fit,
expansion point, the KL step's model and the new policy's estimator); the defaults are the
paper's method.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Callable, NamedTuple

import numpy as np

from .. import lqg
from ..errors import FlatCostError
from ..lqg import LocalModel
from ..models import LinearGaussianPolicy, Rollouts
from ..noise import aware as noise_aware
from ..noise.estimator import FilteredPolicy
from ..noise.strategy import Estimates, NoiseStrategy, resolve, strategy_class
from .base import MethodBase
from .config import AcceptanceConfig, LQRFLMConfig, acceptance_limit, with_paper_scale
from .state import AcceptedPolicy, IterationRecord, PreviousStep, RunState, improved, record, state_rng

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["initial_state", "lqr_flm_iteration", "accepted_iteration", "acceptance_limit", "acceptance_threshold",
           "acceptance_cost",
           "final_policy", "sample", "fit_batch", "Batch", "LQRFLM", "LQR_FLM"]


def initial_state(task: Task, cfg: LQRFLMConfig, seed: int) -> RunState:
    rng = np.random.default_rng(seed)
    return RunState(
        iteration=0,
        policy=task.initial_policy(cfg.init_var),
        mult=1.0,
        prior=None,
        rng_state=rng.bit_generator.state,
    )


_BUDGETS: dict[str, Callable[[LQRFLMConfig, int, float], float | np.ndarray]] = {
    "total": lambda cfg, T, mult: cfg.kl_budget * T * mult,
    "per_step": lambda cfg, T, mult: np.full(T, cfg.kl_budget * mult),
}


def _budget(cfg: LQRFLMConfig, T: int, mult: float):
    """The KL budget of one step: a total ``nu`` or per-step ``(T,)`` budgets (``cfg.kl_mode``)."""
    return _BUDGETS[cfg.kl_mode](cfg, T, mult)


class Batch(NamedTuple):
    """One sampled batch of the current policy and the local model fitted on it (steps 1–3)."""

    rollouts: Rollouts
    estimates: Estimates
    local: LocalModel  # the KL step's model fitted on this batch
    wrap: Callable  # LinearGaussianPolicy -> the policy the task runs (its filter from this batch)
    timings: dict


def sample(task: Task, cfg: LQRFLMConfig, state: RunState, rng: np.random.Generator) -> tuple[Rollouts, dict]:
    """Step 1: ``cfg.samples`` rollouts of ``state.policy`` and their wall time."""
    t0 = time.perf_counter()
    rollouts = task.rollouts(state.policy, cfg.samples, rng, workers=cfg.workers)
    return rollouts, {"rollouts": time.perf_counter() - t0}


def fit_batch(task: Task, cfg: LQRFLMConfig, state: RunState, rollouts: Rollouts, timings: dict,
              rng: np.random.Generator, noise: NoiseStrategy, estimates: Estimates | None = None) -> Batch:
    """Steps 2–3 on the samples of ``state.policy``: the prior update (skipped when ``estimates``
    of this batch are given), the local fit and the cost expansion, as the KL step's model."""
    timings = dict(timings)
    t0 = time.perf_counter()
    est = estimates
    if est is None:
        est = noise.estimate(state.prior, rollouts, cfg.fit, state.policy, rng, previous=state.last_rollouts)
        timings.update(est.timings)
    data = est.data(rollouts)  # what the learner fits on: the measured rollouts unless the estimator says
    dyn = noise.fit(data, cfg.fit, est, state.policy)
    timings["fit"] = time.perf_counter() - t0 - (sum(est.timings.values()) if estimates is None else 0.0)

    s_bar = noise.expansion_point(data, dyn)
    a_bar = rollouts.a.mean(axis=0)
    cost = task.cost_expansion(s_bar, a_bar)
    if not (np.any(cost.C) or np.any(cost.c)):
        raise FlatCostError(
            f"the cost expansion of task {task.name} around the samples of iteration {state.iteration} is zero at "
            f"every step (no gradient or curvature in the state or the action): the cost does not change near "
            "the mean trajectory (an indicator cost such as an alive bonus, or a constant one), so the KL step "
            "has nothing to follow; give the task a smooth cost ([[cost]] terms, docs/tasks.md; for gym: tasks "
            "docs/gym.md)")
    local, wrap = noise.lqg_model(dyn, cost, est, f" (iteration {state.iteration})")
    return Batch(rollouts, est, local, wrap, timings)


def lqr_flm_iteration(task: Task, cfg: LQRFLMConfig, state: RunState,
                      reference: LinearGaussianPolicy | FilteredPolicy | None = None,
                      phase: str = "baseline", noise: NoiseStrategy | None = None,
                      batch: tuple[Rollouts, dict] | None = None) -> RunState:
    """One LQR-FLM iteration (module docstring, steps 1–5). Pure: returns a new state.

    ``noise``: the run's noise strategy (default: resolved from ``cfg.noise`` for ``task``).
    ``batch``: the rollouts of ``state.policy`` and their timings when they are already drawn (with
    ``state.rng_state`` past them); default: drawn here.  With ``cfg.acceptance.enabled`` the
    sampled policy is first judged against the last accepted one (:func:`accepted_iteration`).
    """
    noise = resolve(task, cfg.noise) if noise is None else noise
    rng = state_rng(state)
    rollouts, timings = sample(task, cfg, state, rng) if batch is None else batch
    b = fit_batch(task, cfg, state, rollouts, timings, rng, noise)
    ref = noise.gains(state.policy if reference is None else reference)
    if cfg.acceptance.enabled:
        return accepted_iteration(task, cfg, state, b, ref, rng, phase, noise)
    local, timings = b.local, b.timings

    mult = state.mult
    predicted = actual = float("nan")
    if cfg.adapt_multiplier and state.prev is not None:
        predicted, actual = lqg.laplace_improvements(state.prev.reference, noise.gains(state.policy),
                                                     state.prev.model, local)
        mult = lqg.adapt_multiplier(mult, predicted, actual, cfg.kl)

    t0 = time.perf_counter()
    nu = _budget(cfg, task.T, mult)
    res = lqg.kl_step_local(local, ref, nu, method=cfg.kl_method, config=cfg.kl)
    timings["lqg"] = time.perf_counter() - t0

    rec = record(
        state.iteration, phase, task, rollouts,
        kl=float(np.sum(res.kl)), nu=float(np.sum(nu)), mult=mult, timings=timings,
        extra={"eta_mean": float(np.mean(res.eta)), "predicted_cost": float(res.expected_cost),
               "predicted_improvement": predicted, "actual_improvement": actual},
    )
    return dataclasses.replace(
        state,
        iteration=state.iteration + 1,
        policy=b.wrap(res.policy),
        mult=mult,
        prior=b.estimates.prior,
        rng_state=rng.bit_generator.state,
        history=state.history + (rec,),
        prev=PreviousStep(local, ref),
        best=improved(state.best, float(np.mean(rec.cost)), state.policy, state.iteration),
        last_rollouts=rollouts,
    )


def acceptance_cost(cfg: AcceptanceConfig, rec: IterationRecord) -> tuple[float, float]:
    """``(C_i, se_i)``: the mean total cost of a batch and its standard error, on the cost the
    acceptance test reads (``cfg.cost``: measured or true states; docs/math.md §12.1)."""
    c = np.asarray(rec.cost if cfg.cost == "true" else rec.cost_measured, float)
    return float(np.mean(c)), float(np.std(c, ddof=1) / np.sqrt(c.size)) if c.size > 1 else float("inf")


def acceptance_threshold(cfg: AcceptanceConfig, se: float, accepted: AcceptedPolicy | None) -> float:
    """:func:`acceptance_limit` against the last accepted policy (``inf`` before any is accepted)."""
    if accepted is None:
        return float("inf")
    return acceptance_limit(cfg, accepted.cost_mean, accepted.cost_se, se)


def accepted_iteration(task: Task, cfg: LQRFLMConfig, state: RunState, b: Batch, ref: LinearGaussianPolicy,
                       rng: np.random.Generator, phase: str, noise: NoiseStrategy) -> RunState:
    """Steps 4–5 with step acceptance (docs/math.md §12): the sampled policy ``p_i`` is accepted iff its
    batch's mean cost passes :func:`acceptance_threshold` against the last accepted ``p_a``.

    Accepted: the GPS rule adapts the multiplier (kept below ``state.mult_ceiling``) and the KL step
    is taken around ``p_i``, which becomes ``p_a``.  Rejected: no Laplace adaptation; the step is taken
    again around ``p_a`` on the model fitted on ``p_a``'s own samples, with the multiplier of the
    rejected step times ``acceptance.shrink``; the rejected batch still entered the mixture prior.
    """
    acc_cfg = cfg.acceptance
    timings = b.timings
    rec0 = record(state.iteration, phase, task, b.rollouts)
    c_i, se_i = acceptance_cost(acc_cfg, rec0)
    acc = state.accepted
    threshold = acceptance_threshold(acc_cfg, se_i, acc)
    accept = bool(c_i <= threshold)
    predicted = actual = float("nan")
    if state.prev is not None:
        predicted, actual = lqg.laplace_improvements(state.prev.reference, noise.gains(state.policy),
                                                     state.prev.model, b.local)
    ceiling = state.mult_ceiling
    if accept:
        mult = state.mult
        if cfg.adapt_multiplier and state.prev is not None:
            seen = actual if acc_cfg.actual == "laplace" or acc is None else acc.cost_mean - c_i
            mult = lqg.adapt_multiplier(mult, predicted, seen, cfg.kl)
            if (acc_cfg.hold_when_improved and acc is not None
                    and c_i < acc.cost_mean - acc_cfg.kappa * float(np.hypot(se_i, acc.cost_se))):
                mult = max(mult, state.mult)  # the samples show a clear improvement: do not shrink
        if ceiling is not None:
            if state.mult >= ceiling * (1.0 - 1e-12):
                ceiling = None  # a step at the ceiling was accepted: the rule may grow again
            else:
                mult = min(mult, ceiling)
        step = PreviousStep(b.local, ref)
    else:
        mult = max(state.mult * acc_cfg.shrink, cfg.kl.mult_min)
        if acc_cfg.ceiling < 1.0:
            ceiling = min(ceiling if ceiling is not None else np.inf, acc_cfg.ceiling * state.mult)
        step = acc.step

    t0 = time.perf_counter()
    nu = _budget(cfg, task.T, mult)
    floor = False
    try:
        res = lqg.kl_step_local(step.model, step.reference, nu, method=cfg.kl_method, config=cfg.kl)
        gains, kl, eta_mean, predicted_cost = res.policy, float(np.sum(res.kl)), float(np.mean(res.eta)), float(res.expected_cost)
    except lqg.SolverError as e:
        if "not reachable" not in str(e) or not mult < 1.0:
            raise  # at the base budget or above, an unreachable budget is a failure (e.g. a diverged fit)
        # the multiplier, shrunk by rejections or by the GPS rule, asks for a budget below what the dual
        # resolves (KL at eta_max above it): the limit of a vanishing step is the reference itself, the
        # accepted policy, sampled again next iteration
        gains, kl, eta_mean, predicted_cost, floor = step.reference, 0.0, float("inf"), float("nan"), True
    timings["lqg"] = time.perf_counter() - t0
    if accept:
        new_policy = b.wrap(gains)
        acc = AcceptedPolicy(state.policy, c_i, se_i, state.iteration, step, new_policy, float(mult))
        last = b.rollouts
    else:
        new_policy = noise_aware.with_gains(acc.child, gains)
        last = state.last_rollouts  # the batch the new policy's estimator was learned from

    rec = dataclasses.replace(rec0, kl=kl, nu=float(np.sum(nu)), mult=float(mult), timings=timings,
                              extra={"eta_mean": eta_mean, "predicted_cost": predicted_cost,
                                     "predicted_improvement": predicted, "actual_improvement": actual,
                                     "test_cost": c_i, "test_cost_se": se_i, "accept_threshold": threshold,
                                     "accepted": float(accept), "accepted_iteration": float(acc.iteration),
                                     **({"zero_step": 1.0} if floor else {})})
    return dataclasses.replace(
        state,
        iteration=state.iteration + 1,
        policy=new_policy,
        mult=mult,
        prior=b.estimates.prior,
        rng_state=rng.bit_generator.state,
        history=state.history + (rec,),
        prev=step,
        best=improved(state.best, float(np.mean(rec.cost)), state.policy, state.iteration),
        last_rollouts=last,
        accepted=acc,
        mult_ceiling=ceiling,
    )


def final_policy(cfg: LQRFLMConfig, state: RunState):
    """What a run returns (docs/math.md §12.3): the last accepted policy with step acceptance, else
    (the paper as written) the policy of the last KL step."""
    if cfg.acceptance.enabled and state.accepted is not None:
        return state.accepted.policy
    return state.policy


#: Keys of the command-line overrides that set a top-level field of the run configuration; the
#: others set ``baseline``'s.
_TOP_LEVEL = {"i_switch"}


class LQRFLM(MethodBase):
    """LQR-FLM as a :class:`~soc_opt.methods.base.Method`: reads ``[baseline]``."""

    name = "lqr-flm"
    sections: tuple[str, ...] = ("baseline",)
    seeded = True
    sample_based = True
    cost_phase = "baseline"

    def apply_overrides(self, cfg, values: dict, paper: bool):
        if paper:
            cfg = with_paper_scale(cfg)
        values = dict(values)
        if values.pop("as_written", False):  # --as-written: the paper's step rule (docs/math.md §12)
            values["acceptance"] = cfg.baseline.acceptance.replace(enabled=False)
        base = {k: v for k, v in values.items() if k not in _TOP_LEVEL}
        top = {k: v for k, v in values.items() if k in _TOP_LEVEL}
        return cfg.replace(baseline=cfg.baseline.replace(**base) if base else cfg.baseline, **top)

    def total_iterations(self, cfg) -> int:
        return cfg.baseline.iterations

    def check_task(self, task: Task, cfg=None) -> None:
        """With ``cfg``: the state estimator of ``[baseline.noise]`` can model ``task``
        (:meth:`~soc_opt.noise.strategy.NoiseStrategy.check_task`)."""
        if cfg is not None:
            noise = cfg.baseline.noise
            strategy_class(noise.estimator).check_task(task, noise)

    def initial_state(self, task: Task, cfg, seed: int) -> RunState:
        return initial_state(task, cfg.baseline, seed)

    def iterate(self, task: Task, cfg, state: RunState) -> RunState:
        return lqr_flm_iteration(task, cfg.baseline, state)

    def final_policy(self, cfg, state: RunState):
        return final_policy(cfg.baseline, state)

    def progress_fields(self, record) -> dict[str, float]:
        return {"KL": float(record.kl)}

    def progress_line(self, seed: int, where: str, state: RunState, metrics: str, times: str) -> str:
        rec = state.history[-1]
        em = [r for r in state.history if r.em is not None and r.iteration == rec.iteration]
        em_txt = ""
        if em:
            e = em[-1].em
            em_txt = (f" | EM: cost {np.mean(em[-1].cost):.4g}, surrogate {e.surrogate_old:.4g}->{e.surrogate_new:.4g},"
                      f" logp(Y) {e.loglik_old:.4g}->{e.loglik_new:.4g}")
        verdict = ""
        if "accepted" in rec.extra:
            verdict = ("  accepted" if rec.extra["accepted"] else
                       f"  REJECTED (back to iteration {int(rec.extra['accepted_iteration'])}, mult {rec.mult:.3g})")
        return (f"[{self.name} seed {seed}] {where} cost {np.mean(rec.cost):10.4g} ± {np.std(rec.cost):.3g}"
                f"  KL {rec.kl:.3g}/{rec.nu:.3g}  {metrics}  {times}{verdict}{em_txt}")


LQR_FLM = LQRFLM()
