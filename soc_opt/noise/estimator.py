"""State estimator in the loop: time-varying Kalman filter and the filtered closed loop (docs/math.md §10.2).

Model (docs/math.md §10): ``x_{k+1} = A_k x_k + B_k a_k + c_k + w_k``, ``w_k ~ N(0, W_k)``;
``s_k = x_k + eps_k``, ``eps_k ~ N(0, R)``; ``x_0 ~ N(mu0, P0)``.  The filter
(``docs/noise.md`` §2)::

    xhat^-_0 = mu0, P^-_0 = P0;   xhat^-_k = A xhat_{k-1} + B a_{k-1} + c,  P^-_k = A P_{k-1} A^T + W
    S_k = P^-_k + R,  G_k = P^-_k S_k^{-1},  xhat_k = xhat^-_k + G_k (s_k - xhat^-_k),
    P_k = (I - G_k) P^-_k (I - G_k)^T + G_k R G_k^T

The gains do not depend on data, so a filtered policy is ``(K, k, Sigma)`` acting on ``xhat``
plus its :class:`KalmanFilter`.  In innovation form ``xhat`` is a Markov linear-Gaussian process
(:func:`innovation_dynamics`), the cost on the true state is the cost on ``xhat`` plus
``1/2 tr(C_xx P_k)`` (:func:`cost_correction`), and the augmented model of docs/math.md §1 carries over
with a modified noise covariance (:func:`innovation_augmented`).

Public functions:
    measurement_noise(rho2, n)                         -> R (n, n)
    kalman_filter(dynamics, R, mu0, P0)                -> KalmanFilter
    filter_step(kf, k, s_k, xhat_prev, a_prev)         -> xhat_k      (online, causal, batched)
    filter_states(kf, s, a)                            -> xhat (..., T+1, n)
    filter_pass(kf, s, a)                              -> FilterPass (means, predictions, log p(s | a))
    innovation_dynamics(kf)                            -> LinearGaussianDynamics in xhat
    initial_estimate(kf)                               -> (mean (n,), cov (n, n)) of xhat_0
    cost_correction(kf, cost)                          -> (T,)
    filtered_cost(kf, cost)                            -> QuadraticCost in (xhat, a)
    innovation_augmented(model, kf)                    -> AugmentedModel in xhat
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..linalg import T as _T
from ..linalg import chol, right_cho_solve, tr, tri_solve
from ..models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    QuadraticCost,
    ShapeError,
    check_array,
    check_covariances,
    symmetrize,
)

__all__ = [
    "KalmanFilter",
    "FilteredPolicy",
    "FilterPass",
    "measurement_noise",
    "check_noise_covariance",
    "kalman_filter",
    "filter_step",
    "filter_states",
    "filter_pass",
    "innovation_dynamics",
    "initial_estimate",
    "cost_correction",
    "filtered_cost",
    "innovation_augmented",
]

_LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------- inputs


def measurement_noise(rho2, n: int) -> np.ndarray:
    """``R = rho2 I`` (docs/math.md §10); ``ValueError`` naming ``rho2`` if it is negative or not finite."""
    try:
        r = float(rho2)
    except (TypeError, ValueError):
        raise ValueError(f"rho2 (measurement noise variance) must be a number, got {rho2!r}") from None
    if not math.isfinite(r) or r < 0:
        raise ValueError(f"rho2 (measurement noise variance) must be finite and >= 0, got {rho2!r}")
    if int(n) < 1:
        raise ValueError(f"state dimension n must be >= 1, got {n!r}")
    return r * np.eye(int(n))


def check_noise_covariance(name: str, S, shape: tuple) -> np.ndarray:
    """A covariance (or stack) of the given shape that is symmetric positive semidefinite.

    Raises :class:`ShapeError` / :class:`NotPositiveDefiniteError` naming ``name`` (and the step
    of a stack).
    """
    S = check_array(name, S, shape)
    return check_covariances(name, S, psd_only=True)


# --------------------------------------------------------------------------- filter


@dataclass(frozen=True)
class KalmanFilter:
    """A time-varying Kalman filter and its data-independent gains (docs/math.md §10.2).

    The filter's model:
        A:   (T, n, n), B: (T, n, m), c: (T, n), W: (T, n, n)   ``x_{k+1} = A x + B a + c + w``
        R:   (n, n)      measurement noise covariance
        mu0: (n,), P0: (n, n)   prior of ``x_0``
    Gains and covariances for ``k = 0..T``:
        G:      (T+1, n, n)  Kalman gains ``G_k = P^-_k S_k^{-1}``
        P:      (T+1, n, n)  ``P_k = Cov(x_k | s_0..s_k)``
        P_pred: (T+1, n, n)  ``P^-_k = Cov(x_k | s_0..s_{k-1})`` (``P^-_0 = P0``)
        S:      (T+1, n, n)  innovation covariances ``S_k = P^-_k + R`` (positive definite)

    Build it with :func:`kalman_filter`; arrays are read-only.
    """

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray
    W: np.ndarray
    R: np.ndarray
    mu0: np.ndarray
    P0: np.ndarray
    G: np.ndarray
    P: np.ndarray
    P_pred: np.ndarray
    S: np.ndarray

    def __post_init__(self):
        T, n, m = self.A.shape[0], self.A.shape[1], self.B.shape[2]
        shapes = {"A": (T, n, n), "B": (T, n, m), "c": (T, n), "W": (T, n, n), "R": (n, n), "mu0": (n,),
                  "P0": (n, n), "G": (T + 1, n, n), "P": (T + 1, n, n), "P_pred": (T + 1, n, n), "S": (T + 1, n, n)}
        for name, shape in shapes.items():
            a = check_array(f"filter {name}", getattr(self, name), shape).copy()
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def T(self) -> int:
        return self.A.shape[0]

    @property
    def n(self) -> int:
        return self.A.shape[1]

    @property
    def m(self) -> int:
        return self.B.shape[2]

    def dynamics(self) -> LinearGaussianDynamics:
        """The filter's model ``x_{k+1} ~ N(A x + B a + c, W)``."""
        return LinearGaussianDynamics(self.A, self.B, self.c, self.W)

    def to_dict(self) -> dict:
        """Model, noise, prior and gains as plain arrays (the gains are recomputed by :meth:`from_dict`)."""
        return {k: np.array(getattr(self, k)) for k in ("A", "B", "c", "W", "R", "mu0", "P0", "G", "P", "P_pred", "S")}

    @staticmethod
    def from_dict(d: dict) -> "KalmanFilter":
        """Rebuild from :meth:`to_dict` output (gains recomputed from the model, noise and prior)."""
        return kalman_filter(LinearGaussianDynamics(d["A"], d["B"], d["c"], d["W"]), d["R"], d["mu0"], d["P0"])


def kalman_filter(dynamics: LinearGaussianDynamics, R, mu0, P0) -> KalmanFilter:
    """Gains of the time-varying Kalman filter of ``dynamics`` with measurement noise ``R`` (docs/math.md §10.2).

    ``R``, ``P0`` and ``dynamics.cov`` (``W``) must be symmetric positive semidefinite and every
    innovation covariance ``S_k = P^-_k + R`` positive definite; errors name the matrix and the
    step.  The covariance update is the Joseph form ``(I - G) P^- (I - G)^T + G R G^T`` (a sum of
    PSD terms); every covariance is symmetrised.
    """
    if not isinstance(dynamics, LinearGaussianDynamics):
        raise TypeError(f"dynamics must be a LinearGaussianDynamics, got {type(dynamics).__name__}")
    T, n = dynamics.T, dynamics.n
    R = check_noise_covariance("measurement noise R", R, (n, n))
    mu0 = check_array("filter prior mu0", mu0, (n,))
    P0 = check_noise_covariance("filter prior P0", P0, (n, n))
    A, W = dynamics.A, dynamics.cov
    eye = np.eye(n)
    G = np.empty((T + 1, n, n))
    P = np.empty((T + 1, n, n))
    Pm = np.empty((T + 1, n, n))
    S = np.empty((T + 1, n, n))
    Pm[0] = P0
    for k in range(T + 1):
        if k > 0:
            Pm[k] = symmetrize(A[k - 1] @ P[k - 1] @ A[k - 1].T + W[k - 1])
        S[k] = symmetrize(Pm[k] + R)
        try:
            L = chol(S[k], f"innovation covariance S[{k}] = P^-[{k}] + R")
        except NotPositiveDefiniteError as e:
            raise NotPositiveDefiniteError(
                f"{e}; the predicted covariance P^-[{k}] and the measurement noise R are both singular "
                "in a common direction (give R > 0, or W > 0 and P0 > 0)"
            ) from None
        G[k] = right_cho_solve(Pm[k], L)
        IG = eye - G[k]
        P[k] = symmetrize(IG @ Pm[k] @ IG.T + G[k] @ R @ G[k].T)
    return KalmanFilter(A=dynamics.A, B=dynamics.B, c=dynamics.c, W=W, R=R, mu0=mu0, P0=P0, G=G, P=P, P_pred=Pm, S=S)


def _check_step(kf: KalmanFilter, k: int) -> int:
    if not isinstance(kf, KalmanFilter):
        raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
    if not (isinstance(k, (int, np.integer)) and 0 <= k <= kf.T):
        raise ValueError(f"filter step k must be an integer in [0, {kf.T}], got {k!r}")
    return int(k)


def filter_step(kf: KalmanFilter, k: int, s_k, xhat_prev=None, a_prev=None) -> np.ndarray:
    """One causal filter update: ``xhat_k`` from ``s_k`` and ``(xhat_{k-1}, a_{k-1})`` (docs/math.md §10.2).

    ``s_k (..., n)``; for ``k = 0`` the prediction is ``mu0`` and ``xhat_prev``, ``a_prev`` must be
    ``None``; for ``k >= 1`` they are ``(..., n)`` and ``(..., m)`` with the same leading axes as
    ``s_k`` (one rollout, or ``M`` rollouts at once).
    """
    k = _check_step(kf, k)
    s_k = np.asarray(s_k, dtype=float)
    if s_k.ndim < 1 or s_k.shape[-1] != kf.n:
        raise ShapeError(f"measurement s_k must have shape (..., {kf.n}), got {s_k.shape}")
    lead = s_k.shape[:-1]
    if k == 0:
        if xhat_prev is not None or a_prev is not None:
            raise ValueError("filter_step at k = 0 takes no previous estimate or action (the prediction is mu0)")
        pred = np.broadcast_to(kf.mu0, s_k.shape)
    else:
        if xhat_prev is None or a_prev is None:
            raise ValueError(f"filter_step at k = {k} needs the previous estimate xhat_{k - 1} and action a_{k - 1}")
        xp = check_array(f"xhat_{k - 1}", xhat_prev, lead + (kf.n,))
        ap = check_array(f"a_{k - 1}", a_prev, lead + (kf.m,))
        pred = xp @ kf.A[k - 1].T + ap @ kf.B[k - 1].T + kf.c[k - 1]
    return pred + (s_k - pred) @ kf.G[k].T


class FilterPass(NamedTuple):
    """Output of :func:`filter_pass` for ``s (..., T+1, n)``, ``a (..., T, m)``.

    Fields:
        mean:      (..., T+1, n)  filtered estimates ``xhat_k``
        pred_mean: (..., T+1, n)  predictions ``xhat^-_k`` (``xhat^-_0 = mu0``)
        loglik:    (...,)         ``log p(s_0..s_T | a) = sum_k log N(s_k - xhat^-_k; 0, S_k)``
    """

    mean: np.ndarray
    pred_mean: np.ndarray
    loglik: np.ndarray


def _check_sequences(kf: KalmanFilter, s, a) -> tuple[np.ndarray, np.ndarray]:
    s = np.asarray(s, dtype=float)
    if s.ndim < 2:
        raise ShapeError(f"measurements s must have shape (..., T+1, n) = (..., {kf.T + 1}, {kf.n}), got {s.shape}")
    lead = s.shape[:-2]
    s = check_array("measurements s", s, lead + (kf.T + 1, kf.n))
    a = check_array("actions a", a, lead + (kf.T, kf.m))
    return s, a


def filter_pass(kf: KalmanFilter, s, a) -> FilterPass:
    """Run the filter over whole trajectories (causal: ``xhat_k`` uses ``s_0..s_k``, ``a_0..a_{k-1}``).

    Leading axes of ``s (..., T+1, n)`` and ``a (..., T, m)`` are batch axes.
    """
    s, a = _check_sequences(kf, s, a)
    T, n = kf.T, kf.n
    mean = np.empty(s.shape)
    pred = np.empty(s.shape)
    loglik = np.zeros(s.shape[:-2])
    Ls = chol(kf.S, "innovation covariance S")
    logdet = 2.0 * np.log(np.diagonal(Ls, axis1=-2, axis2=-1)).sum(-1)
    p = np.broadcast_to(kf.mu0, s.shape[:-2] + (n,))
    for k in range(T + 1):
        if k > 0:
            p = mean[..., k - 1, :] @ kf.A[k - 1].T + a[..., k - 1, :] @ kf.B[k - 1].T + kf.c[k - 1]
        nu = s[..., k, :] - p
        pred[..., k, :] = p
        mean[..., k, :] = p + nu @ kf.G[k].T
        white = tri_solve(Ls[k], nu.reshape(-1, n).T).T.reshape(nu.shape)
        loglik -= 0.5 * (n * _LOG_2PI + logdet[k] + np.sum(white * white, axis=-1))
    return FilterPass(mean, pred, loglik)


def filter_states(kf: KalmanFilter, s, a) -> np.ndarray:
    """Filtered estimates ``xhat (..., T+1, n)`` of whole trajectories (see :func:`filter_pass`)."""
    return filter_pass(kf, s, a).mean


# --------------------------------------------------------------------------- filtered policy


@dataclass(frozen=True)
class FilteredPolicy:
    """A linear-Gaussian policy acting on the filtered state, saved with its filter (docs/math.md §10.2).

    ``a_k = K_k xhat_k + k_k + L_k w_k`` with ``xhat_k`` from ``filter``.

    Fields:
        policy: LinearGaussianPolicy ``(K (T, m, n), k (T, m), cov (T, m, m))`` on ``xhat``
        filter: KalmanFilter with the same ``T, n, m``
    """

    policy: LinearGaussianPolicy
    filter: KalmanFilter

    def __post_init__(self):
        if not isinstance(self.policy, LinearGaussianPolicy):
            raise TypeError(f"policy must be a LinearGaussianPolicy, got {type(self.policy).__name__}")
        if not isinstance(self.filter, KalmanFilter):
            raise TypeError(f"filter must be a KalmanFilter, got {type(self.filter).__name__}")
        p, f = self.policy, self.filter
        if (p.T, p.n, p.m) != (f.T, f.n, f.m):
            raise ShapeError(f"policy has (T, n, m) = {(p.T, p.n, p.m)} but its filter has {(f.T, f.n, f.m)}")

    @property
    def T(self) -> int:
        return self.policy.T

    @property
    def n(self) -> int:
        return self.policy.n

    @property
    def m(self) -> int:
        return self.policy.m

    def for_task(self, task) -> "FilteredPolicy":
        """This policy as the rollouts of ``task`` run it (a Kalman filter needs nothing of the task;
        an estimator whose filter evaluates the task's model binds it here)."""
        return self

    def estimate(self, k: int, s_k, xhat_prev=None, a_prev=None) -> np.ndarray:
        """:func:`filter_step` with this policy's filter."""
        return filter_step(self.filter, k, s_k, xhat_prev, a_prev)

    def estimate_rows(self, k: int, s_k, xhat_prev=None, a_prev=None) -> np.ndarray:
        """The estimates ``(B, n)`` of ``B`` rollouts stepped together (``s_k (B, n)``, ``xhat_prev (B, n)``,
        ``a_prev (B, m)``), each row bit for bit what :meth:`estimate` gives that rollout alone (the
        MuJoCo rollouts of a filtered policy step their samples in lockstep through it).  Here one call
        of :meth:`estimate` per row; a filter whose batched step is row-independent overrides it with
        one call (:class:`~soc_opt.noise.kinematic.filter.KinematicFilteredPolicy`)."""
        s_k = np.asarray(s_k, dtype=float)
        out = np.empty(s_k.shape)
        for i in range(s_k.shape[0]):
            out[i] = self.estimate(k, s_k[i]) if k == 0 else self.estimate(k, s_k[i], xhat_prev[i], a_prev[i])
        return out

    def sample_action(self, k: int, xhat_k, rng: np.random.Generator) -> np.ndarray:
        """``a_k = K_k xhat_k + k_k + L_k w_k`` for estimates ``xhat_k (..., n)``."""
        return self.policy.sample_action(k, xhat_k, rng)

    def to_dict(self) -> dict:
        """Flat arrays: the policy's ``K, k, cov`` and the filter's fields as ``filter_<name>``.

        Flat so that ``numpy.savez(**d)`` stores plain arrays, and a reader that only knows
        ``K, k, cov`` (a plain policy file) still finds them.
        """
        return {**self.policy.to_dict(), **{f"filter_{k}": v for k, v in self.filter.to_dict().items()}}

    @staticmethod
    def from_dict(d) -> "FilteredPolicy":
        """Rebuild from :meth:`to_dict` output (or an ``npz`` file opened with ``numpy.load``)."""
        cov = np.asarray(d["cov"], dtype=float)
        singular = bool(cov.size) and bool(np.any(np.linalg.eigvalsh(cov)[..., 0] <= 0.0))
        pol = LinearGaussianPolicy(d["K"], d["k"], cov, allow_singular=singular)
        filt = KalmanFilter.from_dict({k: d[f"filter_{k}"] for k in ("A", "B", "c", "W", "R", "mu0", "P0")})
        return FilteredPolicy(pol, filt)


# --------------------------------------------------------------------------- innovation form


def innovation_dynamics(kf: KalmanFilter) -> LinearGaussianDynamics:
    """The filtered state as a Markov model: ``xhat_{k+1} ~ N(A xhat_k + B a_k + c, G S G^T)``.

    ``cov_k = G_{k+1} S_{k+1} G_{k+1}^T`` (``= P^-_{k+1} - P_{k+1}``), ``k = 0..T-1`` (docs/math.md §10.2,
    ``docs/noise.md`` §3); the KL step (docs/math.md §6) runs unchanged on it.
    """
    if not isinstance(kf, KalmanFilter):
        raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
    G = kf.G[1:]
    cov = symmetrize(G @ kf.S[1:] @ _T(G))
    return LinearGaussianDynamics(kf.A, kf.B, kf.c, cov)


def initial_estimate(kf: KalmanFilter) -> tuple[np.ndarray, np.ndarray]:
    """Distribution of ``xhat_0 = mu0 + G_0 (s_0 - mu0)`` when ``x_0 ~ N(mu0, P0)``: ``(mu0, G_0 S_0 G_0^T)``."""
    if not isinstance(kf, KalmanFilter):
        raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
    return kf.mu0.copy(), symmetrize(kf.G[0] @ kf.S[0] @ kf.G[0].T)


def _check_cost(kf: KalmanFilter, cost: QuadraticCost) -> None:
    if not isinstance(cost, QuadraticCost):
        raise TypeError(f"cost must be a QuadraticCost, got {type(cost).__name__}")
    if (cost.T, cost.n, cost.m) != (kf.T, kf.n, kf.m):
        raise ShapeError(f"cost has (T, n, m) = {(cost.T, cost.n, cost.m)} but the filter has {(kf.T, kf.n, kf.m)}")


def cost_correction(kf: KalmanFilter, cost: QuadraticCost) -> np.ndarray:
    """(T,) ``1/2 tr(C_xx,k P_k)``: ``E[l_k(x, a)] - E[l_k(xhat, a)]`` for a policy acting on ``xhat``."""
    _check_cost(kf, cost)
    n = kf.n
    return 0.5 * tr(cost.C[:, :n, :n] @ kf.P[: kf.T])


def filtered_cost(kf: KalmanFilter, cost: QuadraticCost) -> QuadraticCost:
    """``cost`` as a function of ``(xhat, a)`` with the same expectation as on ``(x, a)``: ``c0 += cost_correction``."""
    return QuadraticCost(cost.C, cost.c, cost.n, cost.c0 + cost_correction(kf, cost))


def innovation_augmented(model: AugmentedModel, kf: KalmanFilter, *, atol: float = 1e-10) -> AugmentedModel:
    """The augmented model of ``(xhat_{k+1}, y_k)`` given ``(xhat_k, a_k)`` (``docs/noise.md`` §6).

    ``model`` is the x-frame augmented model ``(x_{k+1}, y_k) | (x_k, a_k)``; ``kf`` must be the
    filter of ``model.dynamics()`` (checked to ``atol``).  Same ``Ao, co``; noise covariance

        [[G' S' G'^T,                   G' (A P Ay^T + w_y)],
         [(A P Ay^T + w_y)^T G'^T,      s_yy + Ay P Ay^T   ]]

    with ``G' = G_{k+1}``, ``S' = S_{k+1}``, ``P = P_k``, ``w_y, s_yy`` blocks of ``model.So``.
    """
    if not isinstance(model, AugmentedModel):
        raise TypeError(f"model must be an AugmentedModel, got {type(model).__name__}")
    if not isinstance(kf, KalmanFilter):
        raise TypeError(f"kf must be a KalmanFilter, got {type(kf).__name__}")
    if (model.T, model.n, model.m) != (kf.T, kf.n, kf.m):
        raise ShapeError(f"model has (T, n, m) = {(model.T, model.n, model.m)} but the filter has {(kf.T, kf.n, kf.m)}")
    dyn = model.dynamics()
    for name, mv, fv in (("A", dyn.A, kf.A), ("B", dyn.B, kf.B), ("c", dyn.c, kf.c), ("W", dyn.cov, kf.W)):
        if not np.allclose(mv, fv, rtol=0.0, atol=atol * max(1.0, float(np.abs(mv).max(initial=0.0)))):
            raise ValueError(f"the filter was not built from this model: its {name} differs from the model's")
    n, T = model.n, model.T
    G1, S1, P = kf.G[1:], kf.S[1:], kf.P[:T]
    Ay = model.Ao[:, n:, :n]  # (T, 1, n)
    wy = model.So[:, :n, n:]  # (T, n, 1)
    So = np.empty_like(model.So)
    So[:, :n, :n] = G1 @ S1 @ _T(G1)
    cross = G1 @ (kf.A @ P @ _T(Ay) + wy)
    So[:, :n, n:] = cross
    So[:, n:, :n] = _T(cross)
    So[:, n:, n:] = model.So[:, n:, n:] + Ay @ P @ _T(Ay)
    return AugmentedModel(model.Ao, model.co, symmetrize(So), n)
