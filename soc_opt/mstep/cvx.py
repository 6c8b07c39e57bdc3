"""The M-step as CVXPY problems: building (DPP), caching, solving, and the surrogate's CVXPY
maximisers (docs/math.md §5: "the same objective as a disciplined concave program ... built once with
``cp.Parameter``s and re-solved per time step").

Forms
-----
The same objective as a disciplined concave program over ``(F, Sigma)``:
``-1/2 ||Lh^T F Ls - C||_F^2 - 1/2 <H, Sigma>`` plus constants, with ``H = Lh Lh^T``,
``Stilde = Ls Ls^T`` and ``C = Lh^{-1} R Ls^{-T}`` (the completed square, so the unconstrained
optimum of the quadratic is exactly 0).  ``parameter @ variable @ parameter`` is *not* DPP in
CVXPY (a product of two parameter-dependent factors), so an auxiliary variable ``Z = F Ls`` is
introduced and the residual is ``Lh^T Z - C``.  The time-invariant quadratic
``sum_k Stilde_k kron H_k`` does not factor, so it is written ``-1/2 ||Lq^T vec(F) - c||^2``
with ``Lq Lq^T = sum_k Stilde_k kron H_k``.  These two forms are used when ``F`` is unconstrained
(only covariance constraints).  With an ``offset_bound`` and/or a ``trust_region`` the spectral
form below is used instead.  Problems are built once per ``(form, n, m, constraint structure)``,
cached, and re-solved per step by updating parameter values.  Solver statuses other than optimal
raise :class:`SolverError`.

Trust region and offset bound: the spectral form
------------------------------------------------
The spectral form writes the ``F`` part in the eigenbasis of its Hessian
``Q`` (``Stilde kron H``, eigenpairs from those of ``Stilde`` and ``H``; time-invariant: the eigenpairs
of ``sum_k Stilde_k kron H_k``): ``vec F = f0 + U y`` with ``Q = U Diag(lam) U^T`` (``U`` orthogonal) and
reference point ``f0`` (the trust-region centre; the mean of the ``T`` centres for the time-invariant
variant; 0 without a trust region), so the objective is ``-1/2 sum_i lam_i y_i^2 + g^T y`` (plus the
constant ``-1/2 f0^T Q f0 + r^T f0``), a diagonal quadratic with no auxiliary variable or equality
constraint, and, ``U`` being orthogonal, ``||F - F_prev,j||_F = ||y - a_j||_2`` with
``a_j = U^T (vec F_prev,j - f0)``: the trust region is an SOC on the variable itself.  The offset
column of ``F`` is ``f0n + Un y`` with ``Un`` the corresponding ``m`` rows of ``U``.  ``F`` is recovered as
``f0 + U y`` (an exact change of variables; the solver's duals are those of the original
constraints).

Clarabel is run with settings chosen for these problems (why: docs/choices.md, "M-step solver
choices"): problems with a trust region use ``max_step_fraction=0.8`` and a fresh solver per solve
(no warm start), and a solve that ends inaccurately is repeated once with
``max_step_fraction=0.5``.  Tolerances are never changed and no closed form is involved.

Entropy floor
-------------
``log det Sigma >= c`` is not written with ``cp.log_det`` (which CVXPY
lowers to a PSD cone plus exponential cones) but as the equivalent ``det(Sigma)^(1/m) >= e^(c/m)``
in the standard SDP + geometric-mean form, with only PSD and second-order cones: for ``Sigma > 0``,
``det(Sigma)^(1/m) = max geo_mean(diag Z)`` over lower-triangular ``Z`` with
``[[Sigma, Z], [Z^T, Diag(diag Z)]] >= 0``.  (The block condition gives ``Sigma >= Z D^-1 Z^T``,
``D = Diag(diag Z) > 0``, so ``det Sigma >= det(Z)^2 / det D = prod diag Z``; the Cholesky factor
``Sigma = L L^T`` attains it with ``Z = L Diag(diag L)``.)  The constraint is applied to the
whitened ``Sw = Lh^T Sigma Lh`` (``H = Lh Lh^T``; ``log det Sw = log det Sigma + log det H``, so
the right-hand side becomes ``t = exp((c + log det H)/m)``, a parameter); ``Y = Sigma Lh`` is an
auxiliary variable so that every product stays DPP.  The reported ``entropy_floor`` dual is that
of ``log det Sigma >= c``: ``nu = mu t/m`` from the dual ``mu`` of ``geo_mean >= t`` (both are the
sensitivities of the optimal value, and ``dt/dc = t/m``).

Problems with an entropy floor are solved by Clarabel with only symmetric cones (the construction
above), ``max_step_fraction=0.8``, no chordal decomposition of the PSD block and gap tolerances
``clarabel_tol / 100`` (not below 1e-13 unless ``clarabel_tol`` is; tighter, never looser, and
retried at ``clarabel_tol`` if round-off ends the tighter solve as ``optimal_inaccurate``): with a
linear objective on the curved boundary ``det Sigma = e^c`` an interior-point solution locates the
maximiser only to about the square root of its duality gap (docs/choices.md).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from .. import linalg as la
from ..models import symmetrize
from .conditioning import MIN_NORM_HINT, check_time_invariant
from .config import MStepConfig
from .constraints import Resolved, clean_sigma
from .errors import SolverError
from .objectives import ti_normal_equations

__all__: list[str] = []  # internal: used by soc_opt.mstep.maximize and soc_opt.mstep.exact_em


@dataclass
class _CvxProblem:
    problem: cp.Problem
    F: cp.Variable | None  # None for the spectral form (F is recovered from ``y``) and "prec"
    Sigma: cp.Variable | None
    params: dict
    cons: dict
    y: cp.Variable | None = None  # spectral form: coordinates of vec(F - F0) in the eigenbasis


CACHE: dict[tuple, _CvxProblem] = {}

# Clarabel settings for problems with an entropy floor (module docstring, "Entropy floor"; why:
# docs/choices.md).  The duality-gap tolerances are ``clarabel_tol * _ENTROPY_GAP_FACTOR`` but not
# below ``_ENTROPY_GAP_MIN`` (where double precision runs out) unless clarabel_tol itself is;
# tol_feas stays ``clarabel_tol``.
_ENTROPY_CLARABEL_SETTINGS = dict(max_step_fraction=0.8, chordal_decomposition_enable=False)
_ENTROPY_GAP_FACTOR = 1e-2
_ENTROPY_GAP_MIN = 1e-13

# Clarabel settings for problems with a trust region (module docstring, "Trust region and offset bound"; why:
# docs/choices.md): shorter steps, a fresh Clarabel solver per attempt (CVXPY's warm start would
# keep the equilibration of the first instance solved), one retry with still shorter steps.
# Tolerances are never changed.
_TRUST_CLARABEL_SETTINGS = dict(max_step_fraction=0.8, warm_start=False)
_TRUST_RETRY_STEP = 0.5


def _entropy_floor_constraint(Sigma: cp.Variable, m: int, p: dict, aux: list) -> cp.Constraint:
    """``log det Sigma >= c`` as a (whitened) SDP + geometric-mean constraint, SOC/PSD cones only.

    With ``H = Lh Lh^T`` (parameter ``LentT = Lh^T``) and ``Y = Sigma Lh`` (an auxiliary variable,
    so that every product stays DPP), ``Sw = Lh^T Y = Lh^T Sigma Lh`` and the constraint is
    ``det(Sw)^(1/m) >= t`` with ``t = exp((c + log det H)/m)`` (parameter ``t_ent``), written as
    ``[[Sw, Z], [Z^T, Diag(diag Z)]] >= 0`` (PSD), ``Z`` lower triangular, ``geo_mean(diag Z) >= t``.
    Appends the auxiliary constraints to ``aux`` and returns the geometric-mean constraint (its
    dual is converted to the dual of ``log det Sigma >= c`` in :func:`_duals`).
    """
    p["LentT"] = cp.Parameter((m, m), name="LentT")
    p["t_ent"] = cp.Parameter(nonneg=True, name="t_ent")
    Y = cp.Variable((m, m), name="Y_ent")
    z = cp.Variable(m * (m + 1) // 2, name="z_ent")
    Z = cp.vec_to_upper_tri(z, strict=False).T  # lower triangular
    d = cp.diag(Z)
    Sw = p["LentT"] @ Y  # symmetric whenever Y = Sigma Lh; PSD constrains the symmetric part
    aux.append(Y == Sigma @ p["LentT"].T)
    aux.append(cp.bmat([[Sw, Z], [Z.T, cp.diag(d)]]) >> 0)
    return cp.geo_mean(d) >= p["t_ent"]


def _build_problem(key: tuple) -> _CvxProblem:
    """Build a DPP problem.  ``key = (form, n, m, sigma, offset, n_trust)`` with ``form`` one of
    ``"factored"`` (``||LhT F Ls - C||``), ``"kron"`` (``||LqT vec F - c||``), both for an
    unconstrained ``F``, ``"spectral"`` (``F`` constrained by an offset bound and/or trust regions:
    ``-1/2 sum_i lam_i y_i^2 + g^T y`` in the eigenbasis of the Hessian, see "Trust region and
    offset bound" in the module docstring) or ``"prec"`` (exact Sigma-step in the precision ``P``:
    ``max log det P - <W, P>`` s.t. ``Pmin <= P <= Pmax``)."""
    form, n, m, sigma, offset, n_trust = key
    n1 = n + 1
    p: dict = {}
    cons: dict = {}
    if form == "prec":
        P = cp.Variable((m, m), symmetric=True, name="P")
        p["W"] = cp.Parameter((m, m), symmetric=True, name="W")
        p["Pmax"] = cp.Parameter((m, m), symmetric=True, name="Pmax")
        p["Pmin"] = cp.Parameter((m, m), symmetric=True, name="Pmin")
        cons["upper"] = p["Pmax"] - P >> 0
        cons["lower"] = P - p["Pmin"] >> 0
        prob = cp.Problem(cp.Maximize(cp.log_det(P) - cp.sum(cp.multiply(p["W"], P))), list(cons.values()))
        if not prob.is_dpp():  # pragma: no cover
            raise RuntimeError(f"internal error: M-step CVXPY problem {key} is not DPP")
        return _CvxProblem(prob, None, P, p, cons)
    if form in ("factored", "kron") and (offset or n_trust):  # pragma: no cover - internal misuse
        raise RuntimeError(f"internal error: {form} form is for an unconstrained F; use the spectral form")
    F = y = None
    aux: list = []
    if form == "spectral":
        d = m * n1
        y = cp.Variable(d, name="y")
        p["lam"] = cp.Parameter(d, nonneg=True, name="lam")
        p["g"] = cp.Parameter(d, name="g")
        # diagonal quadratic: Clarabel receives P = Diag(lam), no auxiliary variables or equalities
        obj = -0.5 * cp.sum(cp.multiply(p["lam"], cp.square(y))) + p["g"] @ y
        if offset:  # the offset column of F = F0 + unvec(U y): rows n*m .. n*m+m-1 of vec F
            p["b"] = cp.Parameter(m, nonneg=True, name="b")
            p["Un"] = cp.Parameter((m, d), name="Un")
            p["f0n"] = cp.Parameter(m, name="f0n")
            kn = p["Un"] @ y + p["f0n"]
            cons["offset_upper"] = kn <= p["b"]
            cons["offset_lower"] = -kn <= p["b"]
        if n_trust:  # ||F - Fp_j||_F = ||y - a_j||_2, a_j = U^T vec(Fp_j - F0) (U orthogonal)
            p["delta"] = cp.Parameter(nonneg=True, name="delta")
            p["a"] = [cp.Parameter(d, name=f"a{j}") for j in range(n_trust)]
            cons["trust"] = [cp.norm(y - a, 2) <= p["delta"] for a in p["a"]]
    elif form == "factored":
        F = cp.Variable((m, n1), name="F")
        p["LhT"] = cp.Parameter((m, m), name="LhT")
        p["Ls"] = cp.Parameter((n1, n1), name="Ls")
        p["C"] = cp.Parameter((m, n1), name="C")
        # parameter @ variable @ parameter is not DPP (a product of two parameter-dependent
        # factors); an auxiliary variable Z = F Ls keeps every product parameter-affine x
        # parameter-free.
        Z = cp.Variable((m, n1), name="Z")
        aux = [Z == F @ p["Ls"]]
        resid = p["LhT"] @ Z - p["C"]
        obj = -0.5 * cp.sum_squares(resid)
    else:
        F = cp.Variable((m, n1), name="F")
        d = m * n1
        p["LqT"] = cp.Parameter((d, d), name="LqT")
        p["c"] = cp.Parameter(d, name="c")
        resid = p["LqT"] @ cp.vec(F, order="F") - p["c"]
        obj = -0.5 * cp.sum_squares(resid)
    Sigma = None
    if sigma is not None:
        floor, entropy, ceiling = sigma
        Sigma = (cp.Variable((m, m), symmetric=True, name="Sigma") if (floor or entropy)
                 else cp.Variable((m, m), PSD=True, name="Sigma"))
        p["H"] = cp.Parameter((m, m), symmetric=True, name="H")
        obj = obj - 0.5 * cp.sum(cp.multiply(p["H"], Sigma))
        if floor:
            p["Smin"] = cp.Parameter((m, m), symmetric=True, name="Smin")
            cons["cov_floor"] = Sigma - p["Smin"] >> 0
        if ceiling:
            p["Smax"] = cp.Parameter((m, m), symmetric=True, name="Smax")
            cons["cov_ceiling"] = p["Smax"] - Sigma >> 0
        if entropy:
            cons["entropy_floor"] = _entropy_floor_constraint(Sigma, m, p, aux)
    flat = list(aux)
    for v in cons.values():
        flat.extend(v if isinstance(v, list) else [v])
    prob = cp.Problem(cp.Maximize(obj), flat)
    if not prob.is_dpp():  # pragma: no cover - a construction bug, not a user error
        raise RuntimeError(f"internal error: M-step CVXPY problem {key} is not DPP")
    return _CvxProblem(prob, F, Sigma, p, cons, y)


def get_problem(key: tuple) -> _CvxProblem:
    prob = CACHE.get(key)
    if prob is None:
        prob = CACHE[key] = _build_problem(key)
    return prob


def _solver_options(solver: str, cfg: MStepConfig, entropy: bool = False, trust: bool = False) -> list[dict]:
    """Solver options, one dict per attempt (a later attempt is tried only if the earlier failed)."""
    if solver == "CLARABEL":
        t = cfg.clarabel_tol
        opts = dict(tol_gap_abs=t, tol_gap_rel=t, tol_feas=t, max_iter=cfg.clarabel_max_iter)
        # trust region: shorter steps and a fresh solver, then a retry with still shorter steps
        # (see _TRUST_CLARABEL_SETTINGS); the tolerances are the same in every attempt
        if trust:
            opts.update(_TRUST_CLARABEL_SETTINGS)
        if entropy:
            opts.update(_ENTROPY_CLARABEL_SETTINGS)
        retry = [dict(opts, max_step_fraction=_TRUST_RETRY_STEP)] if trust else []
        if not entropy:
            return [opts] + retry
        # see "Entropy floor" in the module docstring; the gap is tightened, never loosened
        g = max(t * _ENTROPY_GAP_FACTOR, min(t, _ENTROPY_GAP_MIN))
        tight = dict(opts, tol_gap_abs=g, tol_gap_rel=g)
        # if the tightened gap runs into round-off (status optimal_inaccurate), retry at clarabel_tol
        return ([tight, opts] if g < t else [opts]) + retry
    return [dict(eps_abs=cfg.scs_eps, eps_rel=cfg.scs_eps, max_iters=cfg.scs_max_iters)]


def solve_cvx(prob: _CvxProblem, solver: str, cfg: MStepConfig, where: str, step: int | None) -> str:
    ok = {cp.OPTIMAL} | ({cp.OPTIMAL_INACCURATE} if cfg.accept_inaccurate else set())
    attempts = _solver_options(solver, cfg, entropy="t_ent" in prob.params, trust="delta" in prob.params)
    for i, opts in enumerate(attempts):
        last = i == len(attempts) - 1
        try:
            with warnings.catch_warnings():  # an inaccurate solution is reported through SolverError
                warnings.filterwarnings("ignore", message="Solution may be inaccurate")
                # the entropy floor's geo_mean has equal weights 1/m: its SOC tower is exact
                warnings.filterwarnings("ignore", message="geo_mean is being approximated")
                prob.problem.solve(solver=solver, verbose=cfg.verbose, **opts)
        except cp.error.SolverError as e:
            if last:
                raise SolverError(f"{where}: CVXPY solver {solver} failed ({e})", status="solver_error",
                                  step=step) from e
            continue
        status = prob.problem.status
        if status in ok:
            return status
        if last:
            raise SolverError(f"{where}: CVXPY solver {solver} returned status {status!r}", status=status, step=step)
    raise AssertionError("unreachable")  # pragma: no cover


def _duals(prob: _CvxProblem) -> dict:
    out = {}
    for name, c in prob.cons.items():
        if isinstance(c, list):
            out[name] = np.array([float(np.asarray(ci.dual_value)) for ci in c])
        else:
            out[name] = np.array(c.dual_value, dtype=float)
    if "entropy_floor" in out:
        # dual mu of det(Sw)^(1/m) >= t  ->  dual nu of log det Sigma >= c: the optimal value's
        # sensitivities satisfy nu = -dV/dc = -dV/dt * dt/dc = mu t/m  (t = exp((c + log det H)/m))
        m = prob.params["LentT"].shape[0]
        out["entropy_floor"] = out["entropy_floor"] * float(prob.params["t_ent"].value) / m
    return out


def _set_sigma_params(prob: _CvxProblem, H: np.ndarray, rc: Resolved, j: int) -> None:
    prob.params["H"].value = symmetrize(H)
    if rc.Smin is not None:
        prob.params["Smin"].value = rc.Smin[j]
    if rc.Smax is not None:
        prob.params["Smax"].value = rc.Smax[j]
    if rc.c is not None:
        Lh = la.chol(symmetrize(H), "H = B^T So^-1 B (entropy floor)")
        m = H.shape[-1]
        prob.params["LentT"].value = Lh.T
        prob.params["t_ent"].value = math.exp((float(rc.c[j]) + float(la.logdet_chol(Lh))) / m)


def vec_batch(X: np.ndarray) -> np.ndarray:
    """Column-major ``vec`` over the last two axes (batched)."""
    return la.T(X).reshape(X.shape[:-2] + (-1,))


def kron_eig(H: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``S kron H = U Diag(lam) U^T`` (batched; ``U`` orthogonal) from the factors' eigenpairs.

    ``S kron H`` is the Hessian of ``1/2 tr(H F S F^T)`` in column-major ``vec F``; with
    ``H = Uh Diag(dh) Uh^T`` and ``S = Us Diag(ds) Us^T``, ``U = Us kron Uh`` and ``lam = ds kron dh``.
    """
    with la.single_thread_blas_cached():
        dh, Uh = np.linalg.eigh(symmetrize(H))
        ds, Us = np.linalg.eigh(symmetrize(S))
    m, n1 = dh.shape[-1], ds.shape[-1]
    lead = dh.shape[:-1]
    lam = (ds[..., :, None] * dh[..., None, :]).reshape(lead + (n1 * m,))
    U = (Us[..., :, None, :, None] * Uh[..., None, :, None, :]).reshape(lead + (n1 * m, n1 * m))
    return lam, U


def spectral_data(lam: np.ndarray, U: np.ndarray, r: np.ndarray, f0: np.ndarray):
    """Data of the spectral form of ``-1/2 f^T Q f + r^T f`` around ``f0`` (batched).

    With ``Q = U Diag(lam) U^T`` and ``f = f0 + U y`` the quadratic is ``q0 - 1/2 sum_i lam_i y_i^2 + g^T y``,
    ``g = U^T r - lam * (U^T f0)`` and ``q0 = -1/2 f0^T Q f0 + r^T f0``.  Returns ``(lam, g, q0)``.
    """
    lam = np.maximum(lam, 0.0)  # round-off only: Q > 0 was checked by the callers
    Ut = la.T(U)
    w0 = (Ut @ f0[..., None])[..., 0]
    g = (Ut @ r[..., None])[..., 0] - lam * w0
    q0 = -0.5 * np.sum(lam * w0 * w0, -1) + np.sum(r * f0, -1)
    return lam, g, q0


def set_spectral_params(prob: _CvxProblem, rc: Resolved, n: int, lam: np.ndarray, g: np.ndarray,
                         U: np.ndarray, f0: np.ndarray, centres: np.ndarray | None) -> None:
    """One solve of the spectral form: ``centres`` are the vec'd trust-region centres (one per
    trust constraint of the problem) or None."""
    m = rc.m
    prob.params["lam"].value = lam
    prob.params["g"].value = g
    if rc.b is not None:
        prob.params["b"].value = rc.b
        prob.params["Un"].value = U[n * m : (n + 1) * m]
        prob.params["f0n"].value = f0[n * m : (n + 1) * m]
    if rc.delta is not None:
        prob.params["delta"].value = rc.delta
        if len(prob.params["a"]) != len(centres):  # pragma: no cover - internal misuse
            raise RuntimeError("internal error: number of trust-region centres does not match the problem")
        for a, c in zip(prob.params["a"], centres):
            a.value = la.T(U) @ (c - f0)


def spectral_F(prob: _CvxProblem, U: np.ndarray, f0: np.ndarray, m: int, n1: int) -> np.ndarray:
    """``F = unvec(f0 + U y)`` from the spectral form's solution."""
    return la.unvec(f0 + U @ np.asarray(prob.y.value, dtype=float), m, n1)


def _factored_data(H: np.ndarray, S: np.ndarray, R: np.ndarray):
    """``(Lh^T, Ls, C)`` with ``C = Lh^{-1} R Ls^{-T}`` (batched)."""
    Lh = la.chol(H, "H = B^T So^-1 B")
    Ls = la.chol(S, "Stilde")
    C = la.T(la.tri_solve(Ls, la.T(la.tri_solve(Lh, R))))
    return la.T(Lh), Ls, C


def cvxpy_tv(model, st, rc, cfg, solver, Fprev):
    T, n, m = model.T, model.n, model.m
    n1 = n + 1
    spectral = rc.f_constrained
    if spectral:  # offset bound / trust region: the spectral form (module docstring)
        key = ("spectral", n, m, rc.sigma_key, rc.b is not None, 1 if rc.delta is not None else 0)
        lam, U = kron_eig(st.H, st.S)
        f0 = vec_batch(Fprev) if rc.delta is not None else np.zeros((T, m * n1))
        lam, g, q0 = spectral_data(lam, U, vec_batch(st.R), f0)
    else:
        key = ("factored", n, m, rc.sigma_key, False, 0)
        LhT, Ls, C = _factored_data(st.H, st.S, st.R)
    prob = get_problem(key)
    F = np.empty((T, m, n1))
    Sigma = np.empty((T, m, m))
    value = np.empty(T)
    status = []
    duals: list = [None] * T
    times = np.empty(T)
    for j in range(T - 1, -1, -1):  # the Proposition's backward sweep
        t0 = time.perf_counter()
        if spectral:
            set_spectral_params(prob, rc, n, lam[j], g[j], U[j], f0[j],
                                 None if rc.delta is None else f0[j : j + 1])
        else:
            prob.params["LhT"].value = LhT[j]
            prob.params["Ls"].value = Ls[j]
            prob.params["C"].value = C[j]
        _set_sigma_params(prob, st.H[j], rc, j)
        status.append(solve_cvx(prob, solver, cfg, f"M-step (cvxpy, time step k={j})", j))
        times[j] = time.perf_counter() - t0
        if spectral:
            F[j] = spectral_F(prob, U[j], f0[j], m, n1)
            value[j] = st.const[j] + q0[j] + float(prob.problem.value)
        else:
            F[j] = prob.F.value
            value[j] = st.const[j] + 0.5 * float(np.sum(C[j] ** 2)) + float(prob.problem.value)
        Sigma[j] = clean_sigma(prob.Sigma.value, rc)
        duals[j] = _duals(prob)
    return F, Sigma, value, tuple(status), tuple(duals), times


def cvxpy_ti(model, st, rc, cfg, solver, Fprev, hint=MIN_NORM_HINT):
    n, m, T = model.n, model.m, model.T
    n1 = n + 1
    Q, r = ti_normal_equations(st)
    check_time_invariant(model, st.S, Q, cfg, min_norm=False, hint=hint)
    spectral = rc.f_constrained
    if spectral:  # offset bound / trust regions: the spectral form (module docstring)
        key = ("spectral", n, m, rc.sigma_key, rc.b is not None, T if rc.delta is not None else 0)
        with la.single_thread_blas_cached():
            lam, U = np.linalg.eigh(Q)
        centres = vec_batch(Fprev) if rc.delta is not None else None
        f0 = centres.mean(0) if centres is not None else np.zeros(m * n1)
        lam, g, q0 = spectral_data(lam, U, r, f0)
    else:
        key = ("kron", n, m, rc.sigma_key, False, 0)
        Lq = la.chol(Q, "sum_k Stilde_k kron H_k")
        c = la.tri_solve(Lq, r)
    prob = get_problem(key)
    t0 = time.perf_counter()
    if spectral:
        set_spectral_params(prob, rc, n, lam, g, U, f0, centres)
    else:
        prob.params["LqT"].value = Lq.T
        prob.params["c"].value = c
    _set_sigma_params(prob, st.H.sum(0), rc.time_invariant(), 0)
    status = solve_cvx(prob, solver, cfg, "time-invariant M-step (cvxpy)", None)
    times = np.array([time.perf_counter() - t0])
    if spectral:
        F = spectral_F(prob, U, f0, m, n1)
        value = float(st.const.sum()) + float(q0) + float(prob.problem.value)
    else:
        F = np.asarray(prob.F.value)
        value = float(st.const.sum()) + 0.5 * float(c @ c) + float(prob.problem.value)
    return (F, clean_sigma(prob.Sigma.value, rc), np.array([value]), (status,), (_duals(prob),), times)
