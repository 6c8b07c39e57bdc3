"""Algorithms (SPEC §7): LQR-FLM baseline, DPSOC-EM (paper Algorithm 1); model-based iLQG
lives in :mod:`soc_opt.ilqg` (re-exported here: :class:`ILQGConfig`, :func:`ilqg`).

The loop is written as a pure step function on an explicit :class:`RunState`
(policy, KL multiplier, mixture prior, RNG state, history), so that a run can be
checkpointed after every iteration and resumed bit-for-bit, and so that
DPSOC-EM can fork from the baseline's state at ``i_switch``.

One LQR-FLM iteration (SPEC §7):

1. sample ``M`` rollouts of the current policy ``p_i`` on the task;
2. fit linear-Gaussian dynamics (mixture prior + NIW posterior, SPEC §2);
3. expand the cost to second order around the sample mean trajectory;
4. adapt the KL budget from predicted vs actual improvement (SPEC §6, GPS rule);
5. KL-constrained LQG step against the reference policy -> ``p_{i+1}``.

DPSOC-EM replaces the reference at iteration ``i_switch`` by the EM policy:
``n_em`` recursions of {sample, fit augmented model, generate ``Y``, E-step,
DP M-step}; the LQG step of that iteration then uses the EM policy as its KL
reference and as the sampling policy (paper eq. constrainObjective).

Noise-aware variants (SPEC §10, ``[baseline.noise]``, :mod:`soc_opt.noise_aware`): a
bias-corrected fit in step 2, and with ``estimator = "kalman"`` policies that act on a Kalman
filter estimate (:class:`~soc_opt.estimator.FilteredPolicy`), steps 4–5 and the EM phase on the
innovation form.  The defaults are the paper's methods.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Literal, NamedTuple

import numpy as np

from . import estep, fit, lqg, mstep, noise_aware
from .config import Config, ConfigError
from .estimator import FilteredPolicy
from .kinematic import loop as kinematic_loop
from .kinematic.filter import KinematicFilteredPolicy
from .ilqg import ILQGConfig, ilqg
from .models import LinearGaussianPolicy, Rollouts, symmetrize
from .noise_aware import NoiseConfig

if TYPE_CHECKING:
    from .tasks import Task

__all__ = [
    "PaperScale",
    "PAPER",
    "LoopKLStepConfig",
    "LQRFLMConfig",
    "EMConfig",
    "EvalConfig",
    "DPSOCConfig",
    "ILQGConfig",
    "RUN_SECTIONS",
    "with_paper_scale",
    "with_task_init_var",
    "BestPolicy",
    "PreviousStep",
    "EMDiagnostics",
    "RunState",
    "IterationRecord",
    "METHODS",
    "initial_state",
    "lqr_flm_iteration",
    "em_update",
    "dpsoc_iteration",
    "run_algorithm",
    "ilqg",
]


class PaperScale(NamedTuple):
    """The scale of the paper's experiments (SPEC §9.5), defined here once.

    iterations: baseline iterations per run (``LQRFLMConfig.iterations``).
    samples:    rollouts per iteration ``M`` (``LQRFLMConfig.samples``).
    i_switch:   EM phase after this many baseline iterations (``DPSOCConfig.i_switch``).
    """

    iterations: int = 14
    samples: int = 20
    i_switch: int = 4


PAPER = PaperScale()


@dataclass(frozen=True)
class LoopKLStepConfig(lqg.KLStepConfig):
    """:class:`soc_opt.lqg.KLStepConfig` as used by the LQR-FLM loop: the same fields and defaults,
    except that the dual is solved to ``kl_rtol = 1e-6`` (a budget is a step size, not a quantity to
    hit to 1e-10); any ``[baseline.kl]`` table starts from these defaults.
    """

    kl_rtol: float = 1e-6


@dataclass(frozen=True)
class LQRFLMConfig(Config):
    """LQR-FLM baseline ("iLQG" in the paper), SPEC §7.

    iterations:  number of sample -> fit -> LQG rounds (default: the paper's, ``PAPER.iterations``).
    samples:     rollouts per iteration ``M`` (default: the paper's, ``PAPER.samples``).
    init_var:    initial policy covariance ``Sigma = init_var * I``; unset (``None``): the task's
                 ``init_var`` (its TOML, default 1.0).  Set here it overrides the task's
                 (:func:`with_task_init_var`; docs/configuration.md).
    kl_budget:   base KL budget per time step; the total budget is ``kl_budget * T * mult``.
    kl_mode:     "total" (one budget ``nu = sum nu_k``, one multiplier: the GPS form) or
                 "per_step" (``nu_k = kl_budget * mult`` with one multiplier per step).
    kl_method:   KL-step solver, "closed_form" (LQR backward pass + dual) or "casadi" (IPOPT).
    adapt_step:  adapt ``mult`` from predicted vs actual improvement (GPS rule, see lqg.adapt_step).
    workers:     parallel rollout workers (results do not depend on it).
    fit:         dynamics-fitting configuration (SPEC §2).
    kl:          KL-step solver and step-adaptation configuration (SPEC §6), the loop's
                 :class:`LoopKLStepConfig` (dual solved to ``kl_rtol = 1e-6``).
    noise:       noise-aware variants (SPEC §10: corrected fit, estimator in the loop); the
                 defaults are the paper's method (:class:`soc_opt.noise_aware.NoiseConfig`).
    """

    iterations: int = PAPER.iterations
    samples: int = PAPER.samples
    init_var: float | None = None
    kl_budget: float = 0.5
    kl_mode: Literal["total", "per_step"] = "total"
    kl_method: Literal["closed_form", "casadi"] = "closed_form"
    adapt_step: bool = True
    workers: int = 1
    fit: fit.FitConfig = field(default_factory=fit.FitConfig)
    kl: LoopKLStepConfig = field(default_factory=LoopKLStepConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.samples < 2:
            raise ValueError(f"samples must be >= 2 (dynamics fitting needs 2 rollouts), got {self.samples}")
        for key in ("init_var", "kl_budget"):
            value = getattr(self, key)
            if value is not None and not value > 0:
                err = ConfigError(f"{key}: must be positive, got {value!r}")
                err.key = key  # Config.from_dict prefixes the table: "baseline.init_var: ..."
                raise err
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")


@dataclass(frozen=True)
class EMConfig(Config):
    """The EM phase of DPSOC-EM (SPEC §3–§5, paper Algorithm 1).

    n_em:          EM recursions at the switch (each samples ``M`` rollouts of the current EM policy).
    y_mode:        cost observations ``Y``: "model" (the paper), "measured", "optimistic" (SPEC §3).
    y_samples:     number of ``Y`` sequences drawn in "model" mode (default: ``samples``).
    method:        M-step solver, "closed_form" or "cvxpy" (``mstep.maximize(method=...)``).
    variant:       "time_varying" (the Proposition's DP sweep) or "time_invariant".
    objective:     "surrogate" (the paper's Lbar) or "exact" (exact EM).
    cov_floor_scale:  ``Sigma_k >= scale * Sigma_k^i`` (covariance floor relative to the
                   current policy, SPEC §5); ignored when ``entropy_floor`` is true.
    entropy_floor: use the entropy floor ``log det Sigma_k >= log det Sigma_k^i`` instead.
    trust_region:  optional Frobenius trust region on ``[K k]`` around the current policy (cvxpy only).
    min_norm:      minimum-norm M-step where the maximiser is not unique.
    mstep:         the M-step's solver tolerances and limits (:class:`soc_opt.mstep.MStepConfig`,
                   passed as ``mstep.maximize(config=...)``; its ``solver`` picks the CVXPY solver).
    """

    n_em: int = 1
    y_mode: Literal["model", "measured", "optimistic"] = "model"
    y_samples: int | None = None
    method: Literal["closed_form", "cvxpy"] = "closed_form"
    variant: Literal["time_varying", "time_invariant"] = "time_varying"
    objective: Literal["surrogate", "exact"] = "surrogate"
    cov_floor_scale: float = 0.5
    entropy_floor: bool = False
    trust_region: float | None = None
    min_norm: bool = True
    mstep: mstep.MStepConfig = field(default_factory=mstep.MStepConfig)

    def __post_init__(self):
        if self.n_em < 1:
            raise ValueError(f"n_em must be >= 1, got {self.n_em}")
        if not 0 < self.cov_floor_scale:
            raise ValueError(f"cov_floor_scale must be positive, got {self.cov_floor_scale}")
        if self.y_samples is not None and self.y_samples < 1:
            raise ValueError(f"y_samples must be >= 1, got {self.y_samples}")
        if self.trust_region is not None and not self.trust_region > 0:
            raise ValueError(f"trust_region must be positive, got {self.trust_region}")


@dataclass(frozen=True)
class EvalConfig(Config):
    """Evaluation of the final policies by ``soc-opt compare`` (SPEC §9.5).

    samples:     fresh rollouts per final policy (default: ``baseline.samples``).
    seed_offset: the evaluation generator is seeded with ``seed_offset + seed``: the same stream
                 for both methods, distinct from the training stream of that seed.
    """

    samples: int | None = None
    seed_offset: int = 10_000

    def __post_init__(self):
        if self.samples is not None and self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if self.seed_offset < 0:
            raise ValueError(f"seed_offset must be >= 0 (it seeds a numpy Generator), got {self.seed_offset}")


@dataclass(frozen=True)
class DPSOCConfig(Config):
    """DPSOC-EM (paper Algorithm 1): baseline until ``i_switch``, EM phase, baseline again.

    The run configuration: it holds every sub-configuration of a run (one TOML file, shared by
    ``soc-opt run --method dpsoc-em|lqr-flm|ilqg`` and ``soc-opt compare``; each method reads
    its own sections and ignores the others, see :meth:`check_for`).

    i_switch:   the EM phase runs after this many baseline iterations (default: the paper's,
                ``PAPER.i_switch``); must be below ``baseline.iterations`` for DPSOC-EM only.
    baseline:   the LQR-FLM configuration (iterations = total baseline iterations).
    em:         the EM phase configuration.
    evaluation: evaluation of the final policies (``soc-opt compare``).
    ilqg:       model-based iLQG (``soc-opt run --method ilqg``), :class:`soc_opt.ilqg.ILQGConfig`.
    """

    i_switch: int = PAPER.i_switch
    baseline: LQRFLMConfig = field(default_factory=LQRFLMConfig)
    em: EMConfig = field(default_factory=EMConfig)
    evaluation: EvalConfig = field(default_factory=EvalConfig)
    ilqg: ILQGConfig = field(default_factory=ILQGConfig)

    def __post_init__(self):
        if self.i_switch < 0:
            raise ValueError(f"i_switch must be >= 0, got {self.i_switch}")

    def check_for(self, method: str) -> None:
        """Method-specific checks (:data:`RUN_SECTIONS` lists what each method reads).

        DPSOC-EM needs ``0 <= i_switch < baseline.iterations``; LQR-FLM and iLQG ignore
        ``i_switch``.  Raises :class:`ConfigError` naming the key, or for an unknown method.
        """
        if method not in RUN_SECTIONS:
            raise ConfigError(f"unknown method {method!r}; use one of {', '.join(map(repr, RUN_SECTIONS))}")
        if method == "dpsoc-em" and not 0 <= self.i_switch < self.baseline.iterations:
            raise ConfigError(
                f"i_switch must be in [0, iterations={self.baseline.iterations}), got {self.i_switch}"
            )

    def sections_for(self, method: str) -> dict:
        """The part of :meth:`to_dict` that ``method`` reads (what a run directory must match)."""
        full = self.to_dict()
        return {k: full[k] for k in RUN_SECTIONS[method] if k in full}


#: The top-level keys of :class:`DPSOCConfig` each method reads (``evaluation`` is read by
#: ``soc-opt compare`` only, after the runs).
RUN_SECTIONS: dict[str, tuple[str, ...]] = {
    "lqr-flm": ("baseline",),
    "dpsoc-em": ("i_switch", "baseline", "em"),
    "ilqg": ("ilqg",),
}


def with_paper_scale(cfg: DPSOCConfig) -> DPSOCConfig:
    """``cfg`` at the paper's scale (:data:`PAPER`: iterations, samples, switch point)."""
    base = cfg.baseline.replace(iterations=PAPER.iterations, samples=PAPER.samples)
    return cfg.replace(baseline=base, i_switch=PAPER.i_switch)


class BestPolicy(NamedTuple):
    """The best policy sampled so far in a run."""

    mean_cost: float  # mean true-state total cost of its samples
    policy: LinearGaussianPolicy | FilteredPolicy
    iteration: int  # the (0-based) iteration in which it was sampled


class PreviousStep(NamedTuple):
    """The previous KL step, for the step-size adaptation (SPEC §6)."""

    model: lqg.LocalModel  # fitted dynamics, cost expansion and initial distribution (innovation form
    #                        with the estimator)
    reference: LinearGaussianPolicy  # the KL reference of that step (its gains, on xhat with the estimator)


@dataclass(frozen=True)
class EMDiagnostics:
    """Diagnostics of one EM recursion (paper Algorithm 1; SPEC §4–§5).

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

    def summary(self) -> dict:
        """The metrics columns of the recursion (``em_recursion`` first, then the fields)."""
        out = dataclasses.asdict(self)
        return {"em_recursion": out.pop("recursion"), **out}


@dataclass(frozen=True)
class IterationRecord:
    """Metrics of one iteration (one sampling round).

    phase: "baseline" or "em".  ``cost`` holds per-sample total costs on the true states.
    em:    the EM recursion's diagnostics (``phase == "em"`` only).
    """

    iteration: int
    phase: Literal["baseline", "em"]
    cost: np.ndarray  # (M,) true-state total cost per sample
    cost_measured: np.ndarray  # (M,) measured-state total cost per sample (SPEC Y)
    kl: float
    nu: float
    mult: float
    metrics: dict[str, float]
    timings: dict[str, float]
    extra: dict[str, float] = field(default_factory=dict)
    em: EMDiagnostics | None = None

    def summary(self) -> dict:
        return {
            "iteration": self.iteration,
            "phase": self.phase,
            "cost_mean": float(np.mean(self.cost)),
            "cost_std": float(np.std(self.cost)),
            "cost_measured_mean": float(np.mean(self.cost_measured)),
            "kl": self.kl,
            "nu": self.nu,
            "mult": self.mult,
            **{f"metric_{k}": v for k, v in self.metrics.items()},
            **{f"time_{k}": v for k, v in self.timings.items()},
            **self.extra,
            **(self.em.summary() if self.em is not None else {}),
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
    last_rollouts: the rollouts of the last iteration.
    """

    iteration: int
    policy: LinearGaussianPolicy | FilteredPolicy
    mult: float
    prior: fit.MixturePrior | None
    rng_state: dict
    history: tuple[IterationRecord, ...] = ()
    prev: PreviousStep | None = None
    best: BestPolicy | None = None
    em_done: bool = False
    last_rollouts: Rollouts | None = None


def with_task_init_var(cfg: DPSOCConfig, task: Task) -> DPSOCConfig:
    """``cfg`` with ``baseline.init_var`` set to the task's ``init_var`` when it is unset.

    Precedence of the initial policy covariance: ``[baseline] init_var`` of the run configuration,
    else the task's ``init_var`` (task TOML; default 1.0).  Run directories record the result.
    """
    if cfg.baseline.init_var is not None:
        return cfg
    task_cfg = getattr(task, "config", None)
    var = float(getattr(task_cfg, "init_var", 1.0))
    return cfg.replace(baseline=cfg.baseline.replace(init_var=var))


def initial_state(task: Task, cfg: LQRFLMConfig, seed: int) -> RunState:
    rng = np.random.default_rng(seed)
    return RunState(
        iteration=0,
        policy=task.initial_policy(cfg.init_var),
        mult=1.0,
        prior=None,
        rng_state=rng.bit_generator.state,
    )


def _rng(state: RunState) -> np.random.Generator:
    rng = np.random.default_rng()
    rng.bit_generator.state = state.rng_state
    return rng


def _initial_distribution(task: Task) -> tuple[np.ndarray, np.ndarray]:
    """``s_0 ~ N(mu0, P0)`` from the task (measurement noise included; docs/choices.md)."""
    return np.asarray(task.mu0, float), np.asarray(task.P0, float)


_BUDGETS: dict[str, Callable[[LQRFLMConfig, int, float], float | np.ndarray]] = {
    "total": lambda cfg, T, mult: cfg.kl_budget * T * mult,
    "per_step": lambda cfg, T, mult: np.full(T, cfg.kl_budget * mult),
}


def _budget(cfg: LQRFLMConfig, T: int, mult: float):
    """The KL budget of one step: a total ``nu`` or per-step ``(T,)`` budgets (``cfg.kl_mode``)."""
    return _BUDGETS[cfg.kl_mode](cfg, T, mult)


def _improved(best: BestPolicy | None, mean_cost: float, policy: LinearGaussianPolicy,
              iteration: int) -> BestPolicy:
    if best is None or mean_cost < best.mean_cost:
        return BestPolicy(mean_cost, policy, iteration)
    return best


def _record(iteration, phase, task, rollouts, *, kl=0.0, nu=0.0, mult=1.0, timings=None, extra=None, em=None):
    return IterationRecord(
        iteration=iteration,
        phase=phase,
        cost=np.asarray(task.true_cost(rollouts).sum(axis=-1)),
        cost_measured=np.asarray(rollouts.total_cost()),
        kl=float(kl),
        nu=float(nu),
        mult=float(mult),
        metrics={k: float(v) for k, v in task.metrics(rollouts).items()},
        timings=timings or {},
        extra=extra or {},
        em=em,
    )


def _local_model(task: Task, cfg: LQRFLMConfig, dyn, cost, iteration: int):
    """The KL step's model and the new policy's filter: the fit as is (the paper), or its
    innovation form with the filter of ``dyn`` (``noise.estimator = "kalman"``, SPEC §10.2)."""
    if cfg.noise.estimator == "none":
        mu0, P0 = _initial_distribution(task)
        return lqg.LocalModel(dyn, cost, mu0, P0), None
    if cfg.noise.estimator == "kinematic":  # the fit is on smoothed states; the start is known
        nm = noise_aware.noise_model(task)
        if cfg.noise.kinematic.kl_model == "innovation":
            kf = noise_aware.loop_filter(dyn, nm, cfg.noise, f" (iteration {iteration})")
            return noise_aware.innovation_local_model(kf, cost), None
        return lqg.LocalModel(dyn, cost, nm.mu0, nm.P0), None
    kf = noise_aware.loop_filter(dyn, noise_aware.noise_model(task), cfg.noise, f" (iteration {iteration})")
    return noise_aware.innovation_local_model(kf, cost), kf


def _update_prior(task: Task, cfg: LQRFLMConfig, prior, rollouts: Rollouts, sampler, rng):
    """Step 2a: the mixture prior on the measured tuples (the paper), or on smoothed ones
    (``noise.prior_data = "smoothed"``); returns ``(prior, smoothed rollouts or None)``."""
    if cfg.fit.prior != "mixture":
        return None, None
    if cfg.noise.prior_data == "measured":
        return fit.update_prior(prior, rollouts, cfg.fit, rng), None
    return noise_aware.update_prior(prior, rollouts, cfg.fit, cfg.noise, noise_aware.noise_model(task), sampler, rng)


def _fit_dynamics(task: Task, cfg: LQRFLMConfig, rollouts: Rollouts, prior, sampler, denoised=None):
    """Step 2b: the paper's fit, or the noise-aware one (``noise.fit_correction``, SPEC §10.1)."""
    if cfg.noise.fit_correction == "none":
        return fit.fit_dynamics(rollouts, cfg.fit, prior)
    return noise_aware.fit_local(rollouts, cfg.fit, prior, cfg.noise, noise_aware.noise_model(task), sampler,
                                 denoised=denoised)


def _kinematic(task: Task, cfg: LQRFLMConfig, rollouts: Rollouts, sampler, timings: dict):
    """``(learner's rollouts, kinematic filter or None)``: the rollouts themselves (the paper, §10),
    or their structured smoothing (``noise.estimator = "kinematic"``, docs/math.md §11.3)."""
    if cfg.noise.estimator != "kinematic":
        return rollouts, None
    learn, filt, diag = kinematic_loop.learn(task, rollouts, sampler, cfg.noise.kinematic)
    timings["estimator"] = diag["kin_time"]
    return learn, filt


def _wrap(policy: LinearGaussianPolicy, kf, kin):
    """The new policy with its filter: Kalman (§10.2), kinematic (§11.3) or none (the paper)."""
    if kin is not None:
        return KinematicFilteredPolicy(policy, kin)
    return policy if kf is None else FilteredPolicy(policy, kf)


def lqr_flm_iteration(task: Task, cfg: LQRFLMConfig, state: RunState,
                      reference: LinearGaussianPolicy | FilteredPolicy | None = None,
                      phase: str = "baseline") -> RunState:
    """One LQR-FLM iteration (module docstring, steps 1–5). Pure: returns a new state."""
    rng = _rng(state)
    timings = {}
    t0 = time.perf_counter()
    rollouts = task.rollouts(state.policy, cfg.samples, rng, workers=cfg.workers)
    timings["rollouts"] = time.perf_counter() - t0

    learn, kin = _kinematic(task, cfg, rollouts, state.policy, timings)
    t0 = time.perf_counter()
    prior, denoised = _update_prior(task, cfg, state.prior, learn, state.policy, rng)
    dyn = _fit_dynamics(task, cfg, learn, prior, state.policy, denoised)
    timings["fit"] = time.perf_counter() - t0

    if cfg.noise.expand_at == "measured":
        s_bar = learn.s.mean(axis=0)
    else:
        s_bar = noise_aware.expansion_point(rollouts, dyn, noise_aware.noise_model(task), cfg.noise)
    a_bar = rollouts.a.mean(axis=0)
    cost = task.cost_expansion(s_bar, a_bar)
    local, kf = _local_model(task, cfg, dyn, cost, state.iteration)
    ref = noise_aware.gains(state.policy if reference is None else reference)

    mult = state.mult
    if cfg.adapt_step and state.prev is not None:
        predicted, actual = lqg.laplace_improvements(state.prev.reference, noise_aware.gains(state.policy),
                                                     state.prev.model, local)
        mult = lqg.adapt_step(mult, predicted, actual, cfg.kl)

    t0 = time.perf_counter()
    nu = _budget(cfg, task.T, mult)
    res = lqg.kl_step(local.dynamics, local.cost, ref, nu, local.mu0, local.P0, method=cfg.kl_method, config=cfg.kl)
    timings["lqg"] = time.perf_counter() - t0

    record = _record(
        state.iteration, phase, task, rollouts,
        kl=float(np.sum(res.kl)), nu=float(np.sum(nu)), mult=mult, timings=timings,
        extra={"eta_mean": float(np.mean(res.eta)), "predicted_cost": float(res.expected_cost)},
    )
    return dataclasses.replace(
        state,
        iteration=state.iteration + 1,
        policy=_wrap(res.policy, kf, kin),
        mult=mult,
        prior=prior,
        rng_state=rng.bit_generator.state,
        history=state.history + (record,),
        prev=PreviousStep(local, ref),
        best=_improved(state.best, float(np.mean(record.cost)), state.policy, state.iteration),
        last_rollouts=rollouts,
    )


def _mstep_constraints(em: EMConfig, policy: LinearGaussianPolicy) -> mstep.MStepConstraints:
    """The M-step's feasible set relative to the current policy (SPEC §5)."""
    if em.entropy_floor:
        cons = mstep.MStepConstraints(entropy_floor=np.linalg.slogdet(policy.cov)[1].tolist())
    else:
        cons = mstep.MStepConstraints(cov_floor=(em.cov_floor_scale * np.asarray(policy.cov)).tolist())
    if em.trust_region is not None:
        cons = dataclasses.replace(cons, trust_region=em.trust_region)
    return cons


def _em_model(task: Task, cfg: DPSOCConfig, rollouts: Rollouts, prior, policy, recursion: int, denoised=None):
    """The EM recursion's augmented model, initial distribution and filter (``None`` for the paper).

    With ``noise.estimator = "kalman"`` the model is the augmented model in ``xhat``
    (``docs/noise.md`` §6) and the EM policy acts on the filter of this fit.
    """
    base = cfg.baseline
    if base.noise.paper:
        model = fit.fit_augmented(rollouts, base.fit, prior)
    else:
        model = noise_aware.fit_local(rollouts, base.fit, prior, base.noise, noise_aware.noise_model(task), policy,
                                      include_y=True, denoised=denoised)
    if base.noise.estimator == "none":
        mu0, P0 = _initial_distribution(task)
        return model, mu0, P0, None
    if base.noise.estimator == "kinematic":
        nm = noise_aware.noise_model(task)
        return model, nm.mu0, symmetrize(nm.P0 + base.noise.estep_p0_jitter * np.eye(model.n)), None
    model, kf, mu0, P0 = noise_aware.filtered_em_model(model, noise_aware.noise_model(task), base.noise,
                                                       f" (EM recursion {recursion})")
    return model, mu0, P0, kf


def em_update(task: Task, cfg: DPSOCConfig, policy: LinearGaussianPolicy | FilteredPolicy, rollouts: Rollouts,
              prior: fit.MixturePrior | None, rng: np.random.Generator,
              recursion: int = 0, denoised: Rollouts | None = None, kin=None
              ) -> tuple[LinearGaussianPolicy | FilteredPolicy, EMDiagnostics]:
    """One EM recursion (paper Algorithm 1): fit augmented model, generate ``Y``, E-step, DP M-step.

    ``rollouts`` are samples of ``policy``.  Returns the EM policy and the recursion's
    :class:`EMDiagnostics` (surrogate and ``log p(Y)`` before/after, timings).  With the
    estimator (SPEC §10.2) the E-/M-step run on the augmented model in ``xhat``, ``policy``'s gains
    read as acting on the new filter's estimate, and the EM policy is returned with that filter.
    With the kinematic estimator (docs/math.md §11.3) ``rollouts`` are the smoothed ones and the
    EM policy is returned with the kinematic filter ``kin``.
    """
    em = cfg.em
    t0 = time.perf_counter()
    model, mu0, P0, kf = _em_model(task, cfg, rollouts, prior, policy, recursion, denoised)
    t_fit = time.perf_counter() - t0
    policy = noise_aware.gains(policy)
    Y = fit.cost_observations(em.y_mode, rollouts, model, policy, mu0, P0, rng, n_samples=em.y_samples)

    t0 = time.perf_counter()
    sm = estep.smooth(model, policy, Y, mu0, P0)
    t_estep = time.perf_counter() - t0

    cons = _mstep_constraints(em, policy)
    t0 = time.perf_counter()
    new = mstep.maximize(
        model, sm, Y, constraints=cons, method=em.method, variant=em.variant,
        objective=em.objective, previous=policy, min_norm=em.min_norm, config=em.mstep,
    )
    t_mstep = time.perf_counter() - t0
    diag = EMDiagnostics(
        recursion=recursion,
        surrogate_old=float(np.sum(mstep.surrogate(model, sm, Y, policy))),
        surrogate_new=float(np.sum(mstep.surrogate(model, sm, Y, new))),
        loglik_old=float(np.mean(sm.loglik)),
        loglik_new=float(np.mean(estep.smooth(model, new, Y, mu0, P0).loglik)),
        time_fit_augmented=t_fit,
        time_estep=t_estep,
        time_mstep=t_mstep,
    )
    return _wrap(new, kf, kin), diag


def dpsoc_iteration(task: Task, cfg: DPSOCConfig, state: RunState) -> RunState:
    """One DPSOC-EM outer iteration: the EM phase when ``iteration == i_switch``, then LQR-FLM."""
    if state.iteration == cfg.i_switch and not state.em_done:
        rng = _rng(state)
        policy = state.policy
        prior = state.prior
        history = state.history
        best = state.best
        for r in range(cfg.em.n_em):
            t0 = time.perf_counter()
            rollouts = task.rollouts(policy, cfg.baseline.samples, rng, workers=cfg.baseline.workers)
            timings = {"rollouts": time.perf_counter() - t0}
            learn, kin = _kinematic(task, cfg.baseline, rollouts, policy, timings)
            prior, denoised = _update_prior(task, cfg.baseline, prior, learn, policy, rng)
            new, diag = em_update(task, cfg, policy, learn, prior, rng, recursion=r, denoised=denoised, kin=kin)
            rec = _record(state.iteration, "em", task, rollouts, timings=timings, em=diag)
            history = history + (rec,)
            best = _improved(best, float(np.mean(rec.cost)), policy, state.iteration)
            policy = new
        state = dataclasses.replace(
            state, policy=policy, prior=prior, rng_state=rng.bit_generator.state,
            history=history, best=best, em_done=True, prev=None,
        )
        # The EM policy is the KL reference (and the sampling policy) of this iteration.
        return lqr_flm_iteration(task, cfg.baseline, state, reference=policy)
    return lqr_flm_iteration(task, cfg.baseline, state)


def _lqr_flm_step(task: Task, cfg: DPSOCConfig, state: RunState) -> RunState:
    return lqr_flm_iteration(task, cfg.baseline, state)


#: One outer iteration of each sample-based method: ``step(task, cfg, state) -> state``.
METHODS: dict[str, Callable[[Task, DPSOCConfig, RunState], RunState]] = {
    "lqr-flm": _lqr_flm_step,
    "dpsoc-em": dpsoc_iteration,
}


def run_algorithm(
    task: Task,
    method: Literal["lqr-flm", "dpsoc-em"],
    cfg: DPSOCConfig,
    seed: int = 0,
    state: RunState | None = None,
    on_iteration: Callable[[RunState], None] | None = None,
) -> RunState:
    """Run LQR-FLM or DPSOC-EM to ``cfg.baseline.iterations`` from ``state`` (or a fresh start).

    ``on_iteration`` is called with the new state after every finished iteration
    (checkpointing, progress lines).  The final state's ``best`` is the best policy sampled.
    """
    step = METHODS.get(method)
    if step is None:
        raise ValueError(f"unknown method {method!r}; use one of {', '.join(map(repr, METHODS))}")
    cfg.check_for(method)
    if state is None:
        state = initial_state(task, cfg.baseline, seed)
    while state.iteration < cfg.baseline.iterations:
        state = step(task, cfg, state)
        if on_iteration is not None:
            on_iteration(state)
    return state
