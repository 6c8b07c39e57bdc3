"""Tests for the M-step solver benchmark (soc_opt.bench.solvers, soc_opt.bench.solvers_report;
docs/math.md §5): the independent references against scipy's constrained solvers and KKT
conditions, every solver within tolerance on tiny sizes, the performance-profile arithmetic and
the written files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize

from soc_opt.bench import solvers as S
from soc_opt.bench import solvers_report as R
from soc_opt.cli import main


def _qp(rng, d):
    M = rng.standard_normal((d, d))
    return M @ M.T / d + 0.1 * np.eye(d), rng.standard_normal(d)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), d=st.integers(1, 8), frac=st.floats(0.05, 2.0))
def test_trust_region_reference_satisfies_the_kkt_conditions(seed, d, frac):
    rng = np.random.default_rng(seed)
    Q, r = _qp(rng, d)
    f0 = rng.standard_normal(d)
    fstar = np.linalg.solve(Q, r)
    delta = frac * np.linalg.norm(fstar - f0)
    f = S.trust_region_reference(Q, r, f0, delta)
    g = r - Q @ f  # ascent direction of -1/2 f'Qf + r'f
    if frac >= 1.0:
        np.testing.assert_allclose(f, fstar, atol=1e-9)
    else:  # on the boundary, gradient along the outward normal with a multiplier >= 0
        assert np.linalg.norm(f - f0) == pytest.approx(delta, rel=1e-10)
        lam = g @ (f - f0) / delta**2
        assert lam >= 0
        np.testing.assert_allclose(g, lam * (f - f0), atol=1e-8 * max(1.0, np.abs(g).max()))


def test_trust_region_reference_matches_scipy_slsqp():
    rng = np.random.default_rng(3)
    Q, r = _qp(rng, 6)
    f0 = np.zeros(6)
    delta = 0.3 * np.linalg.norm(np.linalg.solve(Q, r))
    ref = S.trust_region_reference(Q, r, f0, delta)
    res = minimize(lambda x: 0.5 * x @ Q @ x - r @ x, f0, jac=lambda x: Q @ x - r, method="SLSQP",
                   constraints=[{"type": "ineq", "fun": lambda x: delta**2 - x @ x, "jac": lambda x: -2 * x}],
                   options={"ftol": 1e-15, "maxiter": 1000})
    np.testing.assert_allclose(ref, res.x, atol=1e-6)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), d=st.integers(2, 8), b=st.floats(0.01, 1.0))
def test_offset_reference_satisfies_the_kkt_conditions(seed, d, b):
    rng = np.random.default_rng(seed)
    Q, r = _qp(rng, d)
    idx = np.arange(d // 2, d)
    f = S.offset_reference(Q, r, idx, np.full(len(idx), b))
    g = r - Q @ f
    free = np.setdiff1d(np.arange(d), idx)
    tol = 1e-7 * max(1.0, np.abs(r).max())
    assert np.all(np.abs(f[idx]) <= b + 1e-12)
    assert np.abs(g[free]).max(initial=0.0) <= tol
    for i in idx:  # interior: zero gradient; at a bound: the gradient pushes outward
        if abs(f[i]) < b - 1e-9:
            assert abs(g[i]) <= tol
        else:
            assert g[i] * np.sign(f[i]) >= -tol


def test_every_solver_meets_the_reference_on_tiny_instances():
    rows = S.run(sizes=((2, 1),), T=1, instances=2)
    summ = R.summarize(rows)
    kinds = {s["constraints"] for s in summ}
    assert kinds == set(S.SETS)
    for s in summ:
        assert s["problems"] == 2, s
        assert s["solved"] == s["problems"], s
        assert s["max_gap"] <= R.SUCCESS_TOL and s["max_violation"] <= R.SUCCESS_TOL, s
    got = {(s["constraints"], s["method"]) for s in summ}
    want = {(k, m) for k in S.SETS for m in S.methods_for(k)}
    assert got == want


def test_qp_solvers_are_offered_only_where_the_problem_is_a_qp():
    assert "qp/OSQP" in S.methods_for("offset_bound") and "qp/HIGHS" in S.methods_for("cov_floor")
    assert not any(m in S.methods_for("trust_region") for m in ("qp/OSQP", "qp/HIGHS", "casadi/qrqp"))
    assert "closed_form" not in S.methods_for("trust_region") + S.methods_for("offset_bound")


def _row(method, inst, t, ok=True):
    return dict(n=2, m=1, constraints="x", method=method, instance=inst, step=0, status="optimal" if ok else "failed",
                solve_s=t, abs_gap=0.0, violation=0.0)


def test_performance_profile_ratios_are_time_over_best_and_inf_on_failure():
    rows = [_row("a", 0, 1.0), _row("b", 0, 3.0), _row("a", 1, 2.0, ok=False), _row("b", 1, 4.0)]
    methods, ratios = R.profiles(rows, "x")
    assert methods == ["a", "b"]
    np.testing.assert_allclose(ratios["a"], [1.0, math.inf])
    np.testing.assert_allclose(ratios["b"], [1.0, 3.0])


def test_write_produces_table_csv_json_and_plots(tmp_path):
    rows = S.run(sizes=((2, 1),), T=1, instances=1, sets=("offset_bound",),
                 methods=("library/CLARABEL", "qp/OSQP", "casadi/qrqp"))
    warm = S.warm_vs_cold(2, 1, iterations=3, solvers=("OSQP",))
    paths = R.write(rows, warm, tmp_path, {"test": True})
    names = {p.name for p in paths}
    assert {"rows.csv", "summary.csv", "summary.json", "table.md", "profile_offset_bound.png",
            "accuracy_time_offset_bound.png"} <= names
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert {s["method"] for s in doc["summary"]} == {"library/CLARABEL", "qp/OSQP", "casadi/qrqp"}
    assert "Warm vs cold" in (tmp_path / "table.md").read_text()


def test_solvers_command_rejects_bad_sizes(capsys):
    assert main(["solvers", "--sizes", "4by2", "--no-kl"]) == 2
    assert "4by2" in capsys.readouterr().err


def test_fatrop_mx_stage_formulation_matches_the_closed_form():
    casadi = pytest.importorskip("casadi")
    if not casadi.has_nlpsol("fatrop"):
        pytest.skip("CasADi built without fatrop")
    from soc_opt.bench.fatrop_scale import measure

    r = measure(3, 2, 6, mx=True)
    assert "error" not in r, r
    assert r["max_policy_diff"] <= 1e-7 and r["max_rel_eta_diff"] <= 1e-6, r
    b = measure(3, 2, 6, mx=True, build_only=True)
    assert b["build_s"] > 0 and b["nlpsol_s"] is not None and "max_policy_diff" not in b


# --------------------------------------------------------------------------- soc_opt.bench.qp_bench (issue 32)

from soc_opt.bench import qp_bench as QB  # noqa: E402
from soc_opt.bench import qp_bench_report as QBR  # noqa: E402
from soc_opt.mstep import maximize  # noqa: E402
from soc_opt.mstep.errors import InfeasibleConstraintsError  # noqa: E402


def test_infeasible_family_raises_an_error_naming_the_offset_bound():
    (prob,) = QB.make_problems(sizes=((3, 2),), instances=1, families=("infeasible",))
    with pytest.raises(InfeasibleConstraintsError, match="infeasible constraint set: offset_bound"):
        maximize(prob.model, prob.mom, constraints=prob.constraints(), method="cvxpy")
    rows = QB.run(problems=[prob], methods=("closed_form", "library/CLARABEL", "cvxpy/CLARABEL"), repeats=1,
                  levels=("default",))
    assert all(r["success"] and not r["found"] for r in rows), rows
    assert all(r["names_infeasibility"] for r in rows if r["method"] != "cvxpy/CLARABEL")


def test_solution_error_is_linear_in_the_parameter_error():
    (prob,) = QB.make_problems(sizes=((4, 2),), instances=1, families=("well_conditioned",))
    ref = QB.reference(prob)
    v = np.random.default_rng(0).standard_normal(ref.f.shape)
    e1 = QB.solution_error(ref.f + 1e-6 * v, ref.sigma, ref)
    e2 = QB.solution_error(ref.f + 1e-3 * v, ref.sigma, ref)
    assert e2 / e1 == pytest.approx(1e3, rel=1e-6)  # a gap-based error would give 1e6
    assert e1 == pytest.approx(1e-6 * np.linalg.norm(v) / math.hypot(np.linalg.norm(ref.f), np.linalg.norm(ref.sigma)),
                               rel=1e-9)


def test_kkt_reference_satisfies_the_kkt_conditions_to_1e_12_on_active_instances():
    probs = QB.make_problems(sizes=((2, 1), (4, 2), (8, 3)), instances=3, families=("active",))
    for prob in probs:
        P, q, G, h, _ = QB.qp_data(prob)
        ref = QB.reference(prob)
        scale = max(np.abs(q).max(), np.abs(P).max() * np.abs(ref.f).max())
        pr, du, gap = QB.residuals(P, q, G, h, ref.f, ref.z)
        assert pr <= 1e-12 * max(1.0, prob.b) and du <= 1e-12 * scale and gap <= 1e-12 * scale, (prob.name, pr, du, gap)
        assert np.all(ref.z >= 0) and np.any(ref.z > 0)  # dual feasible; some bound active
        assert np.abs(ref.z * (G @ ref.f - h)).max() <= 1e-12 * scale  # complementarity


def test_kkt_box_reference_matches_an_exhaustive_active_set_search():
    rng = np.random.default_rng(5)
    for _ in range(10):
        M = rng.standard_normal((5, 5))
        P, q = M @ M.T + 0.1 * np.eye(5), rng.standard_normal(5)
        idx, b = np.array([2, 3, 4]), 0.2
        f, _, _ = QB.kkt_box_reference(P, q, idx, b)
        lo, hi = np.full(5, -np.inf), np.full(5, np.inf)
        lo[idx], hi[idx] = -b, b
        best = minimize(lambda x: 0.5 * x @ P @ x + q @ x, np.zeros(5), jac=lambda x: P @ x + q, method="L-BFGS-B",
                        bounds=list(zip(lo, hi)), options={"ftol": 1e-15, "gtol": 1e-12}).x
        np.testing.assert_allclose(f, best, atol=1e-6)


def test_families_have_the_stated_conditioning():
    probs = QB.make_problems(sizes=((4, 2), (8, 3)), instances=2, families=("ill_conditioned", "degenerate"))
    for p in probs:
        P = QB.qp_data(p)[0]
        if p.family == "ill_conditioned":
            assert 1e8 * 0.9 <= p.cond <= 1e12 * 1.1, (p.name, p.cond)
        else:  # two identical columns: exactly singular
            d = p.m * (p.n + 1)
            cols = {tuple(P[:, j]) for j in range(d)}
            assert len(cols) < d


def test_qp_bench_meets_the_references_on_tiny_instances():
    methods = ("closed_form", "library/CLARABEL", "cvxpy/CLARABEL") + tuple(QB.qp_methods()[:2])
    rows = QB.run(sizes=((2, 1), (3, 2)), instances=1, methods=methods, repeats=1, levels=("high", "default"),
                  families=("well_conditioned", "active", "trust_region", "infeasible"))
    summ = QB.summarize(rows)
    assert {s["family"] for s in summ} == {"well_conditioned", "active", "trust_region", "infeasible"}
    for s in summ:
        if s["method"] in ("closed_form", "cvxpy/CLARABEL") and s["family"] != "trust_region":
            assert s["success"] == s["problems"], s
        if s["family"] != "infeasible" and s["level"] == "high" and s["success"]:
            assert s["sol_err_max"] <= 1e-4, s


def test_exported_qpbenchmark_test_set_loads(tmp_path):
    probs = QB.make_problems(sizes=((2, 1), (3, 2)), instances=1)
    paths = QBR.export_qpbenchmark(probs, tmp_path)
    loaded = QBR.load_exported(tmp_path)
    names = {p.name for p in probs if p.family in QBR.EXPORTED_FAMILIES}
    assert {n for n, _ in loaded} == names and paths[-1].name == "mstep_qpbench.py"
    for name, d in loaded:
        p = next(x for x in probs if x.name == name)
        P, q, G, h, _ = QB.qp_data(p)
        np.testing.assert_array_equal(d["P"], P)
        np.testing.assert_array_equal(d["q"], q)
    qpb = pytest.importorskip("qpbenchmark", reason="qpbenchmark not installed (optional)")
    from qpbenchmark.benchmark import load_test_set

    ts = load_test_set(str(paths[-1]))
    got = list(ts)
    assert {p.name for p in got} == names and all(isinstance(p, qpb.Problem) for p in got)


def test_solvers_command_sizes_control_the_kl_step(capsys):
    pytest.importorskip("casadi")
    assert main(["solvers", "--sizes", "2x1x3", "--instances", "1", "--repeats", "1", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {(r["n"], r["m"], r["T"]) for r in doc["kl_step"]} == {(2, 1, 3)}
    assert {s["family"] for s in doc["mstep"]} == set(QB.FAMILIES)
    assert all(r["max_rel_eta_diff"] <= 1e-6 for r in doc["kl_step"])


def test_sqpmethod_kl_step_multipliers_equal_the_closed_form_eta():
    casadi = pytest.importorskip("casadi")
    if not casadi.has_conic("osqp"):
        pytest.skip("CasADi built without osqp")
    from soc_opt.bench import lqg as L
    from soc_opt.lqg import kl_step

    rng = np.random.default_rng([0, 3, 2, 6])
    prob = L.make_instance(3, 2, 6, rng)
    for kind in ("total", "per_step"):
        nu = L.kl_budget_of(kind, 6, rng)
        cf = kl_step(*prob[:3], nu, *prob[3:])
        r = L.sqpmethod_step(prob, nu)
        assert r.solver_stats["success"], r.status
        np.testing.assert_allclose(r.policy.K, cf.policy.K, atol=1e-8)
        np.testing.assert_allclose(r.eta, cf.eta, rtol=1e-6)
