"""M-step solver benchmark (docs/math.md §5): every constraint set, every applicable solver.

Per size ``(n, m)``, ``instances`` random well-posed instances (:func:`soc_opt.bench.mstep.random_instance`)
of ``T`` steps each; every step is one problem.  Constraint sets: ``cov_floor``, ``entropy_floor``
(closed forms), ``offset_bound`` and ``trust_region`` (CVXPY is the library's only path).  Reference:
the library's closed form where it exists; for ``offset_bound`` an exact KKT solve on the active
set (:func:`kkt_box_reference`; the committed tables of this benchmark predate it and used scipy
``L-BFGS-B``), for ``trust_region`` the exact trust-region subproblem (eigendecomposition of
``Stilde kron H`` and a bracketed root of the secular equation) -- both independent of CVXPY.

Solvers (``method`` column):

* ``library/CLARABEL``, ``library/SCS``: ``mstep.maximize(method="cvxpy")``, the whole
  problem over ``([K k], Sigma)`` with ``Sigma`` a PSD variable (DPP, cached).
* ``qp/<S>``: ``Sigma`` fixed at its closed-form optimum (the ``Sigma`` part is separable), the
  ``[K k]`` problem ``min 1/2 |Lq^T f - c|^2`` (``Lq Lq^T = Stilde kron H``) as a CVXPY DPP problem
  with ``S`` in CLARABEL, SCS, OSQP, HIGHS where it is a QP (no trust region) and CLARABEL, SCS
  for the trust region (an SOCP).
* ``casadi/<plugin>``: the same ``[K k]`` problem by CasADi: ``qpsol`` (qrqp, osqp, daqp, qpoases,
  highs) where it is a QP; ``nlpsol`` IPOPT and ``sqpmethod`` with qrqp for the trust region
  (``|f - f0|^2 <= delta^2``).  (hpipm and fatrop need an optimal-control stage structure, which
  one M-step problem does not have: every step is a single dense QP.)

Times: ``build_s`` (CVXPY compilation / CasADi solver construction, once per size and solver),
``solve_s`` (one re-solve with new parameter values), ``solver_s`` (the solver's own time where it
reports one).  Times are CPU seconds of the process (``time.process_time``, single-threaded BLAS):
on the shared development machine wall time mostly measured the other jobs.  Warm vs cold: ``warm_start`` runs 5 consecutive "EM iterations"
(``R`` moving by 1% per iteration) with ``warm_start=True`` on one problem and cold on fresh
ones.  Every warning a solver emits is counted and its first text kept (``warnings``).
``run`` returns rows and prints nothing; :mod:`soc_opt.bench.solvers_report` writes the table,
the Dolan-More profiles and the accuracy-vs-time plots.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from ..mstep import MStepConstraints, maximize
from ..mstep.objectives import moment_stats
from .mstep import random_instance

#: every time is CPU seconds of this process (single-threaded BLAS): on a shared machine wall time
#: mostly measures the other jobs
_clock = time.process_time

__all__ = ["SIZES", "SETS", "run", "problem_data", "trust_region_reference", "offset_reference", "kkt_box_reference", "refine_solution"]

SIZES = ((2, 1), (4, 2), (8, 3), (16, 5), (26, 7))
SETS = ("offset_bound", "trust_region", "cov_floor", "entropy_floor")  # CVXPY-only sets first
CVX_QP = ("CLARABEL", "SCS", "OSQP", "HIGHS")
CASADI_QP = ("qrqp", "osqp", "daqp", "qpoases", "highs")
_CVX_OPTS = {"CLARABEL": {}, "SCS": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 200_000},
             "OSQP": {"eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 200_000, "polishing": True},
             "HIGHS": {}}


# --------------------------------------------------------------------------- problem data


def problem_data(H, S, R):
    """``(Q, r)`` of the ``[K k]`` part ``-1/2 f^T Q f + r^T f`` with ``f = vec F`` (column-major),
    ``Q = S kron H``, ``r = vec R``."""
    return np.kron(S, H), R.ravel(order="F")


def _value(Q, r, f) -> float:
    return float(-0.5 * f @ Q @ f + r @ f)


def trust_region_reference(Q, r, f0, delta):
    """Exact maximiser of ``-1/2 f^T Q f + r^T f`` on ``|f - f0| <= delta`` (``Q > 0``): the
    unconstrained optimum if inside, else ``f0 + (Q + lam I)^-1 (r - Q f0)`` with ``lam > 0`` the root
    of ``|.| = delta`` (the secular equation, bracketed and bisected to machine precision)."""
    from scipy.optimize import brentq

    w, U = np.linalg.eigh(Q)
    g = U.T @ (r - Q @ f0)
    step = lambda lam: float(np.linalg.norm(g / (w + lam)))  # noqa: E731
    if step(0.0) <= delta:
        return f0 + U @ (g / w)
    hi = 1.0
    while step(hi) > delta:
        hi *= 2.0
    lam = brentq(lambda x: step(x) - delta, 0.0, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=500)
    return f0 + U @ (g / (w + lam))


def offset_reference(Q, r, idx, b):
    """Maximiser of ``-1/2 f^T Q f + r^T f`` with ``|f_i| <= b_i`` on the offset entries ``idx``: the
    exact KKT solve of :func:`kkt_box_reference`."""
    return kkt_box_reference(Q, -np.asarray(r, dtype=float), idx, b)[0]


def refine_solution(P, rhs, solve, steps: int = 6):
    """Iterative refinement of ``P x = rhs`` with residuals in extended precision."""
    Pl, rl = P.astype(np.longdouble), rhs.astype(np.longdouble)
    x = solve(rhs)
    for _ in range(steps):
        res = rl - Pl @ x.astype(np.longdouble)
        x = x + solve(np.asarray(res, dtype=float))
    return x


def kkt_box_reference(P, q, idx, b, max_iter: int = 100):
    """Exact minimiser of ``1/2 f^T P f + q^T f`` with ``|f_i| <= b`` on ``idx`` (``P > 0``) and the
    multipliers ``(z_upper, z_lower)`` of ``f_idx <= b``, ``-f_idx <= b``: a primal-dual active-set
    iteration; on the final active set the KKT system (free variables) is solved with refinement
    and every sign checked (raises ``ArithmeticError`` if the iteration does not settle)."""
    import scipy.linalg as sla

    d = len(q)
    idx = np.asarray(idx)
    b = np.broadcast_to(np.asarray(b, dtype=float), idx.shape)
    state = np.zeros(len(idx), dtype=int)  # -1 lower bound, 0 free, +1 upper bound
    for _ in range(max_iter):
        fixed = idx[state != 0]
        free = np.setdiff1d(np.arange(d), fixed)
        f = np.zeros(d)
        f[fixed] = state[state != 0] * b[state != 0]
        Pff = P[np.ix_(free, free)]
        cf = sla.cho_factor(Pff)
        rhs = -q[free] - P[np.ix_(free, fixed)] @ f[fixed]
        f[free] = refine_solution(Pff, rhs, lambda v: sla.cho_solve(cf, v))
        g = np.asarray(P.astype(np.longdouble) @ f.astype(np.longdouble) + q, dtype=float)  # P f + q
        mult = -state * g[idx]  # multiplier of the active bound: g_i = -z_up (upper), +z_lo (lower)
        new = state.copy()
        for j, i in enumerate(idx):
            if state[j] == 0:
                new[j] = 1 if f[i] > b[j] else (-1 if f[i] < -b[j] else 0)
            elif mult[j] < 0:
                new[j] = 0
        if np.array_equal(new, state):
            zu = np.where(state > 0, mult, 0.0)
            zl = np.where(state < 0, mult, 0.0)
            return f, zu, zl
        state = new
    raise ArithmeticError("primal-dual active-set iteration did not settle")



# --------------------------------------------------------------------------- CVXPY [K k] problems


class _CvxQP:
    """``min 1/2 |Lq^T f - c|^2`` over ``f`` (DPP), with an offset bound or a trust region."""

    def __init__(self, d: int, idx, kind: str):
        import cvxpy as cp

        self.cp = cp
        self.f = cp.Variable(d)
        self.LqT = cp.Parameter((d, d))
        self.c = cp.Parameter(d)
        cons = []
        if kind == "offset_bound":
            self.b = cp.Parameter(len(idx), nonneg=True)
            cons = [cp.abs(self.f[idx]) <= self.b]
        elif kind == "trust_region":
            self.f0 = cp.Parameter(d)
            self.delta = cp.Parameter(nonneg=True)
            cons = [cp.norm(self.f - self.f0, 2) <= self.delta]
        self.prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(self.LqT @ self.f - self.c)), cons)

    def set(self, Q, r, extra):
        L = np.linalg.cholesky(Q)
        self.LqT.value = L.T
        self.c.value = np.linalg.solve(L, r)
        if hasattr(self, "b"):
            self.b.value = extra["b"]
        if hasattr(self, "f0"):
            self.f0.value, self.delta.value = extra["f0"], extra["delta"]

    def solve(self, solver: str, warm: bool = True):
        self.prob.solve(solver=solver, warm_start=warm, **_CVX_OPTS[solver])
        st = self.prob.solver_stats
        return np.asarray(self.f.value, dtype=float), self.prob.status, st.solve_time, st.num_iters


# --------------------------------------------------------------------------- CasADi [K k] problems


def _casadi_solver(plugin: str, d: int, idx, kind: str):
    """A CasADi solver of the ``[K k]`` problem with symbolic data ``p = (vec Q, r, f0, delta)``."""
    import casadi as ca

    f = ca.SX.sym("f", d)
    Qs, rs = ca.SX.sym("Q", d, d), ca.SX.sym("r", d)
    f0, dl = ca.SX.sym("f0", d), ca.SX.sym("delta")
    obj = 0.5 * ca.dot(f, ca.mtimes(Qs, f)) - ca.dot(rs, f)
    p = ca.vertcat(ca.vec(Qs), rs, f0, dl)
    if kind == "trust_region":
        g = ca.sumsqr(f - f0) - dl**2
        opts = {"print_time": False}
        if plugin == "ipopt":
            opts["ipopt"] = {"print_level": 0, "tol": 1e-12, "sb": "yes"}
        else:
            opts.update({"qpsol": "qrqp", "qpsol_options": {"print_iter": False, "print_header": False,
                                                           "error_on_fail": False},
                         "print_header": False, "print_iteration": False, "print_status": False,
                         "tol_pr": 1e-12, "tol_du": 1e-12, "max_iter": 200, "error_on_fail": False})
        return ca.nlpsol(f"m_{plugin}", plugin, {"x": f, "f": obj, "g": g, "p": p}, opts)
    # QP: A selects the offset entries (for cov_floor/entropy_floor: unconstrained, one dummy free row)
    rows = list(idx) if kind == "offset_bound" else [0]
    A = np.zeros((len(rows), d))
    A[np.arange(len(rows)), rows] = 1.0
    Hs = ca.Sparsity.dense(d, d)
    opts = {"error_on_fail": False}
    if plugin == "qrqp":
        opts.update({"print_iter": False, "print_header": False})
    elif plugin == "osqp":
        opts["osqp"] = {"verbose": False, "eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 200_000, "polish": True}
    elif plugin == "qpoases":
        opts["printLevel"] = "none"
    elif plugin == "highs":
        opts["highs"] = {"output_flag": False}
    solver = ca.conic(f"m_{plugin}", plugin, {"h": Hs, "a": ca.Sparsity.dense(len(rows), d)}, opts)
    return solver, A


def _casadi_solve(plugin, solver, Q, r, extra, kind, idx):
    t0 = _clock()
    if kind == "trust_region":
        p = np.concatenate([Q.ravel(order="F"), r, extra["f0"], [extra["delta"]]])
        sol = solver(x0=extra["f0"], p=p, lbg=-np.inf, ubg=0.0)
    else:
        sol_, A = solver
        if kind == "offset_bound":
            lba, uba = -extra["b"], extra["b"]
        else:
            lba, uba = np.array([-np.inf]), np.array([np.inf])
        sol = sol_(h=Q, g=-r, a=A, lba=lba, uba=uba)
        solver = sol_
    wall = _clock() - t0
    st = solver.stats()
    ok = bool(st.get("success", False))
    return np.asarray(sol["x"], dtype=float).ravel(), "optimal" if ok else str(st.get("return_status")), wall, \
        st.get("iter_count")


# --------------------------------------------------------------------------- one size


def _constraints(kind: str, m: int, b=None, delta=None) -> MStepConstraints:
    if kind == "entropy_floor":
        return MStepConstraints(entropy_floor=-0.5 * m)
    return MStepConstraints(cov_floor=0.1, offset_bound=b if kind == "offset_bound" else None,
                            trust_region=delta if kind == "trust_region" else None)


def _instances(n, m, T, count, rng):
    """``count`` instances: model, moments, per-step ``(Q, r)``, a previous policy (trust-region
    centre), an active offset bound and an active trust-region radius."""
    from ..models import LinearGaussianPolicy

    out = []
    for _ in range(count):
        model, mom = random_instance(n, m, T, rng)
        st = moment_stats(model, mom)
        data = [problem_data(st.H[k], st.S[k], st.R[k]) for k in range(T)]
        fstar = np.stack([np.linalg.solve(Q, r) for Q, r in data])
        prev = LinearGaussianPolicy(0.3 * rng.standard_normal((T, m, n)), 0.3 * rng.standard_normal((T, m)),
                                    np.broadcast_to(np.eye(m), (T, m, m)).copy())
        f0 = np.concatenate([prev.K, prev.k[..., None]], axis=-1).transpose(0, 2, 1).reshape(T, -1)
        kidx = np.arange(n * m, (n + 1) * m)
        b = float(max(0.5 * np.median(np.abs(fstar[:, kidx])), 1e-3))
        delta = float(max(0.5 * np.min(np.linalg.norm(fstar - f0, axis=1)), 1e-3))
        out.append(dict(model=model, mom=mom, data=data, prev=prev, f0=f0, b=b, delta=delta, kidx=kidx))
    return out


def _reference(inst, kind, k):
    Q, r = inst["data"][k]
    if kind == "offset_bound":
        return offset_reference(Q, r, inst["kidx"], np.full(len(inst["kidx"]), inst["b"]))
    if kind == "trust_region":
        return trust_region_reference(Q, r, inst["f0"][k], inst["delta"])
    return np.linalg.solve(Q, r)


def _err(Q, r, f, fref, kind, inst, k) -> tuple[float, float]:
    """Relative objective gap (positive: worse than the reference) and constraint violation."""
    v, vref = _value(Q, r, f), _value(Q, r, fref)
    gap = (vref - v) / max(1.0, abs(vref))
    viol = 0.0
    if kind == "offset_bound":
        viol = float(max(0.0, np.abs(f[inst["kidx"]]).max() - inst["b"]))
    elif kind == "trust_region":
        viol = float(max(0.0, np.linalg.norm(f - inst["f0"][k]) - inst["delta"]))
    return float(gap), viol


def _record(rows, base, method, inst_i, k, f, status, wall, solver_s, iters, Q, r, fref, kind, inst, warns,
            build_s=None):
    gap, viol = _err(Q, r, f, fref, kind, inst, k) if f is not None and np.all(np.isfinite(f)) else (math.inf, math.inf)
    rows.append(dict(base, method=method, instance=inst_i, step=k, status=status, solve_s=wall, solver_s=solver_s,
                     iters=iters, build_s=build_s, rel_gap=gap, abs_gap=abs(gap), violation=viol,
                     param_err=float(np.abs(f - fref).max() / max(1.0, np.abs(fref).max())) if f is not None else math.inf,
                     warnings=len(warns), warning=(str(warns[0].message)[:160] if warns else "")))


def _run_library(rows, base, insts, kind, solver, refs):
    m, T = base["m"], base["T"]

    def call(inst):
        cons = _constraints(kind, m, inst["b"], inst["delta"])
        return maximize(inst["model"], inst["mom"], constraints=cons, method="cvxpy", solver=solver,
                                       previous=inst["prev"], min_norm=False)

    t0 = _clock()
    try:  # warm-up: builds (or fetches) the cached DPP problem; reported as build time
        call(insts[0])
    except Exception:
        pass
    build = _clock() - t0
    for i, inst in enumerate(insts):
        t0 = _clock()
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            try:
                res, err = call(inst), None
            except Exception as e:  # a solver failure is a row, not a crash
                res, err = None, f"{type(e).__name__}: {e}"
        per = (_clock() - t0) / T
        for k in range(T):
            Q, r = inst["data"][k]
            if res is None:
                _record(rows, base, f"library/{solver}", i, k, None, err[:120], math.nan, None, None, Q, r, refs[i][k],
                        kind, inst, w)
                continue
            F = np.concatenate([res.policy.K[k], res.policy.k[k][:, None]], axis=1)
            _record(rows, base, f"library/{solver}", i, k, F.ravel(order="F"), res.status[T - 1 - k], per,
                    float(res.solve_time[k]), None, Q, r, refs[i][k], kind, inst, w,
                    build if (i == 0 and k == 0) else None)


def _extra(inst, k):
    return {"b": np.full(len(inst["kidx"]), inst["b"]), "f0": inst["f0"][k], "delta": inst["delta"]}


def _run_cvx_qp(rows, base, insts, kind, solver, refs):
    d = base["m"] * (base["n"] + 1)
    t0 = _clock()
    prob = _CvxQP(d, insts[0]["kidx"], kind)
    prob.set(*insts[0]["data"][0], _extra(insts[0], 0))
    try:  # the first solve compiles the DPP problem: reported as build time
        prob.solve(solver, warm=False)
    except Exception:
        pass
    build = _clock() - t0
    for i, inst in enumerate(insts):
        for k in range(base["T"]):
            Q, r = inst["data"][k]
            prob.set(Q, r, _extra(inst, k))
            with warnings.catch_warnings(record=True) as w:
                warnings.simplefilter("always")
                t1 = _clock()
                try:
                    f, status, ssec, it = prob.solve(solver, warm=False)
                except Exception as e:
                    f, status, ssec, it = None, f"{type(e).__name__}: {e}"[:120], None, None
                cpu = _clock() - t1
            _record(rows, base, f"qp/{solver}", i, k, f, status, cpu, ssec, it, Q, r, refs[i][k], kind, inst, w,
                    build if (i == 0 and k == 0) else None)


def _run_casadi(rows, base, insts, kind, plugin, refs):
    d = base["m"] * (base["n"] + 1)
    t0 = _clock()
    try:
        solver = _casadi_solver(plugin, d, insts[0]["kidx"], kind)
    except Exception as e:  # plugin not usable for this problem
        rows.append(dict(base, method=f"casadi/{plugin}", instance=-1, step=-1, status=f"build failed: {e}"[:160],
                         solve_s=math.nan, solver_s=None, iters=None, build_s=math.nan, rel_gap=math.inf,
                         abs_gap=math.inf, violation=math.inf, param_err=math.inf, warnings=0, warning=""))
        return
    build = _clock() - t0
    for i, inst in enumerate(insts):
        for k in range(base["T"]):
            Q, r = inst["data"][k]
            extra = _extra(inst, k)
            with warnings.catch_warnings(record=True) as w:
                warnings.simplefilter("always")
                try:
                    f, status, wall, it = _casadi_solve(plugin, solver, Q, r, extra, kind, inst["kidx"])
                except Exception as e:
                    f, status, wall, it = None, f"{type(e).__name__}: {e}"[:120], math.nan, None
            _record(rows, base, f"casadi/{plugin}", i, k, f, status, wall, None, it, Q, r, refs[i][k], kind, inst, w,
                    build if (i == 0 and k == 0) else None)


def _closed_form_rows(rows, base, insts, kind, refs):
    for i, inst in enumerate(insts):
        cons = _constraints(kind, base["m"])
        t0 = _clock()
        pol = maximize(inst["model"], inst["mom"], constraints=cons, min_norm=False).policy
        per = (_clock() - t0) / base["T"]
        for k in range(base["T"]):
            Q, r = inst["data"][k]
            F = np.concatenate([pol.K[k], pol.k[k][:, None]], axis=1).ravel(order="F")
            _record(rows, base, "closed_form", i, k, F, "optimal", per, None, None, Q, r, refs[i][k], kind, inst, [])


def methods_for(kind: str) -> list[str]:
    """The methods that apply to a constraint set (module docstring)."""
    lib = ["library/CLARABEL", "library/SCS"]
    if kind == "trust_region":
        return lib + ["qp/CLARABEL", "qp/SCS", "casadi/ipopt", "casadi/sqpmethod"]
    cf = ["closed_form"] if kind in ("cov_floor", "entropy_floor") else []
    return cf + lib + [f"qp/{s}" for s in CVX_QP] + [f"casadi/{p}" for p in CASADI_QP]


def warm_vs_cold(n: int, m: int, seed: int = 0, iterations: int = 5, solvers=("OSQP", "SCS")) -> list[dict]:
    """Consecutive "EM iterations" of the offset-bound QP (``R`` moving 1% per iteration): median
    solve time and iterations with ``warm_start=True`` on one problem vs a fresh problem each time."""
    rng = np.random.default_rng([seed, n, m, 7])
    (inst,) = _instances(n, m, 1, 1, rng)
    Q, r0 = inst["data"][0]
    d = len(r0)
    extra = {"b": np.full(len(inst["kidx"]), inst["b"])}
    rs = [r0 * (1 + 0.01 * i * rng.standard_normal(d)) for i in range(iterations)]
    out = []
    for solver in solvers:
        warm = _CvxQP(d, inst["kidx"], "offset_bound")
        for mode in ("cold", "warm"):
            times, its = [], []
            for i, r in enumerate(rs):
                p = warm if mode == "warm" else _CvxQP(d, inst["kidx"], "offset_bound")
                p.set(Q, r, extra)
                if mode == "cold":
                    p.solve(solver, warm=False)  # compile outside the timing; then a cold re-solve
                t0 = _clock()
                _, _, _, it = p.solve(solver, warm=(mode == "warm"))
                if i > 0 or mode == "cold":
                    times.append(_clock() - t0)
                    its.append(it)
            out.append(dict(n=n, m=m, solver=solver, mode=mode, median_solve_s=float(np.median(times)),
                            median_iters=float(np.median([x for x in its if x is not None] or [math.nan]))))
    return out


def run(sizes=SIZES, T: int = 3, instances: int = 10, seed: int = 0, sets=SETS, methods=None,
        on_progress=None) -> list[dict]:
    """One row per (size, constraint set, method, instance, step); see the module docstring.
    ``on_progress(rows)`` is called after every (size, constraint set) with the rows so far."""
    rows: list[dict] = []
    for n, m in sizes:
        rng = np.random.default_rng([seed, n, m])
        insts = _instances(n, m, T, instances, rng)
        for kind in sets:
            refs = [[_reference(inst, kind, k) for k in range(T)] for inst in insts]
            base = dict(n=n, m=m, T=T, constraints=kind)
            for meth in methods_for(kind):
                if methods is not None and meth not in methods:
                    continue
                family, _, name = meth.partition("/")
                if meth == "closed_form":
                    _closed_form_rows(rows, base, insts, kind, refs)
                elif family == "library":
                    _run_library(rows, base, insts, kind, name, refs)
                elif family == "qp":
                    _run_cvx_qp(rows, base, insts, kind, name, refs)
                else:
                    _run_casadi(rows, base, insts, kind, name, refs)
            if on_progress is not None:
                on_progress(rows)
    return rows
