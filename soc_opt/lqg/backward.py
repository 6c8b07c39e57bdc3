"""Backward pass of the KL-constrained LQG step for fixed multipliers, and LQR (docs/math.md §6).

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

Cost.  Both passes are loops over ``T`` of small matrix products whose Python overhead is of
the order of their arithmetic at ``n=26, m=7``: the backward loop runs in deviation coordinates
(no KL cross terms, nothing recomputed per step that does not depend on ``eta``) and calls
BLAS/LAPACK directly (three ``gemm``, one ``potrf``, two ``trtrs`` per step) in place on
preallocated buffers prefilled with the stage cost; everything that is not recursive (``Q0uu``,
``Sigma``, log-determinants, gains) is batched over ``T`` afterwards; the forward loop propagates
``[Cov | mean]`` with two ``gemm`` per step (:mod:`.moments`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import blas, lapack

from ..linalg import logdet_chol
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, NotPositiveDefiniteError, QuadraticCost, symmetrize
from .moments import ForwardWorkspace, expected_cost_marg, forward_arrays
from .problem import KLProblem, KLStepConfig, Marginals, check_dims, check_init, ux_transpose


class NotPDPoint(Exception):
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


def _eta_crit(prob: KLProblem, t: int, Q0uu: np.ndarray) -> float:
    """Smallest ``eta`` making ``Quu(eta) = Q0uu + eta Sh^-1`` PD at step ``t`` (later steps fixed)."""
    Lh = prob.Lh[t]
    lam = float(np.linalg.eigvalsh(symmetrize(Lh.T @ Q0uu @ Lh))[0])
    return max(-lam, 0.0)


def backward_pass(prob: KLProblem, eta: np.ndarray, *, repair: np.ndarray | None = None,
              config: KLStepConfig | None = None) -> _Backward:
    """Backward pass for fixed multipliers ``eta`` (T,).

    ``eta_k = 0``: deterministic LQR step; ``eta_k = inf``: step pinned to the reference.
    The recursion runs in the deviation coordinates ``z' = (s, 1, delta)``, ``delta = a - Kh s - kh``
    (``KLProblem.Fd``, ``Ctd``), where the KL term is ``eta delta^T Sh^-1 delta / 2`` without cross
    terms: with ``Q'`` the Q-function of ``l + V_{k+1}`` in these coordinates,
    ``Quu = Q'uu + eta Sh^-1``, the deviation gain ``[dK, dk] = -Quu^-1 Q'ux`` and
    ``V = Q'xx - Q'xu Quu^-1 Q'ux``.  Nothing here grows with ``eta``, so the policy stays accurate
    when ``eta`` is large and it is close to the reference.  Steps with ``eta_k = 0`` use the
    coordinates ``(s, 1, a)`` (the same operations as :func:`lqr`, so ``nu = inf`` reproduces it
    exactly).  Per step only the Q-function blocks ``Q'xx`` and ``[Quu, Q'ux]``, the Cholesky
    factorisation ``Quu = L L^T``, ``Z = L^-1 Q'ux`` (so ``V = Q'xx - Z^T Z``) and
    ``Quu^-1 [Q'ux, I] = L^-T [Z, L^-1]`` run in the loop; ``Q0uu``, ``Sigma`` and the
    log-determinants are batched afterwards.  Raises :class:`NotPDPoint` at the
    first (latest) step whose ``Quu`` is not PD, unless that step is marked in the boolean mask
    ``repair``: then ``eta_k`` is raised in place by the repair rule (see above) and the pass
    continues.
    """
    T, n, m = prob.T, prob.n, prob.m
    n1 = n + 1
    eta = np.array(eta, dtype=float)
    has_ref = prob.has_ref
    fin = np.isfinite(eta)
    zero = eta == 0
    Ctd = prob.Ctd
    dev = has_ref & ~zero  # steps in deviation coordinates; eta = 0 steps (LQR) in z~ = (s, 1, a)
    if has_ref and zero.any():
        sel = zero[:, None, None]
        Ctd = np.where(sel, prob.Ct, Ctd)
        ws = _Workspace(np.where(sel, ux_transpose(prob.F, n1), prob.Fdut), Ctd, m)
    else:
        if prob.workspace is None:
            prob.workspace = _Workspace(prob.Fdut, Ctd, m)
        ws = prob.workspace
    d = n1 + m
    U, V = ws.U, ws.V
    np.copyto(U, ws.U0)
    if has_ref:
        U[:, :m] += np.where(fin, eta, 0.0)[:, None, None] * prob.Shinv
    np.copyto(V[:T], ws.V0)
    dgemm, dpotrf, dtrtrs = blas.dgemm, lapack.dpotrf, lapack.dtrtrs
    Y, Yx, Yu = ws.Y, ws.Yx, ws.Yu
    W = ws.W_end  # value function of step t + 1 (zero after the last step)
    fin_l = fin.tolist()
    steps = ws.steps
    for t in range(T - 1, -1, -1):
        FdT, FxT, FuT, Qu, Lt, B, Z, Wt = steps[t]
        dgemm(1.0, W, FdT, 0.0, Y, 0, 0, 1)  # Y = V_{t+1} [Fu, Fx]  (n1, d)
        dgemm(1.0, FxT, Yx, 1.0, Wt, 1, 0, 1)  # Q'xx = Fx^T V Fx + Ctd_xx
        if not fin_l[t]:  # pinned to the reference (delta = 0): cost-to-go under phat (KL_t = 0)
            W = Wt
            continue
        dgemm(1.0, FuT, Y, 1.0, Qu, 1, 0, 1)  # [Quu, Q'ux] = Fu^T V [Fu, Fx] + prefill
        if dpotrf(Lt, 1, 1, 1)[1] != 0:
            Q0uu = FuT.T @ Yu + Ctd[t, n1:, n1:]
            _repair(prob, t, Q0uu, eta, repair, config)  # raises eta[t] (or raises NotPDPoint)
            Lt[...] = Q0uu + eta[t] * prob.Shinv[t]
            dpotrf(Lt, 1, 1, 1)
        dtrtrs(Lt, B, 1, 0, 0, m, 1)  # [Z, L^-1] = L^-1 [Q'ux, I]
        dgemm(-1.0, Z, Z, 1.0, Wt, 1, 0, 1)  # V_t = Q'xx - Z^T Z
        dtrtrs(Lt, B, 1, 1, 0, m, 1)  # L^-T [Z, L^-1] = Quu^-1 [Q'ux, I]
        W = Wt
    # batched over T: Q0uu = Fu^T V_{t+1} Fu + Ctd_uu (Quu without the KL term)
    Q0uu = symmetrize(ws.Fut @ V[1:] @ ws.Fu + Ctd[:, n1:, n1:])
    pinned = ~fin
    G = -np.swapaxes(U[:, m:d], 1, 2)  # (T, m, n1) gains of the step's coordinates
    G[pinned] = 0.0  # pinned: the step's coordinate delta = 0
    if has_ref and dev.all():
        Kt, D = prob.Kth + G, G
    elif has_ref:
        devc = dev[:, None, None]
        Kt = np.where(devc, prob.Kth + G, G)
        D = np.where(devc, G, G - prob.Kth)  # deviation gains, computed directly where possible
    else:
        Kt = D = G
    Quu_inv = symmetrize(U[:, d:])
    Quu_inv[pinned] = 0.0
    pos = fin & (eta > 0)
    S = np.where(fin, eta, 0.0)[:, None, None] * Quu_inv  # 0 where eta = 0
    logdetS = np.empty(T)
    logdetS[pos] = m * np.log(eta[pos]) - 2.0 * np.log(np.diagonal(U[pos, :m], axis1=1, axis2=2)).sum(axis=1)
    logdetS[zero] = -np.inf
    if pinned.any():
        S[pinned] = prob.Sh[pinned]
        logdetS[pinned] = logdet_chol(prob.Lh[pinned])
    return _Backward(np.ascontiguousarray(Kt[:, :, :n]), np.ascontiguousarray(Kt[:, :, n]),
                     np.ascontiguousarray(D[:, :, :n]), np.ascontiguousarray(D[:, :, n]),
                     S, logdetS, Quu_inv, Q0uu, eta)


class _Workspace:
    """Buffers of :func:`backward_pass` for one problem, reused by every pass, and their per-step
    Fortran-ordered views (``X[t].T`` of C-ordered stacks; the symmetric blocks are their own
    transposes), built once: the views are a large part of the per-step cost otherwise.

    ``U[t].T = [Quu | Q'ux | I]`` (m, d + m), copied from ``U0`` = ``[Ctd_uu | Ctd_ux | I]`` and
    the KL term ``eta R`` added before each pass, overwritten by ``[L | Quu^-1 Q'ux | Quu^-1]``
    (``Quu = L L^T``); ``V[t].T = Q'xx`` (n1, n1), copied from ``V0 = Ctd_xx``, overwritten by the
    value function ``V_t = Q'xx - Z^T Z``, ``Z = L^-1 Q'ux``; ``V[T] = 0``.  ``Fdut`` (T, d, n1) is
    ``KLProblem.Fdut``, ``Ctd`` (T, d, d) the stage costs in the pass's coordinates.
    """

    def __init__(self, Fdut: np.ndarray, Ctd: np.ndarray, m: int):
        T, d, n1 = Fdut.shape
        self.U0 = np.empty((T, d + m, m))
        self.U0[:, :m] = Ctd[:, n1:, n1:]
        self.U0[:, m:d] = Ctd[:, :n1, n1:]
        self.U0[:, d:] = np.eye(m)
        self.V0 = np.ascontiguousarray(Ctd[:, :n1, :n1])
        self.U = np.empty_like(self.U0)
        self.V = np.zeros((T + 1, n1, n1))
        self.W_end = self.V[T].T
        self.Y = np.empty((n1, d), order="F")
        self.Yu, self.Yx = self.Y[:, :m], self.Y[:, m:]
        self.Fut = np.ascontiguousarray(Fdut[:, :m])  # (T, m, n1) Fu^T
        self.Fu = np.ascontiguousarray(np.swapaxes(self.Fut, 1, 2))  # (T, n1, m)
        U, V = self.U, self.V
        self.steps = [(Fdut[t].T, Fdut[t, m:].T, Fdut[t, :m].T, U[t, :d].T, U[t, :m].T, U[t, m:].T,
                       U[t, m:d].T, V[t].T) for t in range(T)]


def _repair(prob: KLProblem, t: int, Q0uu: np.ndarray, eta: np.ndarray, repair, config) -> None:
    """``Quu_t`` is not PD at ``eta[t]``: raise :class:`NotPDPoint`, or (``repair[t]``) raise ``eta[t]``
    in place by the repair rule until ``Quu_t`` is PD."""
    e = eta[t]
    while True:
        crit = _eta_crit(prob, t, Q0uu) if prob.has_ref else math.inf
        if repair is None or not repair[t]:
            raise NotPDPoint(t, e, crit)
        e = max(config.repair_factor * e, (1.0 + config.repair_margin) * crit)
        if e > config.eta_max:
            raise NotPositiveDefiniteError(
                f"Quu[{t}] is not positive definite for any multiplier up to eta_max={config.eta_max:g} "
                f"(needs eta > {crit:.3e})"
            )
        eta[t] = e
        if lapack.dpotrf(Q0uu + e * prob.Shinv[t], lower=1, clean=1)[1] == 0:
            return


class DualEval(NamedTuple):
    bw: _Backward
    marg: Marginals
    kl: np.ndarray
    cost: np.ndarray
    Md: np.ndarray  # (T, m, m) E[delta delta^T], delta = (K - Kh) s + (k - kh)
    mu_eig: np.ndarray  # (T, m) eigenvalues of Lh^T Q0uu Lh


def evaluate_eta(prob: KLProblem, bw: _Backward) -> DualEval:
    """Forward pass, expected costs and ``KL_k`` of a backward-pass policy.

    The covariance part of ``KL_k`` is evaluated from the eigenvalues ``mu_i`` of
    ``Lh^T Q0uu Lh`` (the eigenvalues of ``Sh^-1 Sigma`` are ``eta/(mu_i + eta)``):
    ``tr(Sh^-1 S) - m - log|Sh^-1 S| = sum_i log1p(mu_i/eta) - mu_i/(mu_i + eta)``, accurate
    even when ``KL`` is many orders below 1 (large ``eta``).
    """
    T = prob.T
    if prob.fwd_workspace is None:
        prob.fwd_workspace = ForwardWorkspace(prob.dynamics)
    marg = forward_arrays(prob.dynamics, bw.K, bw.k, bw.S, prob.mu0, prob.P0, prob.fwd_workspace)
    dm = (bw.dK @ marg.mean[:T, :, None])[:, :, 0] + bw.dk
    Md = bw.dK @ marg.cov[:T] @ np.swapaxes(bw.dK, 1, 2) + dm[:, :, None] * dm[:, None, :]
    quad = np.einsum("tij,tij->t", prob.Shinv, Md)
    LhT = np.swapaxes(prob.Lh, 1, 2)
    mu_eig = np.linalg.eigvalsh(LhT @ bw.Q0uu @ prob.Lh)  # reads the lower triangle only
    eta = bw.eta
    pos = np.isfinite(eta) & (eta > 0)
    cov_part = np.zeros(T)
    e = eta[pos][:, None]
    mu = mu_eig[pos]
    cov_part[pos] = (np.log1p(mu / e) - mu / (mu + e)).sum(axis=1)
    cov_part[eta == 0] = np.inf
    kl = 0.5 * (cov_part + quad)
    kl[np.isinf(eta)] = 0.0
    cost = expected_cost_marg(prob.cost, marg)
    return DualEval(bw, marg, kl, cost, Md, mu_eig)


def direct_dkl(prob: KLProblem, ev: DualEval) -> np.ndarray:
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
    T, n, m = check_dims(dynamics, cost=cost)
    check_init(mu0, P0, n)
    prob = KLProblem(dynamics, cost, None, None, None)
    try:
        bw = backward_pass(prob, np.zeros(T))
    except NotPDPoint as e:
        raise NotPositiveDefiniteError(
            f"Quu[{e.t}] is not positive definite: the cost-to-go is not strictly convex in a_{e.t}, "
            "so the unconstrained LQR problem has no unique minimiser"
        ) from None
    return LinearGaussianPolicy(bw.K, bw.k, np.zeros((T, m, m)), allow_singular=True)
