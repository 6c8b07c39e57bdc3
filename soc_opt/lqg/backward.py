"""Backward pass of the KL-constrained LQG step for fixed multipliers, and LQR (SPEC §6).

Closed form for fixed ``eta`` (``eta_k > 0``).  ``E_p[l] + eta (KL - nu)`` equals
``E_p[l - eta log phat] - eta H(p) - eta nu``; a backward pass with the quadratic
Q-function ``Q_k`` of ``l_k - eta_k log phat + V_{k+1}`` gives
``p(a|s) = N(-Quu^{-1}(Qus s + qu), eta_k Quu^{-1})``, and the value function keeps only its
quadratic and linear parts ``V = Qss - Qsu Quu^{-1} Qus``, ``v = qs - Qsu Quu^{-1} qu``: the
entropy, log-normaliser and noise constants do not affect any policy, and the dual value is
evaluated exactly from the forward pass instead (``g = sum E[l] + sum eta (KL - nu)``).
``eta_k = 0`` (only for ``nu_k = inf``) removes the KL term: the step is the deterministic
LQR step.  ``eta_k = inf`` (only for ``nu_k = 0``) pins the step to the reference.

Every finite budget is active in a non-degenerate problem: as ``eta_k -> 0`` the policy
covariance ``eta_k Quu^{-1}`` collapses and ``KL_k -> inf``.  A budget is slack only when
``nu_k = inf`` (``eta_k = 0`` exactly), or when it is so large that ``KL_k(eta_min) < nu_k``
(then ``eta_k = eta_min``, "numerically zero"; this happens for ``nu_k`` above about
``m/2 log(1/eta_min)``), or in degenerate steps where the action changes no cost.

Quu repair rule (GPS-style).  If a backward pass meets a ``Quu_k`` that is not positive
definite (Cholesky fails), the smallest multiplier making it PD with the later steps fixed is
``eta_crit = -lambda_min(Lh^T Q0uu Lh)`` (``Sh = Lh Lh^T``, ``Q0uu`` = ``Quu`` without the KL term);
the multiplier is raised to ``max(repair_factor * eta, (1 + repair_margin) * eta_crit)`` and the pass
restarted (scalar ``eta``) or continued (per step).  Past ``config.eta_max`` a
:class:`~soc_opt.models.NotPositiveDefiniteError` names the step.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import lapack

from ..linalg import logdet_chol
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, NotPositiveDefiniteError, QuadraticCost, symmetrize
from .moments import _expected_cost_marg, _forward_arrays
from .problem import KLStepConfig, Marginals, _check_dims, _check_init, _Problem


class _NotPD(Exception):
    def __init__(self, t: int, eta: float, eta_crit: float):
        super().__init__(t, eta, eta_crit)
        self.t, self.eta, self.eta_crit = t, eta, eta_crit


class _Backward(NamedTuple):
    K: np.ndarray  # (T, m, n)
    k: np.ndarray  # (T, m)
    dK: np.ndarray  # (T, m, n)  K - Kh  (computed directly, without cancellation)
    dk: np.ndarray  # (T, m)     k - kh
    S: np.ndarray  # (T, m, m) policy covariances eta Quu^-1
    logdetS: np.ndarray  # (T,)
    Quu_inv: np.ndarray  # (T, m, m)  Quu (with the KL term) inverted
    Q0uu: np.ndarray  # (T, m, m)  Quu without the KL term
    eta: np.ndarray  # (T,) multipliers actually used (after repair)


def _eta_crit(prob: _Problem, t: int, Q0uu: np.ndarray) -> float:
    """Smallest ``eta`` making ``Quu(eta) = Q0uu + eta Sh^-1`` PD at step ``t`` (later steps fixed)."""
    Lh = prob.Lh[t]
    lam = float(np.linalg.eigvalsh(symmetrize(Lh.T @ Q0uu @ Lh))[0])
    return max(-lam, 0.0)


def _backward(prob: _Problem, eta: np.ndarray, *, repair: np.ndarray | None = None,
              config: KLStepConfig | None = None) -> _Backward:
    """Backward pass for fixed multipliers ``eta`` (T,).

    ``eta_k = 0``: deterministic LQR step; ``eta_k = inf``: step pinned to the reference.
    For ``eta_k > 0`` the deviation from the reference is computed directly,
    ``[dK, dk] = -Quu^-1 (Q0ux + Q0uu [Kh, kh])``, which stays accurate when ``eta`` is large
    and the policy is close to the reference.  Raises :class:`_NotPD` at the first (latest)
    step whose ``Quu`` is not PD, unless that step is marked in the boolean mask ``repair``:
    then ``eta_k`` is raised in place by the repair rule (see above) and the pass continues.
    """
    T, n, m = prob.T, prob.n, prob.m
    n1 = n + 1
    eta = np.array(eta, dtype=float)
    Kt = np.empty((T, m, n1))
    dKt = np.zeros((T, m, n1))
    S = np.empty((T, m, m))
    Qi_all = np.zeros((T, m, m))  # lower triangles of Quu^-1 (LAPACK potri), symmetrised below
    Q0_all = np.empty((T, m, m))
    logdetS = np.empty(T)
    Ldiag = np.ones((T, m))
    V = np.zeros((n1, n1))
    Ct, Ft, F, H = prob.Ct, prob.Ft, prob.F, prob.H
    has_ref = H is not None
    if has_ref:
        Kth, KthR, Shinv = prob.Kth, prob.KthR, prob.Shinv
    for t in range(T - 1, -1, -1):
        Q = Ct[t] + Ft[t] @ V @ F[t]
        Q0uu = Q[n1:, n1:]
        Q0_all[t] = Q0uu
        e = eta[t]
        if e == math.inf:  # pinned to the reference: cost-to-go under phat (KL_t = 0)
            Kh_t = Kth[t]
            Kt[t] = Kh_t
            S[t] = prob.Sh[t]
            logdetS[t] = logdet_chol(prob.Lh[t])
            QxuK = Q[:n1, n1:] @ Kh_t
            V = Q[:n1, :n1] + QxuK + QxuK.T + Kh_t.T @ Q0uu @ Kh_t
            V = 0.5 * (V + V.T)
            continue
        Quu = Q0uu + e * Shinv[t] if e > 0 else Q0uu
        L, info = lapack.dpotrf(Quu, lower=1, clean=1)
        while info != 0:
            crit = _eta_crit(prob, t, Q0uu) if has_ref else math.inf
            if repair is None or not repair[t]:
                raise _NotPD(t, e, crit)
            e = max(config.repair_factor * e, (1.0 + config.repair_margin) * crit)
            if e > config.eta_max:
                raise NotPositiveDefiniteError(
                    f"Quu[{t}] is not positive definite for any multiplier up to eta_max={config.eta_max:g} "
                    f"(needs eta > {crit:.3e})"
                )
            eta[t] = e
            Quu = Q0uu + e * Shinv[t]
            L, info = lapack.dpotrf(Quu, lower=1, clean=1)
        Qi_all[t] = lapack.dpotri(L, lower=1)[0]
        Ldiag[t] = L.diagonal()
        if e > 0:
            D = -(lapack.dpotrs(L, Q[n1:, :n1] + Q0uu @ Kth[t], lower=1)[0])  # [dK, dk]
            dKt[t] = D
            Kt_t = Kth[t] + D
            # V = min_a Q_eta = Q0xx + Q0xu [K,k] + eta (Hxx + Hxu [K,k]),  Hxx + Hxu [K,k] = -Kth^T R [dK,dk]
            V = Q[:n1, :n1] + Q[:n1, n1:] @ Kt_t - e * (KthR[t] @ D)
        else:
            Kt_t = -lapack.dpotrs(L, Q[n1:, :n1], lower=1)[0]
            if has_ref:
                dKt[t] = Kt_t - Kth[t]
            V = Q[:n1, :n1] + Q[:n1, n1:] @ Kt_t  # Qxx - Qxu Quu^-1 Qux
        Kt[t] = Kt_t
        V = 0.5 * (V + V.T)
    Qi_all = np.tril(Qi_all) + np.swapaxes(np.tril(Qi_all, -1), 1, 2)
    pos = np.isfinite(eta) & (eta > 0)
    S[pos] = eta[pos, None, None] * Qi_all[pos]
    S[eta == 0] = 0.0
    logdetS[pos] = m * np.log(eta[pos]) - 2.0 * np.log(Ldiag[pos]).sum(axis=1)
    logdetS[eta == 0] = -np.inf
    return _Backward(Kt[:, :, :n].copy(), Kt[:, :, n].copy(), dKt[:, :, :n].copy(), dKt[:, :, n].copy(),
                     S, logdetS, Qi_all, Q0_all, eta)


class _Eval(NamedTuple):
    bw: _Backward
    marg: Marginals
    kl: np.ndarray
    cost: np.ndarray
    Md: np.ndarray  # (T, m, m) E[delta delta^T], delta = (K - Kh) s + (k - kh)
    mu_eig: np.ndarray  # (T, m) eigenvalues of Lh^T Q0uu Lh


def _evaluate(prob: _Problem, bw: _Backward) -> _Eval:
    """Forward pass, expected costs and ``KL_k`` of a backward-pass policy.

    The covariance part of ``KL_k`` is evaluated from the eigenvalues ``mu_i`` of
    ``Lh^T Q0uu Lh`` (the eigenvalues of ``Sh^-1 Sigma`` are ``eta/(mu_i + eta)``):
    ``tr(Sh^-1 S) - m - log|Sh^-1 S| = sum_i log1p(mu_i/eta) - mu_i/(mu_i + eta)``, accurate
    even when ``KL`` is many orders below 1 (large ``eta``).
    """
    T = prob.T
    marg = _forward_arrays(prob.dynamics, bw.K, bw.k, bw.S, prob.mu0, prob.P0)
    dm = (bw.dK @ marg.mean[:T, :, None])[:, :, 0] + bw.dk
    Md = bw.dK @ marg.cov[:T] @ np.swapaxes(bw.dK, 1, 2) + dm[:, :, None] * dm[:, None, :]
    quad = np.einsum("tij,tij->t", prob.Shinv, Md)
    LhT = np.swapaxes(prob.Lh, 1, 2)
    mu_eig = np.linalg.eigvalsh(symmetrize(LhT @ bw.Q0uu @ prob.Lh))
    eta = bw.eta
    pos = np.isfinite(eta) & (eta > 0)
    cov_part = np.zeros(T)
    e = eta[pos][:, None]
    mu = mu_eig[pos]
    cov_part[pos] = (np.log1p(mu / e) - mu / (mu + e)).sum(axis=1)
    cov_part[eta == 0] = np.inf
    kl = 0.5 * (cov_part + quad)
    kl[np.isinf(eta)] = 0.0
    cost = _expected_cost_marg(prob.cost, marg)
    return _Eval(bw, marg, kl, cost, Md, mu_eig)


def _direct_dkl(prob: _Problem, ev: _Eval) -> np.ndarray:
    """(T,) ``dKL_k/deta_k`` through step ``k``'s own policy only (later steps and ``p(s_k)`` fixed).

    With ``R = Sh^-1``, ``Quu = Q0 + eta R``, ``delta(s) = (K - Kh) s + k - kh``:
    ``dKL/deta = -tr((Q0 Quu^-1)^2)/(2 eta) - tr(R Quu^-1 R E[delta delta^T])`` (< 0), where
    ``tr((Q0 Quu^-1)^2) = sum_i (mu_i/(mu_i + eta))^2``.  Used by the vector dual solver.
    """
    bw = ev.bw
    eta = np.where(np.isfinite(bw.eta) & (bw.eta > 0), bw.eta, 1.0)
    mu = ev.mu_eig
    t1 = ((mu / (mu + eta[:, None])) ** 2).sum(axis=1)
    R = prob.Shinv
    t2 = np.einsum("tij,tji->t", R @ bw.Quu_inv @ R, ev.Md)
    return -0.5 * t1 / eta - t2


def lqr(dynamics: LinearGaussianDynamics, cost: QuadraticCost, mu0, P0) -> LinearGaussianPolicy:
    """Unconstrained optimum of ``sum_k E[l_k]``: the deterministic LQR policy (``cov = 0``).

    The optimal feedback does not depend on ``(mu0, P0)`` (certainty equivalence); they are
    validated for interface symmetry.  Raises :class:`NotPositiveDefiniteError` naming the step
    if ``Quu_k`` is not positive definite (cost-to-go not strictly convex in ``a_k``).
    """
    T, n, m = _check_dims(dynamics, cost=cost)
    _check_init(mu0, P0, n)
    prob = _Problem(dynamics, cost, None, None, None)
    try:
        bw = _backward(prob, np.zeros(T))
    except _NotPD as e:
        raise NotPositiveDefiniteError(
            f"Quu[{e.t}] is not positive definite: the cost-to-go is not strictly convex in a_{e.t}, "
            "so the unconstrained LQR problem has no unique minimiser"
        ) from None
    return LinearGaussianPolicy(bw.K, bw.k, np.zeros((T, m, m)), allow_singular=True)
