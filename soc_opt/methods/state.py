"""Run state (docs/math.md §7): what a checkpoint holds.

For every method: :class:`IterationRecord`, one row of ``metrics.csv`` (its ``kl``, ``nu``, ``mult``
columns only where a method sets them: the KL-constrained ones), built by :func:`record`;
:class:`BestPolicy`, the best policy sampled so far (iLQG's state reports one too); :func:`state_rng`
and :func:`improved`.  For the two sample-based methods, LQR-FLM and DPSOC-EM (their folders
:mod:`soc_opt.methods.lqr_flm`, :mod:`soc_opt.methods.dpsoc_em`): :class:`RunState` (policy, KL
multiplier, mixture prior, RNG state, history), what one iteration maps to the next, so that a run
can be checkpointed after every iteration and resumed bit for bit, with :class:`PreviousStep`,
:class:`AcceptedPolicy` and :class:`EMDiagnostics`; the run directories and sweeps read it, so it stays
in the core.  These types import nothing above the kernels.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar, NamedTuple

import numpy as np

from ..models import LinearGaussianPolicy, Rollouts
from ..noise.estimator import FilteredPolicy

if TYPE_CHECKING:
    from ..learning.fit import MixturePrior
    from ..lqg import LocalModel

__all__ = ["BestPolicy", "PreviousStep", "AcceptedPolicy", "EMDiagnostics", "IterationRecord", "RunState", "state_rng",
           "improved", "record"]


class BestPolicy(NamedTuple):
    """The best policy sampled so far in a run."""

    mean_cost: float  # mean true-state total cost of its samples
    policy: LinearGaussianPolicy | FilteredPolicy
    iteration: int  # the (0-based) iteration in which it was sampled


class PreviousStep(NamedTuple):
    """The previous KL step, for the step-size adaptation (docs/math.md §6)."""

    model: LocalModel  # fitted dynamics, cost expansion and initial distribution (innovation form
    #                        with the estimator)
    reference: LinearGaussianPolicy  # the KL reference of that step (its gains, on xhat with the estimator)


class AcceptedPolicy(NamedTuple):
    """The last accepted policy ``p_a`` of a run with step acceptance (docs/math.md §12).

    policy:    ``p_a``, the policy a run returns (plain or with its filter).
    cost_mean: ``C_a``, the mean total cost of its own samples (the cost the test reads).
    cost_se:   ``se_a``, the standard error of that mean.
    iteration: the (0-based) iteration in which it was sampled.
    step:      the KL step taken around it: the local model fitted on its samples and that step's
               reference; a rejected successor is replaced by a step on this same model.
    child:     the policy that step produced (a retry keeps its filter, built from ``p_a``'s batch,
               and replaces its gains).
    mult:      the multiplier of the step taken around it.
    costs:     ``(M,)`` the total costs of its own samples, on the cost the test reads: the reference of the
               "rank" test (``[baseline.acceptance] test``; None in states written before it existed).
    """

    policy: LinearGaussianPolicy | FilteredPolicy
    cost_mean: float
    cost_se: float
    iteration: int
    step: PreviousStep
    child: LinearGaussianPolicy | FilteredPolicy
    mult: float
    costs: np.ndarray | None = None


@dataclass(frozen=True)
class EMDiagnostics:
    """Diagnostics of one EM recursion (paper Algorithm 1; docs/math.md §4–§5).

    recursion:     index of the recursion within the EM phase.
    surrogate_old, surrogate_new: ``sum_k Lbar_k`` of the sampled and of the EM policy, both under
                   the smoothed moments of the sampled policy (the M-step raises it).
    loglik_old, loglik_new: mean over the ``Y`` sequences of ``log p(Y)`` under the sampled and
                   the EM policy.
    time_fit_augmented, time_estep, time_mstep: wall time of each phase (seconds).
    """

    recursion: int
    surrogate_old: float
    surrogate_new: float
    loglik_old: float
    loglik_new: float
    time_fit_augmented: float
    time_estep: float
    time_mstep: float

    nonfinite_floats: ClassVar[bool] = True  # a record: state files accept NaN/inf here

    def summary(self) -> dict:
        """The metrics columns of the recursion (``em_recursion`` first, then the fields)."""
        out = dataclasses.asdict(self)
        return {"em_recursion": out.pop("recursion"), **out}


@dataclass(frozen=True)
class IterationRecord:
    """Metrics of one iteration (one sampling round).

    phase: "baseline" or "em" (a method may name its own).  ``cost`` holds per-sample total costs on
           the true states.
    kl, nu, mult: the KL step's divergence, budget and multiplier (``None``: a method without a KL step;
           its rows have no such columns).
    em:    the EM recursion's diagnostics (``phase == "em"`` only).
    """

    iteration: int
    phase: str
    cost: np.ndarray  # (M,) true-state total cost per sample
    cost_measured: np.ndarray  # (M,) measured-state total cost per sample (docs/math.md §0 Y)
    kl: float | None
    nu: float | None
    mult: float | None
    metrics: dict[str, float]
    timings: dict[str, float]
    extra: dict[str, float] = field(default_factory=dict)
    em: EMDiagnostics | None = None

    nonfinite_floats: ClassVar[bool] = True  # a record: state files accept NaN/inf here

    def summary(self) -> dict:
        """The row of ``metrics.csv``: iteration, phase, costs, the KL columns when set, metrics, timings,
        the EM recursion's and the method's extra columns."""
        step = {k: v for k, v in (("kl", self.kl), ("nu", self.nu), ("mult", self.mult)) if v is not None}
        return {
            "iteration": self.iteration,
            "phase": self.phase,
            "cost_mean": float(np.mean(self.cost)),
            "cost_std": float(np.std(self.cost)),
            "cost_measured_mean": float(np.mean(self.cost_measured)),
            **step,
            **{f"metric_{k}": v for k, v in self.metrics.items()},
            **{f"time_{k}": v for k, v in self.timings.items()},
            **(self.em.summary() if self.em is not None else {}),
            **self.extra,
        }


@dataclass(frozen=True)
class RunState:
    """Everything needed to continue a run (checkpointed after each iteration).

    iteration:     number of finished baseline iterations.
    policy:        the current policy ``p_i`` (sampled next); a FilteredPolicy with the estimator.
    mult:          KL budget multiplier (step-size adaptation).
    prior:         mixture prior of the dynamics fit, or None.
    rng_state:     ``numpy`` bit-generator state (JSON-able dict).
    history:       the IterationRecords so far.
    prev:          the previous KL step, for the step adaptation.
    best:          the best policy sampled so far.
    em_done:       whether the DPSOC-EM phase has run.
    last_rollouts: the rollouts of the last iteration (with acceptance: of the last accepted one's
                   batch after a rejection, the batch the sampled policy's estimator comes from).
    accepted:      the last accepted policy (step acceptance, docs/math.md §12; None without).
    mult_ceiling:  upper bound on the multiplier after a rejection (None: ``step_size.mult_max`` only).
    mult_recover:  the multiplier a rejection interrupted, given back once the model predicts well again
                   (``[baseline.acceptance] recover``, docs/math.md §12.2; None: nothing to give back).
    """

    iteration: int
    policy: LinearGaussianPolicy | FilteredPolicy
    mult: float
    prior: MixturePrior | None
    rng_state: dict
    history: tuple[IterationRecord, ...] = ()
    prev: PreviousStep | None = None
    best: BestPolicy | None = None
    em_done: bool = False
    last_rollouts: Rollouts | None = None
    accepted: AcceptedPolicy | None = None
    mult_ceiling: float | None = None
    mult_recover: float | None = None


def state_rng(state: RunState) -> np.random.Generator:
    """A generator continuing ``state``'s stream."""
    rng = np.random.default_rng()
    rng.bit_generator.state = state.rng_state
    return rng


def improved(best: BestPolicy | None, mean_cost: float, policy, iteration: int) -> BestPolicy:
    """``best`` updated with a policy whose samples had ``mean_cost`` (kept when not lower)."""
    if best is None or mean_cost < best.mean_cost:
        return BestPolicy(mean_cost, policy, iteration)
    return best


def record(iteration, phase, task, rollouts, *, kl=None, nu=None, mult=None, timings=None, extra=None,
           em=None) -> IterationRecord:
    """The :class:`IterationRecord` of one sampling round of ``task`` (``kl``, ``nu``, ``mult``: a KL step's,
    left ``None`` by a method without one)."""
    def number(v):
        return None if v is None else float(v)

    return IterationRecord(
        iteration=iteration,
        phase=phase,
        cost=np.asarray(task.true_cost(rollouts).sum(axis=-1)),
        cost_measured=np.asarray(rollouts.total_cost()),
        kl=number(kl),
        nu=number(nu),
        mult=number(mult),
        metrics={k: float(v) for k, v in task.metrics(rollouts).items()},
        timings=timings or {},
        extra=extra or {},
        em=em,
    )
