"""M-step solver benchmark in the QP-benchmark format (docs/math.md §5; docs/results/solvers/README.md).

What the solvers receive.  The M-step problem as the paper poses it: for one time step, the
quadratic form of ``Lbar`` built from the smoother's moments (``H = B^T So^-1 B``, ``R``,
``Stilde``; :func:`soc_opt.mstep.objectives.moment_stats`) and handed over unwhitened,

    minimise  1/2 f^T P f + q^T f + 1/2 tr(H Sigma)    P = Stilde kron H,  q = -vec R,  f = vec [K k]

subject to the family's constraints (``G f <= h`` for ``|k| <= b``; ``|f - f0| <= delta``;
``Sigma >= Sigma_min``).  The ``Sigma`` part is separable (its optimum under a floor is the floor).
QP solvers (through qpsolvers) get ``(P, q, G, h)``; the conic form (through CVXPY) gets the whole
problem in ``(f, Sigma)`` with ``Sigma`` a PSD variable.  The families without an active bound
carry an inactive one, ``|k| <= 1e3 max(1, |k*|)`` (``Problem.inactive_b``): qpsolvers hands a QP
without constraints for clarabel and scs to SciPy's LSQR, not to the solver.  Every timed call starts from the step's
``(model, moments)``: the statistics, the Kronecker product and the solver call are timed
together, and the closed form (:func:`soc_opt.mstep.maximize`) is timed with its own
factorisations.

References (:func:`reference`): the unconstrained optimum by a Cholesky solve with iterative
refinement whose residuals are accumulated in extended precision; for bounds on the offset an
exact KKT solve on the active set found by a primal-dual active-set iteration (every multiplier
sign and every bound checked, else an error); the trust region by its secular equation
(:func:`soc_opt.bench.solvers.trust_region_reference`); exactly degenerate problems by the
minimum-norm solution, their error measured on the range of ``P`` (the identifiable part).

Metrics (per solve): ``sol_err`` = ``|(f, Sigma) - (f_ref, Sigma_ref)| / |(f_ref, Sigma_ref)|``
(Frobenius norms; QP rows: ``f`` only), linear in the parameter error; ``obj_gap`` the relative
objective gap; ``primal_res``, ``dual_res`` and ``gap`` as qpbenchmark defines them
(:func:`residuals`: infinity norms of the constraint violation and of ``P f + q + G^T z``,
``|f^T P f + q^T f + h^T z|``).  Success at an accuracy level: the solver returns a solution,
within the time limit, with all three at most the level's tolerance; on the ``infeasible``
family: it reports infeasibility (library: raises :class:`InfeasibleConstraintsError`).

Accuracy levels (:data:`LEVELS`, qpbenchmark's): ``high`` eps_abs = 1e-9, eps_rel = 0, checked
at 1e-9; ``default`` the solvers' own settings, checked at 1; ``low`` eps_abs = 1e-3, eps_rel = 0,
checked at 1e-3.  Time limit :data:`TIME_LIMIT_S` (passed to solvers that take one, and checked).
Times: CPU seconds (``time.process_time``) and wall seconds (``time.perf_counter``), median of
``repeats`` calls.  Shifted geometric means (:func:`shifted_geomean`) in milliseconds with shift
:data:`SHIFT_MS`, a failure counted at the time limit.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np

from ..estep import Moments
from ..models import AugmentedModel
from ..mstep import MStepConfig, MStepConstraints, maximize
from ..mstep.errors import InfeasibleConstraintsError
from ..mstep.objectives import moment_stats
from ..testing import random_mstep_instance
from .solvers import kkt_box_reference, refine_solution, trust_region_reference

__all__ = ["FAMILIES", "LEVELS", "Level", "Problem", "make_problems", "reference", "residuals", "solution_error",
           "kkt_box_reference", "run", "summarize", "shifted_geomean", "qp_methods", "methods_for"]

FAMILIES = ("well_conditioned", "ill_conditioned", "degenerate", "active", "trust_region", "infeasible")
SIZES = ((2, 1), (4, 2), (8, 3), (16, 5), (26, 7))
QP_SOLVERS = ("clarabel", "piqp", "proxqp", "daqp", "osqp", "highs", "scs", "quadprog")
CONIC_SOLVERS = ("CLARABEL", "SCS")
COV_FLOOR = 0.1
TIME_LIMIT_S = 10.0
#: added to ``repeats * TIME_LIMIT_S`` for the guard's limit on one (problem, method, level) call
CALL_GRACE_S = 30.0
SHIFT_MS = 1.0


@dataclass(frozen=True)
class Level:
    """An accuracy level: solver ``eps_abs`` (None: the solver's defaults) and the success tolerance."""

    eps_abs: float | None
    tol: float


LEVELS = {"high": Level(1e-9, 1e-9), "default": Level(None, 1.0), "low": Level(1e-3, 1e-3)}


@dataclass(frozen=True)
class Problem:
    """One M-step problem (one time step) of a family (module docstring).

    ``model``/``mom`` the step as a ``T = 1`` instance; ``b`` the offset bound (may be < 0: the
    infeasible family), ``f0``/``delta`` the trust region; ``cond`` the condition number of ``P``."""

    name: str
    family: str
    n: int
    m: int
    model: AugmentedModel
    mom: Moments
    b: float | None = None
    f0: np.ndarray | None = None
    delta: float | None = None
    cond: float = math.nan
    inactive_b: float | None = None

    @property
    def kidx(self) -> np.ndarray:
        return np.arange(self.n * self.m, (self.n + 1) * self.m)

    def constraints(self) -> MStepConstraints:
        """The library's constraint set (raises :class:`InfeasibleConstraintsError` when empty)."""
        return MStepConstraints(cov_floor=COV_FLOOR, offset_bound=self.b, trust_region=self.delta)


# --------------------------------------------------------------------------- problem data


def qp_data(prob: Problem):
    """``(P, q, G, h, H)`` from the step's moments (docs/math.md §5; no whitening)."""
    st = moment_stats(prob.model, prob.mom)
    H, S, R = st.H[0], st.S[0], st.R[0]
    P = np.kron(S, H)
    q = -R.ravel(order="F")
    G = h = None
    b = prob.b if prob.b is not None else prob.inactive_b
    if b is not None:
        E = np.zeros((prob.m, len(q)))
        E[np.arange(prob.m), prob.kidx] = 1.0
        G, h = np.vstack([E, -E]), np.full(2 * prob.m, b)
    return P, q, G, h, H


def _slice(model, mom, k):
    return (AugmentedModel(model.Ao[k:k + 1], model.co[k:k + 1], model.So[k:k + 1], model.n),
            Moments(mom.Szz[k:k + 1], mom.Szs[k:k + 1], mom.Sss[k:k + 1], mom.count))


def _cond(model, mom) -> float:
    P = qp_data(Problem("", "", model.n, model.Bs.shape[-1], model, mom))[0]
    w = np.linalg.eigvalsh(P)
    return float(w[-1] / w[0]) if w[0] > 0 else math.inf


def _ill(model, mom, n, m, target_log10: float):
    """Rescale the states (``Sss``, ``Szs`` columns) and the action columns of ``B`` geometrically
    so that ``cond(P)`` is ``10^target`` (bisection on the exponent)."""
    ws = np.linspace(0.0, 1.0, n)
    wa = np.linspace(0.0, 1.0, m) if m > 1 else np.zeros(1)

    def scaled(t):
        ds = np.concatenate([10.0 ** (-t * ws * (0.5 if m > 1 else 1.0)), [1.0]])
        da = 10.0 ** (-t * wa * 0.5)
        Ao = model.Ao.copy()
        Ao[..., n:] *= da
        mom2 = Moments(mom.Szz, mom.Szs * ds, mom.Sss * ds[:, None] * ds, mom.count)
        return AugmentedModel(Ao, model.co, model.So, n), mom2

    lo, hi = 0.0, 2.0 * target_log10
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if math.log10(_cond(*scaled(mid))) < target_log10 else (lo, mid)
    return scaled(0.5 * (lo + hi))


def _degenerate(mom, n):
    """State component 1 an exact copy of component 0 (``Stilde`` exactly singular)."""
    Sss, Szs = mom.Sss.copy(), mom.Szs.copy()
    Sss[:, 1, :], Sss[:, :, 1] = Sss[:, 0, :], Sss[:, :, 0]
    Szs[:, :, 1] = Szs[:, :, 0]
    return Moments(mom.Szz, Szs, Sss, mom.count)


def make_problems(sizes=SIZES, instances: int = 4, seed: int = 0, families=FAMILIES) -> list[Problem]:
    """``instances`` problems per size and family (module docstring; seed ``[seed, n, m, family]``)."""
    out = []
    for n, m in sizes:
        for fi, fam in enumerate(families):
            if fam == "degenerate" and n < 2:
                continue
            rng = np.random.default_rng([seed, n, m, fi])
            for i in range(instances):
                model, mom = random_mstep_instance(n, m, 1, rng)
                kw = {}
                if fam == "ill_conditioned":
                    model, mom = _ill(model, mom, n, m, rng.uniform(8.0, 12.0))
                elif fam == "degenerate":
                    mom = _degenerate(mom, n)
                P, q, _, _, _ = qp_data(Problem("", fam, n, m, model, mom))
                fstar = np.linalg.lstsq(P, -q, rcond=None)[0]
                if fam == "active":
                    kw["b"] = float(max(0.5 * np.median(np.abs(fstar[n * m:])), 1e-3))
                elif fam == "infeasible":
                    kw["b"] = -0.1
                elif fam == "trust_region":
                    f0 = 0.3 * rng.standard_normal(len(q))
                    kw["f0"], kw["delta"] = f0, float(0.5 * np.linalg.norm(fstar - f0))
                else:  # an inactive bound: qpsolvers would hand a constraint-free QP to LSQR, not to the solver
                    kw["inactive_b"] = float(1e3 * max(1.0, np.abs(fstar[n * m:]).max()))
                out.append(Problem(f"mstep_{fam}_n{n}_m{m}_{i}", fam, n, m, model, mom,
                                   cond=_cond(model, mom), **kw))
    return out


# --------------------------------------------------------------------------- references


@dataclass(frozen=True)
class Reference:
    f: np.ndarray
    z: np.ndarray | None  # multipliers of G f <= h
    sigma: np.ndarray
    range_basis: np.ndarray | None = None  # degenerate: orthonormal basis of range(P)


def reference(prob: Problem) -> Reference | None:
    """The reference solution (module docstring); None for the infeasible family."""
    import scipy.linalg as sla

    if prob.family == "infeasible":
        return None
    P, q, G, h, _ = qp_data(prob)
    sigma = COV_FLOOR * np.eye(prob.m)
    if prob.family == "degenerate":
        w, U = np.linalg.eigh(P)
        keep = w > 1e-12 * w[-1]
        Ur = U[:, keep]
        f = Ur @ ((Ur.T @ -q) / w[keep])
        return Reference(f, None, sigma, Ur)
    if prob.family == "active":
        f, zu, zl = kkt_box_reference(P, q, prob.kidx, prob.b)
        return Reference(f, np.concatenate([zu, zl]), sigma)
    if prob.family == "trust_region":
        return Reference(trust_region_reference(P, -q, prob.f0, prob.delta), None, sigma)
    cf = sla.cho_factor(P)
    return Reference(refine_solution(P, -q, lambda v: sla.cho_solve(cf, v)), None, sigma)


# --------------------------------------------------------------------------- metrics


def residuals(P, q, G, h, f, z) -> tuple[float, float, float]:
    """Primal residual, dual residual and duality gap as qpbenchmark defines them (infinity norms;
    ``z`` the multipliers of ``G f <= h``, None when there are none; ``inf`` if missing)."""
    if f is None or not np.all(np.isfinite(f)):
        return math.inf, math.inf, math.inf
    pr = 0.0 if G is None else max(0.0, float(np.max(G @ f - h)))
    grad = P @ f + q
    hz = 0.0
    if G is not None:
        if z is None:
            return pr, math.inf, math.inf
        grad = grad + G.T @ z
        hz = float(h @ z)
    return pr, float(np.abs(grad).max()), abs(float(f @ P @ f + q @ f + hz))


def solution_error(f, sigma, ref: Reference) -> float:
    """``|(f, Sigma) - (f_ref, Sigma_ref)| / |(f_ref, Sigma_ref)|`` (``sigma`` None: ``f`` only;
    degenerate problems: the ``f`` difference projected on the range of ``P``)."""
    df = f - ref.f
    if ref.range_basis is not None:
        df = ref.range_basis @ (ref.range_basis.T @ df)
    num, den = float(df @ df), float(ref.f @ ref.f)
    if sigma is not None:
        num += float(np.sum((sigma - ref.sigma) ** 2))
        den += float(np.sum(ref.sigma**2))
    return math.sqrt(num / max(den, np.finfo(float).tiny))


def objective_gap(P, q, f, ref: Reference) -> float:
    v, vr = 0.5 * f @ P @ f + q @ f, 0.5 * ref.f @ P @ ref.f + q @ ref.f
    return float((v - vr) / max(1.0, abs(vr)))


# --------------------------------------------------------------------------- solvers


def _qp_options(solver: str, level: Level) -> dict:
    """Harmonised settings (qpbenchmark's mapping of eps_abs / eps_rel = 0; time limit)."""
    o: dict = {}
    e = level.eps_abs
    if solver == "osqp":
        o["time_limit"] = TIME_LIMIT_S
    elif solver == "highs":
        o["time_limit"] = TIME_LIMIT_S
    elif solver == "scs":
        o["time_limit_secs"] = TIME_LIMIT_S
    elif solver == "clarabel":
        o["time_limit"] = TIME_LIMIT_S
    if e is None:
        return o
    if solver == "clarabel":
        o.update(tol_feas=e, tol_gap_abs=e, tol_gap_rel=0.0)
    elif solver in ("osqp", "scs"):
        o.update(eps_abs=e, eps_rel=0.0)
    elif solver in ("piqp", "proxqp"):
        o.update(eps_abs=e, eps_rel=0.0, eps_duality_gap_abs=e, eps_duality_gap_rel=0.0, check_duality_gap=True)
    elif solver == "daqp":
        o.update(primal_tol=e, dual_tol=e)
    elif solver == "highs":
        o.update(primal_feasibility_tolerance=e, dual_feasibility_tolerance=e)
    return o


def qp_methods() -> list[str]:
    """``qp/<solver>`` for every solver of :data:`QP_SOLVERS` that qpsolvers finds installed."""
    try:
        import qpsolvers
    except ImportError:
        return []
    return [f"qp/{s}" for s in QP_SOLVERS if s in qpsolvers.available_solvers]


def methods_for(family: str, qp: list[str] | None = None) -> list[str]:
    """Methods that apply to a family: the closed form where one exists, QP solvers where the
    ``f`` problem is a QP (not the trust region), the conic form everywhere."""
    qp = qp_methods() if qp is None else qp
    cf = ["closed_form"] if family in ("well_conditioned", "ill_conditioned", "degenerate", "infeasible") else []
    lib = ["library/CLARABEL"]
    return cf + lib + ([] if family == "trust_region" else list(qp)) + [f"cvxpy/{s}" for s in CONIC_SOLVERS]


@dataclass(frozen=True)
class Outcome:
    f: np.ndarray | None
    sigma: np.ndarray | None
    z: np.ndarray | None
    found: bool
    status: str


def _pol_f(pol):
    return np.concatenate([pol.K[0], pol.k[0][:, None]], axis=1).ravel(order="F")


def _run_closed_form(prob: Problem, level: Level) -> Outcome:
    try:
        pol = maximize(prob.model, prob.mom, constraints=prob.constraints(),
                               min_norm=prob.family == "degenerate").policy
    except InfeasibleConstraintsError as e:
        return Outcome(None, None, None, False, f"InfeasibleConstraintsError: {e}")
    return Outcome(_pol_f(pol), pol.cov[0], None, True, "optimal")


def _run_library(prob: Problem, level: Level) -> Outcome:
    cfg = MStepConfig() if level.eps_abs is None else MStepConfig(clarabel_tol=level.eps_abs)
    try:
        res = maximize(prob.model, prob.mom, constraints=prob.constraints(), method="cvxpy",
                                      solver="CLARABEL", config=cfg, min_norm=prob.family == "degenerate",
                                      previous=_previous(prob))
    except InfeasibleConstraintsError as e:
        return Outcome(None, None, None, False, f"InfeasibleConstraintsError: {e}")
    z = None
    if prob.b is not None and res.duals:
        du = res.duals[0]
        z = np.concatenate([np.ravel(du.get("offset_upper")), np.ravel(du.get("offset_lower"))]).astype(float)
    return Outcome(_pol_f(res.policy), res.policy.cov[0], z, True, res.status[0] if res.status else "optimal")


def _previous(prob: Problem):
    if prob.f0 is None:
        return None
    from ..models import LinearGaussianPolicy

    F = prob.f0.reshape(prob.n + 1, prob.m).T
    return LinearGaussianPolicy(F[None, :, :prob.n].copy(), F[None, :, prob.n].copy(), np.eye(prob.m)[None])


def _run_qp(solver: str):
    def call(prob: Problem, level: Level) -> Outcome:
        import qpsolvers

        P, q, G, h, _ = qp_data(prob)
        qp = qpsolvers.Problem(P, q, G, h)
        sol = qpsolvers.solve_problem(qp, solver=solver, **_qp_options(solver, level))
        found = bool(sol.found) and sol.x is not None
        return Outcome(np.asarray(sol.x, dtype=float) if found else None, None,
                       None if sol.z is None else np.asarray(sol.z, dtype=float), found,
                       "found" if found else "not found")
    return call


def _cvx_options(solver: str, level: Level) -> dict:
    if solver == "CLARABEL":
        o = {"time_limit": TIME_LIMIT_S}
        if level.eps_abs is not None:
            o.update(tol_feas=level.eps_abs, tol_gap_abs=level.eps_abs, tol_gap_rel=0.0)
        return o
    o = {"time_limit_secs": TIME_LIMIT_S}
    if level.eps_abs is not None:
        o.update(eps_abs=level.eps_abs, eps_rel=0.0)
    return o


def _run_cvxpy(solver: str):
    def call(prob: Problem, level: Level) -> Outcome:
        import cvxpy as cp

        P, q, G, h, H = qp_data(prob)
        m = prob.m
        f = cp.Variable(len(q))
        S = cp.Variable((m, m), symmetric=True)
        cons = [S - COV_FLOOR * np.eye(m) >> 0]
        lin = None
        if G is not None:
            lin = G @ f <= h
            cons.append(lin)
        if prob.delta is not None:
            cons.append(cp.norm(f - prob.f0, 2) <= prob.delta)
        obj = 0.5 * cp.quad_form(f, cp.psd_wrap(P)) + q @ f + 0.5 * cp.trace(H @ S)
        pr = cp.Problem(cp.Minimize(obj), cons)
        try:
            pr.solve(solver=solver, **_cvx_options(solver, level))
        except cp.error.SolverError as e:
            return Outcome(None, None, None, False, f"SolverError: {e}"[:120])
        ok = pr.status in ("optimal", "optimal_inaccurate") and f.value is not None
        z = None if lin is None or lin.dual_value is None else np.asarray(lin.dual_value, dtype=float)
        return Outcome(np.asarray(f.value, dtype=float) if ok else None, np.asarray(S.value) if ok else None, z, ok,
                       pr.status)
    return call


def _runner(method: str):
    fam, _, name = method.partition("/")
    if method == "closed_form":
        return _run_closed_form
    if fam == "library":
        return _run_library
    if fam == "qp":
        return _run_qp(name)
    return _run_cvxpy(name)


# --------------------------------------------------------------------------- the benchmark


def _timed(fn, prob, level, repeats):
    cpu, wall, out = [], [], None
    for _ in range(repeats):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                out = fn(prob, level)
            except Exception as e:  # a solver crash is a failed row, not a crashed benchmark
                out = Outcome(None, None, None, False, f"{type(e).__name__}: {e}"[:160])
            c1, w1 = time.process_time(), time.perf_counter()
        cpu.append(c1 - c0)
        wall.append(w1 - w0)
    return out, float(np.median(cpu)), float(np.median(wall))


def evaluate(prob: Problem, ref: Reference | None, out: Outcome, level: Level, cpu_s: float) -> dict:
    """One row's metrics (module docstring)."""
    if prob.family == "infeasible":
        ok = (not out.found) and cpu_s <= TIME_LIMIT_S
        named = "offset_bound" in out.status if out.status.startswith("InfeasibleConstraintsError") else None
        return dict(found=out.found, success=ok, sol_err=math.nan, obj_gap=math.nan, primal_res=math.nan,
                    dual_res=math.nan, gap=math.nan, names_infeasibility=named)
    P, q, G, h, _ = qp_data(prob)
    if not out.found or out.f is None:
        return dict(found=False, success=False, sol_err=math.inf, obj_gap=math.inf, primal_res=math.inf,
                    dual_res=math.inf, gap=math.inf, names_infeasibility=None)
    z = out.z if out.z is not None or prob.inactive_b is None else np.zeros(2 * prob.m)
    pr, du, gp = residuals(P, q, G, h, out.f, z)
    if prob.delta is not None:  # the trust region: its violation; no multiplier for it in the QP residuals
        pr = max(pr, float(np.linalg.norm(out.f - prob.f0) - prob.delta))
        lam = float(max(0.0, -(P @ out.f + q) @ (out.f - prob.f0)) / prob.delta**2)
        g = P @ out.f + q + lam * (out.f - prob.f0)
        du, gp = float(np.abs(g).max()), abs(lam * (float(np.linalg.norm(out.f - prob.f0)) ** 2 - prob.delta**2))
    tol = level.tol
    ok = pr <= tol and du <= tol and gp <= tol and cpu_s <= TIME_LIMIT_S
    return dict(found=True, success=bool(ok), sol_err=solution_error(out.f, out.sigma, ref),
                obj_gap=objective_gap(P, q, out.f, ref), primal_res=pr, dual_res=du, gap=gp,
                names_infeasibility=None)


def timed_method(meth: str, prob: Problem, level: Level, repeats: int):
    """``(Outcome, median CPU s, median wall s)`` of ``repeats`` calls of method ``meth`` (picklable: what
    :class:`soc_opt.bench.guard.Guard` runs in its worker)."""
    return _timed(_runner(meth), prob, level, repeats)


def call_limit_s(repeats: int) -> float:
    """The wall-time limit of one guarded :func:`timed_method` call: ``repeats`` solves at
    :data:`TIME_LIMIT_S` each plus :data:`CALL_GRACE_S` (imports, statistics, the first CVXPY compile)."""
    return repeats * TIME_LIMIT_S + CALL_GRACE_S


def _direct(fn, *args, limit_s, **kwargs):
    return fn(*args, **kwargs)


def run(sizes=SIZES, instances: int = 4, seed: int = 0, families=FAMILIES, levels=tuple(LEVELS), methods=None,
        repeats: int = 3, problems: list[Problem] | None = None, on_progress=None, call=None,
        progress=None) -> list[dict]:
    """One row per (problem, accuracy level, method); see the module docstring.

    ``call``: how each :func:`timed_method` call is made, ``call(fn, *args, limit_s=...)`` (default: in this
    process; ``soc-opt solvers`` passes :meth:`soc_opt.bench.guard.Guard.call`, which enforces the limit
    :func:`call_limit_s` and stops on NaN; a stopped call is a failed row).  ``progress``: a callable given one
    line per problem.
    """
    from .guard import GuardError

    problems = make_problems(sizes, instances, seed, families) if problems is None else problems
    call = _direct if call is None else call
    qp = qp_methods()
    rows: list[dict] = []
    for i, prob in enumerate(problems):
        t0 = time.perf_counter()
        ref = reference(prob)
        stopped = []
        for meth in methods_for(prob.family, qp):
            if methods is not None and meth not in methods:
                continue
            for lv in levels:
                level = LEVELS[lv]
                try:
                    out, cpu, wall = call(timed_method, meth, prob, level, repeats, limit_s=call_limit_s(repeats))
                except GuardError as e:
                    out, cpu, wall = Outcome(None, None, None, False, f"GuardError: {e}"), math.inf, math.inf
                    stopped.append(f"{meth}/{lv}: {e.status}")
                rows.append(dict(problem=prob.name, family=prob.family, n=prob.n, m=prob.m, d=prob.m * (prob.n + 1),
                                 cond=prob.cond, method=meth, level=lv, status=out.status[:160], cpu_s=cpu,
                                 wall_s=wall, variables="f" if meth.startswith("qp/") else "f,Sigma",
                                 **evaluate(prob, ref, out, level, cpu)))
        if on_progress is not None:
            on_progress(rows)
        if progress is not None:
            progress(f"M-step [{i + 1}/{len(problems)}] {prob.name}: {time.perf_counter() - t0:.1f} s"
                     + (f"; stopped: {', '.join(stopped)}" if stopped else ""))
    return rows


def shifted_geomean(values, shift: float) -> float:
    """``prod(v_i + shift)^(1/N) - shift``."""
    v = np.asarray(values, dtype=float)
    return float(np.exp(np.mean(np.log(v + shift))) - shift)


def summarize(rows: list[dict]) -> list[dict]:
    """Per (family, level, method): success rate, shifted geometric mean of CPU time (ms; failures
    at the time limit), and medians / maxima of the solution error, residuals and gap over the
    solves that returned a solution."""
    keys = sorted({(r["family"], r["level"], r["method"]) for r in rows},
                  key=lambda k: (FAMILIES.index(k[0]), list(LEVELS).index(k[1]), k[2]))
    out = []
    for fam, lv, meth in keys:
        rs = [r for r in rows if (r["family"], r["level"], r["method"]) == (fam, lv, meth)]
        t = [1e3 * (r["cpu_s"] if r["success"] else TIME_LIMIT_S) for r in rs]
        fnd = [r for r in rs if r["found"]]

        def med(k, agg=np.median):
            v = [r[k] for r in fnd if r[k] is not None and not math.isnan(r[k])]
            return float(agg(v)) if v else math.nan

        out.append(dict(family=fam, level=lv, method=meth, problems=len(rs), success=sum(r["success"] for r in rs),
                        success_rate=sum(r["success"] for r in rs) / len(rs),
                        shgeom_ms=shifted_geomean(t, SHIFT_MS),
                        median_cpu_ms=float(np.median([1e3 * r["cpu_s"] for r in rs])),
                        median_wall_ms=float(np.median([1e3 * r["wall_s"] for r in rs])),
                        sol_err_median=med("sol_err"), sol_err_max=med("sol_err", np.max),
                        obj_gap_max=med("obj_gap", np.max), primal_res_max=med("primal_res", np.max),
                        dual_res_max=med("dual_res", np.max), gap_max=med("gap", np.max),
                        dual_res_median=med("dual_res")))
    return out
