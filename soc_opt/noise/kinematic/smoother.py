"""Iterated extended Kalman / RTS smoother of the structured model, vectorised over rollouts
(``docs/math.md §11.2``).

Given measurements ``s (M, T+1, n)`` and actions ``a (M, T, m)``, the transition of
:func:`soc_opt.noise.kinematic.model.transition` (linear in ``z``) and the measurement
``s = h(z) + eps``, ``eps ~ N(0, R)``, linearised per rollout and step around ``z_lin``
(``s ~ h(z_lin) + H (z - z_lin) + eps``):

* ``z_lin = None``: an extended Kalman filter that linearises at each step's prediction, followed
  by the RTS pass (the first pass, before any smoothed mean exists);
* ``z_lin`` given: the Kalman filter and RTS smoother of the model linearised there (one
  Gauss-Newton pass of the iterated smoother; call again with the new mean to iterate).

``R = 0`` (``rho^2 = 0``) is exact: ``z`` is read off the measurements with zero covariance.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...models import ShapeError

__all__ = ["Smoothed", "smooth", "LinearGaussianZ"]

_LOG_2PI = math.log(2.0 * math.pi)


class LinearGaussianZ(NamedTuple):
    """The transition in ``z``: ``A (T, nz, nz)``, ``Bz (T, nz, m)``, ``cz (T, nz)``, ``Q (T, nz, nz)``;
    the start ``z0 (nz,)``, ``P0 (nz, nz)``."""

    A: np.ndarray
    Bz: np.ndarray
    cz: np.ndarray
    Q: np.ndarray
    z0: np.ndarray
    P0: np.ndarray


class Smoothed(NamedTuple):
    """Smoother output for ``M`` rollouts.

    Fields:
        mean:   (M, T+1, nz)     ``E[z_k | s, a]``
        cov:    (M, T+1, nz, nz) ``Cov(z_k | s, a)``
        cross:  (M, T, nz, nz)   ``Cov(z_{k+1}, z_k | s, a)``
        loglik: (M,)             ``log p(s | a)`` of the linearised model (0 when ``R = 0``)
        z_lin:  (M, T+1, nz)     the linearisation points used
        lin:    ``(h(z_lin) (M, T+1, n), H(z_lin) (M, T+1, n, nz))``
    """

    mean: np.ndarray
    cov: np.ndarray
    cross: np.ndarray
    loglik: np.ndarray
    z_lin: np.ndarray
    lin: tuple


def _sym(P):
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def _exact(km, s) -> Smoothed:
    z = km.z_of(s)
    M, T1, nz = z.shape
    return Smoothed(z, np.zeros((M, T1, nz, nz)), np.zeros((M, T1 - 1, nz, nz)), np.zeros(M), z, (None, None))


def smooth(km, lg: LinearGaussianZ, s, a, R, z_lin=None, lin=None) -> Smoothed:
    """One pass of the (iterated) extended RTS smoother (module docstring); ``km`` a
    :class:`~soc_opt.noise.kinematic.model.KinematicModel`, ``R (n, n)`` the measurement noise.
    ``lin = (h(z_lin), H(z_lin))`` may be passed to reuse a linearisation (EM with it fixed)."""
    s, a = np.asarray(s, dtype=float), np.asarray(a, dtype=float)
    M, T1, n = s.shape
    T, nz = T1 - 1, km.nz
    if n != km.n or a.shape != (M, T, km.m) or lg.A.shape != (T, nz, nz):
        raise ShapeError(f"smoother: s {s.shape}, a {a.shape} and transition A {lg.A.shape} do not match "
                         f"(n, m, nz) = ({km.n}, {km.m}, {nz})")
    R = np.asarray(R, dtype=float)
    if not np.any(R):
        return _exact(km, s)
    if z_lin is not None:
        z_lin = np.asarray(z_lin, dtype=float)
        if z_lin.shape != (M, T1, nz):
            raise ShapeError(f"smoother: z_lin must have shape {(M, T1, nz)}, got {z_lin.shape}")
        hx_all, H_all = km.measure(z_lin) if lin is None else lin
    else:
        hx_all, H_all = np.empty((M, T1, n)), np.empty((M, T1, n, nz))
    r2 = float(R[0, 0])
    if not np.allclose(R, r2 * np.eye(n)):
        raise ValueError("the kinematic smoother needs R = rho2 I")
    mf = np.empty((M, T1, nz))
    Pf = np.empty((M, T1, nz, nz))
    mp = np.empty((M, T1, nz))
    Pp = np.empty((M, T1, nz, nz))
    Lp = np.empty((M, T1, nz, nz))                                # inverse predicted covariances
    zl = np.empty((M, T1, nz))
    ll = np.full(M, -0.5 * T1 * n * (_LOG_2PI + math.log(r2)))
    mu, P = np.broadcast_to(lg.z0, (M, nz)).copy(), np.broadcast_to(lg.P0, (M, nz, nz)).copy()
    for k in range(T1):
        if k > 0:
            mu = mf[:, k - 1] @ lg.A[k - 1].T + a[:, k - 1] @ lg.Bz[k - 1].T + lg.cz[k - 1]
            P = _sym(lg.A[k - 1] @ Pf[:, k - 1] @ lg.A[k - 1].T + lg.Q[k - 1])
        mp[:, k], Pp[:, k] = mu, P
        if z_lin is None:
            zl[:, k] = mu
            hx, H = km.measure(mu)
            hx_all[:, k], H_all[:, k] = hx, H
        else:
            zl[:, k] = z_lin[:, k]
            hx, H = hx_all[:, k], H_all[:, k]
        nu = s[:, k] - hx - np.einsum("mij,mj->mi", H, mu - zl[:, k])
        Ht = np.swapaxes(H, 1, 2)
        Lprior = _sym(np.linalg.inv(P))
        Lp[:, k] = Lprior
        Pk = _sym(np.linalg.inv(Lprior + Ht @ H / r2))
        g = np.einsum("mij,mj->mi", Ht, nu) / r2                 # H^T R^-1 nu
        Pg = np.einsum("mij,mj->mi", Pk, g)
        mf[:, k] = mu + Pg
        Pf[:, k] = Pk
        # log N(nu; 0, H P H^T + R) by the determinant lemma and Woodbury
        ld = np.linalg.slogdet(P)[1] - np.linalg.slogdet(Pk)[1]
        ll -= 0.5 * (ld + (nu * nu).sum(-1) / r2 - (g * Pg).sum(-1))
    ms, Ps = mf.copy(), Pf.copy()
    cross = np.empty((M, T, nz, nz))
    for k in range(T - 1, -1, -1):
        J = Pf[:, k] @ lg.A[k].T @ Lp[:, k + 1]                   # P_k A^T (P^-_{k+1})^{-1}
        Jt = np.swapaxes(J, 1, 2)
        ms[:, k] = mf[:, k] + np.einsum("mij,mj->mi", J, ms[:, k + 1] - mp[:, k + 1])
        Ps[:, k] = _sym(Pf[:, k] + J @ (Ps[:, k + 1] - Pp[:, k + 1]) @ Jt)
        cross[:, k] = Ps[:, k + 1] @ Jt
    return Smoothed(ms, Ps, cross, ll, zl, (hx_all, H_all))
