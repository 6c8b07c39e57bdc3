"""DPSOC-EM's EM phase (paper Algorithm 1; docs/math.md §3–§5, §7), the step it plugs into the LQR-FLM
iteration at ``i_switch``.

:func:`em_phase` runs ``n_em`` recursions of {sample, fit augmented model (§1–§2), generate ``Y`` (§3),
E-step (§4), DP M-step (§5)} (:func:`em_update`) starting from an accepted batch of the current policy;
the LQR-FLM iteration (:func:`soc_opt.methods.lqr_flm.iteration.lqr_flm_iteration`, its ``em`` step)
then samples the EM policy, judges it like any other step and takes the KL step with the EM policy as
its reference (paper eq. constrainObjective).  The run's noise strategy (:mod:`soc_opt.noise.strategy`)
supplies the fit and the model the E-/M-step run on (with ``[baseline.noise] estimator = "kalman"``,
docs/math.md §10.2: the augmented model in ``xhat``).
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING

import numpy as np

from ... import estep, mstep
from ...learning import fit
from ...models import LinearGaussianPolicy, Rollouts
from ...noise.estimator import FilteredPolicy
from ...noise.strategy import Estimates, NoiseStrategy, resolve
from ..lqr_flm.acceptance import Verdict
from ..lqr_flm.iteration import Drawn, draw, fit_batch
from ..state import AcceptedPolicy, EMDiagnostics, PreviousStep, RunState, improved

if TYPE_CHECKING:
    from ...tasks import Task

__all__ = ["em_update", "em_phase"]


def em_update(task: Task, cfg, policy: LinearGaussianPolicy | FilteredPolicy, rollouts: Rollouts,
              prior: fit.MixturePrior | None, rng: np.random.Generator,
              recursion: int = 0, estimates: Estimates | None = None, noise: NoiseStrategy | None = None
              ) -> tuple[LinearGaussianPolicy | FilteredPolicy, EMDiagnostics]:
    """One EM recursion (paper Algorithm 1): fit augmented model, generate ``Y``, E-step, DP M-step.

    ``cfg``: the run configuration (:class:`~soc_opt.methods.config.DPSOCConfig`; ``[em]`` and ``[baseline]``
    are read).  ``rollouts`` are samples of ``policy``.  Returns the EM policy and the recursion's
    :class:`EMDiagnostics` (surrogate and ``log p(Y)`` before/after, timings).  With the
    estimator (docs/math.md §10.2) the E-/M-step run on the augmented model in ``xhat``, ``policy``'s gains
    read as acting on the new filter's estimate, and the EM policy is returned with that filter.
    ``estimates``: what the strategy found in ``rollouts`` (``NoiseStrategy.estimate``, whose
    ``prior`` must be ``prior``; default: nothing beyond ``prior``); the fit and the cost
    observations use ``estimates.data(rollouts)``.  ``noise``: the run's noise strategy (default:
    resolved from ``cfg.baseline.noise``).
    """
    em = cfg.em
    noise = resolve(task, cfg.baseline.noise) if noise is None else noise
    if estimates is None:
        estimates = Estimates(prior)
    elif estimates.prior is not prior:
        raise ValueError("em_update: estimates.prior is not prior (pass the Estimates of these rollouts)")
    data = estimates.data(rollouts)
    t0 = time.perf_counter()
    fitted = noise.fit(data, cfg.baseline.fit, estimates, policy, include_y=True)
    model, mu0, P0, wrap = noise.em_model(fitted, estimates, f" (EM recursion {recursion})")
    t_fit = time.perf_counter() - t0
    policy = noise.gains(policy)
    Y = fit.cost_observations(em.y_mode, data, model, policy, mu0, P0, rng, n_samples=em.y_samples)

    t0 = time.perf_counter()
    sm = estep.smooth(model, policy, Y, mu0, P0)
    t_estep = time.perf_counter() - t0

    t0 = time.perf_counter()
    new = em.maximize(model, sm, Y, previous=policy)  # the M-step recipe (mstep.recipe)
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
    return wrap(new), diag


def em_phase(cfg, task: Task, state: RunState, drawn: Drawn, verdict: Verdict, rng: np.random.Generator,
             noise: NoiseStrategy) -> RunState:
    """The EM phase on the accepted batch ``drawn`` of ``state.policy`` ``p_s`` (an
    :data:`~soc_opt.methods.lqr_flm.iteration.EMStep` once ``cfg`` is bound): ``cfg.em.n_em`` recursions of
    :func:`em_update`, the first on ``drawn``, each next one on a new batch of the last EM policy; one
    ``"em"`` history row per recursion (the first with the verdict's columns).  Returns the state whose
    policy is the EM policy, with ``em_done``, no previous step (the next step is not adapted) and, when
    the verdict was a test, ``p_s`` as the accepted policy (a rejected EM policy is replaced by an
    LQR-FLM step around ``p_s``)."""
    base = cfg.baseline
    accepted = state.accepted
    if verdict.tested:
        b = fit_batch(task, base, state, drawn, noise)
        gains = noise.gains(state.policy)
        accepted = AcceptedPolicy(state.policy, verdict.cost, verdict.se, state.iteration, PreviousStep(b.local, gains),
                                  b.wrap(gains), float(state.mult), verdict.costs)
    current = state
    history, best = state.history, state.best
    for r in range(cfg.em.n_em):
        d = drawn if r == 0 else draw(task, base, current, rng, noise)
        new, diag = em_update(task, cfg, current.policy, d.rollouts, d.estimates.prior, rng, recursion=r,
                              estimates=d.estimates, noise=noise)
        rec = dataclasses.replace(d.record, phase="em", timings=d.timings, em=diag,
                                  extra=verdict.columns(state.iteration) if r == 0 else {})
        history = history + (rec,)
        best = improved(best, float(np.mean(rec.cost)), current.policy, state.iteration)
        # the next batch: of the EM policy, its prior updated past this one, whose batch its estimator learned from
        current = dataclasses.replace(current, policy=new, prior=d.estimates.prior, last_rollouts=d.rollouts)
    return dataclasses.replace(
        state, policy=current.policy, prior=current.prior, rng_state=rng.bit_generator.state,
        history=history, best=best, em_done=True, prev=None, last_rollouts=current.last_rollouts, accepted=accepted,
    )
