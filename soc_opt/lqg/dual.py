"""Dual solvers of the KL-constrained LQG step (method ``"closed_form"``, docs/math.md §6).

Each solver counts its backward passes (one backward pass = one policy; each is followed by
one forward pass for the moments and ``KL_k``):

* scalar ``eta`` (total budget): ``KL(eta) = sum_k KL_k`` is continuous and strictly decreasing,
  so we solve ``log KL(e^x) = log nu`` for ``x = log eta`` by safeguarded inverse quadratic
  interpolation / Newton-secant steps with bisection fallback (:func:`solve_scalar`).
  Typically 5-8 backward passes.
* vector ``eta`` (per-step budgets): the concave dual is maximised over ``eta_k >= eta_min`` by a
  projected, preconditioned L-BFGS method in ``x = log eta`` with the analytic gradient
  ``eta_k (KL_k - nu_k)`` (:func:`solve_vector`); the preconditioner is a per-step diagonal
  model with a fitted geometric coupling between steps (:func:`_fit_coupling`).  Typically 10-16
  backward passes (12-13 at ``n=26, m=7, T=100``), independent of ``T``.

Both apply the Quu repair rule of :mod:`.backward` to non-PD points.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..models import NotPositiveDefiniteError
from .backward import DualEval, NotPDPoint, backward_pass, direct_dkl, evaluate_eta
from .problem import BudgetUnreachable, KLProblem, KLStepConfig, SolverError

_MEM = 10
_NEAR = 0.1  # L-BFGS memory is used only once every free |log(KL_k/nu_k)| < _NEAR ...
_GATE_ITERS = 25  # ... or after this many iterations (strongly coupled, e.g. non-convex, problems)


class _Counter:
    def __init__(self, prob: KLProblem, config: KLStepConfig):
        self.prob, self.config, self.n = prob, config, 0

    def __call__(self, eta: np.ndarray, repair=None) -> DualEval | NotPDPoint:
        if self.n >= self.config.max_backward:
            raise SolverError(
                f"dual solver exceeded max_backward={self.config.max_backward} backward passes"
            )
        self.n += 1
        try:
            bw = backward_pass(self.prob, eta, repair=repair, config=self.config)
        except NotPDPoint as e:
            return e
        return evaluate_eta(self.prob, bw)


def solve_scalar(prob: KLProblem, nu: float, config: KLStepConfig, eta0) -> tuple[DualEval, int, int, str]:
    """Root of ``f(x) = log sum_k KL_k(e^x) - log nu`` (continuous, strictly decreasing) in ``x = log eta``.

    Safeguarded root finding in log-log coordinates (:func:`_scalar_proposal`): inverse
    quadratic interpolation through the last three points once there are three, else a Newton
    step whose slope is the secant through the last two points when they are within 1 of each
    other in ``log eta``, else the analytic slope ``eta sum_k dKL_k/deta / sum_k KL_k`` through
    each step's own policy (:func:`direct_dkl`); slopes clipped to ``[-10, -1e-3]``, steps capped
    at ``max_log_step``; a step leaving the current bracket, or two steps in a row that do not
    halve ``|f|``, is replaced by bisection.  (``f`` is concave in ``x``, its slope going from about
    0 at small ``eta`` to -2 at large ``eta``: a first Newton step from a small ``eta`` overshoots,
    and the interpolation through three points uses that curvature; it saves about one backward
    pass in eight against the secant.)  Non-PD points raise ``eta`` by the repair rule and
    become a lower end of the bracket.  Stops when ``|KL - nu| <= kl_rtol nu + T kl_atol``;
    ``KL(eta_min) < nu`` returns ``eta_min`` (slack budget).  Typically 5-8 backward passes.
    Returns ``(eval, n_backward, n_iter, status)``.
    """
    T = prob.T
    call = _Counter(prob, config)
    ftol = math.log1p(config.kl_rtol + T * config.kl_atol / nu)
    xmin, xmax = math.log(config.eta_min), math.log(config.eta_max)
    cap = config.max_log_step
    e0 = np.asarray(config.eta_init if eta0 is None else eta0, dtype=float).ravel()
    e0 = e0[np.isfinite(e0) & (e0 > 0)]
    e0 = float(np.max(e0)) if e0.size else config.eta_init
    x = min(max(math.log(max(e0, config.eta_min)), xmin), xmax)
    lo, hi = -math.inf, math.inf  # f(lo) > 0 (or lo outside the domain), f(hi) < 0
    pts: list[tuple[float, float]] = []  # last evaluated (x, f), oldest first
    slow = 0
    it = 0
    while True:
        it += 1
        r = call(np.full(T, config.eta_min if x <= xmin else math.exp(x)))
        if isinstance(r, NotPDPoint):  # repair rule: raise eta
            lo = max(lo, x)
            e = max(config.repair_factor * math.exp(x), (1.0 + config.repair_margin) * r.eta_crit)
            if e > config.eta_max:
                raise NotPositiveDefiniteError(
                    f"Quu[{r.t}] is not positive definite for any multiplier up to eta_max={config.eta_max:g} "
                    f"(needs eta > {r.eta_crit:.3e})"
                )
            x = math.log(e)
            if x >= hi:
                x = 0.5 * (lo + hi)
            continue
        ksum = float(r.kl.sum())
        if ksum == 0.0:
            # KL = 0 exactly: the policy is the reference, the cost does not move it at this multiplier (a
            # cost flat in the action).  KL decreases in eta, so the budget is slack down to eta_min or met
            # below this point: try eta_min (no slope to follow from a zero KL)
            if x <= xmin:
                return r, call.n, it, "slack (eta = eta_min): KL = 0, the policy is the reference"
            hi, x = min(hi, x), xmin
            continue
        if not ksum > 0.0:  # a KL is >= 0: a negative or NaN total means the evaluation at eta is wrong
            raise SolverError(f"KL(eta={math.exp(x):.6g}) = {ksum!r} is negative or not a number: the KL of a Gaussian policy to "
                              "its reference cannot be; the dual's KL evaluation (lqg/backward.py) or the problem's "
                              "covariances are wrong")
        f = math.log(ksum) - math.log(nu)
        if abs(f) <= ftol:
            return r, call.n, it, "converged"
        if f > 0:
            lo = max(lo, x)
            if x >= xmax:
                raise BudgetUnreachable(f"KL budget nu={nu:g} not reachable: KL(eta_max={config.eta_max:g}) = {ksum:.3e}")
        else:
            hi = min(hi, x)
            if x <= xmin:
                return r, call.n, it, "slack (eta = eta_min)"
        if hi - lo < 1e-13:
            if abs(f) > 1e3 * ftol:
                raise SolverError(f"scalar dual did not converge: KL/nu - 1 = {math.expm1(f):.3e}")
            return r, call.n, it, "converged (bracket width)"
        slow = slow + 1 if pts and abs(f) > 0.5 * abs(pts[-1][1]) else 0
        pts = (pts + [(x, f)])[-3:]
        xn = _scalar_proposal(pts, lo, hi, cap, lambda: math.exp(x) * float(direct_dkl(prob, r).sum()) / ksum)
        if not lo < xn < hi or (slow >= 2 and math.isfinite(lo) and math.isfinite(hi)):
            if math.isfinite(lo) and math.isfinite(hi):
                xn = 0.5 * (lo + hi)
                slow = 0
            else:
                xn = x + (cap if f > 0 else -cap)
        x = min(max(xn, xmin), xmax)


def _scalar_proposal(pts: list, lo: float, hi: float, cap: float, direct_slope) -> float:
    """Next ``x`` of :func:`solve_scalar` from the last points ``pts = [(x, f), ...]`` (current
    last): inverse quadratic interpolation through three points with distinct ``f`` when it lands
    inside the bracket ``(lo, hi)`` within ``cap`` of the current point, else the capped Newton step
    with the secant slope (last two points within 1 in ``x``) or ``direct_slope()``."""
    x, f = pts[-1]
    if len(pts) == 3:
        (a, fa), (b, fb), (c, fc) = pts
        if fa != fb and fa != fc and fb != fc:
            xn = (a * fb * fc / ((fa - fb) * (fa - fc)) + b * fa * fc / ((fb - fa) * (fb - fc))
                  + c * fa * fb / ((fc - fa) * (fc - fb)))
            if lo < xn < hi and abs(xn - x) <= cap:
                return xn
    slope = None
    if len(pts) >= 2 and abs(x - pts[-2][0]) < 1.0 and pts[-2][1] != f:
        slope = (f - pts[-2][1]) / (x - pts[-2][0])
    if slope is None or not -10.0 < slope < -1e-3:
        sd = direct_slope()
        slope = min(max(sd, -10.0), -1e-3) if math.isfinite(sd) else -1.0
    return x + min(max(-f / slope, -cap), cap)


def solve_vector(prob: KLProblem, nu: np.ndarray, config: KLStepConfig, eta0) -> tuple[DualEval, int, int, str]:
    """Maximise the concave dual over ``eta_k >= eta_min`` (steps with finite ``nu_k > 0``).

    Minimises ``phi(x) = -g(e^x)`` over ``x = log eta >= log eta_min`` (gradient
    ``eta_k (nu_k - KL_k)``):

    * diagonal model: per step the Newton step of ``log KL_k(x_k) = log nu_k`` in log-log
      coordinates, with the slope ``dlog KL_k/dx_k`` through step ``k``'s own policy
      (:func:`direct_dkl`).  This is exact for the power law ``KL ~ eta^-2`` of large ``eta`` and
      moves a slack budget to ``eta_min`` in a few steps.  As a curvature it tends to the diagonal
      ``eta_k^2 |dKL_k/deta_k|`` of the dual Hessian at the solution, and the preconditioned
      Hessian is well conditioned (eigenvalues in about [0.6, 1.3] on random instances);
    * coupling: the steps interact through the value function and the state marginals, which
      the diagonal misses (on the benchmark instances at ``n=26, m=7, T=100`` the eigenvalues of
      the diagonally preconditioned Hessian spread over about [0.62, 1.07], with a few
      smooth, collective outliers, and the relative off-diagonal entries decay like
      ``0.85^|k-j|``).  A two-parameter model ``S^1/2 (I - a K_rho) S^1/2`` of the Hessian,
      ``K_rho[k, j] = rho^|k-j|`` off the diagonal, is fitted to each curvature pair and, once
      the previous fit has predicted the new pair, used as the initial inverse Hessian of
      L-BFGS (:func:`_fit_coupling`, :class:`_CouplingModel`; the best such model at the
      solution narrows the spread to about [0.94, 1.07]); the solve then takes 12-13 instead of
      15-16 backward passes there, and about as many as before on small problems;
    * L-BFGS (memory 10) with that initial inverse Hessian, the memory used only once every
      free budget is within 10 % (``|log KL_k/nu_k| < 0.1``) or after 25 iterations: far from
      the solution the coupling between steps (through the value function and the state
      marginals) is nonlinear and curvature pairs hurt (notably while slack budgets travel to
      ``eta_min``), but when the coupling dominates (non-convex costs with budgets that put the
      solution close to the PD boundary of some ``Quu``) only the memory makes progress; the
      memory is reset when the active set changes;
    * each component of the step capped at ``max_log_step``; Armijo backtracking on
      ``phi`` (non-PD trial points are rejected, roundoff-level increases of ``phi`` tolerated);
      the bound ``eta_min`` by projection with the usual active set (at the bound and pushed
      outwards).

    ``nu_k = inf`` steps keep ``eta_k = 0`` and ``nu_k = 0`` steps ``eta_k = inf``.  The first
    point is repaired (non-PD ``Quu_k`` raise ``eta_k`` by the repair rule).  Stops when
    ``|KL_k - nu_k| <= kl_rtol nu_k + kl_atol`` for every free step off the bound and
    ``KL_k <= nu_k (1 + kl_rtol) + kl_atol`` at the bound.
    """
    T = prob.T
    dual = _VectorDual(prob, nu, config)
    call, free, xmin, xmax = dual.call, dual.free, dual.xmin, dual.xmax
    if not free.any():
        r = call(dual.eta)
        if isinstance(r, NotPDPoint):
            _raise_unbounded(r)
        return r, call.n, 0, "no finite budget"
    e0 = np.full(T, config.eta_init) if eta0 is None else np.broadcast_to(np.asarray(eta0, float), (T,))
    e0 = np.where(np.isfinite(e0) & (e0 > 0), e0, config.eta_init)  # warm start may hold 0 / inf entries
    x = np.zeros(T)
    x[free] = np.clip(np.log(np.maximum(e0[free], config.eta_min)), xmin, xmax)
    r = call(dual.full(x), repair=free)  # first point: repair non-PD steps upwards
    if isinstance(r, NotPDPoint):
        _raise_unbounded(r)
    x[free] = np.log(r.bw.eta[free])
    phi, g = dual.merit(r)
    mem_s: list[np.ndarray] = []
    mem_y: list[np.ndarray] = []
    prev_active = None
    coup, use_coup = None, False
    it = 0
    while True:
        if dual.converged(r, x):
            return r, call.n, it, "converged"
        it += 1
        h, lr = dual.diag_model(r, x, g)
        active = ~free | ((x <= xmin + 1e-12) & (g > 0))
        near = it > _GATE_ITERS or np.all(np.abs(lr)[~active[free]] < _NEAR)
        if not near or (prev_active is not None and np.any(active != prev_active)):
            mem_s.clear()
            mem_y.clear()
        prev_active = active
        h0 = _CouplingModel(h, active, coup) if use_coup else None
        d = _lbfgs_direction(g, h, active, mem_s, mem_y, dual.cap, h0)
        xn, rn, phin, gn = dual.line_search(x, d, phi, g)
        s_ = np.where(active, 0.0, xn - x) if near else np.zeros(T)
        y_ = np.where(active, 0.0, gn - g)
        coup, use_coup = _fit_coupling(h, active, np.where(active, 0.0, xn - x), y_, coup)
        _remember(mem_s, mem_y, s_, y_)
        x, r, phi, g = xn, rn, phin, gn
        if np.any(x[free] >= xmax - 1e-12):
            t = int(np.flatnonzero(free & (x >= xmax - 1e-12))[0])
            raise BudgetUnreachable(f"KL budget nu[{t}]={nu[t]:g} not reachable below eta_max={config.eta_max:g}", step=t)


class _VectorDual:
    """The fixed data of one :func:`solve_vector` run and its per-iteration pieces, in
    ``x = log eta`` (only the free steps, finite ``nu_k > 0``, are variables)."""

    def __init__(self, prob: KLProblem, nu: np.ndarray, config: KLStepConfig):
        self.prob, self.config, self.T = prob, config, prob.T
        self.call = _Counter(prob, config)
        self.free = np.isfinite(nu) & (nu > 0)
        self.eta = np.where(np.isinf(nu), 0.0, np.where(nu == 0, np.inf, 0.0))  # fixed entries
        self.nuf = nu[self.free]
        self.xmin, self.xmax = math.log(config.eta_min), math.log(config.eta_max)
        self.cap = config.max_log_step

    def full(self, xv: np.ndarray) -> np.ndarray:
        """(T,) multipliers of the point ``xv``."""
        out = self.eta.copy()
        free = self.free
        # exactly eta_min at the bound (within the active-set tolerance 1e-12 used below: a point
        # a few ulps above xmin must not report eta = 1.0000000000000044e-12 > eta_min)
        out[free] = np.where(xv[free] <= self.xmin + 1e-12, self.config.eta_min, np.exp(xv[free]))
        return out

    def merit(self, rr: DualEval) -> tuple[float, np.ndarray]:
        """``(phi, dphi/dx)`` with ``phi = -g(eta)``."""
        free, nuf = self.free, self.nuf
        ef = rr.bw.eta[free]
        grad = np.zeros(self.T)
        grad[free] = ef * (nuf - rr.kl[free])
        return -(rr.cost.sum() + ef @ (rr.kl[free] - nuf)), grad

    def converged(self, r: DualEval, x: np.ndarray) -> bool:
        """Stopping rule of :func:`solve_vector` (active budgets met, bound budgets not exceeded)."""
        free, nuf, config = self.free, self.nuf, self.config
        kl = r.kl[free]
        at_lo = x[free] <= self.xmin + 1e-12
        tol = config.kl_rtol * nuf + config.kl_atol
        ok = np.where(at_lo, kl <= nuf + tol, np.abs(kl - nuf) <= tol)
        return bool(ok.all())

    def diag_model(self, r: DualEval, x: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(h, lr)``: the diagonal curvature (T,) and ``log(KL_k / nu_k)`` of the free steps.

        Per step the Newton step of ``log KL_k = log nu_k`` in ``v_k = log(eta_k - c_k)``,
        ``c_k = max(0, -lambda_min(Lh^T Q0uu Lh))`` the PD threshold of ``Quu_k`` (0 for convex
        costs), with the slope through step k's own policy; as a curvature ``h_k = -g_k / d_k``,
        which tends to ``eta_k^2 |dKL_k/deta_k|`` (the diagonal of the dual Hessian) at the
        solution.
        """
        free, nuf, cap = self.free, self.nuf, self.cap
        etaf = np.exp(x)
        eta_fr, kl_fr = etaf[free], np.maximum(r.kl[free], 1e-300)
        dkl = np.abs(direct_dkl(self.prob, r))[free]
        c = np.minimum(np.maximum(-r.mu_eig[free].min(axis=1), 0.0), 0.999 * eta_fr)
        gap = eta_fr - c
        lr = np.log(kl_fr / nuf)
        sv = np.maximum(gap * dkl / kl_fr, 1e-12)  # |dlog KL / dv|
        dv = np.clip(lr / sv, -cap, cap)
        dx = np.log((c + gap * np.exp(dv)) / eta_fr)
        h = np.ones(self.T)
        h_lim = np.maximum(eta_fr ** 2 * dkl, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            h_dir = -g[free] / dx
        h[free] = np.where((np.abs(lr) > 1e-8) & (h_dir > 0) & np.isfinite(h_dir), h_dir, h_lim)
        return h, lr

    def line_search(self, x: np.ndarray, d: np.ndarray, phi: float, g: np.ndarray):
        """Armijo backtracking from ``x`` along ``d`` (non-PD trial points rejected); returns
        ``(x, eval, phi, grad)`` of the accepted point."""
        free, xmin, xmax = self.free, self.xmin, self.xmax
        step = 1.0
        slope = g @ d
        while True:
            xn = np.where(free, np.clip(x + step * d, xmin, xmax), x)
            rn = self.call(self.full(xn))
            if not isinstance(rn, NotPDPoint):
                phin, gn = self.merit(rn)
                if phin <= phi + 1e-4 * step * slope + 1e-12 * abs(phi):
                    return xn, rn, phin, gn
            step *= 0.5
            if step < 1e-12:
                raise SolverError("vector dual line search failed (no decrease along the quasi-Newton direction)")


_RHOS = (0.3, 0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.93, 0.96)  # decay rates tried by _fit_coupling
_EXPLAIN = 0.5  # a coupling fit must remove half of the squared secant mismatch of its own pair ...
_VALID = 0.5  # ... and the previous fit as much of the next pair's before a fit is used


def _kms(t: np.ndarray, rho: float) -> np.ndarray:
    """``K[i, j] = rho^|t_i - t_j|`` off the diagonal, 0 on it."""
    K = rho ** np.abs(t[:, None] - t[None, :]).astype(float)
    np.fill_diagonal(K, 0.0)
    return K


def _kms_apply(u: np.ndarray, rho: float) -> np.ndarray:
    """``K_rho u`` over all ``T`` steps in O(T): ``sum_{j != i} rho^|i - j| u_j`` by two
    first-order recursive filters (forward and backward in time)."""
    from scipy.signal import lfilter  # here, not at the top: importing scipy.signal takes ~0.5 s

    a = [1.0, -rho]
    return lfilter([0.0, rho], a, u) + lfilter([0.0, rho], a, u[::-1])[::-1]


def _fit_coupling(h: np.ndarray, active: np.ndarray, s: np.ndarray, y: np.ndarray, prev):
    """Fit the coupling model of :class:`_CouplingModel` to the last curvature pair.

    The Hessian of ``phi`` in ``x`` is modelled on the free steps as
    ``S^1/2 (I - a K_rho) S^1/2`` with ``S = diag(h)`` (the diagonal model) and
    ``K_rho[i, j] = rho^|t_i - t_j|`` off the diagonal (a coupling between steps that decays
    geometrically with their distance in time, through the value function backwards and the
    state marginals forwards).  With ``u = S^1/2 s`` the pair ``(s, y)`` (T,) should satisfy
    ``r = u - S^-1/2 y = a K_rho u``: for each ``rho`` in ``_RHOS`` ``a`` is the least-squares
    fit, and the ``rho`` with the smallest residual is kept.  Returns ``(fit, use)``: ``fit`` is
    ``(rho, a)``, or None if it removes less than ``_EXPLAIN`` of ``|r|^2`` or ``I - a K_rho``
    would have an eigenvalue below 0.2; ``use`` is True when the previous fit ``prev`` also
    predicted this pair (out of sample: residual at most ``_VALID |r|^2``), so that a fit is used
    only once the model has been seen to predict.
    """
    free = ~active
    if free.sum() < 3:
        return None, False
    sq = np.sqrt(h[free])
    u = np.zeros(h.size)
    u[free] = sq * s[free]
    r = u[free] - y[free] / sq
    nr = r @ r
    if not nr > 0 or not np.isfinite(nr):
        return None, False
    use = False
    if prev is not None:
        e = r - prev[1] * _kms_apply(u, prev[0])[free]
        use = bool(e @ e <= _VALID * nr)
    best = None
    for rho in _RHOS:
        v = _kms_apply(u, rho)[free]
        vv = v @ v
        if not vv > 0:
            continue
        a = (r @ v) / vv
        res = nr - a * (r @ v)
        if best is None or res < best[0]:
            best = (res, rho, a)
    if best is None or best[0] > _EXPLAIN * nr:
        return None, False
    _, rho, a = best
    # the eigenvalues of K_rho lie in (-2 rho/(1 + rho), 2 rho/(1 - rho)): |a| <= lim keeps those
    # of I - a K_rho >= 0.2
    lim = 0.8 * min((1 - rho) / (2 * rho), (1 + rho) / (2 * rho))
    if abs(a) > lim:
        return None, False
    return (float(rho), float(a)), use


class _CouplingModel:
    """Initial inverse Hessian of the L-BFGS recursion with coupling between steps:
    ``H0 q = S^-1/2 (I - a K_rho)^-1 S^-1/2 q`` on the free steps, 0 on the active set
    (``S = diag(h)``, ``coup = (rho, a)`` from :func:`_fit_coupling`; one Cholesky factorisation
    of the free-step block)."""

    def __init__(self, h: np.ndarray, active: np.ndarray, coup: tuple[float, float]):
        rho, a = coup
        self.free = ~active
        t = np.flatnonzero(self.free)
        self.isq = 1.0 / np.sqrt(h[self.free])
        self.cf = cho_factor(np.eye(t.size) - a * _kms(t, rho), lower=True)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        out = np.zeros_like(q)
        out[self.free] = self.isq * cho_solve(self.cf, self.isq * q[self.free])
        return out


def _lbfgs_direction(g: np.ndarray, h: np.ndarray, active: np.ndarray, mem_s: list, mem_y: list,
                     cap: float, h0: _CouplingModel | None = None) -> np.ndarray:
    """L-BFGS two-loop direction with the initial inverse Hessian ``h0`` (default ``diag(1/h)``),
    zero on the active set, components capped at ``cap``; not a descent direction: the memory is
    dropped and ``-h0 g`` used, or the diagonal step if that is not one either (capping)."""
    q = np.where(active, 0.0, g)
    alphas = []
    for s_, y_ in zip(reversed(mem_s), reversed(mem_y)):
        rho = 1.0 / (y_ @ s_)
        a_ = rho * (s_ @ q)
        q = q - a_ * y_
        alphas.append((rho, a_, s_, y_))
    d = np.where(active, 0.0, q / h) if h0 is None else h0(q)
    for rho, a_, s_, y_ in reversed(alphas):
        b_ = rho * (y_ @ d)
        d = d + s_ * (a_ - b_)
    d = np.clip(np.where(active, 0.0, -d), -cap, cap)
    if g @ d >= 0:  # not a descent direction: drop the memory, use the diagonal step
        mem_s.clear()
        mem_y.clear()
        d = None if h0 is None else np.clip(-h0(g), -cap, cap)
        if d is None or not g @ d < 0:
            d = np.clip(np.where(active, 0.0, -g / h), -cap, cap)
    return d


def _remember(mem_s: list, mem_y: list, s_: np.ndarray, y_: np.ndarray) -> None:
    """Append the curvature pair ``(s, y)`` if ``s^T y > 0`` (relatively), keeping the last ``_MEM``."""
    if s_ @ y_ > 1e-12 * np.linalg.norm(s_) * np.linalg.norm(y_):
        mem_s.append(s_)
        mem_y.append(y_)
        if len(mem_s) > _MEM:
            mem_s.pop(0)
            mem_y.pop(0)


def _raise_unbounded(e: NotPDPoint):
    raise NotPositiveDefiniteError(
        f"Quu[{e.t}] is not positive definite at eta={e.eta:g} on a step without a finite KL budget: "
        "the cost-to-go is not strictly convex in the action there"
    )


def dual_objective(ev: DualEval, eta: np.ndarray, nu: np.ndarray) -> float:
    """``g(eta) = sum_k E[l_k] + sum_k eta_k (KL_k - nu_k)`` at the backward-pass policy ``ev`` of ``eta``
    (docs/math.md §6); steps with ``eta_k = 0`` (unconstrained) or ``inf`` (pinned, ``KL_k = 0``) add nothing."""
    use = np.isfinite(eta) & (eta > 0)
    return float(ev.cost.sum() + eta[use] @ (ev.kl[use] - nu[use]))


def dual_function(prob: KLProblem, eta: np.ndarray, nu: np.ndarray) -> tuple[float, DualEval]:
    """The Lagrange dual function of the KL step at any multipliers ``eta`` (T,) with per-step budgets ``nu``
    (T,): ``g(eta) = min_p sum_k E_p[l_k] + sum_k eta_k (KL_k - nu_k)`` (docs/math.md §6), attained by the
    backward-pass policy of ``eta`` (returned in the :class:`DualEval`).  By weak duality
    ``g(eta) <= sum_k E_p[l_k]`` for every ``p`` meeting the budgets; the closed form maximises ``g``.  A total
    budget ``nu`` with one multiplier is ``eta_k = eta``, ``nu_k = nu / T``.  Raises ``NotPDPoint`` when some
    ``Quu_k`` is not positive definite at ``eta`` (no minimiser)."""
    eta = np.asarray(eta, dtype=float)
    ev = evaluate_eta(prob, backward_pass(prob, eta))
    return dual_objective(ev, eta, np.asarray(nu, dtype=float)), ev
