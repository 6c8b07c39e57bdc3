"""The kinematic estimator in the learning loop (``docs/math.md §11.3``).

One call per batch of rollouts: EM for the acceleration map (from the sampling policy's filter's map
and from the batch's own initial map; ``warm_start`` and ``restart_from_data`` choose the starts,
``start_select`` how the two are compared: the likelihood of the previous batch, held out, or of
this one; ``filter_start`` which of them the online filter is built from), the rollouts with ``s``
replaced by the smoothed states ``h(E[z_k | s, a])`` and their costs recomputed on them (what the
paper's fit, prior and cost expansion then learn from), and the online filter the next policy acts
on (exact ``h`` through MuJoCo, gains linearised along the mean smoothed trajectory).  Uses the
robot's kinematics, not its masses, inertia or damping.
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


def learn(task, rollouts: Rollouts, sampler, cfg: KinematicConfig,
          previous: Rollouts | None = None) -> tuple[Rollouts, KinematicFilter, dict]:
    """``(smoothed rollouts, filter, diagnostics)`` of ``rollouts`` sampled by ``sampler`` (module docstring;
    with ``cfg.learn_on = "filtered"`` the rollouts carry the new filter's estimates instead).
    ``previous``: the batch before (the one ``sampler``'s filter was learned from, drawn under other
    gains and another filter); with ``cfg.start_select = "previous"`` the two EM starts' maps are
    compared by their likelihood of it (:func:`~soc_opt.noise.kinematic.em.loglik`), else, or when
    there is none, by their final likelihood of this batch; ``"data"`` keeps the batch's own start.

    Diagnostics: ``kin_loglik_first``/``kin_loglik_last`` (EM, summed over rollouts, of the start kept),
    ``kin_start`` (``"sampler"`` or ``"data"``: the EM start kept), ``kin_heldout_sampler`` and
    ``kin_heldout_data`` (the two maps' likelihood of ``previous``, when compared on it),
    ``kin_filter_start`` (the EM run the filter was built from),
    ``kin_time`` (s) and, with ``cfg.fit_moments = "posterior"``, ``posterior``
    (:func:`posterior_moments` of the smoothed states).
    """
    t0 = time.perf_counter()
    km = KinematicModel(task)
    init = None
    if cfg.warm_start and isinstance(sampler, KinematicFilteredPolicy):
        init = sampler.filter.accel()
    rho2 = float(task.rho2)
    restart = init is not None and cfg.restart_from_data and rho2 > 0.0  # (at rho^2 = 0 the states are exact)
    runs = em.fit_starts(km, rollouts.s, rollouts.a, rho2, cfg, [init, None] if restart else [init],
                         cfg.parallel_starts)
    res = runs[0]
    from_sampler = res if init is not None else None
    start = "data" if init is None else "sampler"
    diag = {}
    if restart:
        fresh = runs[1]
        if cfg.start_select == "data":
            better = True
        elif cfg.start_select == "previous" and previous is not None:
            held = [em.loglik(km, r.accel, previous.s, previous.a, rho2, cfg) for r in (res, fresh)]
            diag.update(kin_heldout_sampler=held[0], kin_heldout_data=held[1])
            better = held[1] > held[0]
        else:
            better = fresh.loglik[-1] > res.loglik[-1]
        if better:
            res, start = fresh, "data"
    fres = from_sampler if cfg.filter_start == "sampler" and from_sampler is not None else res
    filt = build_filter(km, fres.accel, em.z_model(km, fres.accel, cfg), fres.smoothed.mean.mean(axis=0), rho2,
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
    diag.update(kin_loglik_first=float(res.loglik[0]), kin_loglik_last=float(res.loglik[-1]), kin_start=start,
                kin_filter_start="sampler" if fres is from_sampler else start)
    if cfg.fit_moments == "posterior" and float(task.rho2) > 0.0 and cfg.learn_on == "smoothed":
        diag["posterior"] = posterior_moments(res.smoothed)
    diag["kin_time"] = time.perf_counter() - t0
    return smoothed, filt, diag
