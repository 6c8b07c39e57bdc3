"""KL-constrained LQG step: closed-form dual vs CasADi/IPOPT and fatrop (docs/math.md §6).

``run()`` builds random, stable, convex instances (time-varying dynamics with process noise,
quadratic costs with a PD action block, a PD reference policy) and solves the KL step with
each method for a total budget (one multiplier, the GPS form) and per-step budgets.  One row
per (size, budget kind):

    n, m, T, budget          problem size and budget kind ("total" or "per_step")
    cf_ms_median, cf_ms_min  closed-form wall time (median / min over ``repeats`` calls)
    n_backward               backward passes of the closed-form dual solve
    ipopt_size               (n, m, T) IPOPT was run on (always the row's size), else None
    ipopt_formulation        "symbolic" or "structured" (``KLStepConfig.casadi_nlp``; "auto"
                             picks "structured" above 600 NLP variables)
    ipopt_status, ipopt_iter IPOPT's return status and iterations
    ipopt_s                  IPOPT wall time of the whole ``kl_step`` call (NLP build included)
    ipopt_build_s, ipopt_solve_s, ipopt_vars
    speedup                  ipopt_s / closed-form median time
    speedup_solve            ipopt_solve_s / closed-form median time (IPOPT iterations only)
    objective_gap            closed-form minus IPOPT expected cost
    max_policy_diff          max |difference| of K, k, Sigma
    max_rel_eta_diff         max relative difference of the multipliers (active budgets)
    worst_violation          max over both solutions of (KL - nu) / nu (<= 0: feasible)
    fatrop_status, fatrop_iter, fatrop_s, fatrop_build_s, fatrop_solve_s
                             the same KL step solved by fatrop (``method="fatrop"``, multiple shooting
                             in the joint moments; see ``soc_opt.lqg.fatrop_nlp``)
    fatrop_max_policy_diff, fatrop_max_rel_eta_diff, fatrop_worst_violation
                             its policy and multipliers against the closed form, its (KL - nu) / nu
    sqp_status, sqp_iter, sqp_s, sqp_build_s, sqp_solve_s, sqp_max_policy_diff, sqp_max_rel_eta_diff,
    sqp_worst_violation      the structured NLP (the same oracle and derivative callbacks IPOPT gets)
                             solved by CasADi's ``sqpmethod`` with ``qpsol`` (default ``osqp``;
                             :func:`sqpmethod_step`), when ``sqp=True``
    cf_cpu_ms_median, ipopt_cpu_s, fatrop_cpu_s, sqp_cpu_s
                             the same calls' CPU time of this process (``time.process_time``; the
                             ``*_s`` / ``*_ms`` columns above are wall time, ``time.perf_counter``)
    note                     why IPOPT or fatrop was skipped, if it was

At ``n=26, m=7, T=100`` (21 700 NLP variables) the symbolic formulation (dense exact Hessian
built by CasADi) is out of reach, and "auto" uses the structured one (per-step block-diagonal
Hessian, exact at the solution; see ``soc_opt.lqg``): IPOPT converges in 15-16 iterations,
7.5-10 s (per-step budgets) and 6-7.5 s (total budget) including about 1-3 s of NLP build, on
the 2-core development machine while it was shared with another job (closed form: 75-130 ms and
36-57 ms), agreeing with the closed form to about 1e-11 in policy and multipliers.  Wall times
on a loaded machine vary by up to a factor 2 between runs.
``ipopt_max_vars`` (default: no limit) skips IPOPT above that many NLP variables,
``fatrop_max_vars`` (default: ``FATROP_MAX_VARS``) fatrop, with the reason in ``note``: at
``n=26, m=7, T=100`` building fatrop's solver (CasADi AD of 100 stages of 377 states and 217
controls) did not finish within 7 minutes (5.9 GB resident).  At ``n=4, m=2, T=20`` fatrop takes
0.5-0.7 s to build and 0.02-0.03 s to solve (10-11 iterations), policy and multipliers within
about 1e-9 of the closed form.  The run at ``(26, 7, 100)`` with CPU times and
sqpmethod (``sqp=True``) is in docs/results/solvers/README.md ("KL step at the paper's size").
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..lqg import KLStepConfig, kl_step
from ..lqg.casadi_nlp import casadi_kinds, nlp_solution
from ..lqg.problem import KLProblem, KLStepResult, check_nu
from ..lqg.structured_nlp import StructuredNLP
from ..testing import make_kl_instance as make_instance

__all__ = ["QUICK", "run", "make_instance", "kl_budget_of", "FATROP_MAX_VARS", "KL_TIME_LIMIT_S"]

#: wall-time limit of one guarded solver call of the KL-step comparison (s): IPOPT at n=26, m=7, T=100 takes
#: 6-10 s with its NLP build, the closed form's timing loop well under 1 s
KL_TIME_LIMIT_S = 120.0

FATROP_MAX_VARS = 5000
"""Default ``fatrop_max_vars`` of :func:`run` (NLP variables in the closed-form count): fatrop's
solver build did not finish within 7 minutes at 21 700 (``n=26, m=7, T=100``)."""
_FATROP_SKIP_REASON = "solver build > 7 min and > 5.9 GB at n=26, m=7, T=100"


def kl_budget_of(kind: str, T: int, rng: np.random.Generator):
    per_step = rng.uniform(0.05, 0.5, T)
    return float(per_step.sum()) if kind == "total" else per_step


def _nlp_vars(n: int, m: int, T: int) -> int:
    return T * (m * n + m + m * (m + 1) // 2)


def _violation(res, nu) -> float:
    if np.isscalar(nu):
        return float((res.kl.sum() - nu) / nu)
    return float(np.max((res.kl - nu) / nu))


def _direct(fn, *args, limit_s, **kwargs):
    return fn(*args, **kwargs)


def _time_closed_form(prob, nu, repeats: int, config):
    times, cpu = [], []
    res = None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        res = kl_step(*prob[:3], nu, *prob[3:], config=config)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return res, np.array(times), np.array(cpu)


def sqpmethod_step(prob, nu, config: KLStepConfig | None = None, qpsol: str = "osqp", max_iter: int = 100,
                   tol: float = 1e-10) -> KLStepResult:
    """The KL step (docs/math.md §6) by CasADi ``sqpmethod``: the structured single-shooting NLP of
    :mod:`soc_opt.lqg.structured_nlp` (the oracle and exact-at-the-solution block Hessian IPOPT is
    given), each SQP subproblem by ``qpsol``; ``prob`` is ``(dynamics, cost, reference, mu0, P0)``.
    ``solver_stats`` has ``build_s`` and ``solve_s`` (wall)."""
    import casadi as ca

    config = KLStepConfig() if config is None else config
    nu_arr, scalar = check_nu(nu, prob[0].A.shape[0])
    kp = KLProblem(prob[0], prob[1], prob[2], prob[3], prob[4])
    nu_full, kind = casadi_kinds(nu_arr, scalar, kp.T)
    free = np.flatnonzero(kind == "free")
    ub = [float(nu_arr[0])] if scalar else [float(nu_full[t]) for t in free]
    t0 = time.perf_counter()
    nlp = StructuredNLP(kp, kind, scalar, config.chol_floor)
    x, f, g = nlp.oracle(ca)
    grad_f, jac_g, hess = nlp.derivative_functions(ca)
    qopts = {"print_iter": False, "print_header": False, "error_on_fail": False} if qpsol == "qrqp" else \
        {"osqp": {"verbose": False}, "error_on_fail": False} if qpsol == "osqp" else {}
    # sqpmethod takes the gradient and Jacobian together and the full symmetric Hessian
    xs, ps, sg, lg = ca.MX.sym("x", nlp.nx), ca.MX.sym("p", 0, 1), ca.MX.sym("lam_f"), ca.MX.sym("lam_g", nlp.ng)
    fv, gfv = grad_f(xs, ps)
    gv, Jv = jac_g(xs, ps)
    jac_fg = ca.Function("kl_jac_fg", [xs, ps], [fv, gfv, gv, Jv], ["x", "p"], ["f", "grad_f_x", "g", "jac_g_x"])
    hess_l = ca.Function("kl_hess_l", [xs, ps, sg, lg], [ca.triu2symm(hess(xs, ps, sg, lg))],
                         ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    opts = {"jac_fg": jac_fg, "hess_lag": hess_l, "qpsol": qpsol, "qpsol_options": qopts,
            "max_iter": max_iter, "tol_pr": tol, "tol_du": tol, "print_header": False, "print_iteration": False,
            "print_status": False, "print_time": False, "error_on_fail": False}
    solver = ca.nlpsol("kl_sqp", "sqpmethod", {"x": x, "f": f, "g": g}, opts)
    build_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    sol = solver(x0=nlp.x0, lbx=nlp.lbx, ubx=np.inf, lbg=-np.inf, ubg=ub)
    solve_s = time.perf_counter() - t1
    st = solver.stats()
    lam = np.asarray(sol["lam_g"]).ravel()[:nlp.ng]
    G, S, _ = nlp.policy(np.asarray(sol["x"]).ravel())
    K, k = G[:, :, :kp.n].copy(), G[:, :, kp.n].copy()
    policy, eta, marg, kl, costs = nlp_solution(kp, kind, free, scalar, K, k, S, lam)
    status = str(st.get("return_status", "unknown"))
    return KLStepResult(policy=policy, eta=eta, kl=kl, expected_cost=float(costs.sum()), n_backward=0,
                        scalar_eta=scalar, nu=float(nu_arr[0]) if scalar else nu_arr.copy(), dual_value=math.nan,
                        method="sqpmethod", n_iter=int(st.get("iter_count", -1)), status=status, marginals=marg,
                        lam_g=lam, solver_stats={"build_s": build_s, "solve_s": solve_s,
                                                 "success": bool(st.get("success", False))})


def _compare_to(cf, res, nu, config) -> dict:
    """Policy, multiplier and feasibility differences of ``res`` against the closed form ``cf``."""
    active = cf.eta > 10 * config.eta_min
    pol_diff = max(np.abs(cf.policy.K - res.policy.K).max(), np.abs(cf.policy.k - res.policy.k).max(),
                   np.abs(cf.policy.cov - res.policy.cov).max())
    return {
        "max_policy_diff": float(pol_diff),
        "max_rel_eta_diff": float(np.max(np.abs(res.eta[active] / cf.eta[active] - 1))) if active.any() else 0.0,
        "violation": _violation(res, nu),
    }


def _solve_and_compare(prob, nu, cf, method: str, config):
    """``(result, wall seconds, _compare_to(cf, result) with its CPU seconds)`` of one NLP solve."""
    t0, c0 = time.perf_counter(), time.process_time()
    if method == "sqpmethod":
        res = sqpmethod_step(prob, nu, config)
    else:
        res = kl_step(*prob[:3], nu, *prob[3:], method=method, config=config)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return res, wall, dict(_compare_to(cf, res, nu, config), cpu_s=cpu)


def _guarded(call, what: str, fn, *args):
    """``call(fn, *args)`` with the KL step's time limit; ``(result, None)`` or ``(None, "stopped: ...")``
    when the guard stopped it (time limit, NaN, a dead worker) or the solver raised."""
    from .guard import GuardError

    try:
        return call(fn, *args, limit_s=KL_TIME_LIMIT_S), None
    except GuardError as e:
        return None, f"stopped: {e}"
    except Exception as e:  # noqa: BLE001 -- a solver failure is a row, not a crashed benchmark
        return None, f"failed: {type(e).__name__}: {e}"[:300]


def _sqp_columns(prob, nu, cf, config, run: bool, call=None) -> dict:
    keys = ("sqp_status", "sqp_iter", "sqp_s", "sqp_cpu_s", "sqp_build_s", "sqp_solve_s", "sqp_max_policy_diff",
            "sqp_max_rel_eta_diff", "sqp_worst_violation")
    row = {k: None for k in keys}
    if not run:
        return row
    got, why = _guarded(call or _direct, "sqpmethod", _solve_and_compare, prob, nu, cf, "sqpmethod", config)
    if got is None:
        return dict(row, sqp_status=why)
    r, t, d = got
    row.update({"sqp_status": r.status, "sqp_iter": r.n_iter, "sqp_s": t, "sqp_cpu_s": d["cpu_s"],
                "sqp_build_s": r.solver_stats["build_s"], "sqp_solve_s": r.solver_stats["solve_s"],
                "sqp_max_policy_diff": d["max_policy_diff"], "sqp_max_rel_eta_diff": d["max_rel_eta_diff"],
                "sqp_worst_violation": d["violation"]})
    return row


def _fatrop_columns(prob, nu, cf, config, run: bool, call=None) -> dict:
    row = {k: None for k in ("fatrop_status", "fatrop_iter", "fatrop_s", "fatrop_cpu_s", "fatrop_build_s", "fatrop_solve_s",
                             "fatrop_max_policy_diff", "fatrop_max_rel_eta_diff", "fatrop_worst_violation")}
    if not run:
        return row
    got, why = _guarded(call or _direct, "fatrop", _solve_and_compare, prob, nu, cf, "fatrop", config)
    if got is None:
        return dict(row, fatrop_status=why)
    fr, t_fr, d = got
    row.update({"fatrop_status": fr.status, "fatrop_iter": fr.n_iter, "fatrop_s": t_fr, "fatrop_cpu_s": d["cpu_s"],
                "fatrop_build_s": fr.solver_stats["build_s"], "fatrop_solve_s": fr.solver_stats["solve_s"],
                "fatrop_max_policy_diff": d["max_policy_diff"], "fatrop_max_rel_eta_diff": d["max_rel_eta_diff"],
                "fatrop_worst_violation": d["violation"]})
    return row


def _row(n, m, T, kind, seed, repeats, config, run_ipopt: bool, note=None, run_fatrop: bool = True,
         run_sqp: bool = False, call=None) -> dict:
    rng = np.random.default_rng([seed, n, m, T])
    prob = make_instance(n, m, T, rng)
    nu = kl_budget_of(kind, T, rng)
    got, why = _guarded(call or _direct, "closed form", _time_closed_form, prob, nu, repeats, config)
    if got is None:  # nothing to compare the NLP solvers with
        return {"n": n, "m": m, "T": T, "budget": kind, "note": f"closed form {why}"}
    cf, times, cpu = got
    row = {
        "n": n, "m": m, "T": T, "budget": kind,
        "cf_ms_median": 1e3 * float(np.median(times)), "cf_ms_min": 1e3 * float(times.min()),
        "cf_cpu_ms_median": 1e3 * float(np.median(cpu)), "ipopt_cpu_s": None,
        "n_backward": cf.n_backward,
        "ipopt_size": None, "ipopt_formulation": None, "ipopt_status": None, "ipopt_iter": None, "ipopt_s": None,
        "ipopt_build_s": None, "ipopt_solve_s": None, "ipopt_vars": _nlp_vars(n, m, T), "speedup": None,
        "speedup_solve": None, "objective_gap": None, "max_policy_diff": None,
        "max_rel_eta_diff": None, "worst_violation": _violation(cf, nu), "note": note,
    }
    row.update(_fatrop_columns(prob, nu, cf, config, run_fatrop, call))
    row.update(_sqp_columns(prob, nu, cf, config, run_sqp, call))
    if not run_ipopt:
        return row
    got, why = _guarded(call or _direct, "IPOPT", _solve_and_compare, prob, nu, cf, "casadi", config)
    if got is None:
        return dict(row, ipopt_status=why)
    ip, t_ip, d = got
    row.update({
        "ipopt_size": (n, m, T), "ipopt_formulation": ip.solver_stats["formulation"], "ipopt_status": ip.status,
        "ipopt_iter": ip.n_iter, "ipopt_s": t_ip, "ipopt_cpu_s": d["cpu_s"], "ipopt_build_s": ip.solver_stats["build_s"],
        "ipopt_solve_s": ip.solver_stats["solve_s"],
        "speedup": t_ip / float(np.median(times)),
        "speedup_solve": ip.solver_stats["solve_s"] / float(np.median(times)),
        "objective_gap": cf.expected_cost - ip.expected_cost,
        "max_policy_diff": d["max_policy_diff"],
        "max_rel_eta_diff": d["max_rel_eta_diff"],
        "worst_violation": max(_violation(cf, nu), d["violation"]),
    })
    return row


def run(sizes=((4, 2, 20), (26, 7, 100)), seed: int = 0, *, repeats: int = 7, ipopt_max_vars: int | None = None,
        fatrop_max_vars: int | None = FATROP_MAX_VARS, budgets=("total", "per_step"),
        config: KLStepConfig | None = None, sqp: bool = False, call=None, progress=None) -> list[dict]:
    """Closed form vs CasADi/IPOPT and fatrop on random instances; one row per (size, budget)
    (module docstring).

    IPOPT runs at every size (formulation from ``config.casadi_nlp``, default "auto"), unless the
    NLP has more than ``ipopt_max_vars`` variables, and fatrop unless more than ``fatrop_max_vars``
    (default :data:`FATROP_MAX_VARS`; ``None``: no limit): then the row says so in ``note``.

    ``call``: how each solver call is made, ``call(fn, *args, limit_s=KL_TIME_LIMIT_S)`` (default: in this
    process; ``soc-opt solvers`` passes :meth:`soc_opt.bench.guard.Guard.call`): a call it stops, or a solver
    that raises, fills that solver's status column with the reason.  ``progress``: a callable given one
    line per row.
    """
    config = KLStepConfig() if config is None else config
    rows = []
    for n, m, T in sizes:
        nv = _nlp_vars(n, m, T)
        run_ipopt = ipopt_max_vars is None or nv <= ipopt_max_vars
        run_fatrop = fatrop_max_vars is None or nv <= fatrop_max_vars
        notes = [f"{name} skipped: {nv} NLP variables > {name.lower()}_max_vars={lim}"
                 for name, ok, lim in (("IPOPT", run_ipopt, ipopt_max_vars), ("fatrop", run_fatrop, fatrop_max_vars))
                 if not ok]
        if not run_fatrop and fatrop_max_vars == FATROP_MAX_VARS:
            notes[-1] += f" ({_FATROP_SKIP_REASON})"
        for kind in budgets:
            t0 = time.perf_counter()
            row = _row(n, m, T, kind, seed, repeats, config, run_ipopt, note="; ".join(notes) or None,
                       run_fatrop=run_fatrop, run_sqp=sqp, call=call)
            rows.append(row)
            if progress is not None:
                stat = ", ".join(f"{k.split('_')[0]} {row[k]}" for k in ("ipopt_status", "fatrop_status", "sqp_status")
                                 if row.get(k) is not None)
                progress(f"KL step n={n} m={m} T={T} {kind}: {time.perf_counter() - t0:.1f} s"
                         + (f" ({stat})" if stat else "") + (f"; {row['note']}" if row.get("note") else ""))
    return rows


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"sizes": ((3, 1, 5),), "repeats": 1}


if __name__ == "__main__":
    cols = ["n", "m", "T", "budget", "cf_ms_median", "n_backward", "ipopt_formulation", "ipopt_status", "ipopt_s",
            "ipopt_build_s", "ipopt_solve_s", "ipopt_iter", "speedup", "speedup_solve", "objective_gap",
            "max_policy_diff", "max_rel_eta_diff", "worst_violation", "fatrop_build_s", "fatrop_solve_s",
            "fatrop_iter", "fatrop_max_policy_diff", "fatrop_max_rel_eta_diff"]
    out = run()
    print(" | ".join(cols))
    for r in out:
        print(" | ".join(_fmt(r[c]) for c in cols) + (f"   ({r['note']})" if r["note"] else ""))
