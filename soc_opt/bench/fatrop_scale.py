"""fatrop at paper scale (docs/math.md §6): the KL step's multiple-shooting formulation with the
free stages written as matrix-valued MX expressions instead of scalar SX.

The library's fatrop path (:mod:`soc_opt.lqg.fatrop_nlp`) writes each free stage as one SX
function whose ``log|Sigma|`` comes from the ``LDL^T`` pivots of the ``(n+m) x (n+m)`` joint
covariance written out entry by entry; CasADi then differentiates that scalar graph twice.  At
``n=26, m=7`` (594 stage variables) the symbolic Hessian alone is what makes the build take
minutes.  Here the same stage is an MX function on whole matrices: ``vech`` maps as constant
0/1 matrices, ``Sigma = Saa - Sas P^-1 Sas^T`` by a linear solve and ``log|Sigma|`` by
``log(det(Sigma))`` (``m x m``), whose derivatives CasADi forms as matrix expressions.  Same
variables, same rows, same start point: only the expression graph differs.

:func:`mx_stages` is a context manager that swaps the free-stage builder of
:mod:`soc_opt.lqg.fatrop_nlp` for the MX one while a benchmark runs (``fatrop_expand`` must be
False: an MX function of matrix operations cannot be expanded to SX); :func:`measure` times one
KL step with either builder.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np

__all__ = ["mx_stages", "measure"]


def _vech_matrix(n: int) -> np.ndarray:
    """``E`` (n*n, n(n+1)/2) with ``vec(P) = E vech(P)`` (column-major ``vec``)."""
    from ..lqg.fatrop_nlp import vech_pairs

    pairs = vech_pairs(n)
    E = np.zeros((n * n, len(pairs)))
    for idx, (i, j) in enumerate(pairs):
        E[i + j * n, idx] = 1.0
        E[j + i * n, idx] = 1.0
    return E


def _vech_select(n: int) -> np.ndarray:
    """``S`` with ``vech(P) = S vec(P)``."""
    from ..lqg.fatrop_nlp import vech_pairs

    pairs = vech_pairs(n)
    S = np.zeros((len(pairs), n * n))
    for idx, (i, j) in enumerate(pairs):
        S[idx, i + j * n] = 1.0
    return S


def _stage_function_mx(ca, n: int, m: int, kind: str, r: int = 0, _orig=None):
    """The ``"moment"`` stage as an MX function (module docstring); other kinds unchanged."""
    from ..lqg import fatrop_nlp as F

    if kind != "moment":
        return _orig(ca, n, m, kind, r)
    nvp = n * (n + 1) // 2
    mu, pv = ca.MX.sym("mu", n), ca.MX.sym("p", nvp)
    u = ca.MX.sym("u", F.n_controls(kind, n, m, r))
    sizes = [("A", n, n), ("B", n, m), ("c", n, 1), ("W", n, n), ("C", n + m, n + m), ("cl", n + m, 1),
             ("c0", 1, 1), ("Kh", m, n), ("kh", m, 1), ("R", m, m), ("logdetSh", 1, 1)]
    dat = ca.MX.sym("data", sum(a * b for _, a, b in sizes))
    D, pos = {}, 0
    for name, a, b in sizes:
        D[name] = ca.reshape(dat[pos : pos + a * b], a, b)
        pos += a * b
    En, Em = ca.DM(_vech_matrix(n)), ca.DM(_vech_matrix(m))
    P = ca.reshape(ca.mtimes(En, pv), n, n)
    a_mean = u[:m]
    Sas = ca.reshape(u[m : m + m * n], m, n)
    Saa = ca.reshape(ca.mtimes(Em, u[m + m * n :]), m, m)
    Sz = ca.blockcat([[P, Sas.T], [Sas, Saa]])
    zbar = ca.vertcat(mu, a_mean)
    C, R, Kh = D["C"], D["R"], D["Kh"]
    obj = 0.5 * ca.sum1(ca.sum2(C * Sz)) + 0.5 * ca.mtimes([zbar.T, C, zbar]) + ca.dot(D["cl"], zbar) + D["c0"]
    dm = a_mean - ca.mtimes(Kh, mu) - D["kh"]
    KhSsa = ca.mtimes(Kh, Sas.T)
    cov_d = Saa - KhSsa - KhSsa.T + ca.mtimes([Kh, P, Kh.T])
    S = Saa - ca.mtimes(Sas, ca.solve(P, Sas.T))
    kl = 0.5 * (ca.sum1(ca.sum2(R * cov_d)) + ca.mtimes([dm.T, R, dm]) - m + D["logdetSh"] - ca.log(ca.det(S)))
    AB = ca.horzcat(D["A"], D["B"])
    mu_n = ca.mtimes(AB, zbar) + D["c"]
    P_n = ca.mtimes([AB, Sz, AB.T]) + D["W"]
    pv_n = ca.mtimes(ca.DM(_vech_select(n)), ca.vec(0.5 * (P_n + P_n.T)))
    return ca.Function(f"kl_stage_{kind}_mx", [mu, pv, u, dat], [obj, kl, mu_n, pv_n])


@contextlib.contextmanager
def mx_stages():
    """Use :func:`_stage_function_mx` for the free stages of :mod:`soc_opt.lqg.fatrop_nlp` inside the block."""
    from ..lqg import fatrop_nlp as F

    orig = F.stage_function
    F.stage_function = lambda ca, n, m, kind, r=0: _stage_function_mx(ca, n, m, kind, r, _orig=orig)
    try:
        yield
    finally:
        F.stage_function = orig


class _Built(Exception):
    """Raised instead of solving when only the build is measured."""


@contextlib.contextmanager
def _build_only(record: dict):
    """Make ``casadi.nlpsol`` record its construction time and return a solver that stops the run."""
    import casadi as ca

    orig = ca.nlpsol

    def timed(*a, **kw):
        t0 = time.perf_counter()
        solver = orig(*a, **kw)
        record["nlpsol_s"] = time.perf_counter() - t0

        def stop(**_):
            raise _Built()

        return stop if solver is not None else solver

    ca.nlpsol = timed
    try:
        yield
    finally:
        ca.nlpsol = orig


def measure(n: int, m: int, T: int, *, mx: bool, seed: int = 0, budget: str = "per_step",
            build_only: bool = False) -> dict:
    """One KL step at ``(n, m, T)`` (the instance of :mod:`soc_opt.bench.lqg`) by fatrop, SX (library)
    or MX (``mx``) stages: build and solve seconds, iterations, policy difference to the closed form.
    ``build_only``: stop after the solver is built and report ``build_s`` (graph + ``nlpsol``)."""
    from ..lqg import KLStepConfig, kl_step
    from .lqg import kl_budget_of, make_instance

    rng = np.random.default_rng([seed, n, m, T])
    prob = make_instance(n, m, T, rng)
    nu = kl_budget_of(budget, T, rng)
    cfg = KLStepConfig(fatrop_expand=not mx)
    t0 = time.perf_counter()
    cf = kl_step(*prob[:3], nu, *prob[3:], config=cfg)
    t_cf = time.perf_counter() - t0
    out = {"n": n, "m": m, "T": T, "stages": "MX" if mx else "SX (library)", "closed_form_s": t_cf}
    ctx = mx_stages() if mx else contextlib.nullcontext()
    rec: dict = {}
    with ctx, (_build_only(rec) if build_only else contextlib.nullcontext()):
        t0 = time.perf_counter()
        try:
            fr = kl_step(*prob[:3], nu, *prob[3:], method="fatrop", config=cfg)
        except _Built:
            out.update(build_s=time.perf_counter() - t0, nlpsol_s=rec.get("nlpsol_s"))
            return out
        except Exception as e:  # reported, not raised: this is a measurement
            out["error"] = f"{type(e).__name__}: {e}"[:300]
            return out
    diff = max(np.abs(cf.policy.K - fr.policy.K).max(), np.abs(cf.policy.k - fr.policy.k).max(),
               np.abs(cf.policy.cov - fr.policy.cov).max())
    out.update(status=fr.status, iterations=fr.n_iter, build_s=fr.solver_stats["build_s"],
               solve_s=fr.solver_stats["solve_s"], max_policy_diff=float(diff),
               max_rel_eta_diff=float(np.max(np.abs(fr.eta / cf.eta - 1))))
    return out
