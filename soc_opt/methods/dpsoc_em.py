"""DPSOC-EM (paper Algorithm 1; docs/math.md §7): LQR-FLM with an EM phase at ``i_switch``.

At iteration ``i_switch`` the reference of the KL step is replaced by the EM policy: ``n_em``
recursions of {sample, fit augmented model (§1–§2), generate ``Y`` (§3), E-step (§4), DP M-step
(§5)}; the LQG step of that iteration then uses the EM policy as its KL reference and as the
sampling policy (paper eq. constrainObjective).  The run's noise strategy
(:mod:`soc_opt.noise.strategy`) supplies the fit and the model the E-/M-step run on (with
``[baseline.noise] estimator = "kalman"``, docs/math.md §10.2: the augmented model in ``xhat``).
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING

import numpy as np

from .. import estep, mstep
from ..config import ConfigError
from ..learning import fit
from ..models import LinearGaussianPolicy, Rollouts
from ..noise.estimator import FilteredPolicy
from ..noise.strategy import Estimates, NoiseStrategy, resolve
from .config import DPSOCConfig
from .lqr_flm import LQRFLM, acceptance_cost, acceptance_threshold, fit_batch, lqr_flm_iteration, sample
from .state import AcceptedPolicy, EMDiagnostics, PreviousStep, RunState, improved, record, state_rng

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["em_update", "dpsoc_iteration", "DPSOCEM", "DPSOC_EM"]


def em_update(task: Task, cfg: DPSOCConfig, policy: LinearGaussianPolicy | FilteredPolicy, rollouts: Rollouts,
              prior: fit.MixturePrior | None, rng: np.random.Generator,
              recursion: int = 0, estimates: Estimates | None = None, noise: NoiseStrategy | None = None
              ) -> tuple[LinearGaussianPolicy | FilteredPolicy, EMDiagnostics]:
    """One EM recursion (paper Algorithm 1): fit augmented model, generate ``Y``, E-step, DP M-step.

    ``rollouts`` are samples of ``policy``.  Returns the EM policy and the recursion's
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


def dpsoc_iteration(task: Task, cfg: DPSOCConfig, state: RunState) -> RunState:
    """One DPSOC-EM outer iteration: the EM phase when ``iteration == i_switch``, then LQR-FLM.

    With step acceptance (docs/math.md §12) the EM phase starts from an accepted policy: the first
    recursion's batch is the acceptance test of the policy it samples; if that policy is rejected,
    the iteration is an ordinary rejected LQR-FLM iteration and the EM phase runs at the next
    iteration.  The EM policy is then judged like any other step, on the samples it produced.
    """
    noise = resolve(task, cfg.baseline.noise)
    if state.iteration >= cfg.i_switch and not state.em_done:
        rng = state_rng(state)
        policy = state.policy
        prior = state.prior
        history = state.history
        best = state.best
        previous = state.last_rollouts
        accepted = state.accepted
        acc_cfg = cfg.baseline.acceptance
        first = first_est = None
        if acc_cfg.enabled:
            first = sample(task, cfg.baseline, state, rng)
            first_rec = record(state.iteration, "em", task, first[0])
            first_est = None
            if acc_cfg.cost == "estimated":  # the test reads the estimator's states: estimate the batch first
                first_est = noise.estimate(prior, first[0], cfg.baseline.fit, policy, rng, previous=previous)
                first[1].update(first_est.timings)
            c_s, se_s = acceptance_cost(acc_cfg, first_rec, None if first_est is None else first_est.data(first[0]))
            threshold = acceptance_threshold(acc_cfg, se_s, accepted)
            if not c_s <= threshold:  # the policy to start EM from is rejected: an ordinary rejected step
                return lqr_flm_iteration(task, cfg.baseline, dataclasses.replace(state, rng_state=rng.bit_generator.state),
                                         noise=noise, batch=first, estimates=first_est)
        for r in range(cfg.em.n_em):
            if r == 0 and first is not None:
                rollouts, timings = first
            else:
                t0 = time.perf_counter()
                rollouts = task.rollouts(policy, cfg.baseline.samples, rng, workers=cfg.baseline.workers)
                timings = {"rollouts": time.perf_counter() - t0}
            if r == 0 and first_est is not None:
                est = first_est
            else:
                est = noise.estimate(prior, rollouts, cfg.baseline.fit, policy, rng, previous=previous)
                timings.update(est.timings)
            prior = est.prior
            extra = {}
            if r == 0 and first is not None:
                # p_s is accepted; a rejected EM policy is replaced by an LQR-FLM step around p_s
                b = fit_batch(task, cfg.baseline, state, rollouts, timings, rng, noise, estimates=est)
                gains = noise.gains(policy)
                accepted = AcceptedPolicy(policy, c_s, se_s, state.iteration, PreviousStep(b.local, gains),
                                          b.wrap(gains), float(state.mult))
                extra = {"test_cost": c_s, "test_cost_se": se_s, "accept_threshold": threshold, "accepted": 1.0,
                         "accepted_iteration": float(state.iteration)}
            new, diag = em_update(task, cfg, policy, rollouts, prior, rng, recursion=r, estimates=est, noise=noise)
            if r == 0 and first is not None:  # the batch's costs and metrics are already in first_rec
                rec = dataclasses.replace(first_rec, timings=timings, em=diag, extra=extra)
            else:
                rec = record(state.iteration, "em", task, rollouts, timings=timings, em=diag, extra=extra)
            history = history + (rec,)
            best = improved(best, float(np.mean(rec.cost)), policy, state.iteration)
            policy = new
            previous = rollouts  # the batch the new policy's estimator was learned from
        state = dataclasses.replace(
            state, policy=policy, prior=prior, rng_state=rng.bit_generator.state,
            history=history, best=best, em_done=True, prev=None, last_rollouts=previous, accepted=accepted,
        )
        # The EM policy is the KL reference (and the sampling policy) of this iteration.
        return lqr_flm_iteration(task, cfg.baseline, state, reference=policy, noise=noise)
    return lqr_flm_iteration(task, cfg.baseline, state, noise=noise)



class DPSOCEM(LQRFLM):
    """DPSOC-EM as a :class:`~soc_opt.methods.base.Method`: reads ``i_switch``, ``[baseline]``, ``[em]``."""

    name = "dpsoc-em"
    sections: tuple[str, ...] = ("i_switch", "baseline", "em")

    def check_config(self, cfg) -> None:
        """DPSOC-EM needs ``0 <= i_switch < baseline.iterations``."""
        if not 0 <= cfg.i_switch < cfg.baseline.iterations:
            raise ConfigError(
                f"i_switch must be in [0, iterations={cfg.baseline.iterations}), got {cfg.i_switch}"
            )

    def iterate(self, task: Task, cfg, state: RunState) -> RunState:
        return dpsoc_iteration(task, cfg, state)


DPSOC_EM = DPSOCEM()
