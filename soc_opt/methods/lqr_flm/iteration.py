"""One LQR-FLM iteration (the paper's baseline, "iLQG" in the paper; docs/math.md §7, §12), in one place.

On an explicit :class:`~soc_opt.methods.state.RunState`, :func:`lqr_flm_iteration`:

1. :func:`draw`: sample ``M`` rollouts of the current policy ``p_i`` and let the run's noise strategy
   estimate the batch (the mixture prior is updated past it);
2. :func:`~soc_opt.methods.lqr_flm.acceptance.judge` the batch against the last accepted policy
   (docs/math.md §12.1; with acceptance off, the paper as written, every batch is accepted);
   an ``em`` step (DPSOC-EM's EM phase) plugged in here runs on an accepted batch and hands back the
   state whose policy is the EM policy, which is then drawn and judged in turn;
3. :func:`fit_batch`: fit linear-Gaussian dynamics (mixture prior + NIW posterior, §2) and expand the
   cost to second order around the batch's mean trajectory, the KL step's local model;
4. :func:`~soc_opt.methods.lqr_flm.acceptance.next_multiplier`: the KL budget from the predicted and
   actual improvement of the last step (§6, GPS rule) on an accepted batch, the shrunk multiplier of a
   rejected one;
5. the KL-constrained LQG step: around ``p_i`` on its own batch's model when accepted, else again
   around the last accepted policy on that policy's model (§12.2) -> ``p_{i+1}``.

Noise-aware variants (docs/math.md §10, ``[baseline.noise]``): steps 1, 3 and 5 call the run's
:class:`~soc_opt.noise.strategy.NoiseStrategy` (state estimates for the prior, corrected fit,
expansion point, the KL step's model and the new policy's estimator); the defaults are the
paper's method.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Callable, NamedTuple

import numpy as np

from ... import lqg
from ...errors import FlatCostError
from ...lqg import LocalModel
from ...models import LinearGaussianPolicy, Rollouts
from ...noise import aware as noise_aware
from ...noise.strategy import Estimates, NoiseStrategy, resolve
from ..state import AcceptedPolicy, IterationRecord, PreviousStep, RunState, improved, record, state_rng
from .acceptance import Verdict, judge, next_multiplier
from .config import LQRFLMConfig

if TYPE_CHECKING:
    from ...tasks import Task

__all__ = ["initial_state", "Drawn", "draw", "Batch", "fit_batch", "shaped_gains", "EMStep", "lqr_flm_iteration",
           "final_policy", "sample"]


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


class Drawn(NamedTuple):
    """One sampled batch of a policy (step 1): the rollouts, what the noise strategy estimated in them
    (its ``prior`` the mixture prior updated past them), the wall times, and the batch's history row
    (phase ``"baseline"``, no step yet)."""

    rollouts: Rollouts
    estimates: Estimates
    timings: dict
    record: IterationRecord

    def learned(self) -> Rollouts:
        """The batch as the learner sees it (:meth:`Estimates.data`)."""
        return self.estimates.data(self.rollouts)


def sample(task: Task, cfg: LQRFLMConfig, policy, rng: np.random.Generator) -> tuple[Rollouts, dict]:
    """``cfg.samples`` rollouts of ``policy`` and their wall time."""
    t0 = time.perf_counter()
    rollouts = task.rollouts(policy, cfg.samples, rng, workers=cfg.workers)
    return rollouts, {"rollouts": time.perf_counter() - t0}


def draw(task: Task, cfg: LQRFLMConfig, state: RunState, rng: np.random.Generator, noise: NoiseStrategy) -> Drawn:
    """Step 1 on ``state.policy``: its samples, estimated from ``state.prior`` and ``state.last_rollouts``.
    Timings: ``rollouts``, the estimator's own (``estimator``), and ``prior``, the rest of the estimate
    (the mixture prior's variational fit, docs/math.md §2)."""
    rollouts, timings = sample(task, cfg, state.policy, rng)
    t0 = time.perf_counter()
    est = noise.estimate(state.prior, rollouts, cfg.fit, state.policy, rng, previous=state.last_rollouts)
    spent = time.perf_counter() - t0
    timings.update(est.timings)
    timings["prior"] = max(spent - sum(est.timings.values()), 0.0)  # the rest of step 2a: the mixture prior's fit
    return Drawn(rollouts, est, timings, record(state.iteration, "baseline", task, rollouts, kl=0.0, nu=0.0, mult=1.0))


class Batch(NamedTuple):
    """A drawn batch and the local model fitted on it (steps 1 and 3)."""

    rollouts: Rollouts
    estimates: Estimates
    local: LocalModel  # the KL step's model fitted on this batch
    wrap: Callable  # LinearGaussianPolicy -> the policy the task runs (its filter from this batch)
    timings: dict


def fit_batch(task: Task, cfg: LQRFLMConfig, state: RunState, drawn: Drawn, noise: NoiseStrategy) -> Batch:
    """Step 3 on the batch ``drawn`` of ``state.policy``: the local fit and the cost expansion, as the KL
    step's model."""
    timings = dict(drawn.timings)
    t0 = time.perf_counter()
    est = drawn.estimates
    data = est.data(drawn.rollouts)  # what the learner fits on: the measured rollouts unless the estimator says
    dyn = noise.fit(data, cfg.fit, est, state.policy)
    timings["fit"] = time.perf_counter() - t0
    s_bar = noise.expansion_point(data, dyn)
    a_bar = drawn.rollouts.a.mean(axis=0)
    cost = task.cost_expansion(s_bar, a_bar)
    if not (np.any(cost.C) or np.any(cost.c)):
        raise FlatCostError(
            f"the cost expansion of task {task.name} around the samples of iteration {state.iteration} is zero at "
            f"every step (no gradient or curvature in the state or the action): the cost does not change near "
            "the mean trajectory (an indicator cost such as an alive bonus, or a constant one), so the KL step "
            "has nothing to follow; give the task a smooth cost ([[cost]] terms, docs/tasks.md; for gym: tasks "
            "docs/gym.md)")
    local, wrap = noise.lqg_model(dyn, cost, est, f" (iteration {state.iteration})")
    return Batch(drawn.rollouts, est, local, wrap, timings)


def shaped_gains(noise: NoiseStrategy, res, b: Batch, wrap: Callable | None = None) -> LinearGaussianPolicy:
    """The KL step's policy ``res.policy`` as the next policy acts (``[baseline.noise] feedback``,
    docs/math.md §13.2): as solved (``"estimate"``), its gains calibrated to how well the new filter's
    estimates of the batch ``b`` predict the learner's states (``"calibrated"``), or without feedback
    (``"open_loop"``).  ``wrap``: what makes the new policy acting on its filter (default ``b.wrap``)."""
    mode = noise.cfg.feedback
    if mode == "estimate" or (mode == "calibrated" and float(noise.task.rho2) == 0.0):
        return res.policy  # without sensor noise the estimate is the state
    if mode == "open_loop":
        return noise_aware.open_loop_gains(res.policy, res.marginals.a_mean)
    wrapped = (b.wrap if wrap is None else wrap)(res.policy)
    estimated = noise_aware.policy_estimates(wrapped.for_task(noise.task) if hasattr(wrapped, "for_task") else wrapped,
                                             b.rollouts)
    gamma = noise_aware.calibration(b.estimates.data(b.rollouts).s, estimated)
    return noise_aware.calibrated_gains(res.policy, gamma, res.marginals.mean)


#: A step plugged into the iteration between the verdict and the KL step (DPSOC-EM's EM phase):
#: ``(task, state, drawn, verdict, rng, noise) -> state``, called on an accepted batch ``drawn`` of
#: ``state.policy``; the state it returns (its policy sampled next, its RNG continued by ``rng``) is
#: drawn, judged and stepped by the rest of the iteration.
EMStep = Callable[["Task", RunState, Drawn, Verdict, np.random.Generator, NoiseStrategy], RunState]


def lqr_flm_iteration(task: Task, cfg: LQRFLMConfig, state: RunState, *, noise: NoiseStrategy | None = None,
                      em: EMStep | None = None) -> RunState:
    """One iteration (module docstring, steps 1–5). Pure: returns a new state.

    ``noise``: the run's noise strategy (default: resolved from ``cfg.noise`` for ``task``).  ``em``: a
    step run on an accepted batch before the KL step (:data:`EMStep`; DPSOC-EM's EM phase).
    """
    noise = resolve(task, cfg.noise) if noise is None else noise
    rng = state_rng(state)
    drawn = draw(task, cfg, state, rng, noise)
    verdict = judge(cfg.acceptance, drawn.record, drawn.learned(), state.accepted)
    if em is not None and verdict.accept:
        state = em(task, state, drawn, verdict, rng, noise)
        drawn = draw(task, cfg, state, rng, noise)
        verdict = judge(cfg.acceptance, drawn.record, drawn.learned(), state.accepted)
    return _step(task, cfg, state, fit_batch(task, cfg, state, drawn, noise), drawn.record, verdict, rng, noise)


def _step(task: Task, cfg: LQRFLMConfig, state: RunState, b: Batch, rec: IterationRecord, verdict: Verdict,
          rng: np.random.Generator, noise: NoiseStrategy) -> RunState:
    """Steps 4–5 after ``verdict`` on the batch ``b`` of ``state.policy`` (history row ``rec``).

    Accepted: the GPS rule adapts the multiplier (below ``state.mult_ceiling``; with ``acceptance.recover``
    a good prediction gives back ``state.mult_recover``; history column ``mult_recover``) and the KL step is taken
    around ``p_i`` on ``b``'s model; with a test made, ``p_i`` becomes the accepted policy.  Rejected: no
    adaptation; the step is taken again around ``p_a`` on the model fitted on ``p_a``'s own samples, with
    the multiplier shrunk; the rejected batch still entered the mixture prior.  A tested step whose budget
    (multiplier below 1) is below what the dual resolves is the zero step: the reference itself.
    """
    timings = b.timings
    ref = noise.gains(state.policy)
    acc = state.accepted
    improvements = None
    if state.prev is not None:
        improvements = lqg.laplace_improvements(state.prev.reference, ref, state.prev.model, b.local)
    nxt = next_multiplier(cfg.step_size, cfg.acceptance, verdict, state.mult, state.mult_ceiling, improvements, acc,
                          cfg.adapt_multiplier, state.mult_recover)
    mult = nxt.mult
    step = PreviousStep(b.local, ref) if verdict.accept else acc.step
    retry = None if verdict.accept else (lambda g: noise_aware.with_gains(acc.child, g))

    t0 = time.perf_counter()
    nu = _budget(cfg, task.T, mult)
    zero_step = False
    try:
        res = lqg.kl_step_local(step.model, step.reference, nu, method=cfg.kl_method, config=cfg.kl)
        gains = shaped_gains(noise, res, b, retry)
        kl, eta_mean, predicted_cost = float(np.sum(res.kl)), float(np.mean(res.eta)), float(res.expected_cost)
    except lqg.BudgetUnreachable:
        if not (verdict.tested and mult < 1.0):
            raise  # as written, or at the base budget or above: a failure (e.g. a diverged fit)
        # the shrunk multiplier asks for less than the dual resolves: the limit of a vanishing step is the
        # reference itself, the accepted policy, sampled again next iteration
        gains, kl, eta_mean, predicted_cost, zero_step = step.reference, 0.0, float("inf"), float("nan"), True
    timings["lqg"] = time.perf_counter() - t0

    if verdict.accept:
        new_policy, last = b.wrap(gains), b.rollouts
        if verdict.tested:
            acc = AcceptedPolicy(state.policy, verdict.cost, verdict.se, state.iteration, step, new_policy, float(mult),
                                 verdict.costs)
    else:
        new_policy = retry(gains)
        last = state.last_rollouts  # the batch the new policy's estimator was learned from
    predicted, actual = (float("nan"), float("nan")) if improvements is None else improvements
    extra = {"eta_mean": eta_mean, "predicted_cost": predicted_cost, "predicted_improvement": predicted,
             "actual_improvement": actual, **verdict.columns(acc.iteration if verdict.tested else -1),
             **({"zero_step": 1.0} if zero_step else {}), **_recover_column(cfg, nxt)}
    rec = dataclasses.replace(rec, kl=kl, nu=float(np.sum(nu)), mult=float(mult), timings=timings, extra=extra)
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
        mult_ceiling=nxt.ceiling,
        mult_recover=nxt.recover_to,
    )


def _recover_column(cfg: LQRFLMConfig, nxt) -> dict[str, float]:
    """The history column ``mult_recover`` with ``acceptance.recover`` (the multiplier still to be given back
    after this step, NaN when none; docs/math.md §12.2); no column without it."""
    if not cfg.acceptance.recover:
        return {}
    return {"mult_recover": float("nan") if nxt.recover_to is None else float(nxt.recover_to)}


def final_policy(cfg: LQRFLMConfig, state: RunState):
    """What a run returns (docs/math.md §12.3): the last accepted policy with step acceptance, else
    (the paper as written) the policy of the last KL step."""
    if cfg.acceptance.enabled and state.accepted is not None:
        return state.accepted.policy
    return state.policy
