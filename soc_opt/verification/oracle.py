"""The E-step's oracle (docs/math.md §4): brute-force conditioning of the joint Gaussian of
``(s_0..s_T, y_0..y_{T-1})`` on ``Y``, built straight from the augmented model and the policy with
the action kept explicit (so it shares no formula with ``estep.closed_loop``), and the scale-free
distance of a smoother's output to it.

Every variable is an affine map of independent noises ``(x0, w_0, eo_0, ..., w_{T-1}, eo_{T-1})``:
``s_0 = mu0 + x0``, ``a_k = K_k s_k + k_k + w_k``, ``zeta_k = Ao_k (s_k, a_k) + co_k + eo_k`` with
``x0 ~ N(0, P0)``, ``w_k ~ N(0, Sigma_k)``, ``eo_k ~ N(0, So_k)``.  Dense numpy, for small ``T``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag

from ..models import AugmentedModel, LinearGaussianPolicy, symmetrize

__all__ = ["DensePosterior", "dense_posterior", "SmootherErrors", "smoother_errors"]

_LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class DensePosterior:
    """``E[s_t | Y]`` (T+1, n), ``Cov(s_t | Y)`` (T+1, n, n), ``Cov(s_{t+1}, s_t | Y)`` (T, n, n), ``log p(Y)``."""

    mean: np.ndarray
    cov: np.ndarray
    cross: np.ndarray
    loglik: float


def _joint(model: AugmentedModel, policy: LinearGaussianPolicy, mu0, P0):
    n, m, T = model.n, model.m, model.T
    d = n + T * (m + n + 1)
    W = block_diag(np.asarray(P0, dtype=float), *[block_diag(policy.cov[t], model.So[t]) for t in range(T)])
    s_mean = np.asarray(mu0, dtype=float).copy()
    s_map = np.zeros((n, d))
    s_map[:, :n] = np.eye(n)
    means, maps, y_means, y_maps = [s_mean], [s_map], [], []
    for t in range(T):
        off = n + t * (m + n + 1)
        a_mean = policy.K[t] @ s_mean + policy.k[t]
        a_map = policy.K[t] @ s_map
        a_map[:, off: off + m] += np.eye(m)
        A, B = model.Ao[t][:, :n], model.Ao[t][:, n:]
        z_mean = A @ s_mean + B @ a_mean + model.co[t]
        z_map = A @ s_map + B @ a_map
        z_map[:, off + m: off + m + n + 1] += np.eye(n + 1)
        s_mean, s_map = z_mean[:n], z_map[:n]
        y_means.append(z_mean[n])
        y_maps.append(z_map[n])
        means.append(s_mean)
        maps.append(s_map)
    mean = np.concatenate(means + [np.array(y_means)])
    L = np.vstack(maps + [np.array(y_maps).reshape(T, d)])
    return mean, symmetrize(L @ W @ L.T)


def dense_posterior(model: AugmentedModel, policy: LinearGaussianPolicy, y, mu0, P0) -> DensePosterior:
    """The posterior of the states given one sequence ``y (T,)`` by dense conditioning (docs/math.md §4)."""
    n, T = model.n, model.T
    mean, cov = _joint(model, policy, mu0, P0)
    ns = (T + 1) * n
    Css, Csy, Cyy = cov[:ns, :ns], cov[:ns, ns:], cov[ns:, ns:]
    r = np.asarray(y, dtype=float) - mean[ns:]
    Ly = np.linalg.cholesky(Cyy)
    u = np.linalg.solve(Ly, r)
    V = np.linalg.solve(Ly, Csy.T)  # Ly^-1 Cys
    post_mean = (mean[:ns] + V.T @ u).reshape(T + 1, n)
    post = symmetrize(Css - V.T @ V)
    loglik = float(-0.5 * (T * _LOG_2PI + 2.0 * np.log(np.diagonal(Ly)).sum() + u @ u))
    blk = lambda i, j: post[i * n:(i + 1) * n, j * n:(j + 1) * n]  # noqa: E731
    cov_t = np.stack([blk(t, t) for t in range(T + 1)])
    cross = np.stack([blk(t + 1, t) for t in range(T)]) if T else np.zeros((0, n, n))
    return DensePosterior(post_mean, cov_t, cross, loglik)


@dataclass(frozen=True)
class SmootherErrors:
    """Distances of a smoother's output to the dense posterior, each free of the state's units.

    mean:   max_t ||L_t^-1 (s_hat_t - m_t)||               (``P_t|T = L_t L_t^T`` of the oracle)
    cov:    max_t ||L_t^-1 (P_t - P*_t) L_t^-T||_2
    cross:  max_t ||L_{t+1}^-1 (C_t - C*_t) L_t^-T||_2      (``C_t = Cov(s_{t+1}, s_t | Y)``)
    loglik: |log p(Y) - log p*(Y)| / max(1, |log p*(Y)|)  (``Y`` is not rescaled with the state)
    """

    mean: float
    cov: float
    cross: float
    loglik: float

    @property
    def worst(self) -> float:
        return max(self.mean, self.cov, self.cross, self.loglik)


def smoother_errors(smoothed, oracle: DensePosterior) -> SmootherErrors:
    """:class:`SmootherErrors` of one smoothed sequence (``Smoothed`` fields without a batch axis).

    Whitening by the oracle's own ``P_t|T`` makes every error relative to the posterior's size in each
    direction, so rescaling the state (or the action) does not move the verdict; it needs
    ``P_t|T > 0`` (the standing hypotheses, :mod:`soc_opt.verification.hypotheses`).
    """
    L = np.linalg.cholesky(oracle.cov)
    white = lambda X, i, j: np.linalg.solve(L[i], np.linalg.solve(L[j], X.T).T)  # noqa: E731  L_i^-1 X L_j^-T
    T = oracle.cross.shape[0]
    e_mean = max(float(np.linalg.norm(np.linalg.solve(L[t], np.asarray(smoothed.mean)[t] - oracle.mean[t])))
                 for t in range(T + 1))
    e_cov = max(float(np.linalg.norm(white(np.asarray(smoothed.cov)[t] - oracle.cov[t], t, t), 2))
                for t in range(T + 1))
    e_cross = max((float(np.linalg.norm(white(np.asarray(smoothed.cross)[t] - oracle.cross[t], t + 1, t), 2))
                   for t in range(T)), default=0.0)
    e_ll = abs(float(smoothed.loglik) - oracle.loglik) / max(1.0, abs(oracle.loglik))
    return SmootherErrors(e_mean, e_cov, e_cross, e_ll)
