"""The KL-constrained LQG step as a nonlinear program solved by IPOPT (method ``"casadi"``,
docs/math.md §6).

The same problem as an NLP over ``(K_k, k_k, L_k)`` with single-shooting moments, solved by
IPOPT (:func:`kl_step_casadi`), in one of two formulations (``KLStepConfig.casadi_nlp``, by
default chosen by size):

* ``"symbolic"`` (:func:`_casadi_symbolic`, up to ``casadi_auto_max_vars = 600`` NLP variables):
  SX expressions and CasADi's symbolic exact Hessian, dense in all variables; a reference solver
  for small problems (documented and tested for ``n <= 6, T <= 20``).
* ``"structured"`` (:class:`.structured_nlp.StructuredNLP`, above that size): the policy
  variables rescaled by the reference policy (KL Hessian close to the identity), objective and constraints as chained
  per-step CasADi functions, the gradient and the constraint Jacobian from the adjoint
  (value-function) recursion of the moment dynamics, and a per-step block-diagonal Hessian of
  the Lagrangian.  The Lagrangian is linear in the state second moments, and at a KKT point the
  backward-pass optimality ``(Q_ux + Q_uu G_k) X_k = 0`` makes every cross-step block of the
  exact Hessian vanish: IPOPT sees the exact Hessian at the solution and converges
  superlinearly, in 12-16 iterations from the reference on the random instances up to
  ``n=26, m=7, T=100`` (21 700 variables; about 10 s), about 40 when some budget is slack and
  ``Sigma_k`` collapses onto the ``chol_floor`` bound.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..linalg import logdet_pd
from ..models import symmetrize
from .moments import expected_cost_marg, forward_arrays, kl_batched
from .problem import KLProblem, KLStepConfig, KLStepResult, SolverError, policy_from
from .structured_nlp import StructuredNLP

_IPOPT_OK = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def casadi_kinds(nu: np.ndarray, scalar: bool, T: int) -> tuple[np.ndarray, np.ndarray]:
    """``(nu per step, kind per step)``: ``"free"`` (finite ``nu_k > 0``: ``K, k, L`` variables and a
    KL row), ``"det"`` (``nu_k = inf``: ``K, k`` only, ``Sigma_k = 0``), ``"pin"`` (``nu_k = 0``: the
    reference, no variables)."""
    nu_full = np.full(T, nu[0]) if scalar else nu
    return nu_full, np.where(np.isinf(nu_full), "det", np.where(nu_full == 0, "pin", "free"))


def casadi_n_vars(kind: np.ndarray, n: int, m: int) -> int:
    """NLP size (both formulations): ``m n + m`` per unpinned step, ``m (m+1)/2`` more per free step."""
    return int(np.sum(kind != "pin") * (m * n + m) + np.sum(kind == "free") * (m * (m + 1) // 2))


def kl_step_casadi(prob: KLProblem, nu: np.ndarray, scalar: bool, nu_out, config: KLStepConfig) -> KLStepResult:
    """The same problem as a nonlinear program solved by IPOPT (CasADi ``nlpsol``).

    Decision variables per step: the gain ``K_k``, the offset ``k_k`` and the lower-triangular
    Cholesky factor ``L_k`` of ``Sigma_k = L_k L_k^T`` (directly, or affinely rescaled in the
    structured formulation).  Single shooting: the state moments are functions of the policy
    through the moment recursion, so every iterate is a valid policy with PSD moments.
    (A multiple-shooting variant with free ``P_k`` variables was tried and rejected: the
    bilinear ``K P`` terms make the Lagrangian Hessian strongly indefinite away from the
    solution and IPOPT failed on most ``T = 20`` instances; at ``n = 26`` its KKT systems would
    also have dense 350-variable covariance blocks per step.)  Objective ``sum_k E[l_k]`` and
    constraints ``KL_k <= nu_k`` (or ``sum_k KL_k <= nu``) in closed form.  Steps with
    ``nu_k = inf`` are deterministic (no ``L_k``, no constraint); steps with ``nu_k = 0`` are fixed
    to the reference.  Warm start: the reference policy.  The multipliers ``lam_g >= 0`` of the
    KL rows (CasADi Lagrangian ``f + lam_g^T g``, active upper bound) are the ``eta_k``.
    IPOPT's status is checked: anything but ``Solve_Succeeded``, ``Solved_To_Acceptable_Level``
    or ``Search_Direction_Becomes_Too_Small`` at an iterate whose primal and dual infeasibilities
    are below ``ipopt_acceptable_tol`` (``tol = 1e-12`` is below the roundoff floor of some
    problems with large multipliers) raises :class:`SolverError` (:func:`_ipopt_solve`).

    Two formulations (``config.casadi_nlp``; ``"auto"`` picks ``"symbolic"`` up to
    ``config.casadi_auto_max_vars`` NLP variables and ``"structured"`` above):
    :func:`_casadi_symbolic` (CasADi builds the dense exact Hessian symbolically: small problems)
    and :func:`_casadi_structured` (analytic adjoint derivatives and a per-step block-diagonal
    Hessian that is exact at the solution: scales to ``n=26, m=7, T=100``).
    """
    T, n, m = prob.T, prob.n, prob.m
    nu_full, kind = casadi_kinds(nu, scalar, T)
    n_vars = casadi_n_vars(kind, n, m)
    form = config.casadi_nlp
    if form == "auto":
        form = "symbolic" if n_vars <= config.casadi_auto_max_vars else "structured"
    free = np.flatnonzero(kind == "free")
    if scalar and free.size:
        ub = [float(nu[0])]
    else:
        ub = [float(nu_full[t]) for t in free]
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.tol": config.ipopt_tol,
        "ipopt.acceptable_tol": config.ipopt_acceptable_tol,
        "ipopt.max_iter": config.ipopt_max_iter,
        "ipopt.bound_relax_factor": 0.0,  # keep L_ii >= chol_floor > 0 exactly (log L_ii)
    }
    if n_vars == 0:  # every step pinned to the reference: nothing to optimise
        Kout, kout, Sout = prob.reference.K.copy(), prob.reference.k.copy(), prob.reference.cov.copy()
        lam, status, n_iter, fval = np.zeros(0), "nothing to solve (nu = 0)", 0, float("nan")
        timing = {"build_s": 0.0, "solve_s": 0.0}
    elif form == "structured":
        Kout, kout, Sout, lam, status, n_iter, fval, timing = _casadi_structured(prob, kind, scalar, ub, opts, config)
    else:
        Kout, kout, Sout, lam, status, n_iter, fval, timing = _casadi_symbolic(prob, kind, scalar, ub, opts, config)
    policy, eta, marg, kl, costs = nlp_solution(prob, kind, free, scalar, Kout, kout, Sout, lam)
    return KLStepResult(
        policy=policy, eta=eta, kl=kl, expected_cost=float(costs.sum()), n_backward=0, scalar_eta=scalar,
        nu=nu_out, dual_value=fval, method="casadi", n_iter=n_iter, status=status, marginals=marg, lam_g=lam,
        solver_stats={"n_vars": n_vars, "formulation": form if n_vars else "none", **timing},
    )


def nlp_solution(prob: KLProblem, kind: np.ndarray, free: np.ndarray, scalar: bool, K, k, S, lam):
    """The KL step's result from an NLP's policy ``(K, k, S)`` and its KL-row multipliers ``lam``
    (shared by the IPOPT and fatrop forms): ``eta`` (``inf`` on pinned steps, 0 on unconstrained
    ones, ``lam`` on the constrained ones or everywhere for a total budget), the policy, its
    marginals, ``KL_k`` and the expected stage costs."""
    eta = np.where(kind == "pin", np.inf, 0.0)
    if scalar:
        if lam.size:
            eta[:] = lam[0]
    else:
        eta[free] = lam
    policy = policy_from(K, k, symmetrize(S), eta)
    marg = forward_arrays(prob.dynamics, policy.K, policy.k, policy.cov, prob.mu0, prob.P0)
    ref = prob.reference
    kl = kl_batched(policy.K, policy.k, policy.cov, logdet_pd(policy.cov), ref.K, ref.k, prob.Shinv,
                    prob.logdetSh, marg.mean, marg.cov)
    return policy, eta, marg, kl, expected_cost_marg(prob.cost, marg)


def _ipopt_solve(solver_fn, x0, lbx, ub, n_kl, acceptable_tol: float):
    """Run an ``nlpsol`` and check IPOPT's status; returns ``(x, lam_g, status, n_iter, f, solve_s)``.

    Accepted: ``Solve_Succeeded``, ``Solved_To_Acceptable_Level``, and
    ``Search_Direction_Becomes_Too_Small`` when the last iterate's (scaled) primal and dual
    infeasibilities are at most ``acceptable_tol`` (IPOPT converged to the roundoff floor, above
    ``tol``, and stopped before its ``acceptable_iter`` count); anything else raises
    :class:`SolverError`.
    """
    t1 = time.perf_counter()
    sol = solver_fn(x0=x0, lbx=lbx, ubx=np.inf, lbg=-np.inf, ubg=ub)
    solve_s = time.perf_counter() - t1
    stats = solver_fn.stats()
    status = str(stats.get("return_status", "unknown"))
    ok = status in _IPOPT_OK
    if status == "Search_Direction_Becomes_Too_Small":
        its = stats.get("iterations", {})
        last = [its.get(k, [math.inf])[-1] if its.get(k) else math.inf for k in ("inf_pr", "inf_du")]
        ok = max(last) <= acceptable_tol
    if not ok:
        raise SolverError(f"IPOPT failed: return_status={status!r}", status=status)
    lam = np.asarray(sol["lam_g"]).ravel()[:n_kl]
    return (np.asarray(sol["x"]).ravel(), lam, status, int(stats.get("iter_count", -1)), float(sol["f"]),
            solve_s)


def _casadi_symbolic(prob: KLProblem, kind: np.ndarray, scalar: bool, ub, opts: dict, config: KLStepConfig):
    """SX single shooting in ``(K_k, k_k, L_k)`` with CasADi's symbolic exact Hessian.

    ``L_k`` is the Cholesky factor of ``Sigma_k`` itself, its diagonal bounded below by
    ``chol_floor``.  The exact Hessian is dense in the ``T (m n + m + m(m+1)/2)`` variables and
    CasADi builds it symbolically, which dominates the run time (about 0.5 s at ``n=4, m=2,
    T=10``, 25 s at ``n=6, m=3, T=20``, out of reach at ``n=26, m=7, T=100``): the reference
    solver for small problems, agreeing with the closed form to about 1e-10.
    Returns ``(K, k, Sigma, lam_g, status, n_iter, f, timing)``.
    """
    import casadi as ca

    T, n, m = prob.T, prob.n, prob.m
    dyn, cst, ref = prob.dynamics, prob.cost, prob.reference
    tril = [(i, j) for i in range(m) for j in range(i + 1)]

    xs, x0, lbx = [], [], []

    def newvar(name, size, init, lb=-np.inf):
        v = ca.SX.sym(name, size)
        xs.append(v)
        x0.extend(np.ravel(init).tolist())
        lbx.extend(np.broadcast_to(lb, (size,)).tolist())
        return v

    obj = 0
    kl_terms: list[Any] = []
    mu, P = ca.DM(prob.mu0), ca.DM(prob.P0)
    for t in range(T):
        if kind[t] == "pin":
            K, kk, S = ca.DM(ref.K[t]), ca.DM(ref.k[t]), ca.DM(ref.cov[t])
        else:
            K = ca.reshape(newvar(f"K{t}", m * n, ref.K[t].T), m, n)  # column-major
            kk = newvar(f"k{t}", m, ref.k[t])
            if kind[t] == "det":
                S = ca.DM.zeros(m, m)
            else:
                Lh = np.linalg.cholesky(ref.cov[t])
                lv = newvar(f"L{t}", len(tril), [Lh[i, j] for i, j in tril],
                            lb=np.array([config.chol_floor if i == j else -np.inf for i, j in tril]))
                L = ca.SX.zeros(m, m)
                for idx, (i, j) in enumerate(tril):
                    L[i, j] = lv[idx]
                S = ca.mtimes(L, L.T)
        D = {"A": ca.DM(dyn.A[t]), "B": ca.DM(dyn.B[t]), "c": ca.DM(dyn.c[t]), "W": ca.DM(dyn.cov[t]),
             "C": ca.DM(cst.C[t]), "cl": ca.DM(cst.c[t]), "c0": float(cst.c0[t]), "Kh": ca.DM(ref.K[t]),
             "kh": ca.DM(ref.k[t]), "R": ca.DM(prob.Shinv[t]), "logdetSh": float(prob.logdetSh[t])}
        logdetS = 2 * sum(ca.log(L[i, i]) for i in range(m)) if kind[t] == "free" else None
        stage_obj, kl, mu_n, P_n = stage_terms(ca, D, n, mu, P, K, kk, S, logdetS)
        obj = obj + stage_obj
        if kl is not None:
            kl_terms.append(kl)
        if t < T - 1:
            mu, P = mu_n, P_n

    g_kl = ([sum(kl_terms)] if scalar else kl_terms) if kl_terms else []
    opts = dict(opts)
    opts.update({f"ipopt.{k}": v for k, v in config.ipopt_options.items()})
    x = ca.vertcat(*xs)
    g = ca.vertcat(*g_kl) if g_kl else ca.SX.zeros(0, 1)
    t0 = time.perf_counter()
    solver = ca.nlpsol("kl_step", "ipopt", {"x": x, "f": obj, "g": g}, opts)
    build_s = time.perf_counter() - t0
    sol_x, lam, status, n_iter, fval, solve_s = _ipopt_solve(solver, x0, lbx, ub, len(g_kl),
                                                             config.ipopt_acceptable_tol)

    Kout, kout, Sout = np.empty((T, m, n)), np.empty((T, m)), np.empty((T, m, m))
    pos = 0
    for t in range(T):  # same variable order as created
        if kind[t] == "pin":
            Kout[t], kout[t], Sout[t] = ref.K[t], ref.k[t], ref.cov[t]
            continue
        Kout[t] = sol_x[pos : pos + m * n].reshape(n, m).T
        pos += m * n
        kout[t] = sol_x[pos : pos + m]
        pos += m
        Sout[t] = 0.0
        if kind[t] == "free":
            Lt = np.zeros((m, m))
            for idx, (i, j) in enumerate(tril):
                Lt[i, j] = sol_x[pos + idx]
            pos += len(tril)
            Sout[t] = Lt @ Lt.T
    return Kout, kout, Sout, lam, status, n_iter, fval, {"build_s": build_s, "solve_s": solve_s}


def stage_terms(ca, D: dict, n: int, mu, P, K, kk, S, logdetS):
    """CasADi expressions of one step (docs/math.md §6): ``(E[l], KL or None, E[s'], Cov(s'))`` for the state
    moments ``(mu, P)``, the policy ``(K, kk, S)`` and the step's data ``D`` (keys ``A, B, c, W, C, cl,
    c0, Kh, kh, R = Sh^-1, logdetSh``); ``KL`` only when ``logdetS`` (``log|S|``) is given.  Shared by
    the symbolic IPOPT NLP and the fatrop stages."""
    C = D["C"]
    a_mean = ca.mtimes(K, mu) + kk
    PKt = ca.mtimes(P, K.T)
    Pa = ca.mtimes(K, PKt) + S
    zbar = ca.vertcat(mu, a_mean)
    trace = (ca.sum1(ca.sum2(C[:n, :n] * P)) + 2 * ca.sum1(ca.sum2(C[:n, n:] * PKt))
             + ca.sum1(ca.sum2(C[n:, n:] * Pa)))
    obj = 0.5 * trace + 0.5 * ca.mtimes([zbar.T, C, zbar]) + ca.dot(D["cl"], zbar) + D["c0"]
    kl = None
    if logdetS is not None:
        R, m = D["R"], K.shape[0]
        dK = K - D["Kh"]
        dm = ca.mtimes(dK, mu) + kk - D["kh"]
        kl = 0.5 * (ca.sum1(ca.sum2(R * S)) - m + D["logdetSh"] - logdetS
                    + ca.mtimes([dm.T, R, dm]) + ca.sum1(ca.sum2(ca.mtimes([R, dK, P]) * dK)))
    A, B = D["A"], D["B"]
    Acl = A + ca.mtimes(B, K)
    mu_n = ca.mtimes(Acl, mu) + ca.mtimes(B, kk) + D["c"]
    P_n = ca.mtimes([Acl, P, Acl.T]) + ca.mtimes([B, S, B.T]) + D["W"]
    return obj, kl, mu_n, 0.5 * (P_n + P_n.T)


def _casadi_structured(prob: KLProblem, kind: np.ndarray, scalar: bool, ub, opts: dict, config: KLStepConfig):
    """:class:`StructuredNLP` solved by IPOPT: objective and constraints as CasADi MX graphs of
    per-step SX functions, first derivatives and the block-diagonal Hessian from NumPy callbacks.

    MUMPS uses the QAMD ordering (``mumps_pivot_order = 6``: the per-step KL rows of the Jacobian
    are dense; the default ordering makes the factorisation about 4 times slower at ``n=26, m=7,
    T=100``).  Returns ``(K, k, Sigma, lam_g, status, n_iter, f, timing)``.
    """
    import casadi as ca

    t0 = time.perf_counter()
    nlp = StructuredNLP(prob, kind, scalar, config.chol_floor)
    x, f, g = nlp.oracle(ca)
    grad_f, jac_g, hess = nlp.derivative_functions(ca)
    opts = dict(opts, **{"ipopt.mumps_pivot_order": 6, "grad_f": grad_f, "jac_g": jac_g, "hess_lag": hess})
    opts.update({f"ipopt.{k}": v for k, v in config.ipopt_options.items()})
    solver = ca.nlpsol("kl_step", "ipopt", {"x": x, "f": f, "g": g}, opts)
    build_s = time.perf_counter() - t0
    sol_x, lam, status, n_iter, fval, solve_s = _ipopt_solve(solver, nlp.x0, nlp.lbx, ub, nlp.ng,
                                                             config.ipopt_acceptable_tol)
    G, S, _ = nlp.policy(sol_x)
    n = prob.n
    K, k = G[:, :, :n].copy(), G[:, :, n].copy()
    pin = kind == "pin"
    K[pin], k[pin] = prob.reference.K[pin], prob.reference.k[pin]  # exactly the reference
    S[kind == "det"] = 0.0
    return K, k, S, lam, status, n_iter, fval, {"build_s": build_s, "solve_s": solve_s}
