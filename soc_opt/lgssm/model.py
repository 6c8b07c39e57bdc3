"""The Gaussian core's parameter bundles and results (docs/math.md §4; :mod:`soc_opt.lgssm`'s module
docstring gives the model and the shape conventions)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Initial", "Dynamics", "Emissions", "Params", "Filtered", "Posterior"]


class Initial(NamedTuple):
    """``z_0 ~ N(mean, cov)``: mean ``(n,)`` or ``(M, n)``; cov ``(n, n)`` or ``(M, n, n)``."""

    mean: np.ndarray
    cov: np.ndarray


class Dynamics(NamedTuple):
    """``z_{k+1} = F_k z_k + b_k + w_k``, ``w_k ~ N(0, Q_k)``, ``k = 0..T-1``.

    Fields:
        weights: (T, n, n) or (M, T, n, n)  ``F_k``
        bias:    (T, n) or (M, T, n)        ``b_k``
        cov:     (T, n, n) or (M, T, n, n)  ``Q_k`` (positive semidefinite)
    """

    weights: np.ndarray
    bias: np.ndarray
    cov: np.ndarray


class Emissions(NamedTuple):
    """``y_k = H_k z_k + d_k + v_k``, ``v_k ~ N(0, R_k)``, ``k = 0..K-1`` with ``K = T`` or ``T+1``.

    Fields:
        weights: (K, p, n) or (M, K, p, n)  ``H_k``
        bias:    (K, p) or (M, K, p)        ``d_k``
        cov:     (K, p, p) or (M, K, p, p)  ``R_k`` (positive definite where ``C_k != 0``)
    """

    weights: np.ndarray
    bias: np.ndarray
    cov: np.ndarray


class Params(NamedTuple):
    """A linear-Gaussian state-space model (module docstring).

    Fields:
        initial:   :class:`Initial`
        dynamics:  :class:`Dynamics`
        emissions: :class:`Emissions`
        noise_cross_cov: (T, n, p) or (M, T, n, p) ``C_k = Cov(w_k, v_k)``, or ``None`` (independent noises)
    """

    initial: Initial
    dynamics: Dynamics
    emissions: Emissions
    noise_cross_cov: np.ndarray | None = None


class Filtered(NamedTuple):
    """Output of :func:`kalman_filter`; ``*`` is ``()`` when the covariances are shared, ``(M,)`` otherwise.

    Fields:
        predicted_means:       (M, T+1, n)     ``m_k = E[z_k | y_0..y_{k-1}]`` (``m_0 = mu0``)
        predicted_covariances: (*, T+1, n, n)  ``P_k = Cov(z_k | y_0..y_{k-1})``
        filtered_means:        (M, K, n)       ``E[z_k | y_0..y_k]``
        filtered_covariances:  (*, K, n, n)    ``Cov(z_k | y_0..y_k)``
        marginal_loglik:       (M,)            ``log p(y_0..y_{K-1})``

    The names are dynamax's (``PosteriorGSSMFiltered``).
    """

    predicted_means: np.ndarray
    predicted_covariances: np.ndarray
    filtered_means: np.ndarray
    filtered_covariances: np.ndarray
    marginal_loglik: np.ndarray


class Posterior(NamedTuple):
    """Output of :func:`rts_smoother`; ``*`` as in :class:`Filtered`.

    Fields:
        smoothed_means:             (M, T+1, n)     ``E[z_k | Y]``
        smoothed_covariances:       (*, T+1, n, n)  ``Cov(z_k | Y)``
        smoothed_cross_covariances: (*, T, n, n)    ``Cov(z_{k+1}, z_k | Y)``
        marginal_loglik:            (M,)            ``log p(Y)``

    The names are dynamax's (``PosteriorGSSMSmoothed``).
    """

    smoothed_means: np.ndarray
    smoothed_covariances: np.ndarray
    smoothed_cross_covariances: np.ndarray
    marginal_loglik: np.ndarray
