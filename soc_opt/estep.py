"""E-step: Kalman filter and RTS smoother on the closed loop (docs/math.md §4).

Under the current policy ``a_k = K_k s_k + k_k + L_k w_k`` the action is
integrated out of the augmented model (docs/math.md §1), giving the closed loop

    zeta_k = (s_{k+1}, y_k) | s_k ~ N(M_k s_k + m_k, S_k),
    M_k = As_k + Bs_k K_k,  m_k = Bs_k k_k + co_k,  S_k = So_k + Bs_k Sigma_k Bs_k^T,

with ``As_k = [A_k; Ay_k]`` and ``Bs_k = [B_k; By_k]``.  The noise of ``s_{k+1}``
and the noise of ``y_k`` are correlated (off-diagonal block of ``S_k``); the
Gaussian core (:mod:`soc_opt.lgssm`) treats this exactly by decorrelation.  The filter and
smoother are the core's one entry point each (:func:`soc_opt.lgssm.kalman_filter`,
:func:`soc_opt.lgssm.rts_smoother`) on :func:`params`, the closed loop as an ``lgssm.Params``;
the functions below are adapters from ``(model, policy, y, mu0, P0)`` to them (inputs checked once,
one sequence without the ``M`` axis).

Also the sufficient statistics (:class:`Moments`) the M-step consumes.

Public functions:
    closed_loop(model, policy)                       -> (Mk, mk, Sk)
    params(model, policy, mu0, P0)                   -> lgssm.Params
    kalman_filter(model, policy, y, mu0, P0)         -> lgssm.Filtered      (adapter)
    smooth(model, policy, y, mu0, P0)                -> Smoothed            (adapter)
    log_likelihood(model, policy, y, mu0, P0)        -> float | (M,)        (adapter)
    moments(smoothed, y)                             -> Moments
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import lgssm
from .models import (
    AugmentedModel,
    LinearGaussianPolicy,
    ShapeError,
    Smoothed,
    check_array,
    check_covariances,
    symmetrize,
)

__all__ = [
    "Moments",
    "closed_loop",
    "kalman_filter",
    "log_likelihood",
    "moments",
    "params",
    "smooth",
]

# --------------------------------------------------------------------------- closed loop


def _check_pair(model: AugmentedModel, policy: LinearGaussianPolicy) -> None:
    """Type and dimension consistency of a model and a policy (errors name both)."""
    if not isinstance(model, AugmentedModel):
        raise TypeError(f"model must be an AugmentedModel, got {type(model).__name__}")
    if not isinstance(policy, LinearGaussianPolicy):
        raise TypeError(f"policy must be a LinearGaussianPolicy, got {type(policy).__name__}")
    for what, pv, mv in (("horizon T", policy.T, model.T), ("state dimension n", policy.n, model.n),
                         ("action dimension m", policy.m, model.m)):
        if pv != mv:
            raise ShapeError(f"policy {what}={pv} does not match model {what}={mv}")


def closed_loop(model: AugmentedModel, policy: LinearGaussianPolicy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-loop augmented model ``zeta_k | s_k ~ N(M_k s_k + m_k, S_k)`` (docs/math.md §4).

    Returns:
        Mk: (T, n+1, n)    ``As_k + Bs_k K_k``
        mk: (T, n+1)       ``Bs_k k_k + co_k``
        Sk: (T, n+1, n+1)  ``So_k + Bs_k Sigma_k Bs_k^T`` (symmetrised; positive definite
                           because ``So_k`` is, even for a singular policy covariance).
    """
    _check_pair(model, policy)
    return _closed_loop(model, policy)


def _closed_loop(model: AugmentedModel, policy: LinearGaussianPolicy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`closed_loop` of a pair already checked (batched products over the ``T`` steps)."""
    Bs = model.Bs
    Mk = model.As + Bs @ policy.K
    mk = (Bs @ policy.k[:, :, None])[:, :, 0] + model.co
    Sk = symmetrize(model.So + Bs @ policy.cov @ np.swapaxes(Bs, 1, 2))
    return Mk, mk, Sk


# --------------------------------------------------------------------------- validation


def _validate(model, policy, y, mu0, P0) -> tuple[np.ndarray, bool, np.ndarray, np.ndarray]:
    """Check all E-step inputs once; return ``(Y (M, T), batched, mu0, P0)``."""
    _check_pair(model, policy)
    T, n = model.T, model.n
    y_arr = np.asarray(y, dtype=float)
    if y_arr.ndim == 1:
        Y = check_array("y", y_arr, (T,))[None]
        batched = False
    elif y_arr.ndim == 2:
        Y = check_array("y", y_arr, (None, T))
        if Y.shape[0] == 0:
            raise ShapeError(f"y must hold at least one sequence, got shape {Y.shape}")
        batched = True
    else:
        raise ShapeError(f"y must have shape ({T},) or (M, {T}), got {y_arr.shape}")
    mu0 = check_array("mu0", mu0, (n,))
    P0 = check_covariances("P0", check_array("P0", P0, (n, n)))
    return Y, batched, mu0, P0


# --------------------------------------------------------------------------- filter


def params(model: AugmentedModel, policy: LinearGaussianPolicy, mu0, P0) -> lgssm.Params:
    """The closed loop (:func:`closed_loop`) as the Gaussian core's model (:mod:`soc_opt.lgssm`).

    State rows ``s_{k+1} = Ms_k s_k + ms_k + e_s``, observation row ``y_k = My_k s_k + my_k + e_y``,
    ``Cov(e_s, e_y) = S_sy`` (correlated noise), ``z_0 ~ N(mu0, P0)``; ``s_T`` is not observed.
    """
    _check_pair(model, policy)
    return _params(model, policy, mu0, P0)


def _params(model: AugmentedModel, policy: LinearGaussianPolicy, mu0, P0) -> lgssm.Params:
    """:func:`params` of inputs already checked (:func:`_validate`, the one check of the E-step's entry points)."""
    n = model.n
    Mk, mk, Sk = _closed_loop(model, policy)
    return lgssm.Params(lgssm.Initial(mu0, P0), lgssm.Dynamics(Mk[:, :n], mk[:, :n], Sk[:, :n, :n]),
                        lgssm.Emissions(Mk[:, n:], mk[:, n:], Sk[:, n:, n:]), Sk[:, :n, n:])


def _unbatch(x: np.ndarray, batched: bool, M: int, shared: bool = False) -> np.ndarray:
    """Shape an output: ``shared`` arrays (no ``M`` axis) are broadcast read-only when batched."""
    if shared:
        return np.broadcast_to(x, (M,) + x.shape) if batched else x
    return x if batched else x[0]


def kalman_filter(model: AugmentedModel, policy: LinearGaussianPolicy, y, mu0, P0) -> lgssm.Filtered:
    """:func:`soc_opt.lgssm.kalman_filter` on the closed loop (:func:`params`, docs/math.md §4).

    An adapter: checks ``(model, policy, y, mu0, P0)`` once, runs the Gaussian core's one filter on
    :func:`params` (correlated ``s_{k+1}``/``y_k`` noise removed by decorrelation, lgssm's module
    docstring, step 1) and returns its :class:`~soc_opt.lgssm.Filtered`.  ``y`` is ``(T,)`` or
    ``(M, T)``; for ``(T,)`` the fields have no ``M`` axis and ``marginal_loglik`` is a float, for
    ``(M, T)`` the covariances (which do not depend on ``y``) are read-only broadcast views.
    ``predicted_means[T]`` is ``E[s_T | Y]`` (``s_T`` is not observed).
    """
    Y, batched, mu0, P0 = _validate(model, policy, y, mu0, P0)
    fp = lgssm.kalman_filter(_params(model, policy, mu0, P0), Y[:, :, None])
    M = Y.shape[0]
    return lgssm.Filtered(
        predicted_means=_unbatch(fp.predicted_means, batched, M),
        predicted_covariances=_unbatch(fp.predicted_covariances, batched, M, shared=True),
        filtered_means=_unbatch(fp.filtered_means, batched, M),
        filtered_covariances=_unbatch(fp.filtered_covariances, batched, M, shared=True),
        marginal_loglik=fp.marginal_loglik if batched else float(fp.marginal_loglik[0]),
    )


def log_likelihood(model: AugmentedModel, policy: LinearGaussianPolicy, y, mu0, P0) -> float | np.ndarray:
    """``log p(Y)`` under the closed loop (:func:`kalman_filter`'s ``marginal_loglik``): a float, or
    ``(M,)`` for ``y (M, T)``."""
    return kalman_filter(model, policy, y, mu0, P0).marginal_loglik


# --------------------------------------------------------------------------- smoother


def smooth(model: AugmentedModel, policy: LinearGaussianPolicy, y, mu0, P0) -> Smoothed:
    """:func:`soc_opt.lgssm.rts_smoother` on the closed loop (:func:`params`, docs/math.md §4).

    An adapter, as :func:`kalman_filter`: the Gaussian core's Kalman filter and RTS smoother (lgssm's
    module docstring, steps 1-4) on :func:`params`, returned as the :class:`~soc_opt.models.Smoothed`
    the M-step takes (:func:`moments`).

    Args:
        model: the augmented model :class:`~soc_opt.models.AugmentedModel` of
            ``zeta_k = (s_{k+1}, y_k)`` given ``(s_k, a_k)`` (docs/math.md §1), horizon ``T``, state size ``n``.
        policy: the :class:`~soc_opt.models.LinearGaussianPolicy` closing the loop,
            ``K (T, m, n)``, ``k (T, m)``, ``cov (T, m, m)``.
        y: the cost observations ``y_0..y_{T-1}``: ``(T,)`` for one sequence or ``(M, T)`` for
            ``M`` sequences smoothed at once.
        mu0: ``(n,)`` mean of the initial state ``s_0``.
        P0: ``(n, n)`` covariance of ``s_0`` (positive definite).

    Returns :class:`~soc_opt.models.Smoothed` (``mean``, ``cov``, ``cross = Cov(s_{k+1}, s_k | Y)``,
    ``loglik = log p(Y)``); for ``y (M, T)`` every field has a leading ``M`` axis (covariances are
    read-only broadcast views: they do not depend on ``y``).
    Raises :class:`~soc_opt.models.ShapeError` for inconsistent shapes and
    :class:`~soc_opt.models.NotPositiveDefiniteError` when a predicted covariance is not
    positive definite.
    """
    Y, batched, mu0, P0 = _validate(model, policy, y, mu0, P0)
    post = lgssm.rts_smoother(_params(model, policy, mu0, P0), Y[:, :, None])
    M = Y.shape[0]
    return Smoothed(
        mean=_unbatch(post.smoothed_means, batched, M),
        cov=_unbatch(post.smoothed_covariances, batched, M, shared=True),
        cross=_unbatch(post.smoothed_cross_covariances, batched, M, shared=True),
        loglik=post.marginal_loglik if batched else float(post.marginal_loglik[0]),
    )


# --------------------------------------------------------------------------- moments


@dataclass(frozen=True)
class Moments:
    """Smoothed second moments per step, averaged over observation sequences (docs/math.md §5).

    With ``zeta_k = (s_{k+1}, y_k)`` and ``stilde_k = (s_k, 1)``:
        Szz: (T, n+1, n+1)  E[zeta_k zeta_k^T | Y]
        Szs: (T, n+1, n+1)  E[zeta_k stilde_k^T | Y]
        Sss: (T, n+1, n+1)  E[stilde_k stilde_k^T | Y]   (``G_k`` and ``s_hat_k`` blocks, 1 in the corner)
        count: number of sequences averaged.
    """

    Szz: np.ndarray
    Szs: np.ndarray
    Sss: np.ndarray
    count: int = 1

    @property
    def T(self) -> int:
        return self.Szz.shape[0]

    @property
    def n(self) -> int:
        return self.Szz.shape[1] - 1


def moments(smoothed: Smoothed, y: np.ndarray) -> Moments:
    """Sufficient statistics of the M-step from smoothed moments and observations ``y``.

    ``y`` is ``(T,)`` for one sequence or ``(M, T)`` matching a batched ``smoothed``;
    statistics are averaged over the ``M`` sequences.
    """
    mean, cov, cross = smoothed.mean, smoothed.cov, smoothed.cross
    if mean.ndim == 2:
        mean, cov, cross = mean[None], cov[None], cross[None]
    M, T1, n = mean.shape
    T = T1 - 1
    y = check_array("y", np.atleast_2d(y), (M, T))
    mu_k, mu_k1 = mean[:, :-1], mean[:, 1:]
    G = cov + np.einsum("mti,mtj->mtij", mean, mean)  # E[s s^T], (M, T+1, n, n)
    C = cross + np.einsum("mti,mtj->mtij", mu_k1, mu_k)  # E[s_{k+1} s_k^T], (M, T, n, n)

    Szz = np.zeros((M, T, n + 1, n + 1))
    Szz[:, :, :n, :n] = G[:, 1:]
    Szz[:, :, :n, n] = y[..., None] * mu_k1
    Szz[:, :, n, :n] = y[..., None] * mu_k1
    Szz[:, :, n, n] = y**2

    Szs = np.zeros((M, T, n + 1, n + 1))
    Szs[:, :, :n, :n] = C
    Szs[:, :, :n, n] = mu_k1
    Szs[:, :, n, :n] = y[..., None] * mu_k
    Szs[:, :, n, n] = y

    Sss = np.zeros((M, T, n + 1, n + 1))
    Sss[:, :, :n, :n] = G[:, :-1]
    Sss[:, :, :n, n] = mu_k
    Sss[:, :, n, :n] = mu_k
    Sss[:, :, n, n] = 1.0

    return Moments(symmetrize(Szz.mean(0)), Szs.mean(0), symmetrize(Sss.mean(0)), count=M)
