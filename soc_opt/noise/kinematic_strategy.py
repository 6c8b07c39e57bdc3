"""``estimator = "kinematic"`` as the loop's noise strategy (docs/math.md §11.3).

Per batch of rollouts, :meth:`KinematicEstimator.estimate` runs the structured smoother and EM of
:mod:`soc_opt.noise.kinematic` (:func:`soc_opt.noise.kinematic.loop.learn`): the learner (mixture
prior, fit, cost expansion, the EM phase's cost observations) then works on the smoothed rollouts
(:attr:`Estimates.learn`), and the new policy acts on the batch's online filter
(:attr:`Estimates.filter`, a :class:`~soc_opt.noise.kinematic.filter.KinematicFilteredPolicy`).
Everything per batch travels in the :class:`~soc_opt.noise.strategy.Estimates`; the strategy
holds none of it.  Its options are :class:`~soc_opt.noise.kinematic.config.KinematicConfig`
(``[baseline.noise.kinematic]``); registered in :mod:`soc_opt.noise.registry`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..config import config_error
from ..learning import fit
from ..lqg import LocalModel
from ..models import symmetrize
from . import aware as noise_aware
from .kinematic import loop as kinematic_loop
from .kinematic import model as kinematic_model
from .kinematic.config import KinematicConfig
from .kinematic.dynamics import structured_dynamics, structured_prior, with_dynamics
from .kinematic.filter import KinematicFilter, KinematicFilteredPolicy
from .strategy import EMModel, Estimates, LoopModel, NoiseStrategy, kalman_em_model, kalman_lqg_model

__all__ = ["KinematicEstimator", "posterior_correction"]


def posterior_correction(Px: np.ndarray, Cx: np.ndarray, n: int, m: int, weight: float):
    """The ``correct`` hook of :func:`soc_opt.learning.fit.fit_dynamics`: the joint moments of the smoothed
    tuples ``(x_k, a_k, x_{k+1}[, y_k])`` plus the smoother's posterior (co)variances ``Px (T+1, n, n)``,
    ``Cx (T, n, n)`` (:func:`soc_opt.noise.kinematic.loop.posterior_moments`), scaled by ``weight``
    (``M / (M + n0)`` under the NIW prior, whose posterior weighs the data's moments so)."""
    nz = n + m
    x1 = slice(nz, nz + n)

    def correct(mu, Lam):
        Lam = np.array(Lam)
        Lam[:, :n, :n] += weight * Px[:-1]
        Lam[:, x1, x1] += weight * Px[1:]
        Lam[:, x1, :n] += weight * Cx
        Lam[:, :n, x1] += weight * np.swapaxes(Cx, -1, -2)
        return mu, symmetrize(Lam)

    return correct


class KinematicEstimator(NoiseStrategy):
    """Learn from the kinematic smoother's states, act on its online filter (module docstring).

    ``NoiseConfig`` requires the fit correction, expansion point, prior data and time window at
    their defaults with this estimator, so the inherited ``fit`` and ``expansion_point`` are the
    paper's, applied to the smoothed rollouts.  The start ``x_0 ~ N(mu0, task.P0 - R)`` (docs/math.md §10;
    with a start range ``task.P0 - R`` holds its ``start_cov``, §8.1) is the initial distribution of the KL
    step and the E-step.
    """

    name = "kinematic"
    settings = KinematicConfig
    state_types = (KinematicFilter, KinematicFilteredPolicy)

    @classmethod
    def check_config(cls, cfg) -> None:
        """The shared options that change what the learner fits (fit correction, expansion point, prior
        data, time window) must stay at their defaults: it learns from its own smoothed states; the one
        correction it takes is ``"eiv"``, which refits its fit with the states latent (docs/math.md §13.1)."""
        other = {"expand_at": "measured", "prior_data": "measured", "time_window": 0}
        bad = [f"{k} = {getattr(cfg, k)!r}" for k, v in other.items() if getattr(cfg, k) != v]
        if cfg.fit_correction not in ("none", "eiv"):
            bad.insert(0, f"fit_correction = {cfg.fit_correction!r}")
        if bad:
            raise config_error("estimator", f"'kinematic' learns from its own smoothed states; {', '.join(bad)} "
                               "cannot be combined with it (leave them at their defaults)")

    @classmethod
    def check_task(cls, task, cfg) -> None:
        """A MuJoCo task (gym: ones included) whose state holds every joint that moves one of its points
        (:func:`soc_opt.noise.kinematic.model.check_task`)."""
        kinematic_model.check_task(task)

    def estimate(self, prior, rollouts, fit_cfg, sampler, rng: np.random.Generator, previous=None) -> Estimates:
        """Smooth ``rollouts`` (sampled by ``sampler``), then the mixture prior on the smoothed tuples;
        ``previous``: the batch ``sampler``'s filter was learned from (held out for the EM start's choice)."""
        learn, filt, diag = kinematic_loop.learn(self.task, rollouts, sampler, self.cfg.kinematic, previous)
        base = super().estimate(prior, learn, fit_cfg, sampler, rng)
        return base._replace(learn=learn, filter=filt, moments=diag.get("posterior"),
                             timings={"estimator": diag["kin_time"]}, measured=rollouts)

    def fit(self, rollouts, fit_cfg, estimates: Estimates, sampler, *, include_y: bool = False):
        """The paper's fit of the smoothed rollouts; with ``fit_moments = "posterior"`` on their expected
        sufficient statistics (:func:`posterior_correction`); with ``structured_prior > 0`` pulled towards
        the filter's structured transition (:func:`~soc_opt.noise.kinematic.dynamics.structured_prior`).
        With ``fit_correction = "eiv"`` that fit starts the errors-in-variables fit of the measured batch
        (:func:`~soc_opt.noise.aware.eiv_local`; prior at the smoothed tuples, uncorrected)."""
        start = self._fit(rollouts, fit_cfg, estimates, sampler, include_y=include_y)
        if self.cfg.fit_correction != "eiv" or estimates.measured is None or float(self.task.rho2) == 0.0:
            return start
        measured = dataclasses.replace(estimates.measured, y=rollouts.y) if include_y else estimates.measured
        return noise_aware.eiv_local(measured, fit_cfg, estimates.prior, self.cfg, self.noise, start,
                                     prior_tuples=rollouts)

    def _fit(self, rollouts, fit_cfg, estimates: Estimates, sampler, *, include_y: bool = False):
        kin = self.cfg.kinematic
        use_structured = kin.structured_prior > 0 and isinstance(estimates.filter, KinematicFilter)
        if estimates.moments is None and not use_structured:
            return super().fit(rollouts, fit_cfg, estimates, sampler, include_y=include_y)
        used_prior = estimates.prior is not None and fit_cfg.prior == "mixture"
        count = rollouts.M + fit_cfg.n0 if used_prior else float(rollouts.M)
        steps = []
        if estimates.moments is not None:
            steps.append(posterior_correction(*estimates.moments, rollouts.n, rollouts.m, rollouts.M / count))
        if use_structured:
            steps.append(structured_prior(structured_dynamics(estimates.filter, kin.w_floor), kin.structured_prior, count))

        def correct(mu, Lam):
            for step in steps:
                mu, Lam = step(mu, Lam)
            return mu, Lam

        return (fit.fit_augmented if include_y else fit.fit_dynamics)(rollouts, fit_cfg, estimates.prior,
                                                                       correct=correct)

    def _wrap(self, estimates: Estimates):
        return lambda policy: KinematicFilteredPolicy(policy, estimates.filter)

    def lqg_model(self, dynamics, cost, estimates: Estimates, where: str = "") -> LoopModel:
        """The fit on the smoothed states (or, with ``dynamics = "structured"``, the filter's own
        transition: :mod:`soc_opt.noise.kinematic.dynamics`) from the task's start (``kl_model = "plain"``), or its
        innovation form with the Kalman filter of that fit (``"innovation"``, docs/math.md §10.2).
        With ``filter = "fit"`` the policy acts on that Kalman filter (as ``estimator = "kalman"``)."""
        kin = self.cfg.kinematic
        if kin.filter == "fit":
            return kalman_lqg_model(self.noise, self.cfg, dynamics, cost, where)
        if kin.dynamics == "structured":
            dynamics = structured_dynamics(estimates.filter, kin.w_floor)
        if kin.kl_model == "innovation":
            kf = noise_aware.loop_filter(dynamics, self.noise, self.cfg, where)
            local = noise_aware.innovation_local_model(kf, cost)
        else:
            local = LocalModel(dynamics, cost, self.noise.mu0, self.noise.P0)
        return LoopModel(local, self._wrap(estimates))

    def em_model(self, model, estimates: Estimates, where: str = "") -> EMModel:
        """The fit on the smoothed states as is (its state rows replaced by the filter's transition with
        ``dynamics = "structured"``), from the task's start (``P0`` plus ``estep_p0_jitter``);
        with ``filter = "fit"`` the augmented model in the estimate of that fit's Kalman filter."""
        kin = self.cfg.kinematic
        if kin.filter == "fit":
            return kalman_em_model(self.noise, self.cfg, model, where)
        if kin.dynamics == "structured":
            model = with_dynamics(model, structured_dynamics(estimates.filter, kin.w_floor))
        P0 = symmetrize(self.noise.P0 + self.cfg.estep_p0_jitter * np.eye(model.n))
        return EMModel(model, self.noise.mu0, P0, self._wrap(estimates))
