"""Dynamics fitting from noisy measurements (docs/math.md §10.1; math in ``docs/noise.md`` §7–8).

Model: ``x_{k+1} = A_k x_k + B_k a_k + c_k + w_k``, ``s_k = x_k + eps_k``, ``eps_k ~ N(0, R)`` with
``R`` known.  Regressing ``s_{k+1}`` on ``z_k = (s_k, a_k)`` is biased (errors in variables, and
``Cov(eps_k, a_k) = X_k != 0`` under feedback).  Two estimators:

* **Bias-corrected regression** (:func:`corrected_fit`, :func:`correct_joint`):
  ``[A B] = Cov(s', z) (Cov(z) - E)^{-1}`` with ``E = [[R, X], [0, 0]]``,
  ``Cov(zt) = Cov(z) - [[R, X], [X^T, 0]]`` kept PD by a reliability floor,
  ``W = Cov(s') - R - [A B] Cov(zt) [A B]^T`` (floored).  :func:`correct_joint` applies the
  correction to joint tuple moments ``(mu, Lambda)`` of ``(s_k, a_k, s_{k+1}[, y_k])`` (the form the
  NIW posterior of docs/math.md §2 takes), returning the moments of the true tuple
  ``(x_k, a_k, x_{k+1}[, y_k])``, so that the usual conditioning gives the corrected model.
* **SSM-EM** (:func:`ssm_em`): maximum likelihood of the linear-Gaussian state-space model with
  latent ``x`` and known ``R`` by EM; E-step :func:`smooth_states` (the RTS smoother of the Gaussian
  core :mod:`soc_opt.lgssm`), M-step closed-form per step.

Public functions:
    noise_action_cov(R, K, G=None)            -> X (T, n, m)
    estimate_noise_action_cov(s, a, R)        -> X (T, n, m)  (sampler acting on s)
    sample_moments(s, a, y=None)              -> (mu (T, d), Lam (T, d, d))
    correct_joint(mu, Lam, n, m, R, X, ...)   -> CorrectedMoments
    condition_joint(mu, Lam, nz, min_eig)     -> (Ao, co, So)
    naive_fit(s, a, config)                   -> LinearGaussianDynamics
    corrected_fit(s, a, R, X, config)         -> LinearGaussianDynamics
    smooth_states(kf, s, a)                   -> Smoothed  (batched, covariances shared)
    ssm_em(s, a, R, config, X=None, init=None) -> SSMFit
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .. import lgssm
from ..config import Config, Interval
from ..linalg import T as _T
from ..linalg import cho_solve, chol, right_cho_solve, tri_solve
from ..models import LinearGaussianDynamics, ShapeError, Smoothed, check_array, symmetrize
from .estimator import check_noise_covariance, filter_pass, kalman_filter

__all__ = [
    "NoiseFitConfig",
    "CorrectedMoments",
    "SSMFit",
    "noise_action_cov",
    "estimate_noise_action_cov",
    "sample_moments",
    "correct_joint",
    "condition_joint",
    "naive_fit",
    "corrected_fit",
    "smooth_states",
    "ssm_em",
]

_ABS_EIG_FLOOR = 1e-12


@dataclass(frozen=True)
class NoiseFitConfig(Config):
    """Hyperparameters of the noise-aware fits (docs/math.md §10.1, ``docs/noise.md`` §7–8).

    Fields (defaults in brackets):
        min_reliability: floor of the reliabilities ``1 - mu_i`` (generalised eigenvalues of
                         ``Cov(z) - D`` relative to ``Cov(z)``) that keeps ``Cov(zt)`` PD [0.05].
        min_eig:         relative eigenvalue floor of the fitted noise covariance (times the mean
                         diagonal of the ``zeta`` block), as in ``FitConfig.min_eig`` [1e-9].
        em_max_iter:     maximum SSM-EM iterations [500].
        em_tol:          SSM-EM stops when ``log p(s | a)`` increases by less than ``em_tol`` per
                         sequence and time step [1e-8].
        em_initial:      SSM-EM also estimates the initial-state prior ``(mu0, P0)`` [true].
    """

    min_reliability: float = 0.05
    min_eig: float = 1e-9
    em_max_iter: int = 500
    em_tol: float = 1e-8
    em_initial: bool = True

    _constraints = {
        "min_reliability": [Interval(0.0, 1.0, "right")],
        "min_eig": [Interval(0, None, "neither")],
        "em_max_iter": [Interval(1)],
        "em_tol": [Interval(0)],
    }


# --------------------------------------------------------------------------- inputs


def _check_data(s, a, min_M: int = 2) -> tuple[np.ndarray, np.ndarray]:
    s = np.asarray(s, dtype=float)
    if s.ndim != 3:
        raise ShapeError(f"measured states s must have shape (M, T+1, n), got {s.shape}")
    M, T1, n = s.shape
    if T1 < 2:
        raise ShapeError(f"measured states s need at least two time steps (T+1 >= 2), got shape {s.shape}")
    a = np.asarray(a, dtype=float)
    if a.ndim != 3:
        raise ShapeError(f"actions a must have shape (M, T, m) = ({M}, {T1 - 1}, m), got {a.shape}")
    s = check_array("measured states s", s, (M, T1, n))
    a = check_array("actions a", a, (M, T1 - 1, a.shape[2]))
    if M < min_M:
        raise ValueError(f"fitting needs at least {min_M} rollouts, got M={M}")
    return s, a


def noise_action_cov(R, K, G=None) -> np.ndarray:
    """``X_k = Cov(eps_k, a_k)`` of the sampling policy: ``R K_k^T``, or ``R G_k^T K_k^T`` when it acts
    on the filtered state with gains ``G`` (``(T+1, n, n)`` or ``(T, n, n)``; ``G_k`` for ``k < T`` used).

    ``K`` is ``(T, m, n)`` (the policy that *sampled* the data).  Returns ``(T, n, m)``.
    """
    K = np.asarray(K, dtype=float)
    if K.ndim != 3:
        raise ShapeError(f"sampling policy gains K must have shape (T, m, n), got {K.shape}")
    T, m, n = K.shape
    K = check_array("sampling policy gains K", K, (T, m, n))
    R = check_noise_covariance("measurement noise R", R, (n, n))
    if G is None:
        return R @ _T(K)
    G = np.asarray(G, dtype=float)
    if G.ndim != 3 or G.shape[0] not in (T, T + 1) or G.shape[1:] != (n, n):
        raise ShapeError(f"filter gains G must have shape ({T + 1}, {n}, {n}) or ({T}, {n}, {n}), got {G.shape}")
    G = check_array("filter gains G", G, G.shape)
    return R @ _T(G[:T]) @ _T(K)


def estimate_noise_action_cov(s, a, R) -> np.ndarray:
    """``X_k = R K_k^T`` with ``K_k`` the regression of ``a_k`` on ``(s_k, 1)``.

    Consistent for a sampler acting on ``s`` (``a_k = K_k s_k + k_k + noise``, noise independent of
    ``s_k``); not for one acting on a filtered state (use :func:`noise_action_cov` with its gains).
    """
    s, a = _check_data(s, a)
    M, T1, n = s.shape
    T = T1 - 1
    if M <= n + 1:
        raise ValueError(f"estimating the sampling gains needs more than n+1={n + 1} rollouts, got M={M}")
    R = check_noise_covariance("measurement noise R", R, (n, n))
    sk = s[:, :T] - s[:, :T].mean(0)
    ak = a - a.mean(0)
    Css = np.einsum("mti,mtj->tij", sk, sk) / M
    Cas = np.einsum("mti,mtj->tij", ak, sk) / M
    K = right_cho_solve(Cas, chol(Css, "Cov(s_k)"))
    return R @ _T(K)


# --------------------------------------------------------------------------- moments and correction


def sample_moments(s, a, y=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-step mean ``(T, d)`` and covariance ``(T, d, d)`` (``1/M``) of ``(s_k, a_k, s_{k+1}[, y_k])``."""
    s, a = _check_data(s, a)
    parts = [s[:, :-1], a, s[:, 1:]]
    if y is not None:
        parts.append(check_array("observed costs y", y, a.shape[:2])[..., None])
    X = np.concatenate(parts, axis=-1)
    mu = X.mean(0)
    Xc = X - mu
    return mu, symmetrize(np.einsum("mti,mtj->tij", Xc, Xc) / X.shape[0])


class CorrectedMoments(NamedTuple):
    """Output of :func:`correct_joint`.

    Fields:
        mean:        (T, d)      means (unchanged: ``E[x] = E[s]``)
        cov:         (T, d, d)   joint covariance of ``(x_k, a_k, x_{k+1}[, y_k])``
        reliability: (T, n+m)    generalised eigenvalues ``1 - mu_i`` before flooring (ascending)
        floored:     (T,)        number of directions floored at ``min_reliability`` per step
    """

    mean: np.ndarray
    cov: np.ndarray
    reliability: np.ndarray
    floored: np.ndarray


def correct_joint(mu, Lam, n: int, m: int, R, X, *, min_reliability: float = 0.05) -> CorrectedMoments:
    """Remove the measurement noise from joint tuple moments (docs/math.md §10.1, ``docs/noise.md`` §7).

    ``mu (T, d)``, ``Lam (T, d, d)`` are moments (empirical or NIW posterior) of
    ``(s_k, a_k, s_{k+1}[, y_k])`` with ``d = 2n+m`` or ``2n+m+1``; ``R (n, n)``; ``X (T, n, m)``
    the noise-action covariance of the sampler (:func:`noise_action_cov`).  Returns the moments of
    ``(x_k, a_k, x_{k+1}[, y_k])``: ``Cov(zt) = Lam_zz - [[R, X], [X^T, 0]]`` (reliability floor),
    ``Cov(zeta, zt) = Ao Cov(zt)`` with ``Ao = Lam_{zeta z} (Cov(zt) + [[0, 0], [X^T, 0]])^{-1}``,
    ``Cov(x_{k+1}) = Lam_{s's'} - R``; the ``y`` rows are corrected like the state rows.
    """
    mu = np.asarray(mu, dtype=float)
    if mu.ndim != 2 or mu.shape[1] not in (2 * n + m, 2 * n + m + 1):
        raise ShapeError(f"tuple mean mu must have shape (T, 2n+m[+1]) = (T, {2 * n + m}[+1]), got {mu.shape}")
    T, d = mu.shape
    mu = check_array("tuple mean mu", mu, (T, d))
    Lam = check_array("tuple covariance Lam", Lam, (T, d, d))
    R = check_noise_covariance("measurement noise R", R, (n, n))
    X = check_array("noise-action covariance X", X, (T, n, m))
    if not 0.0 < min_reliability <= 1.0:
        raise ValueError(f"min_reliability must be in (0, 1], got {min_reliability!r}")
    nz = n + m
    Czz = symmetrize(Lam[:, :nz, :nz])
    D = np.zeros((T, nz, nz))
    D[:, :n, :n] = R
    D[:, :n, n:] = X
    D[:, n:, :n] = _T(X)
    L = chol(Czz, "observed covariance of (s_k, a_k)")
    Mrel = symmetrize(tri_solve(L, _T(tri_solve(L, D))))  # L^{-1} D L^{-T}
    mu_e, V = np.linalg.eigh(Mrel)
    rel = 1.0 - mu_e[:, ::-1]  # ascending reliabilities
    r = np.maximum(1.0 - mu_e, min_reliability)
    LV = L @ V
    Czt = symmetrize(np.einsum("tij,tj,tkj->tik", LV, r, LV))
    U = np.zeros((T, nz, nz))
    U[:, n:, :n] = _T(X)
    Ao = _T(np.linalg.solve(_T(Czt + U), Lam[:, :nz, nz:]))  # Cov(zeta, z) Cov(zt, z)^{-1}
    out = Lam.copy()
    out[:, :nz, :nz] = Czt
    cross = Ao @ Czt
    out[:, nz:, :nz] = cross
    out[:, :nz, nz:] = _T(cross)
    out[:, nz : nz + n, nz : nz + n] -= R
    floored = np.sum(1.0 - mu_e < min_reliability, axis=1)
    return CorrectedMoments(mu.copy(), symmetrize(out), rel, floored)


def condition_joint(mu, Lam, nz: int, min_eig: float = 1e-9):
    """Condition ``N(mu, Lam)`` on its first ``nz`` coordinates -> ``(Ao (T, dy, nz), co (T, dy), So (T, dy, dy))``.

    Cholesky solve of the leading block; ``So`` symmetrised and its eigenvalues floored at
    ``max(min_eig * |mean diag Lam_yy|, 1e-12)`` (the rule of ``soc_opt.learning.fit``).
    """
    L = chol(Lam[:, :nz, :nz], "covariance of the regressors (x_k, a_k)")
    Szy = Lam[:, :nz, nz:]
    Ao = _T(cho_solve(L, Szy))
    co = mu[:, nz:] - np.einsum("tij,tj->ti", Ao, mu[:, :nz])
    Syy = Lam[:, nz:, nz:]
    So = symmetrize(Syy - Ao @ Szy)
    dy = So.shape[-1]
    floor = np.maximum(min_eig * np.abs(np.trace(Syy, axis1=1, axis2=2)) / dy, _ABS_EIG_FLOOR)
    ev, V = np.linalg.eigh(So)
    ev = np.maximum(ev, floor[:, None])
    return Ao, co, symmetrize(np.einsum("tij,tj,tkj->tik", V, ev, V))


def _to_dynamics(Ao, co, So, n: int) -> LinearGaussianDynamics:
    return LinearGaussianDynamics(Ao[:, :n, :n], Ao[:, :n, n:], co[:, :n], So[:, :n, :n])


def naive_fit(s, a, config: NoiseFitConfig = NoiseFitConfig()) -> LinearGaussianDynamics:
    """Plain per-step least squares of ``s_{k+1}`` on ``(s_k, a_k, 1)`` (the biased baseline)."""
    mu, Lam = sample_moments(s, a)
    n, m = s.shape[2], a.shape[2]
    return _to_dynamics(*condition_joint(mu, Lam, n + m, config.min_eig), n)


def corrected_fit(s, a, R, X, config: NoiseFitConfig = NoiseFitConfig()) -> LinearGaussianDynamics:
    """Bias-corrected per-step regression (docs/math.md §10.1): ``x_{k+1} ~ N(A x + B a + c, W)``.

    ``s (M, T+1, n)``, ``a (M, T, m)``, ``R (n, n)``, ``X (T, n, m)`` from :func:`noise_action_cov`
    (or :func:`estimate_noise_action_cov`).
    """
    mu, Lam = sample_moments(s, a)
    n, m = s.shape[2], a.shape[2]
    cm = correct_joint(mu, Lam, n, m, R, X, min_reliability=config.min_reliability)
    return _to_dynamics(*condition_joint(cm.mean, cm.cov, n + m, config.min_eig), n)


# --------------------------------------------------------------------------- SSM-EM


def smooth_states(kf, s, a) -> Smoothed:
    """RTS smoother of the latent ``x`` given ``s (M, T+1, n)`` and known actions ``a (M, T, m)``.

    The Gaussian core (:func:`soc_opt.lgssm.rts_smoother`) on the filter's model: dynamics
    ``(A_k, B_k a_k + c_k, W_k)``, emissions ``s_k = x_k + eps_k``, ``eps_k ~ N(0, R)``, prior
    ``(mu0, P0)``.  Returns :class:`~soc_opt.models.Smoothed` with a leading ``M`` axis; ``cov`` and
    ``cross`` are read-only broadcast views (shared by all sequences) and ``loglik`` is
    ``log p(s | a)`` per sequence.
    """
    s = np.asarray(s, dtype=float)
    s3, a3 = (s, np.asarray(a, dtype=float)) if s.ndim == 3 else (s[None], np.asarray(a, dtype=float)[None])
    T, n = kf.T, kf.n
    s3 = check_array("measurements s", s3, (s3.shape[0], T + 1, n))
    a3 = check_array("actions a", a3, (s3.shape[0], T, kf.m))
    eye = np.broadcast_to(np.eye(n), (T + 1, n, n))
    params = lgssm.Params(lgssm.Initial(kf.mu0, kf.P0), lgssm.Dynamics(kf.A, np.einsum("mtj,tij->mti", a3, kf.B) + kf.c, kf.W),
                          lgssm.Emissions(eye, np.zeros((T + 1, n)), np.broadcast_to(kf.R, (T + 1, n, n))))
    post = lgssm.rts_smoother(params, s3)
    M = s3.shape[0]
    return Smoothed(
        mean=post.smoothed_means,
        cov=np.broadcast_to(post.smoothed_covariances, (M,) + post.smoothed_covariances.shape),
        cross=np.broadcast_to(post.smoothed_cross_covariances, (M,) + post.smoothed_cross_covariances.shape),
        loglik=post.marginal_loglik,
    )


class SSMFit(NamedTuple):
    """Output of :func:`ssm_em`.

    Fields:
        dynamics:  LinearGaussianDynamics ``(A, B, c, W)`` of the latent state
        mu0:       (n,)    initial-state mean
        P0:        (n, n)  initial-state covariance
        loglik:    (n_iter+1,) ``sum over sequences of log p(s | a)`` before each M-step and at the end
        n_iter:    EM iterations done
        converged: whether the ``em_tol`` criterion was met
    """

    dynamics: LinearGaussianDynamics
    mu0: np.ndarray
    P0: np.ndarray
    loglik: np.ndarray
    n_iter: int
    converged: bool


def _psd_floor(S: np.ndarray, floor: float) -> np.ndarray:
    ev, V = np.linalg.eigh(symmetrize(S))
    return symmetrize((V * np.maximum(ev, floor)) @ V.T)


def _m_step(sm: Smoothed, a: np.ndarray, min_eig: float):
    """Closed-form ``(A, B, c, W)`` per step from smoothed moments (``docs/noise.md`` §8)."""
    xs = sm.mean
    Ps, cross = sm.cov[0], sm.cross[0]
    M, T1, n = xs.shape
    T, m = T1 - 1, a.shape[2]
    ones = np.ones((M, T, 1))
    zt = np.concatenate([xs[:, :T], a, ones], axis=-1)  # (M, T, n+m+1)
    Ezz = np.einsum("mti,mtj->tij", zt, zt) / M
    Ezz[:, :n, :n] += Ps[:T]
    Exz = np.einsum("mti,mtj->tij", xs[:, 1:], zt) / M
    Exz[:, :, :n] += cross
    Exx = np.einsum("mti,mtj->tij", xs[:, 1:], xs[:, 1:]) / M + Ps[1:]
    F = right_cho_solve(Exz, chol(symmetrize(Ezz), "smoothed second moment of (x_k, a_k, 1)"))
    W = symmetrize(Exx - F @ _T(Exz))
    Cx = Exx - np.einsum("ti,tj->tij", xs[:, 1:].mean(0), xs[:, 1:].mean(0))
    floor = np.maximum(min_eig * np.abs(np.trace(Cx, axis1=1, axis2=2)) / n, _ABS_EIG_FLOOR)
    W = np.stack([_psd_floor(W[k], floor[k]) for k in range(T)])
    return LinearGaussianDynamics(F[:, :, :n], F[:, :, n : n + m], F[:, :, n + m], W)


def _em_start(dyn: LinearGaussianDynamics) -> LinearGaussianDynamics:
    """Starting point of EM: ``W_k`` eigenvalues floored at half their mean.

    ``W = 0`` is a fixed point of EM (the smoother then ties ``x_{k+1}`` to the model exactly and the
    M-step returns ``W = 0`` again), and near it EM moves in proportion to ``W``; a corrected fit with
    a sampling-noise-floored ``W`` would start EM in that trap.  Steps whose ``W`` has no positive mean
    eigenvalue are left as they are.
    """
    W = dyn.cov.copy()
    n = dyn.n
    for k in range(dyn.T):
        mean_ev = np.trace(W[k]) / n
        if mean_ev > 0:
            W[k] = _psd_floor(W[k], 0.5 * mean_ev)
    return LinearGaussianDynamics(dyn.A, dyn.B, dyn.c, W)


def ssm_em(s, a, R, config: NoiseFitConfig = NoiseFitConfig(), *, X=None,
           init: LinearGaussianDynamics | None = None, mu0=None, P0=None) -> SSMFit:
    """EM for the linear-Gaussian state-space model with latent ``x`` and known ``R`` (docs/math.md §10.1).

    Start: ``init``, else :func:`corrected_fit` when the sampler's ``X`` is given, else
    :func:`naive_fit`, with the eigenvalues of each ``W_k`` floored at half their mean (``W = 0`` is
    a fixed point of EM); ``mu0 = mean(s_0)``, ``P0 = Cov(s_0) - R`` projected to PSD unless given.
    Each iteration: E-step :func:`smooth_states`, M-step closed form (and ``mu0, P0`` when
    ``config.em_initial``).  ``log p(s | a)`` never decreases (up to the floors).
    """
    s, a = _check_data(s, a, min_M=2)
    M, T1, n = s.shape
    T, m = T1 - 1, a.shape[2]
    R = check_noise_covariance("measurement noise R", R, (n, n))
    if init is not None:
        if not isinstance(init, LinearGaussianDynamics):
            raise TypeError(f"init must be a LinearGaussianDynamics, got {type(init).__name__}")
        if (init.T, init.n, init.m) != (T, n, m):
            raise ShapeError(f"init has (T, n, m) = {(init.T, init.n, init.m)} but the data have {(T, n, m)}")
        dyn = init
    elif X is not None:
        dyn = corrected_fit(s, a, R, X, config)
    else:
        dyn = naive_fit(s, a, config)
    dyn = _em_start(dyn)
    s0 = s[:, 0]
    mu0 = s0.mean(0) if mu0 is None else check_array("initial mean mu0", mu0, (n,))
    if P0 is None:
        C0 = (s0 - s0.mean(0)).T @ (s0 - s0.mean(0)) / M
        P0 = _psd_floor(C0 - R, 0.0)
    P0 = check_noise_covariance("initial covariance P0", P0, (n, n))
    history = []
    converged = False
    it = 0
    for it in range(1, config.em_max_iter + 1):
        kf = kalman_filter(dyn, R, mu0, P0)
        sm = smooth_states(kf, s, a)
        history.append(float(sm.loglik.sum()))
        if len(history) > 1 and history[-1] - history[-2] < config.em_tol * M * T1:
            converged = True
            it -= 1
            break
        dyn = _m_step(sm, a, config.min_eig)
        if config.em_initial:
            x0 = sm.mean[:, 0]
            mu0 = x0.mean(0)
            spread = (x0 - mu0).T @ (x0 - mu0) / M
            P0 = _psd_floor(sm.cov[0, 0] + spread, 0.0)
    else:
        kf = kalman_filter(dyn, R, mu0, P0)
        history.append(float(filter_pass(kf, s, a).loglik.sum()))
    return SSMFit(dyn, np.asarray(mu0), np.asarray(P0), np.array(history), it, converged)
