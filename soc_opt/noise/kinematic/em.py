"""EM for the acceleration map of the structured model (``docs/math.md §11.2``).

E-step: the iterated extended RTS smoother (:mod:`soc_opt.noise.kinematic.smoother`).  M-step: the
acceleration ``u_k = (qd_{k+1} - qd_k) / dt`` is a linear function of ``(z_k, z_{k+1})``, so its
expected sufficient statistics against ``zeta_k = (a_k, z_k, 1)`` follow from the smoothed means
*and* covariances (``Cov(z_k)``, ``Cov(z_{k+1}, z_k)``)::

    E[zeta zeta^T] = zbar zbar^T + blockdiag(0, Cov(z_k), 0)
    E[u zeta^T]    = ubar zbar^T + [0, Cov(u_k, z_k), 0],   Cov(u_k, z_k) = (Cov(qd_{k+1}, z_k) - Cov(qd_k, z_k)) / dt
    E[u u^T]       = ubar ubar^T + Cov(u_k)

summed over rollouts and the steps of a time segment, plus ``prior_strength`` times the
time-pooled statistics per sample (a conjugate prior centred on the time-invariant map);
``[B D c] = E[u zeta^T] E[zeta zeta^T]^{-1}``, ``S`` the expected residual covariance.
With ``prior_strength = 0`` this is the exact M-step (the joint-angle rows' noise is fixed), so
with the linearisation of ``h`` held fixed the likelihood never decreases.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ...parallel import fork_map
from .config import KinematicConfig
from .model import AccelMap, KinematicModel, transition
from .rigid import rigid_body_map
from .smoother import LinearGaussianZ, Smoothed, smooth

__all__ = ["initial_map", "mstep", "EMResult", "fit", "fit_starts", "z_model", "loglik"]


def initial_map(km: KinematicModel, s, rho2: float, floor: float, start_map: str = "zero") -> AccelMap:
    """The batch's own EM start (``docs/math.md §11.2``): per-joint noise ``S = Var(d qd) / dt^2 - 2 rho2 / dt^2``
    (floored) from the second differences of the measured velocities, and ``B = D = c = 0``
    (``start_map = "zero"``) or the robot's contact-free rigid-body map linearised along the batch's
    mean measured trajectory (``"rigid_body"``, :func:`~soc_opt.noise.kinematic.rigid.rigid_body_map`)."""
    z = km.z_of(s)
    qd = z[..., km.nq:]
    dqd = np.diff(qd, axis=-2).reshape(-1, km.nq)
    var = np.maximum(dqd.var(axis=0) / km.dt ** 2 - 2.0 * rho2 / km.dt ** 2, floor)
    S = np.broadcast_to(np.diag(var), (km.T, km.nq, km.nq))
    if start_map == "rigid_body":
        return rigid_body_map(km, z[:, :km.T].mean(axis=0), S)
    return AccelMap.zero(km.T, km.nq, km.m, S)


def z_model(km: KinematicModel, accel: AccelMap, cfg: KinematicConfig) -> LinearGaussianZ:
    """The transition in ``z`` of ``accel`` from the task's start ``z_0 ~ N(z(x_0), p0 I + P_start)``, where
    ``P_start`` is the covariance of the start range of ``[process_noise] start`` in ``z`` (``r^2 / 3`` on the
    angles of ``state.joints``; :attr:`KinematicModel.start_cov`, docs/math.md §8.1), absent for a known start."""
    A, Bz, cz, Q = transition(accel, km.dt, km.c2, cfg.q_noise ** 2)
    P0 = cfg.p0 * np.eye(km.nz)
    if km.start_cov is not None:
        P0 = P0 + km.start_cov
    return LinearGaussianZ(A, Bz, cz, Q, km.z_of(km.task.x0), P0)


def _stats(sm: Smoothed, a: np.ndarray, nq: int, dt: float):
    """Per-step sums over rollouts: ``Szz (T, p, p)``, ``Suz (T, nq, p)``, ``Suu (T, nq, nq)``."""
    ms, Ps, X = sm.mean, sm.cov, sm.cross
    M, T1, nz = ms.shape
    T, m = T1 - 1, a.shape[-1]
    v = slice(nq, nz)
    ub = (ms[:, 1:, v] - ms[:, :-1, v]) / dt
    Xv = X[:, :, v, v]
    Cu = (Ps[:, 1:, v, v] + Ps[:, :-1, v, v] - Xv - np.swapaxes(Xv, -1, -2)) / dt ** 2
    Cuz = (X[:, :, v, :] - Ps[:, :-1, v, :]) / dt
    zeta = np.concatenate([a, ms[:, :-1], np.ones((M, T, 1))], axis=-1)
    p = zeta.shape[-1]
    zs = slice(m, m + nz)
    Szz = np.einsum("mti,mtj->tij", zeta, zeta)
    Szz[:, zs, zs] += Ps[:, :-1].sum(0)
    Suz = np.einsum("mti,mtj->tij", ub, zeta)
    Suz[:, :, zs] += Cuz.sum(0)
    Suu = np.einsum("mti,mtj->tij", ub, ub) + Cu.sum(0)
    return Szz, Suz, Suu, p


def mstep(sm: Smoothed, a, dt: float, nq: int, segments: int, prior_strength: float, s_floor: float) -> AccelMap:
    """The acceleration map maximising the expected log-likelihood (module docstring)."""
    a = np.asarray(a, dtype=float)
    M, T, m = a.shape
    Szz, Suz, Suu, p = _stats(sm, a, nq, dt)
    seg = np.minimum((np.arange(T) * segments) // T, segments - 1)
    nseg = int(seg.max()) + 1
    Gzz = np.stack([Szz[seg == g].sum(0) for g in range(nseg)])
    Guz = np.stack([Suz[seg == g].sum(0) for g in range(nseg)])
    Guu = np.stack([Suu[seg == g].sum(0) for g in range(nseg)])
    cnt = np.array([M * np.sum(seg == g) for g in range(nseg)], dtype=float)
    if prior_strength > 0:
        w = prior_strength / (M * T)
        Gzz = Gzz + w * Szz.sum(0)
        Guz = Guz + w * Suz.sum(0)
        Guu = Guu + w * Suu.sum(0)
        cnt = cnt + prior_strength
    scale = np.einsum("gii->g", Gzz) / p
    Wt = np.linalg.solve(Gzz + 1e-10 * scale[:, None, None] * np.eye(p), np.swapaxes(Guz, 1, 2))
    W = np.swapaxes(Wt, 1, 2)                                     # (G, nq, p)
    S = (Guu - W @ np.swapaxes(Guz, 1, 2)) / cnt[:, None, None]
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    ev, V = np.linalg.eigh(S)
    S = np.einsum("gij,gj,gkj->gik", V, np.maximum(ev, s_floor), V)
    W, S = W[seg], S[seg]
    return AccelMap(W[:, :, :m], W[:, :, m:m + 2 * nq], W[:, :, -1], S)


class EMResult(NamedTuple):
    """``accel``: the fitted map; ``smoothed``: the final E-step; ``loglik``: ``log p(s | a)`` summed
    over rollouts before each M-step and after the last one (linearisation fixed), ``(em_iters + 1,)``."""

    accel: AccelMap
    smoothed: Smoothed
    loglik: np.ndarray


def fit(km: KinematicModel, s, a, rho2: float, cfg: KinematicConfig, init: AccelMap | None = None) -> EMResult:
    """EM for the acceleration map from ``init`` (default :func:`initial_map`); ``docs/math.md §11.2``.

    EKF pass, ``cfg.relin`` Gauss-Newton passes, then ``cfg.em_iters`` EM iterations with the
    linearisation held fixed (at the mean of the last Gauss-Newton pass); the returned smoothed
    moments are those of the last E-step.
    """
    s, a = np.asarray(s, dtype=float), np.asarray(a, dtype=float)
    R = rho2 * np.eye(km.n)
    accel = initial_map(km, s, rho2, cfg.s_floor, cfg.start_map) if init is None else init
    lg = z_model(km, accel, cfg)
    sm = smooth(km, lg, s, a, R)
    for _ in range(cfg.relin):
        sm = smooth(km, lg, s, a, R, sm.mean)
    ll = [float(sm.loglik.sum())]
    for _ in range(cfg.em_iters):
        accel = mstep(sm, a, km.dt, km.nq, cfg.segments, cfg.prior_strength, cfg.s_floor)
        lg = z_model(km, accel, cfg)
        sm = smooth(km, lg, s, a, R, sm.z_lin, sm.lin)
        ll.append(float(sm.loglik.sum()))
    return EMResult(accel, sm, np.array(ll))


def fit_starts(km: KinematicModel, s, a, rho2: float, cfg: KinematicConfig, inits, parallel: bool = True) -> list[EMResult]:
    """:func:`fit` from each start in ``inits`` (``None``: the batch's own initial map), in order.

    With ``parallel``, every start after the first runs in a forked child process while this one runs
    the first (:func:`soc_opt.parallel.fork_map`; in turn where forking cannot help).  Each start's
    arithmetic is the same either way, so the results are identical (tested); only the wall time differs.
    """
    s, a = np.asarray(s, dtype=float), np.asarray(a, dtype=float)
    return fork_map(lambda init: fit(km, s, a, rho2, cfg, init), list(inits), parallel)


def loglik(km: KinematicModel, accel: AccelMap, s, a, rho2: float, cfg: KinematicConfig) -> float:
    """``log p(s | a)`` of rollouts under a fixed acceleration map, summed over rollouts: the extended
    Kalman filter's prediction-error decomposition (one pass, linearised at each prediction), i.e.
    how well the filter of ``accel`` predicts these measurements (``docs/math.md §11.2``)."""
    s, a = np.asarray(s, dtype=float), np.asarray(a, dtype=float)
    return float(smooth(km, z_model(km, accel, cfg), s, a, rho2 * np.eye(km.n)).loglik.sum())
