"""Maximisation of the exact-EM objective (``objective="exact"``, docs/math.md §5) by inner EM iterations.

The objective ``exact_k = E[log N(zeta; M s + m, S)]`` (action integrated out) is defined in
:mod:`soc_opt.mstep.objectives`; maximising ``sum_k exact_k`` is the M-step under which
``log p(Y)`` is provably non-decreasing (the EM lemma).

It is maximised by inner EM iterations with the action as the latent variable (a generalized-EM
step started from ``previous``).  Given ``(s, zeta)`` the action posterior is Gaussian with mean
``G zeta + J stilde`` (``G = Sigma B^T S^{-1}``, ``J = F - G M``) and covariance
``V = Sigma - G B Sigma``, so ``E[a stilde^T] = G Szs + J Stilde`` and
``E[a a^T] = V + (G, J) [[Szz, Szs], [Szs^T, Stilde]] (G, J)^T`` follow from the moments.  The inner
M-step is ``F' = E[a stilde^T] Stilde^{-1}``, ``Sigma' = E[(a - F' stilde)(a - F' stilde)^T] =: W``.
Constraints are applied to the inner M-step: ``cov_floor``/``cov_ceiling`` by clipping the
eigenvalues of ``W`` whitened by the bound (the Gaussian-likelihood maximiser over the Loewner
half-space), ``entropy_floor`` by ``max(1, e^{(c - log det W)/m}) W``, floor and ceiling together
by the relaxation rule or a CVXPY log-det program in the precision, and ``offset_bound``/``trust_region``
by a CVXPY step in ``F`` with ``Sigma`` held at its current value (an ECM step).  Every inner step
does not decrease ``sum_k exact_k`` (from a feasible start); iteration stops when the relative
change is below ``MStepConfig.exact_tol``.  ``entropy_floor`` combined with another covariance
constraint is not supported for the exact objective.
"""

from __future__ import annotations

import numpy as np

from .. import linalg as la
from ..estep import Moments
from ..models import AugmentedModel, LinearGaussianPolicy, symmetrize
from .config import MStepConfig
from .constraints import Resolved, feasible_sigma
from .errors import ClosedFormUnavailableError, NonUniqueMaximizerError
from .objectives import atil, exact_objective_from_moments, min_eig_rel, policy_F

__all__: list[str] = []  # internal: used by soc_opt.mstep.maximize


def _action_posterior(model: AugmentedModel, mom: Moments, F: np.ndarray, Sigma: np.ndarray):
    """``E[a stilde^T]`` (T, m, n+1) and ``E[a a^T]`` (T, m, m) under the action posterior."""
    B = model.Bs
    Mt = atil(model) + B @ F
    S = symmetrize(model.So + B @ Sigma @ la.T(B))
    L = la.chol(S, "closed-loop covariance S")
    G = la.T(la.cho_solve(L, B @ Sigma))  # Sigma B^T S^{-1}
    J = F - G @ Mt
    V = symmetrize(Sigma - G @ B @ Sigma)
    Eas = G @ mom.Szs + J @ mom.Sss
    X = G @ mom.Szs @ la.T(J)
    Eaa = symmetrize(V + G @ mom.Szz @ la.T(G) + X + la.T(X) + J @ mom.Sss @ la.T(J))
    return Eas, Eaa


def _clip_whitened(W: np.ndarray, S0: np.ndarray, lower: bool) -> np.ndarray:
    """Maximiser of ``-log|X| - tr(X^{-1} W)`` over ``X >= S0`` (lower) or ``X <= S0`` (upper)."""
    L = np.linalg.cholesky(S0)
    Wt = la.tri_solve(L, la.T(la.tri_solve(L, W)))
    d, U = np.linalg.eigh(symmetrize(Wt))
    d = np.maximum(d, 1.0) if lower else np.minimum(d, 1.0)
    Y = (U * d[..., None, :]) @ la.T(U)
    return symmetrize(L @ Y @ la.T(L))


def sigma_exact(W: np.ndarray, rc: Resolved, method: str, solver: str, cfg: MStepConfig, labels: list[str]):
    """Inner M-step for Sigma: maximise ``-1/2 (log|Sigma| + tr(Sigma^{-1} W))`` over the covariance set
    (batched; ``rc`` resolved for as many steps as ``W`` has)."""
    floor, entropy, ceiling = rc.sigma_key
    W = symmetrize(W)
    m = W.shape[-1]
    if not (floor or entropy or ceiling):
        return W
    if entropy:
        L = la.chol(W, "inner-EM action covariance W")
        beta = np.exp(np.maximum(0.0, (rc.c - la.logdet_chol(L)) / m))
        return beta[:, None, None] * W
    if floor and not ceiling:
        return _clip_whitened(W, rc.Smin, lower=True)
    if ceiling and not floor:
        return _clip_whitened(W, rc.Smax, lower=False)
    out = np.empty_like(W)
    for i in range(W.shape[0]):
        X = _clip_whitened(W[i], rc.Smin[i], lower=True)
        if feasible_sigma(X, rc, i, cfg, skip="cov_floor"):
            out[i] = X
            continue
        X = _clip_whitened(W[i], rc.Smax[i], lower=False)
        if feasible_sigma(X, rc, i, cfg, skip="cov_ceiling"):
            out[i] = X
            continue
        if method != "cvxpy":
            raise ClosedFormUnavailableError(
                f"{labels[i]}: cov_floor and cov_ceiling are active together in the exact-EM covariance "
                f"step, which has no closed form; use method='cvxpy'"
            )
        from .cvx import get_problem, solve_cvx  # cvxpy only when a CVXPY step runs (maximize.py)

        prob = get_problem(("prec", 0, m, None, False, 0))
        prob.params["W"].value = W[i]
        prob.params["Pmax"].value = la.inv_from_chol(np.linalg.cholesky(rc.Smin[i]))
        prob.params["Pmin"].value = la.inv_from_chol(np.linalg.cholesky(rc.Smax[i]))
        solve_cvx(prob, solver, cfg, f"{labels[i]} (exact-EM covariance step)", None)
        out[i] = la.inv_from_chol(la.chol(symmetrize(prob.Sigma.value), "precision P"))
    return out


def _f_step_exact(model, Eas, S, Sigma, rc, method, solver, cfg, Fprev, min_norm, labels):
    """Inner M-step for F: unconstrained ``E[a stilde^T] Stilde^{-1}``; with offset/trust constraints a
    CVXPY step weighted by ``Sigma^{-1}`` (Sigma held fixed: ECM).  Batched over the leading axis."""
    n, m = model.n, model.m
    p_min, p_rel = min_eig_rel(S)
    if np.any(p_rel <= cfg.eig_tol):
        if not min_norm:
            i = int(np.flatnonzero(p_rel <= cfg.eig_tol)[-1])
            raise NonUniqueMaximizerError(
                f"exact-EM M-step is not resolved at {labels[i]}: Stilde (so P_k) has relative smallest eigenvalue "
                f"{p_rel[i]:.3e} <= eig_tol = {cfg.eig_tol:g} (smallest eigenvalue {p_min[i]:.3e}, condition number "
                f"{(1.0 / p_rel[i]) if p_rel[i] > 0 else float('inf'):.3e}). Pass min_norm=True for the minimum-norm "
                "maximiser."
            )
        F = Eas @ np.linalg.pinv(S, rcond=cfg.eig_tol, hermitian=True)
    else:
        F = la.right_cho_solve(Eas, la.chol(S, "Stilde"))
    if not rc.f_constrained:
        return F
    if method != "cvxpy":
        raise ClosedFormUnavailableError(
            "offset_bound and trust_region have no closed form (also in the exact-EM step); use method='cvxpy'"
        )
    from .cvx import get_problem, kron_eig, set_spectral_params, solve_cvx, spectral_data, spectral_F, vec_batch

    N = F.shape[0]
    n1 = n + 1
    n_trust = 0 if rc.delta is None else (1 if N == model.T else model.T)
    prob = get_problem(("spectral", n, m, None, rc.b is not None, n_trust))
    la.chol(S, "Stilde")  # the constrained step needs Stilde > 0
    H = la.inv_from_chol(la.chol(Sigma, "Sigma"))  # Sigma^{-1}
    # E[log N(a; F stilde, Sigma)] = const - 1/2 tr(H F S F^T) + tr(F^T H E[a stilde^T])
    lam, U = kron_eig(H, S)
    if rc.delta is not None:
        Fp = vec_batch(Fprev)
        centres = [Fp[i : i + 1] if n_trust == 1 else Fp for i in range(N)]
        f0 = np.stack([c.mean(0) for c in centres])
    else:
        centres = [None] * N
        f0 = np.zeros((N, m * n1))
    lam, g, _ = spectral_data(lam, U, vec_batch(H @ Eas), f0)
    out = np.empty_like(F)
    for i in range(N - 1, -1, -1):
        set_spectral_params(prob, rc, n, lam[i], g[i], U[i], f0[i], centres[i])
        solve_cvx(prob, solver, cfg, f"{labels[i]} (exact-EM mean step)", None)
        out[i] = spectral_F(prob, U[i], f0[i], m, n1)
    return out


def run_exact_em(model, mom, rc, cfg, method, solver, variant, previous, min_norm):
    T, n = model.T, model.n
    if previous is None:
        raise ValueError("objective='exact' needs previous= (the current policy): the exact-EM M-step "
                         "is an iteration started from it")
    if previous.allow_singular or np.any(np.linalg.eigvalsh(previous.cov)[:, 0] <= 0):
        raise ValueError("objective='exact' needs a previous policy with positive definite covariances")
    if rc.c is not None and (rc.Smin is not None or rc.Smax is not None):
        raise ValueError("objective='exact' supports entropy_floor only on its own, not combined with "
                         "cov_floor or cov_ceiling")
    for name, S0 in (("cov_floor", rc.Smin), ("cov_ceiling", rc.Smax)):
        if S0 is not None and np.linalg.eigvalsh(S0)[:, 0].min() <= 0:
            raise ValueError(f"objective='exact' needs a positive definite {name}")
    F = policy_F(previous).copy()
    Sigma = np.array(previous.cov)
    Fprev = policy_F(previous)
    ti = variant == "time_invariant"
    if ti:  # start from the time average of the previous policy
        F = np.broadcast_to(F.mean(0), F.shape).copy()
        Sigma = np.broadcast_to(symmetrize(Sigma.mean(0)), Sigma.shape).copy()
        labels = ["time-invariant M-step"]
    else:
        labels = [f"time step k={k}" for k in range(T)]

    def policy_of(F, Sigma):
        return LinearGaussianPolicy(F[..., :n], F[..., n], Sigma)

    hist = [exact_objective_from_moments(model, mom, policy_of(F, Sigma))]
    converged = False
    it = 0
    Sss = symmetrize(np.asarray(mom.Sss, dtype=float))
    for it in range(1, cfg.exact_max_iter + 1):
        Eas, Eaa = _action_posterior(model, mom, F, Sigma)
        if ti:
            Fn = _f_step_exact(model, Eas.sum(0)[None], Sss.sum(0)[None], Sigma[:1], rc, method, solver, cfg,
                               Fprev, min_norm, labels)
            Fn = np.broadcast_to(Fn, F.shape)
        else:
            Fn = _f_step_exact(model, Eas, Sss, Sigma, rc, method, solver, cfg, Fprev, min_norm, labels)
        X = Fn @ la.T(Eas)
        W = symmetrize(Eaa - X - la.T(X) + Fn @ Sss @ la.T(Fn))
        if ti:
            Sn = sigma_exact(W.mean(0)[None], rc.time_invariant(), method, solver, cfg, labels)
            Sn = np.broadcast_to(Sn, Sigma.shape)
        else:
            Sn = sigma_exact(W, rc, method, solver, cfg, labels)
        F, Sigma = np.array(Fn), np.array(symmetrize(Sn))
        hist.append(exact_objective_from_moments(model, mom, policy_of(F, Sigma)))
        a, b = hist[-2], hist[-1]
        if ti:
            a, b = a.sum(keepdims=True), b.sum(keepdims=True)
        if np.all(np.abs(b - a) <= cfg.exact_tol * (1.0 + np.abs(b))):
            converged = True
            break
    return policy_of(F, Sigma), np.array(hist), it, converged
