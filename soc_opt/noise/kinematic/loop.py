"""The kinematic estimator in the learning loop (``docs/math.md §11.3``).

One call per batch of rollouts: EM for the acceleration map (from the sampling policy's filter's map
and from the batch's own initial map, the higher final likelihood kept; ``warm_start`` and
``restart_from_data`` choose the starts), the rollouts with ``s`` replaced by the smoothed states ``h(E[z_k | s, a])`` and
their costs recomputed on them (what the paper's fit, prior and cost expansion then learn from),
and the online filter the next policy acts on (exact ``h`` through MuJoCo, gains linearised along
the mean smoothed trajectory).  Uses the robot's kinematics, not its masses, inertia or damping.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ...models import Rollouts
from . import em
from .config import KinematicConfig
from .filter import KinematicFilter, KinematicFilteredPolicy, build_filter
from .model import KinematicModel

__all__ = ["learn", "posterior_moments"]


def posterior_moments(sm) -> tuple[np.ndarray, np.ndarray]:
    """``(Px (T+1, n, n), Cx (T, n, n))``: the smoother's ``Cov(z_k)`` and ``Cov(z_{k+1}, z_k)`` carried
    into task coordinates with ``H`` at the linearisation point, averaged over the rollouts::

        Px_k = mean_i H_ik P_ik H_ik^T,    Cx_k = mean_i H_i,k+1 C_ik H_ik^T
    """
    H = sm.lin[1]
    Ht = np.swapaxes(H, -1, -2)
    Px = (H @ sm.cov @ Ht).mean(axis=0)
    Cx = (H[:, 1:] @ sm.cross @ Ht[:, :-1]).mean(axis=0)
    return 0.5 * (Px + np.swapaxes(Px, -1, -2)), Cx


def learn(task, rollouts: Rollouts, sampler, cfg: KinematicConfig) -> tuple[Rollouts, KinematicFilter, dict]:
    """``(smoothed rollouts, filter, diagnostics)`` of ``rollouts`` sampled by ``sampler`` (module docstring;
    with ``cfg.learn_on = "filtered"`` the rollouts carry the new filter's estimates instead).

    Diagnostics: ``kin_loglik_first``/``kin_loglik_last`` (EM, summed over rollouts, of the start kept),
    ``kin_start`` (``"sampler"`` or ``"data"``: the EM start kept),
    ``kin_time`` (s) and, with ``cfg.fit_moments = "posterior"``, ``posterior``
    (:func:`posterior_moments` of the smoothed states).
    """
    t0 = time.perf_counter()
    km = KinematicModel(task)
    init = None
    if cfg.warm_start and isinstance(sampler, KinematicFilteredPolicy):
        init = sampler.filter.accel()
    res = em.fit(km, rollouts.s, rollouts.a, float(task.rho2), cfg, init)
    start = "data" if init is None else "sampler"
    if init is not None and cfg.restart_from_data and float(task.rho2) > 0.0:  # (at rho^2 = 0 the states are exact)
        fresh = em.fit(km, rollouts.s, rollouts.a, float(task.rho2), cfg, None)
        if fresh.loglik[-1] > res.loglik[-1]:
            res, start = fresh, "data"
    lg = em.z_model(km, res.accel, cfg)
    filt = build_filter(km, res.accel, lg, res.smoothed.mean.mean(axis=0), float(task.rho2),
                        online=cfg.gains == "online").attach(km)
    if float(task.rho2) == 0.0:  # exact: the smoother returns the measured states (h(z(s)) = s to 1e-15)
        smoothed = rollouts
    else:
        if cfg.learn_on == "filtered":
            xs = filt.states(rollouts.s, rollouts.a)
        else:
            xs = km.measure(res.smoothed.mean, False)
        cost = np.asarray(task.cost(xs, rollouts.a))
        smoothed = dataclasses.replace(rollouts, s=xs, cost=cost, y=np.exp(-task.y_scale * cost))
    diag = {"kin_loglik_first": float(res.loglik[0]), "kin_loglik_last": float(res.loglik[-1]), "kin_start": start}
    if cfg.fit_moments == "posterior" and float(task.rho2) > 0.0 and cfg.learn_on == "smoothed":
        diag["posterior"] = posterior_moments(res.smoothed)
    diag["kin_time"] = time.perf_counter() - t0
    return smoothed, filt, diag
