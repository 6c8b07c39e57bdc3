"""Exact LQG reference for a known linear system with measurement noise (docs/math.md §10.3).

For ``x_{k+1} = A x + B a + c + w`` (``w ~ N(0, W)``), ``s = x + eps`` (``eps ~ N(0, R)``),
``x_0 ~ N(mu0, P0)`` and a quadratic cost on ``(x, a)``, the optimum over causal policies of the
measurements is the Kalman filter of the true model (:mod:`soc_opt.noise.estimator`) plus the LQR gains
(docs/math.md §6 with ``nu = inf``) acting on ``xhat`` (separation principle).

The expected cost of any filtered policy, including one whose filter model differs from the true
system, is exact from the ``2n``-dimensional Gaussian of ``(x_k, xhat_k)`` (``docs/noise.md`` §9)::

    (x_{k+1}, xhat_{k+1}) = F_k (x_k, xhat_k) + f_k + noise,
    F_k = [[A, B K], [G' A, (I - G')(Af + Bf K) + G' B K]],  D = [B; (I - G') Bf + G' B],
    noise cov = D Sigma D^T + [I; G'] W [I; G']^T + [0; G'] R [0; G']^T

(``Af, Bf, cf`` the filter's model, ``G' = G_{k+1}``), started from ``x_0 ~ N(mu0, P0)`` and
``xhat_0 = (I - G_0) mu0_f + G_0 (x_0 + eps_0)``.

Public functions:
    closed_loop_moments(dynamics, R, fpolicy, mu0, P0) -> ClosedLoopMoments
    expected_cost(dynamics, cost, R, fpolicy, mu0, P0)  -> (T,)
    lqg(dynamics, cost, R, mu0, P0)                     -> LQGSolution
    simulate(dynamics, R, fpolicy, mu0, P0, M, rng)     -> ClosedLoopSamples   (Monte Carlo, online filter)
    task_reference(task)                                -> LQGSolution for a linear task (e.g. linear2d)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import lqg as _lqg
from ..linalg import T as _T
from ..linalg import as_generator
from ..models import LinearGaussianDynamics, QuadraticCost, ShapeError, check_array, symmetrize
from .estimator import FilteredPolicy, check_noise_covariance, kalman_filter, measurement_noise

__all__ = [
    "ClosedLoopMoments",
    "ClosedLoopSamples",
    "LQGSolution",
    "closed_loop_moments",
    "expected_cost",
    "lqg",
    "simulate",
    "task_reference",
]


class ClosedLoopMoments(NamedTuple):
    """Exact moments of a filtered policy on a known linear system.

    Fields:
        mean:   (T+1, 2n)      ``E[(x_k, xhat_k)]``
        cov:    (T+1, 2n, 2n)  ``Cov((x_k, xhat_k))``
        a_mean: (T, m)         ``E[a_k]``
        a_cov:  (T, m, m)      ``Cov(a_k)``
        xa_cov: (T, n, m)      ``Cov(x_k, a_k)``
    """

    mean: np.ndarray
    cov: np.ndarray
    a_mean: np.ndarray
    a_cov: np.ndarray
    xa_cov: np.ndarray


class ClosedLoopSamples(NamedTuple):
    """Monte Carlo samples of the filtered closed loop.

    Fields:
        x:    (M, T+1, n) true states
        s:    (M, T+1, n) measurements
        xhat: (M, T+1, n) filter estimates (online)
        a:    (M, T, m)   actions
    """

    x: np.ndarray
    s: np.ndarray
    xhat: np.ndarray
    a: np.ndarray


class LQGSolution(NamedTuple):
    """The LQG controller and its exact expected cost.

    Fields:
        policy:     FilteredPolicy (LQR gains on ``xhat``, ``Sigma = 0``, plus the true-model filter)
        stage_cost: (T,) ``E[l_k(x_k, a_k)]``
        total:      ``sum_k E[l_k]``
    """

    policy: FilteredPolicy
    stage_cost: np.ndarray
    total: float


def _check(dynamics, R, fpolicy, mu0, P0):
    if not isinstance(dynamics, LinearGaussianDynamics):
        raise TypeError(f"dynamics must be a LinearGaussianDynamics, got {type(dynamics).__name__}")
    if not isinstance(fpolicy, FilteredPolicy):
        raise TypeError(f"fpolicy must be a FilteredPolicy, got {type(fpolicy).__name__}")
    T, n, m = dynamics.T, dynamics.n, dynamics.m
    if (fpolicy.policy.T, fpolicy.policy.n, fpolicy.policy.m) != (T, n, m):
        raise ShapeError(
            f"filtered policy has (T, n, m) = {(fpolicy.policy.T, fpolicy.policy.n, fpolicy.policy.m)} "
            f"but the system has {(T, n, m)}"
        )
    R = check_noise_covariance("measurement noise R", R, (n, n))
    mu0 = check_array("initial mean mu0", mu0, (n,))
    P0 = check_noise_covariance("initial covariance P0", P0, (n, n))
    return R, mu0, P0


def closed_loop_moments(dynamics: LinearGaussianDynamics, R, fpolicy: FilteredPolicy, mu0, P0) -> ClosedLoopMoments:
    """Exact Gaussian of ``(x_k, xhat_k)`` under ``fpolicy`` on the true system ``dynamics`` (docs/math.md §10.3).

    ``R`` is the true measurement noise and ``(mu0, P0)`` the true distribution of ``x_0``; the
    filter (its model, noise and prior) is the policy's own and may differ from them.
    """
    R, mu0, P0 = _check(dynamics, R, fpolicy, mu0, P0)
    T, n = dynamics.T, dynamics.n
    A, B, c, W = dynamics.A, dynamics.B, dynamics.c, dynamics.cov
    kf, pol = fpolicy.filter, fpolicy.policy
    K, kk, Sig = pol.K, pol.k, pol.cov
    I = np.eye(n)
    Z = np.zeros((n, n))

    mean = np.empty((T + 1, 2 * n))
    cov = np.empty((T + 1, 2 * n, 2 * n))
    G0 = kf.G[0]
    mean[0] = np.concatenate([mu0, (I - G0) @ kf.mu0 + G0 @ mu0])
    cov[0] = symmetrize(np.block([[P0, P0 @ G0.T], [G0 @ P0, G0 @ (P0 + R) @ G0.T]]))
    for t in range(T):
        G1 = kf.G[t + 1]
        IG = I - G1
        BK = B[t] @ K[t]
        F = np.block([[A[t], BK], [G1 @ A[t], IG @ (kf.A[t] + kf.B[t] @ K[t]) + G1 @ BK]])
        f = np.concatenate([B[t] @ kk[t] + c[t], IG @ (kf.B[t] @ kk[t] + kf.c[t]) + G1 @ (B[t] @ kk[t] + c[t])])
        D = np.vstack([B[t], IG @ kf.B[t] + G1 @ B[t]])
        Hw = np.vstack([I, G1])
        He = np.vstack([Z, G1])
        N = D @ Sig[t] @ D.T + Hw @ W[t] @ Hw.T + He @ R @ He.T
        mean[t + 1] = F @ mean[t] + f
        cov[t + 1] = symmetrize(F @ cov[t] @ F.T + N)
    a_mean = np.einsum("tij,tj->ti", K, mean[:T, n:]) + kk
    a_cov = symmetrize(K @ cov[:T, n:, n:] @ _T(K) + Sig)
    xa_cov = cov[:T, :n, n:] @ _T(K)
    return ClosedLoopMoments(mean, cov, a_mean, a_cov, xa_cov)


def _stage_costs(cost: QuadraticCost, mean_x, cov_x, a_mean, a_cov, xa_cov) -> np.ndarray:
    """``E[l_k] = 1/2 tr(C Cov(z)) + l_k(E z)`` for ``z = (x_k, a_k)``."""
    n, T = cost.n, cost.T
    C = cost.C
    zbar = np.concatenate([mean_x[:T], a_mean], axis=1)
    trace = (
        np.einsum("tij,tij->t", C[:, :n, :n], cov_x[:T])
        + 2.0 * np.einsum("tij,tij->t", C[:, :n, n:], xa_cov)
        + np.einsum("tij,tij->t", C[:, n:, n:], a_cov)
    )
    return 0.5 * trace + 0.5 * np.einsum("ti,tij,tj->t", zbar, C, zbar) + np.einsum("ti,ti->t", zbar, cost.c) + cost.c0


def expected_cost(dynamics: LinearGaussianDynamics, cost: QuadraticCost, R, fpolicy: FilteredPolicy, mu0, P0) -> np.ndarray:
    """(T,) exact ``E[l_k(x_k, a_k)]`` (cost on the **true** state) of ``fpolicy`` on ``dynamics``."""
    if not isinstance(cost, QuadraticCost):
        raise TypeError(f"cost must be a QuadraticCost, got {type(cost).__name__}")
    if (cost.T, cost.n, cost.m) != (dynamics.T, dynamics.n, dynamics.m):
        raise ShapeError(f"cost has (T, n, m) = {(cost.T, cost.n, cost.m)} but the system has {(dynamics.T, dynamics.n, dynamics.m)}")
    mom = closed_loop_moments(dynamics, R, fpolicy, mu0, P0)
    n = dynamics.n
    return _stage_costs(cost, mom.mean[:, :n], mom.cov[:, :n, :n], mom.a_mean, mom.a_cov, mom.xa_cov)


def lqg(dynamics: LinearGaussianDynamics, cost: QuadraticCost, R, mu0, P0, *, filter_P0=None) -> LQGSolution:
    """The LQG optimum: filter of the true model and prior, LQR gains on ``xhat`` (docs/math.md §10.3).

    ``filter_P0`` replaces ``P0`` in the filter only.  It is needed in one case: without
    measurement noise (``R = 0``) and with a deterministic start (``P0 = 0``) the innovation
    covariance ``S_0`` is singular, while every positive definite prior gives the exact filter
    ``G_k = I`` (``xhat = s = x``); pass e.g. ``filter_P0 = I`` (the cost is evaluated with ``P0``).
    Raises what :func:`soc_opt.lqg.lqr` raises when the cost-to-go is not strictly convex in the
    action, and what :func:`soc_opt.noise.estimator.kalman_filter` raises for a bad noise model.
    """
    kf = kalman_filter(dynamics, R, mu0, P0 if filter_P0 is None else filter_P0)
    policy = _lqg.lqr(dynamics, cost, kf.mu0, kf.P0)
    fpol = FilteredPolicy(policy, kf)
    stage = expected_cost(dynamics, cost, kf.R, fpol, kf.mu0, P0)
    return LQGSolution(fpol, stage, float(stage.sum()))


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    """``L`` with ``L L^T = P`` for symmetric PSD ``P`` (batched; eigen-decomposition)."""
    w, V = np.linalg.eigh(P)
    return V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]


def simulate(dynamics: LinearGaussianDynamics, R, fpolicy: FilteredPolicy, mu0, P0, M: int,
             rng: np.random.Generator) -> ClosedLoopSamples:
    """``M`` Monte Carlo rollouts of ``fpolicy`` on the true system, the filter run online step by step.

    Draw order per step: ``x_0`` (then) for each ``k``: ``eps_k``, policy noise, process noise.
    """
    R, mu0, P0 = _check(dynamics, R, fpolicy, mu0, P0)
    if not (isinstance(M, (int, np.integer)) and M >= 1):
        raise ValueError(f"number of rollouts M must be a positive integer, got {M!r}")
    rng = as_generator(rng)
    T, n, m = dynamics.T, dynamics.n, dynamics.m
    LR, LW, L0 = _sqrt_psd(R), _sqrt_psd(dynamics.cov), _sqrt_psd(P0)
    x = np.empty((M, T + 1, n))
    s = np.empty((M, T + 1, n))
    xh = np.empty((M, T + 1, n))
    a = np.empty((M, T, m))
    x[:, 0] = mu0 + rng.standard_normal((M, n)) @ L0.T
    for k in range(T + 1):
        s[:, k] = x[:, k] + rng.standard_normal((M, n)) @ LR.T
        xh[:, k] = fpolicy.estimate(k, s[:, k]) if k == 0 else fpolicy.estimate(k, s[:, k], xh[:, k - 1], a[:, k - 1])
        if k == T:
            break
        a[:, k] = fpolicy.sample_action(k, xh[:, k], rng)
        xi = rng.standard_normal((M, n)) @ LW[k].T
        x[:, k + 1] = x[:, k] @ dynamics.A[k].T + a[:, k] @ dynamics.B[k].T + dynamics.c[k] + xi
    return ClosedLoopSamples(x, s, xh, a)


def task_reference(task, P0=None) -> LQGSolution:
    """LQG reference of a linear task (``kind = "linear"``, e.g. ``linear2d``) at its ``rho2``.

    Uses the task's exact model (``task.linearize()``), its cost (quadratic, so its expansion is
    exact) and the true initial distribution: ``x_0 = task.mu0`` deterministic, i.e. ``P0 = 0``
    unless given.  At ``rho2 = 0`` the result is the LQR policy with perfect states (``G = I``).
    """
    for attr in ("linearize", "cost_expansion", "rho2", "mu0", "n", "m", "T"):
        if not hasattr(task, attr):
            raise TypeError(f"task_reference needs a linear task with '{attr}', got {type(task).__name__}")
    dyn = task.linearize()
    mu0 = np.asarray(task.mu0, dtype=float)
    s = np.broadcast_to(mu0, (task.T + 1, task.n)).copy()
    cost = task.cost_expansion(s, np.zeros((task.T, task.m)))
    other = task.cost_expansion(s + 1.0, np.ones((task.T, task.m)))
    if not np.allclose(cost.C, other.C, rtol=1e-9, atol=1e-12):
        raise ValueError(f"task {getattr(task, 'name', '?')!r} has a non-quadratic cost; the LQG reference needs a quadratic one")
    P0 = np.zeros((task.n, task.n)) if P0 is None else np.asarray(P0, dtype=float)
    R = measurement_noise(task.rho2, task.n)
    filter_P0 = np.eye(task.n) if task.rho2 == 0 else None
    return lqg(dyn, cost, R, mu0, P0, filter_P0=filter_P0)
