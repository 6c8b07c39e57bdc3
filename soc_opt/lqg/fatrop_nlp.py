"""The KL-constrained LQG step as a multiple-shooting optimal control problem solved by fatrop
(method ``"fatrop"``, docs/math.md §6).

fatrop (a CasADi ``nlpsol`` plugin) is an interior-point method whose linear solver is a Riccati
recursion over the stages of an optimal control problem.  It needs that structure explicitly
(``structure_detection="manual"``): variables ordered by stage ``[x_0, u_0, x_1, u_1, ...]``; per
interval ``k`` first the gap-closing rows ``x_{k+1} - f_k(x_k, u_k) = 0``, then the stage's own
(path) constraints; a Lagrangian Hessian that is block diagonal in the stages.  The KL step has
that form in multiple shooting on the moments, in the joint (lifted) moments of each step:

* state ``x_k = (E[s_k], vech P_k)``, ``P_k = Cov(s_k)`` (``n + n(n+1)/2``; none at ``k = 0``, whose
  moments are the given ``(mu0, P0)``), for a total budget also the running sum
  ``c_k = sum_{j<k} KL_j``;
* control ``u_k = (E[a_k], vec Cov(a_k, s_k), vech Cov(a_k))`` at a step with a finite budget
  ``nu_k > 0``, none at a step with ``nu_k = 0`` (the reference); the policy is recovered as
  ``K = Cov(a, s) P^-1``, ``k = E[a] - K E[s]``, ``Sigma = Cov(a) - K Cov(s, a)``;
* dynamics ``E[s'] = [A B] E[z] + c``, ``P' = [A B] Cov(z) [A B]^T + W``: linear;
* objective ``sum_k E[l_k]``: linear in ``Cov(z)``, convex quadratic in ``E[z]``;
* path constraint ``KL_k = nu_k`` (total budget: ``c_{T-1} + KL_{T-1} = nu`` at the last stage)
  as an equality (below), ``KL_k = 1/2 [tr(Sh^-1 Cov(a - Kh s)) + |E[a] - Kh E[s] - kh|^2_{Sh^-1} - m + log|Sh| - log|Sigma|]``:
  linear terms plus ``-log|Sigma|``, ``Sigma`` the Schur complement of ``P`` in ``Cov(z)``, which
  is jointly convex.  ``log|Sigma|`` comes from the last ``m`` pivots of an ``LDL^T`` factorisation
  of ``Cov(z)`` written out in SX.

For a convex stage cost the NLP (with ``KL_k <= nu_k``) is convex.  The KL rows are posed as
equalities: every finite budget is active in a non-degenerate problem (:mod:`.backward`), and a
KKT point of the equality form with multipliers ``>= 0`` is one of the inequality form; the
multipliers are checked, and a negative one (a slack budget) raises :class:`SolverError`.  (As
inequalities, fatrop condenses the barrier of the active rows, about ``lambda / s ~ 1e11`` when
the barrier parameter reaches 1e-9, into the stage Hessians of its Riccati recursion; the
inertia test then failed, the regularisation went to 1e4-1e5 and fatrop stalled at a dual
infeasibility of 1e-7 to 1e-5 on 5 of 12 per-step instances at ``n=4, m=2, T=20``.)  fatrop starts
from the policy ``(Kh, kh, alpha_t Sh_t)`` and its moments, ``alpha_t`` in (0, 1) chosen so that every
KL row holds (:meth:`_FatropOCP._start_covariances`; from the reference itself the KL rows have
zero gradients and fatrop failed on the benchmark's instances).  It then converged in 8-15
iterations on 40 benchmark instances (``n, m, T = 4, 2, 20`` and ``6, 3, 10``, both budget kinds),
to 6e-10 in policy and relative multipliers against the closed form (``tol = 1e-8``).  When
``P0`` is singular the first step keeps the moment form in the coordinates ``U^T s``, ``U``
(n, r) spanning the range of ``P0``: controls ``(E[a], vec Cov(a, U^T s), vech Cov(a))``, ``log|S|``
from the pivots of ``[[U^T P0 U, Cov(U^T s, a)], [Cov(a, U^T s), Cov(a)]]``, still convex; then
``K_0 U = Cov(a, U^T s) (U^T P0 U)^-1`` and ``K_0 = Kh_0`` on the null space of ``P0`` (not
identifiable: the action ``K_0 s_0 + k_0`` is the same).  (The policy parametrisation ``K_0 = Kh_0 + Delta U^T``,
``Sigma_0 = L L^T`` with ``log L_ii``, tried first, is not convex; with per-step budgets fatrop's
first step left the region where the next stage's pivots are positive and it failed on NaNs.)
Each kind of stage is one SX function of ``(x_k, u_k)``
and the step's data, called once per step in an MX graph; CasADi's exact Hessian is block
diagonal by construction.  The multipliers of the KL rows are the ``eta_k`` (CasADi's sign
convention, as for IPOPT).  fatrop's status is checked (``success``); a failure raises
:class:`SolverError`.

What does not work, tried on ``n=4, m=2, T=10-20``:

* multiple shooting in the policy ``(K_k, k_k, L_k)`` with covariance states: the bilinear
  ``(A + B K) P (A + B K)^T`` makes the Hessian strongly indefinite away from the solution;
  fatrop's inertia correction ran away (regularisation 1e17, restoration phases) and failed on
  every instance (as IPOPT did on that form, see :mod:`.casadi_nlp`);
* ``L_ii`` with a lower bound: fatrop turns bounds into slack constraints, iterates leave them and
  ``log L_ii`` gave NaNs (hence logarithms);
* steps with ``nu_k = inf`` (deterministic, ``Cov(z)`` singular) and budgets that are slack at the
  solution (the closed form gives ``Sigma_k = eta_min Quu^-1``, about 1e-12): ``Sigma_k`` collapses
  onto the boundary of the moment parametrisation; with a floor ``>= 1e-9 ... 1e-4`` on the pivots
  of ``Sigma_k`` fatrop made no progress (the pivots of a nearly singular ``Cov(z)`` are
  ill-conditioned).  ``nu_k = inf`` is rejected up front (:class:`ValueError`); a slack finite
  budget ends in :class:`SolverError`.  Use ``method="casadi"`` there.

Cost.  A stage has ``n + n(n+1)/2`` states and ``m + m n + m(m+1)/2`` controls (377 and 217 at
``n=26, m=7``); fatrop's Riccati recursion is cubic in the stage size, and CasADi builds the
dense per-stage Hessian blocks by AD: at ``n=26, m=7, T=100`` building the solver did not finish
within 7 minutes (5.9 GB resident, ``fatrop_expand = True``) on the 2-core development machine;
:mod:`soc_opt.bench.lqg` skips fatrop there.
"""

from __future__ import annotations

import time

import numpy as np

from ..linalg import chol, right_cho_solve
from ..models import symmetrize
from .casadi_nlp import casadi_kinds, casadi_n_vars, nlp_solution, stage_terms
from .moments import forward_arrays
from .problem import KLProblem, KLStepConfig, KLStepResult, SolverError


def vech_pairs(n: int) -> list[tuple[int, int]]:
    """Index pairs of ``vech`` (lower triangle, column by column)."""
    return [(i, j) for j in range(n) for i in range(j, n)]


def _stage_data(prob: KLProblem, t: int, with_ref_cov: bool) -> np.ndarray:
    """Step ``t``'s data as one column-major vector (the layout :func:`stage_function` unpacks)."""
    d, c, r = prob.dynamics, prob.cost, prob.reference
    parts = [d.A[t], d.B[t], d.c[t], d.cov[t], c.C[t], c.c[t], [c.c0[t]], r.K[t], r.k[t], prob.Shinv[t],
             [prob.logdetSh[t]]]
    if with_ref_cov:
        parts.append(r.cov[t])
    return np.concatenate([np.ravel(np.asarray(p, dtype=float), order="F") for p in parts])


def _ldl_pivots(ca, M, size: int) -> list:
    """Pivots ``D_ii`` of the (unpivoted) ``LDL^T`` factorisation of the symmetric SX matrix ``M``."""
    M = ca.SX(M)
    piv = []
    for j in range(size):
        d = M[j, j]
        piv.append(d)
        if j + 1 < size:
            col = M[j + 1 :, j] / d
            M[j + 1 :, j + 1 :] = M[j + 1 :, j + 1 :] - ca.mtimes(col, M[j, j + 1 :])
    return piv


def stage_function(ca, n: int, m: int, kind: str, r: int = 0):
    """SX function ``(mu, vech P, u, data) -> (E[l], KL, mu', vech P')`` of one kind of stage.

    Kinds: ``"moment"`` (a free step, controls ``(a_mean, vec Cov(a, s), vech Cov(a))``),
    ``"moment0"`` (a free first step when ``P0 = Cov(s_0)`` is singular: the same in the
    coordinates ``U^T s``, ``U`` (n, r) spanning the range of ``P0`` (the data's last block),
    controls ``(a_mean, vec Cov(a, U^T s), vech Cov(a))``), ``"pin"`` (``nu_k = 0``, the
    reference, no controls).
    """
    vp = vech_pairs(n)
    mu, pv = ca.SX.sym("mu", n), ca.SX.sym("p", len(vp))
    u = ca.SX.sym("u", n_controls(kind, n, m, r))
    sizes = [("A", n, n), ("B", n, m), ("c", n, 1), ("W", n, n), ("C", n + m, n + m), ("cl", n + m, 1),
             ("c0", 1, 1), ("Kh", m, n), ("kh", m, 1), ("R", m, m), ("logdetSh", 1, 1)]
    if kind == "pin":
        sizes.append(("Sh", m, m))
    if kind == "moment0":
        sizes.append(("U", n, r))
    dat = ca.SX.sym("data", sum(rows * cols for _, rows, cols in sizes))
    D, pos = {}, 0
    for name, rows, cols in sizes:
        D[name] = ca.reshape(dat[pos : pos + rows * cols], rows, cols)
        pos += rows * cols
    P = _sym_from_vech(ca, pv, n)
    if kind == "pin":
        obj, kl, mu_n, P_n = stage_terms(ca, D, n, mu, P, D["Kh"], D["kh"], D["Sh"], None)
    else:
        obj, kl, mu_n, P_n = _moment_terms(ca, D, n, m, mu, P, u, D.get("U"))
    pv_n = ca.vertcat(*[P_n[i, j] for i, j in vp])
    kl = ca.SX(0) if kl is None else kl
    return ca.Function(f"kl_stage_{kind}", [mu, pv, u, dat], [obj, kl, mu_n, pv_n])


def _sym_from_vech(ca, v, n: int):
    P = ca.SX(n, n)
    for idx, (i, j) in enumerate(vech_pairs(n)):
        P[i, j] = v[idx]
        P[j, i] = v[idx]
    return P


def n_controls(kind: str, n: int, m: int, r: int = 0) -> int:
    return {"moment": m + m * n + m * (m + 1) // 2, "moment0": m + m * r + m * (m + 1) // 2, "pin": 0}[kind]


def _moment_terms(ca, D: dict, n: int, m: int, mu, P, u, U=None):
    """``(E[l], KL, E[s'], Cov(s'))`` in the joint moments ``zbar = (mu, a_mean)``,
    ``Sz = [[P, Sas^T], [Sas, Saa]]`` (convex: everything is linear in ``Sz`` except
    ``-log|S|``, ``S = Saa - Sas P^-1 Sas^T`` the policy covariance, which is jointly convex).

    With ``U`` (n, r), orthonormal columns spanning the range of ``P`` (a singular ``P``, the
    first step), the controls hold ``Sas_r = Cov(a, U^T s)`` (m, r) instead, ``Sas = Sas_r U^T``,
    and ``log|S|`` comes from the pivots of ``[[U^T P U, Sas_r^T], [Sas_r, Saa]]`` (positive
    definite iff ``S > 0``)."""
    r = n if U is None else U.shape[1]
    a_mean = u[:m]
    Sas_r = ca.reshape(u[m : m + m * r], m, r)
    Saa = _sym_from_vech(ca, u[m + m * r :], m)
    Sas = Sas_r if U is None else ca.mtimes(Sas_r, U.T)
    Sz = ca.blockcat([[P, Sas.T], [Sas, Saa]])
    Pr = P if U is None else ca.mtimes([U.T, P, U])
    Sz_r = Sz if U is None else ca.blockcat([[Pr, Sas_r.T], [Sas_r, Saa]])
    zbar = ca.vertcat(mu, a_mean)
    C, R, Kh = D["C"], D["R"], D["Kh"]
    obj = 0.5 * ca.sum1(ca.sum2(C * Sz)) + 0.5 * ca.mtimes([zbar.T, C, zbar]) + ca.dot(D["cl"], zbar) + D["c0"]
    dm = a_mean - ca.mtimes(Kh, mu) - D["kh"]
    KhSsa = ca.mtimes(Kh, Sas.T)
    cov_d = Saa - KhSsa - KhSsa.T + ca.mtimes([Kh, P, Kh.T])  # Cov(a - Kh s)
    logdetS = sum(ca.log(d) for d in _ldl_pivots(ca, Sz_r, r + m)[r:])  # pivots of S, the Schur complement
    kl = 0.5 * (ca.sum1(ca.sum2(R * cov_d)) + ca.mtimes([dm.T, R, dm]) - m + D["logdetSh"] - logdetS)
    AB = ca.horzcat(D["A"], D["B"])
    mu_n = ca.mtimes(AB, zbar) + D["c"]
    P_n = ca.mtimes([AB, Sz, AB.T]) + D["W"]
    return obj, kl, mu_n, 0.5 * (P_n + P_n.T)


class _FatropOCP:
    """The stage layout of the multiple-shooting NLP (see the module docstring).

    Per step ``t``: a stage kind (:func:`stage_function`), ``nx[t]`` states (0 at ``t = 0``),
    ``nu[t]`` controls, ``ng[t]`` path rows (the KL row, if any), in fatrop's order.
    """

    def __init__(self, prob: KLProblem, kind: np.ndarray, scalar: bool, config: KLStepConfig):
        T, n, m = prob.T, prob.n, prob.m
        self.prob, self.kind, self.scalar, self.config = prob, kind, scalar, config
        self.T, self.n, self.m = T, n, m
        self.nvp = n * (n + 1) // 2
        ev, U = np.linalg.eigh(prob.P0)
        big = ev > 1e-8 * max(1.0, float(np.abs(ev).max()))
        self.U0 = U[:, big]  # (n, r) range of P0
        # the moment form needs Cov(s_t) > 0: always for t >= 1 (W > 0), at t = 0 only if P0 > 0
        self.stage = ["pin" if k == "pin" else "moment" if (t > 0 or big.all()) else "moment0"
                      for t, k in enumerate(kind)]
        nxs = n + self.nvp + (1 if scalar else 0)
        self.nx = [0] + [nxs] * (T - 1)
        self.nu = [n_controls(k, n, m, self.U0.shape[1]) for k in self.stage]
        free = kind == "free"
        if scalar:
            self.has_kl = np.zeros(T, bool)
            self.has_kl[-1] = free.any()
        else:
            self.has_kl = free.copy()
        self.ng = [int(h) for h in self.has_kl]

    def _start_covariances(self, ub) -> np.ndarray:
        """(T, m, m) covariances ``alpha_t Sh_t`` of the start policy ``(Kh, kh, alpha_t Sh_t)``, whose
        KL is ``m/2 (alpha - 1 - log alpha)`` at every step whatever the state moments; ``alpha_t``
        in (0, 1) makes it the step's budget (total: an equal share per free step).  At the reference
        itself (``alpha = 1``) every KL row has a zero gradient: the equality rows are degenerate and
        fatrop's first steps were cut back to ~1e-5 and it failed on the benchmark instances."""
        ref, m = self.prob.reference, self.m
        free = np.flatnonzero(self.kind == "free")
        share = np.full(free.size, ub[0] / max(free.size, 1)) if self.scalar else np.asarray(ub, float)
        alpha = np.ones(self.T)
        alpha[free] = [_alpha_for_kl(2.0 * b / m) for b in share]
        return alpha[:, None, None] * ref.cov

    def _guess(self, t: int, mg, S0: np.ndarray) -> tuple[list, list]:
        """Start values of step ``t``'s controls (the policy ``(Kh, kh, S0)`` in its own moments) and
        their lower bounds."""
        ref, m = self.prob.reference, self.m
        kind = self.stage[t]
        if kind == "pin":
            return [], []
        P, mu = mg.cov[t], mg.mean[t]
        Sas = ref.K[t] @ P
        Saa = Sas @ ref.K[t].T + S0[t]
        if kind == "moment0":
            Sas = Sas @ self.U0
        x0 = list(ref.K[t] @ mu + ref.k[t]) + list(np.ravel(Sas, order="F")) + [Saa[i, j] for i, j in vech_pairs(m)]
        return x0, [-np.inf] * len(x0)

    def build(self, ca, ub):
        """``(nlp dict, x0, lbx, lbg, ubg)`` of the MX graph, variables and rows in fatrop's order."""
        prob, T, n = self.prob, self.T, self.n
        ref = prob.reference
        funcs = {k: stage_function(ca, n, self.m, k, self.U0.shape[1]) for k in set(self.stage)}
        X = [None] + [ca.MX.sym(f"x{t}", self.nx[t]) for t in range(1, T)]
        U = [ca.MX.sym(f"u{t}", self.nu[t]) for t in range(T)]
        S0 = self._start_covariances(ub)
        mg = forward_arrays(prob.dynamics, ref.K, ref.k, S0, prob.mu0, prob.P0)
        vp = vech_pairs(n)
        w, x0, lbx, g, lbg, ubg = [], [], [], [], [], []
        obj = 0
        n_free = 0
        self.kl_rows = []
        for t in range(T):
            if t == 0:
                mu, pv, c = ca.DM(prob.mu0), ca.DM([prob.P0[i, j] for i, j in vp]), 0
            else:
                w.append(X[t])
                mu, pv = X[t][:n], X[t][n : n + self.nvp]
                c = X[t][n + self.nvp] if self.scalar else 0
                x0 += list(mg.mean[t]) + [mg.cov[t][i, j] for i, j in vp] + ([0.0] if self.scalar else [])
                lbx += [-np.inf] * self.nx[t]
            if self.nu[t]:
                w.append(U[t])
                gx, gl = self._guess(t, mg, S0)
                x0 += gx
                lbx += gl
            data = _stage_data(prob, t, self.stage[t] == "pin")
            if self.stage[t] == "moment0":
                data = np.concatenate([data, np.ravel(self.U0, order="F")])
            data = ca.DM(data)
            l_t, kl_t, mu_n, pv_n = funcs[self.stage[t]](mu, pv, U[t], data)
            obj = obj + l_t
            if t < T - 1:
                nxt = [mu_n, pv_n] + ([c + kl_t] if self.scalar else [])
                g.append(X[t + 1] - ca.vertcat(*nxt))
                lbg += [0.0] * self.nx[t + 1]
                ubg += [0.0] * self.nx[t + 1]
            if self.has_kl[t]:
                self.kl_rows.append(len(lbg))
                g.append(c + kl_t if self.scalar else kl_t)
                lbg.append(ub[0] if self.scalar else ub[n_free])  # equality: see the module docstring
                ubg.append(lbg[-1])
            n_free += int(self.kind[t] == "free")
        nlp = {"x": ca.vertcat(*w), "f": obj, "g": ca.vertcat(*g)}
        return nlp, np.array(x0), np.array(lbx), np.array(lbg), np.array(ubg)

    def policy(self, sol_x: np.ndarray):
        """``(K, k, Sigma)`` of a solution vector (pinned steps: the reference; moment stages:
        ``K = Sas P^-1``, ``k = a_mean - K mu``, ``Sigma = Saa - K Sas^T`` with the stage's state
        moments ``(mu, P)`` from the solution)."""
        T, n, m = self.T, self.n, self.m
        ref = self.prob.reference
        K, k, S = ref.K.copy(), ref.k.copy(), ref.cov.copy()
        pos = 0
        mu, P = self.prob.mu0, self.prob.P0
        for t in range(T):
            if self.nx[t]:
                mu = sol_x[pos : pos + n]
                P = _vech_to_sym(sol_x[pos + n : pos + n + self.nvp], n)
            pos += self.nx[t]
            u = sol_x[pos : pos + self.nu[t]]
            pos += self.nu[t]
            kind = self.stage[t]
            if kind in ("moment", "moment0"):
                r = n if kind == "moment" else self.U0.shape[1]
                Sas_r = u[m : m + m * r].reshape(r, m).T
                Saa = _vech_to_sym(u[m + m * r :], m)
                if kind == "moment":
                    K[t] = right_cho_solve(Sas_r, chol(P, f"Cov(s_{t}) of the fatrop solution"))
                else:  # K U0 = Sas_r (U0^T P U0)^-1; K = Kh on the null space of P0 (not identifiable)
                    KU = right_cho_solve(Sas_r, chol(symmetrize(self.U0.T @ P @ self.U0), "U0^T P0 U0"))
                    K[t] = ref.K[t] + (KU - ref.K[t] @ self.U0) @ self.U0.T
                k[t] = u[:m] - K[t] @ mu
                S[t] = Saa - KU @ Sas_r.T if kind == "moment0" else Saa - K[t] @ Sas_r.T
        return K, k, S


def _alpha_for_kl(b: float) -> float:
    """The root ``alpha`` in (0, 1] of ``alpha - 1 - log alpha = b`` (``b >= 0``), by Newton's method
    from below (the function is convex and decreasing there, so the iterates increase to the root)."""
    if b <= 0.0:
        return 1.0
    a = np.exp(-1.0 - b)  # a - 1 - log a = a + b > b: left of the root
    for _ in range(100):
        f = a - 1.0 - np.log(a) - b
        a_new = a - f / (1.0 - 1.0 / a)
        if abs(a_new - a) <= 1e-15 * a:
            return float(a_new)
        a = a_new
    return float(a)


def _vech_to_sym(v: np.ndarray, n: int) -> np.ndarray:
    P = np.zeros((n, n))
    for idx, (i, j) in enumerate(vech_pairs(n)):
        P[i, j] = P[j, i] = v[idx]
    return P


def kl_step_fatrop(prob: KLProblem, nu: np.ndarray, scalar: bool, nu_out, config: KLStepConfig) -> KLStepResult:
    """The KL step solved by fatrop (module docstring); the result carries ``lam_g`` (the KL rows'
    multipliers) and ``solver_stats`` like the IPOPT path (formulation ``"multiple_shooting"``)."""
    import casadi as ca

    T, n, m = prob.T, prob.n, prob.m
    nu_full, kind = casadi_kinds(nu, scalar, T)
    if np.any(kind == "det"):
        t = int(np.flatnonzero(kind == "det")[0])
        raise ValueError(f"method='fatrop' needs finite budgets: nu is inf at step {t} (a deterministic step makes "
                         "the joint covariance of the moment formulation singular); use method='casadi'")
    n_vars = casadi_n_vars(kind, n, m)
    free = np.flatnonzero(kind == "free")
    ub = [float(nu[0])] if scalar else [float(nu_full[t]) for t in free]
    ocp = _FatropOCP(prob, kind, scalar, config)
    if n_vars == 0:  # every step pinned to the reference
        Kout, kout, Sout = prob.reference.K.copy(), prob.reference.k.copy(), prob.reference.cov.copy()
        lam, status, n_iter, fval, timing = np.zeros(0), "nothing to solve (nu = 0)", 0, float("nan"), {}
    else:
        t0 = time.perf_counter()
        nlp, x0, lbx, lbg, ubg = ocp.build(ca, ub)
        opts = {"structure_detection": "manual", "N": T - 1, "nx": ocp.nx, "nu": ocp.nu, "ng": ocp.ng,
                "expand": config.fatrop_expand, "print_time": False,
                "fatrop": {"print_level": 0, "tol": config.fatrop_tol, "max_iter": config.fatrop_max_iter,
                           **config.fatrop_options}}
        solver = ca.nlpsol("kl_step_fatrop", "fatrop", nlp, opts)
        build_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        sol = solver(x0=x0, lbx=lbx, ubx=np.inf, lbg=lbg, ubg=ubg)
        solve_s = time.perf_counter() - t1
        stats = solver.stats()
        status = f"fatrop return_status={stats.get('return_status')}"
        if not stats.get("success", False):
            raise SolverError(f"fatrop failed: {status} after {stats.get('iter_count')} iterations",
                              status=str(stats.get("return_status")))
        sol_x = np.asarray(sol["x"]).ravel()
        lam_all = np.asarray(sol["lam_g"]).ravel()
        lam = lam_all[ocp.kl_rows]
        if np.any(lam < -1e-6 * max(1.0, float(np.abs(lam).max()))):
            i = int(np.argmin(lam))
            where = "the total budget" if scalar else f"the budget of step {int(free[i])}"
            raise SolverError(f"fatrop: {where} is slack at the solution (multiplier {lam[i]:.3e} < 0 in the "
                              "equality form); use method='casadi'", status="slack budget",
                              step=None if scalar else int(free[i]))
        Kout, kout, Sout = ocp.policy(sol_x)
        n_iter, fval = int(stats.get("iter_count", -1)), float(sol["f"])
        timing = {"build_s": build_s, "solve_s": solve_s}
    policy, eta, marg, kl, costs = nlp_solution(prob, kind, free, scalar, Kout, kout, Sout, lam)
    return KLStepResult(
        policy=policy, eta=eta, kl=kl, expected_cost=float(costs.sum()), n_backward=0, scalar_eta=scalar,
        nu=nu_out, dual_value=fval, method="fatrop", n_iter=n_iter, status=status, marginals=marg, lam_g=lam,
        solver_stats={"n_vars": n_vars, "formulation": "multiple_shooting" if n_vars else "none",
                      "n_ocp_vars": int(sum(ocp.nx) + sum(ocp.nu)), **timing},
    )
