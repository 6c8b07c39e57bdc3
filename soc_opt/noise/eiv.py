"""Errors in variables: the local dynamics by maximum likelihood with the states latent (docs/math.md §13.1).

Regressing ``s_{k+1}`` on ``(s_k, a_k)`` attributes the sensor noise to the process: the residual
covariance estimates about ``W + R + A R A^T`` and the slopes are attenuated.  With the states as
latent variables (``x_{k+1} = A_k x_k + B_k a_k + c_k + w_k``, ``s_k = x_k + eps_k``, ``R`` known)
EM attributes each to its source (Shumway and Stoffer)::

    E-step   the RTS smoother of x under the current model (per sequence means, shared covariances)
    M-step   [A B c]_k = E[x_{k+1} z_k^T] E[z_k z_k^T]^{-1},  z_k = (x_k, a_k, 1)
             W_k       = E[(x_{k+1} - [A B c]_k z_k)(...)^T]

with the expected sufficient statistics pooled over the rollouts and the step's normal-inverse-Wishart
prior folded in as pseudo-data (docs/math.md §2), so the fit is maximum a posteriori.  For a plant
without process noise the maximiser has ``W -> 0``, where plain EM crawls (its rate tends to one as
``W`` does: ``docs/noise.md`` §8); :func:`eiv_fit` therefore extrapolates EM's steps (SQUAREM,
Varadhan and Roland 2008): from ``theta_0`` two EM steps give ``r = theta_1 - theta_0`` and
``v = theta_2 - 2 theta_1 + theta_0``; with ``alpha = -|r| / |v|`` (capped at ``-1``) the point
``theta_0 - 2 alpha r + alpha^2 v`` is stabilised by one more EM step and kept only if its
likelihood does not fall below ``theta_2``'s.  ``W`` is kept positive definite by an eigenvalue
floor relative to ``R`` (``w_floor``), the only place the fit is told anything about the plant.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..models import AugmentedModel, LinearGaussianDynamics, NotPositiveDefiniteError, Rollouts, symmetrize
from .estimator import kalman_filter
from .noisefit import condition_joint, smooth_states

__all__ = ["EIVFit", "eiv_fit", "smoothed_moments"]


class EIVFit(NamedTuple):
    """Result of :func:`eiv_fit`.

    model:   the fitted ``LinearGaussianDynamics`` (or ``AugmentedModel`` with the cost row)
    loglik:  ``(iterations + 1,)`` ``log p(s | a)`` summed over sequences, at the start and after each
             accepted update
    iterations: EM updates done (an accepted extrapolation counts as three: its two EM steps and the
             stabilising one)
    converged:  the relative change of ``log p(s | a)`` fell below the tolerance
    """

    model: LinearGaussianDynamics | AugmentedModel
    loglik: np.ndarray
    iterations: int
    converged: bool


def smoothed_moments(sm, rollouts: Rollouts, include_y: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-step mean ``(T, d)`` and covariance ``(T, d, d)`` of ``(x_k, a_k, x_{k+1}[, y_k])`` under the
    smoother: the sample moments of the smoothed means plus the shared posterior covariances::

        Lam[x x]   += P_k,   Lam[x' x'] += P_{k+1},   Lam[x' x] += Cov(x_{k+1}, x_k | s)
    """
    xs = sm.mean
    n, m = rollouts.n, rollouts.m
    nz = n + m
    parts = [xs[:, :-1], rollouts.a, xs[:, 1:]] + ([rollouts.y[..., None]] if include_y else [])
    X = np.concatenate(parts, axis=-1)
    mu = X.mean(axis=0)
    Xc = X - mu
    Lam = np.einsum("mti,mtj->tij", Xc, Xc) / X.shape[0]
    P, C = sm.cov[0], sm.cross[0]
    Lam[:, :n, :n] += P[:-1]
    Lam[:, nz:nz + n, nz:nz + n] += P[1:]
    Lam[:, nz:nz + n, :n] += C
    Lam[:, :n, nz:nz + n] += np.swapaxes(C, 1, 2)
    return mu, symmetrize(Lam)


def _rows(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(model, AugmentedModel):
        return model.Ao, model.co, model.So
    return np.concatenate([model.A, model.B], axis=2), model.c, model.cov


def _model(Ao, co, So, n: int, include_y: bool):
    if include_y:
        return AugmentedModel(Ao, co, So, n)
    return LinearGaussianDynamics(Ao[:, :, :n], Ao[:, :, n:], co, So)


def _floor(S: np.ndarray, floor: float) -> np.ndarray:
    ev, V = np.linalg.eigh(symmetrize(S))
    return symmetrize(np.einsum("...ij,...j,...kj->...ik", V, np.maximum(ev, floor), V))


class _Problem(NamedTuple):
    rollouts: Rollouts
    n: int
    nz: int
    R: np.ndarray
    mu0: np.ndarray
    P0: np.ndarray
    prior: tuple[np.ndarray, np.ndarray] | None  # NIW centre (T, d) and covariance (T, d, d)
    k0: float
    n0: float
    lam: float  # ridge on the (x, a) block
    min_eig: float
    w_floor: float
    include_y: bool


def _estep(p: _Problem, theta):
    Ao, co, So = theta
    n = p.n
    W = _floor(So[:, :n, :n], p.w_floor)
    kf = kalman_filter(LinearGaussianDynamics(Ao[:, :n, :n], Ao[:, :n, n:], co[:, :n], W), p.R, p.mu0, p.P0)
    return smooth_states(kf, p.rollouts.s, p.rollouts.a)


def _mstep(p: _Problem, sm):
    mu, Lam = smoothed_moments(sm, p.rollouts, p.include_y)
    M = p.rollouts.M
    if p.prior is not None:
        d = mu - p.prior[0]
        mu = (p.k0 * p.prior[0] + M * mu) / (p.k0 + M)
        Lam = (p.n0 * p.prior[1] + M * Lam + (p.k0 * M / (p.k0 + M)) * np.einsum("ti,tj->tij", d, d)) / (M + p.n0)
    Lam = symmetrize(Lam)
    idx = np.arange(p.nz)
    Lam[:, idx, idx] += p.lam
    return condition_joint(mu, Lam, p.nz, p.min_eig)


def _em(p: _Problem, theta):
    """One EM update from ``theta``: ``(new theta, log p(s | a) of theta)``."""
    sm = _estep(p, theta)
    return _mstep(p, sm), float(sm.loglik.sum())


def _loglik(p: _Problem, theta) -> float:
    return float(_estep(p, theta).loglik.sum())


def _extrapolate(p: _Problem, t0, t1, t2):
    """The SQUAREM point from three EM iterates (module docstring), or ``None`` when they coincide."""
    r = [b - a for a, b in zip(t0, t1)]
    v = [c - 2 * b + a for a, b, c in zip(t0, t1, t2)]
    nr = np.sqrt(sum(float(np.sum(x * x)) for x in r))
    nv = np.sqrt(sum(float(np.sum(x * x)) for x in v))
    if not (nv > 0 and np.isfinite(nv) and np.isfinite(nr)):
        return None
    alpha = min(-nr / nv, -1.0)
    Ao, co, So = (a - 2 * alpha * ri + alpha * alpha * vi for a, ri, vi in zip(t0, r, v))
    return Ao, co, _floor(So, p.w_floor)


def eiv_fit(rollouts: Rollouts, start, R, mu0, P0, *, prior=None, k0: float = 1.0, n0: float = 1.0,
            reg: float = 1e-6, min_eig: float = 1e-9, w_floor: float = 1e-6, max_iter: int = 100,
            tol: float = 1e-7, accelerate: bool = True) -> EIVFit:
    """Maximum a posteriori local dynamics with latent states, from the model ``start`` (module docstring).

    ``rollouts``: the *measured* batch (``s (M, T+1, n)``, ``a``; ``y`` for an augmented ``start``);
    ``start``: a ``LinearGaussianDynamics`` (fits the dynamics) or ``AugmentedModel`` (also the cost row);
    ``R (n, n)``: the sensor noise; ``mu0, P0``: the true start's distribution (the smoother's prior);
    ``prior``: the per-step NIW ``(centre (T, d), covariance (T, d, d))`` over ``(x_k, a_k, x_{k+1}[, y_k])``
    with counts ``k0``, ``n0`` (``None``: none); ``reg``: ridge on the ``(x, a)`` block relative to the
    batch's mean variance of ``(s, a)``; ``w_floor``: eigenvalue floor of ``W`` relative to the mean
    eigenvalue of ``R``; stops when ``log p(s | a)`` changes by less than ``tol`` relative, or after
    ``max_iter`` EM updates.  ``accelerate``: SQUAREM extrapolation (plain EM otherwise).
    """
    include_y = isinstance(start, AugmentedModel)
    n, m = rollouts.n, rollouts.m
    nz = n + m
    z = np.concatenate([rollouts.s[:, :-1], rollouts.a], axis=-1).reshape(-1, nz)
    scale = float(z.var(axis=0).mean())
    lam = reg * (scale if scale > 0 and np.isfinite(scale) else 1.0)
    R = np.asarray(R, dtype=float)
    floor = max(w_floor * float(np.trace(R)) / n, 1e-12)
    p = _Problem(rollouts, n, nz, R, np.asarray(mu0, float), np.asarray(P0, float), prior, k0, n0, lam, min_eig,
                 floor, include_y)
    Ao, co, So = _rows(start)
    theta = (Ao, co, _floor(So, floor))
    history: list[float] = []
    iters, converged = 0, False
    while iters < max_iter:
        t1, ll0 = _em(p, theta)            # EM(theta), and log p(s | a) at theta
        iters += 1
        if history and abs(ll0 - history[-1]) <= tol * max(abs(ll0), 1.0):
            history.append(ll0)
            converged = True
            break
        history.append(ll0)
        nxt = t1
        if accelerate and iters + 2 <= max_iter:
            t2, ll1 = _em(p, t1)           # EM(EM(theta)), and log p(s | a) at t1
            iters += 1
            nxt = t2
            cand = _extrapolate(p, theta, t1, t2)
            if cand is not None:
                try:
                    t3, llc = _em(p, cand)  # EM(cand), and log p(s | a) at cand
                except (np.linalg.LinAlgError, NotPositiveDefiniteError, FloatingPointError):
                    t3, llc = None, -np.inf  # an extrapolation too far: keep the EM step
                iters += 1
                if np.isfinite(llc) and llc >= ll1:
                    nxt = t3
        theta = nxt
    else:
        history.append(_loglik(p, theta))
    Ao, co, So = theta
    return EIVFit(_model(Ao, co, So, n, include_y), np.array(history), iters, converged)
