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
The filter and the RTS pass are those of the Gaussian core (:func:`soc_opt.lgssm.rts_smoother`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ... import lgssm
from ...models import ShapeError

__all__ = ["Smoothed", "smooth", "LinearGaussianZ"]

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
    zl = np.empty((M, T1, nz))
    linearize = None
    if z_lin is None:  # extended filter: linearise at each step's prediction
        def linearize(k, mu):
            zl[:, k] = mu
            hx, H = km.measure(mu)
            hx_all[:, k], H_all[:, k] = hx, H
            return H, hx - np.einsum("mij,mj->mi", H, mu)
        H_lin, d_lin = np.zeros((T1, n, nz)), np.zeros((T1, n))  # replaced step by step
    else:
        zl[:] = z_lin
        H_lin, d_lin = H_all, hx_all - np.einsum("mkij,mkj->mki", H_all, z_lin)
    params = lgssm.Params(lgssm.Initial(lg.z0, lg.P0), lgssm.Dynamics(lg.A, np.einsum("mtj,tij->mti", a, lg.Bz) + lg.cz, lg.Q),
                          lgssm.Emissions(H_lin, d_lin, np.broadcast_to(R, (T1, n, n))))
    post = lgssm.rts_smoother(params, s, linearize)
    return Smoothed(post.smoothed_means, post.smoothed_covariances, post.smoothed_cross_covariances, post.marginal_loglik,
                    zl, (hx_all, H_all))
