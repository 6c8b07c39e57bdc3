"""The scripts in examples/ run as documented (they are part of the user documentation)."""

import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.mark.parametrize("name", ["em_iteration_by_hand.py", "custom_mstep_constraint.py"])
def test_example_runs(name, capsys):
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    out = capsys.readouterr().out
    assert out.strip()
    if name == "custom_mstep_constraint.py":
        assert "status optimal" in out


@pytest.mark.parametrize("path", sorted(EXAMPLES.rglob("*.py")), ids=lambda p: str(p.relative_to(EXAMPLES)))
def test_examples_import_only_public_names(path):
    """Examples are user code: they use the public API, no ``_private`` names of soc_opt modules."""
    import ast

    tree = ast.parse(path.read_text())
    private = [f"{node.module}.{a.name}" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
               and (node.module or "").startswith("soc_opt") for a in node.names if a.name.startswith("_")]
    private += [ast.unparse(node) for node in ast.walk(tree) if isinstance(node, ast.Attribute)
                and node.attr.startswith("_") and not node.attr.startswith("__")]
    assert private == []


def test_noise_sweep_table_gives_mean_interval_and_per_seed_values(tmp_path):
    """examples/studies/noise_sweep_table.py: one row per (variant, rho^2, method), t-interval of the seeds' mean."""
    import csv

    import numpy as np
    from scipy import stats

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_sweep_table.py"))
    vals = [0.9, 0.5, 0.7]
    path = tmp_path / "trials.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, ["task", "setting", "method", "seed", "state", "final_cost", "metric_success_rate"])
        w.writeheader()
        for s, v in enumerate(vals):
            w.writerow({"task": "peg", "setting": "kinematic,rho2=0.1", "method": "lqr-flm", "seed": s,
                        "state": "done", "final_cost": 10 + s, "metric_success_rate": v})
        w.writerow({"task": "peg", "setting": "kinematic,rho2=0.1", "method": "lqr-flm", "seed": 3,
                    "state": "failed", "final_cost": "", "metric_success_rate": ""})
    lines = mod["table"](mod["rows"](str(path))).strip().splitlines()
    assert len(lines) == 3
    half = stats.t.ppf(0.975, 2) * np.std(vals, ddof=1) / np.sqrt(3)
    assert lines[2].startswith("| kinematic | 0.1 | lqr-flm | success_rate | 0.700 ± 0.200 |")
    assert f"[{0.7 - half:.3f}, {0.7 + half:.3f}]" in lines[2] and "| 3 (0–2) | 0.90, 0.50, 0.70 | 11.0 ± 1.0 |" in lines[2]


def test_noise_sweep_claims_count_the_seeds_where_dpsoc_em_is_lower(tmp_path):
    import csv

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_sweep_table.py"))
    path = tmp_path / "trials.csv"
    cols = ["task", "setting", "method", "seed", "state", "final_cost", "state_spread", "action_spread", "metric_success_rate"]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, cols)
        w.writeheader()
        for s, (lc, dc) in enumerate([(10.0, 8.0), (10.0, 12.0), (10.0, 9.0)]):
            for m, c in (("lqr-flm", lc), ("dpsoc-em", dc)):
                w.writerow({"task": "peg", "setting": "kinematic,rho2=0.1", "method": m, "seed": s, "state": "done",
                            "final_cost": c, "state_spread": 1.0, "action_spread": 2.0 if m == "lqr-flm" else 1.0,
                            "metric_success_rate": 1.0})
    lines = mod["claims"](mod["rows"](str(path)), "kinematic", 0.1).strip().splitlines()
    assert "| 2/3 | yes |" in lines[2] and "| 0/3 | no |" in lines[3] and "| 3/3 | yes |" in lines[4]
    # a second task with the same seeds: one table per task, seeds compared within the task
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, cols)
        for s in range(3):
            for m, c in (("lqr-flm", 5.0), ("dpsoc-em", 6.0)):
                w.writerow({"task": "door", "setting": "kinematic,rho2=0.1", "method": m, "seed": s, "state": "done",
                            "final_cost": c, "state_spread": 1.0, "action_spread": 1.0, "metric_success_rate": 0.5})
    text = mod["claims"](mod["rows"](str(path)), "kinematic", 0.1)
    door, peg = text.split("### peg")
    assert door.startswith("### door") and "| 0/3 | no |" in door.splitlines()[4]
    assert "| 2/3 | yes |" in peg.splitlines()[4]


def test_filter_noise_example_rebuilds_the_filter_around_the_scaled_acceleration_noise():
    """examples/studies/noise_kinematic_filter_noise.py: factor 1 gives the learned filter back; factor 2 doubles
    the velocity block of the transition noise (``dt^2 S``) and changes the gains."""
    import numpy as np

    from soc_opt.noise.kinematic import loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
    from soc_opt.noise.kinematic.model import KinematicModel
    from soc_opt.tasks import load_task

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_kinematic_filter_noise.py"))
    task = load_task("peg", overrides={"rho2": 0.1, "T": 20})
    km, pol = KinematicModel(task), task.initial_policy(0.5)
    _, filt, _ = loop.learn(task, task.rollouts(pol, 5, np.random.default_rng(0)), pol, KinematicConfig())
    policy = KinematicFilteredPolicy(pol, filt)
    same = mod["scaled"](policy, km, 1.0, KinematicConfig().q_noise)
    np.testing.assert_array_equal(same.filter.Q, filt.Q)
    np.testing.assert_array_equal(same.filter.G, filt.G)
    double = mod["scaled"](policy, km, 2.0, KinematicConfig().q_noise)
    v = slice(km.nq, km.nz)
    np.testing.assert_allclose(double.filter.Q[:, v, v], 2.0 * filt.Q[:, v, v], rtol=1e-12)
    assert not np.allclose(double.filter.G, filt.G)


def test_final_modes_oracle_map_is_the_m_step_on_the_true_states_and_estimates_them_better(tmp_path):
    """examples/studies/noise_kinematic_final_modes.py --oracle-map: the policy keeps its gains; its filter's map is
    the M-step on the last batch's true states; on that batch its estimates of the joint angles are
    closer to the truth than those of the filter learned from the measurements."""
    import numpy as np

    from soc_opt.noise.kinematic import em, loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
    from soc_opt.noise.kinematic.model import KinematicModel
    from soc_opt.noise.kinematic.smoother import smooth
    from soc_opt.tasks import load_task

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_kinematic_final_modes.py"))
    task = load_task("peg", overrides={"rho2": 0.1, "T": 30})
    km, pol = KinematicModel(task), task.initial_policy(0.5)
    batch = task.rollouts(pol, 8, np.random.default_rng(0))
    _, filt, _ = loop.learn(task, batch, pol, KinematicConfig())
    policy = KinematicFilteredPolicy(pol, filt)
    (tmp_path / "samples").mkdir()
    np.savez(tmp_path / "samples" / "iter_000.npz", x=batch.x, a=batch.a)
    oracle = mod["oracle_map_policy"](task, policy, tmp_path)
    assert oracle.policy is policy.policy
    exact = smooth(km, em.z_model(km, filt.accel(), KinematicConfig()), batch.x, batch.a, np.zeros((km.n, km.n)))
    cfg = KinematicConfig()
    ref = em.mstep(exact, batch.a, km.dt, km.nq, cfg.segments, cfg.prior_strength, cfg.s_floor)
    np.testing.assert_array_equal(oracle.filter.accel_D, ref.D)
    q = km.zidx[:km.nq]
    err = [np.sqrt(np.mean((f.states(batch.s, batch.a)[..., q] - batch.x[..., q]) ** 2)) for f in (filt, oracle.filter)]
    assert err[1] < err[0], err


def test_first_fit_study_parses_variants_and_averages_the_relative_error_over_steps():
    """examples/studies/noise_kinematic_first_fit.py: ``KEY=VALUE+...`` typed from the defaults; the error is
    ``mean_k ||X_k - Y_k||_F / ||Y_k||_F`` over the selected rows."""
    import numpy as np

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_kinematic_first_fit.py"))
    assert mod["parse_variant"]("em_iters=30+segments=2+start_map=rigid_body+q_noise=0.01") == {
        "em_iters": 30, "segments": 2, "start_map": "rigid_body", "q_noise": 0.01}
    assert mod["parse_variant"]("") == {}
    Y = np.stack([np.eye(2), 2.0 * np.eye(2)])
    X = Y.copy()
    X[:, 0, 0] += 1.0
    assert mod["relative_error"](Y, Y) == 0.0
    np.testing.assert_allclose(mod["relative_error"](X, Y), np.mean([1 / np.sqrt(2), 1 / np.sqrt(8)]), rtol=1e-14)
    np.testing.assert_allclose(mod["relative_error"](X, Y, [1]), 0.0)


def test_oracle_loop_split_variants_take_exactly_their_part_from_the_true_states():
    """examples/studies/noise_kinematic_oracles_loop.py: ``oracle object rows`` is the smoothed fit with the door's
    rows (hinge, handle) from the true-state fit and no noise coupling between the two blocks; ``oracle mean
    dynamics`` is the true-state fit's ``A, B, c`` with the smoothed fit's ``W``."""
    import numpy as np

    from soc_opt.experiments.run import load_run_config
    from soc_opt.noise.aware import NoiseConfig
    from soc_opt.noise.strategy import resolve
    from soc_opt.tasks import load_task

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_kinematic_oracles_loop.py"))
    task = load_task("door", overrides={"rho2": 0.1, "T": 12})
    fc = load_run_config("door", paper=True, method="lqr-flm").baseline.fit
    strategy = resolve(task, NoiseConfig(estimator="kinematic"))
    pol = task.initial_policy()
    ro = task.rollouts(pol, 6, np.random.default_rng(0))
    est = strategy.estimate(None, ro, fc, pol, np.random.default_rng(1))
    args = (strategy, est.data(ro), fc, est, pol)
    smoothed, true = mod["_fit"](*args), mod["_oracle_dynamics"](*args)
    assert not np.allclose(smoothed.A, true.A)
    rows = np.array([("hinge" in lb or "handle" in lb) for lb in task.state_labels])
    assert 0 < rows.sum() < task.n
    obj = mod["_oracle_object_rows"](*args)
    for f in ("A", "B", "c"):
        np.testing.assert_array_equal(getattr(obj, f)[:, rows], getattr(true, f)[:, rows])
        np.testing.assert_array_equal(getattr(obj, f)[:, ~rows], getattr(smoothed, f)[:, ~rows])
    np.testing.assert_array_equal(obj.cov[:, rows][:, :, rows], true.cov[:, rows][:, :, rows])
    np.testing.assert_array_equal(obj.cov[:, ~rows][:, :, ~rows], smoothed.cov[:, ~rows][:, :, ~rows])
    assert not obj.cov[:, rows][:, :, ~rows].any()
    assert np.all(np.linalg.eigvalsh(obj.cov) > -1e-12)
    mean = mod["_oracle_mean_dynamics"](*args)
    for f in ("A", "B", "c"):
        np.testing.assert_array_equal(getattr(mean, f), getattr(true, f))
    np.testing.assert_array_equal(mean.cov, smoothed.cov)


def test_oracle_loop_variant_names_say_how_it_learns_and_where_it_is_scored():
    """examples/studies/noise_kinematic_oracles_loop.py: `` @ true state`` learns as the variant without the
    suffix and scores on the true state; ``oracle state`` always scores there; a misspelt name is an error."""
    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_kinematic_oracles_loop.py"))
    parse = mod["parse_variant"]
    assert parse("kinematic") == ("kinematic", False)
    assert parse("oracle fit") == ("oracle fit", False)
    assert parse("oracle fit @ true state") == ("oracle fit", True)
    assert parse("kinematic @ true state") == ("kinematic", True)
    assert parse("oracle state") == ("oracle state", True)
    with pytest.raises(ValueError, match="oracle fitt"):
        parse("oracle fitt @ true state")


def test_internal_model_estimate_is_the_linear_model_state_and_ignores_the_measurements(monkeypatch):
    """examples/studies/noise_unkept_variants.py ``--variant internal``: on a system that is its local model
    (``x_{k+1} = A_k x_k + B_k a_k + c_k`` from ``mu_0``), the estimate is the true state for any actions,
    whatever is measured, and the plan's mean when the actions are the plan's."""
    import types

    import numpy as np

    monkeypatch.syspath_prepend(str(EXAMPLES / "studies"))  # it imports the peg geometry of a study beside it
    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_unkept_variants.py"))
    rng = np.random.default_rng(0)
    T, n, m, B_rows = 6, 4, 2, 3
    A = 0.3 * rng.standard_normal((T, n, n)) + np.eye(n)
    B = rng.standard_normal((T, n, m))
    c = rng.standard_normal((T, n))
    abar = rng.standard_normal((T, m))
    mu = np.empty((T + 1, n))
    mu[0] = rng.standard_normal(n)
    for k in range(T):
        mu[k + 1] = A[k] @ mu[k] + B[k] @ abar[k] + c[k]
    pol = types.SimpleNamespace(mu=mu, A=A, B=B, abar=abar)
    est = mod["InternalModelPolicy"].estimate
    a = abar + rng.standard_normal((B_rows, T, m))
    x = np.broadcast_to(mu[0], (B_rows, n)).copy()
    xhat = est(pol, 0, 100.0 * rng.standard_normal((B_rows, n)))
    np.testing.assert_array_equal(xhat, x)
    for k in range(1, T + 1):
        x = x @ A[k - 1].T + a[:, k - 1] @ B[k - 1].T + c[k - 1]
        xhat = est(pol, k, 100.0 * rng.standard_normal((B_rows, n)), xhat, a[:, k - 1])
        np.testing.assert_allclose(xhat, x, rtol=1e-10, atol=1e-10)
    xhat = est(pol, 0, rng.standard_normal(n))
    for k in range(1, T + 1):
        xhat = est(pol, k, rng.standard_normal(n), xhat, abar[k - 1])
        np.testing.assert_allclose(xhat, mu[k], rtol=1e-12, atol=1e-12)
    with pytest.raises(SystemExit, match="unknown variant"):
        mod["patch"]("w-scale 0.1")


def test_restarts_emulation_returns_the_restart_with_the_cheaper_last_batch(tmp_path, capsys):
    """examples/studies/restarts_emulation.py: seeds s and s + offset are one run's two restarts; the run
    returns the one whose last sampled batch cost less (not the one that evaluates better)."""
    import json

    runs = {600: (-1.0, 5.0), 601: (-0.5, 2.0), 602: (-0.9, 9.0), 603: (-0.7, 1.0)}  # seed: (min hinge, last batch)
    for seed, (hinge, last) in runs.items():
        d = tmp_path / "trials" / "door" / "recover-half,rho2=0" / "lqr-flm" / f"seed_{seed}"
        d.mkdir(parents=True)
        (d / "result.json").write_text(json.dumps({"metrics": {"min_hinge": hinge},
                                                   "metrics_mean_action": {"min_hinge": hinge - 0.01},
                                                   "final_vs_last_last_sampled_cost": last}))
    mod = runpy.run_path(str(EXAMPLES / "studies" / "restarts_emulation.py"))
    mod["main"]([str(tmp_path), "--offset", "2"])
    out = capsys.readouterr().out
    assert "one half-sample run, 4 seeds: mean -0.775, 1 / 4 at the goal" in out
    # run 600+602 returns 600 (last batch 5 < 9): -1.00; run 601+603 returns 603 (1 < 2): -0.70
    assert "2 runs: sampled -0.850 (1 / 2 at the goal)" in out
    assert "picked by evaluation (oracle): 1 / 2" in out
    assert "-1.00 -0.70" in out


def test_peg_landing_is_the_first_step_at_table_height_or_the_lowest_one():
    """examples/studies/noise_peg_landing.py: the landing step is the first step at or below the height, the
    lowest step of a rollout that never gets there; errors and offsets are horizontal only."""
    import numpy as np

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_peg_landing.py"))
    target = mod["TARGET"]
    z = np.array([[-0.30, -0.35, -0.39, -0.45, -0.50], [-0.30, -0.33, -0.37, -0.36, -0.35]])
    x = np.zeros((2, 5, 3))
    x[..., 0] = target[0] + 0.03 * np.arange(5)  # 3 cm further from the hole's centre each step
    x[..., 1] = target[1]
    x[..., 2] = z
    xhat = x + np.array([0.0, 0.04, 1.0])  # 4 cm off horizontally, 1 m off in height (ignored)
    k, err, off = mod["landing"](x, xhat, -0.38)
    np.testing.assert_array_equal(k, [2, 2])  # rollout 0 first at -0.39; rollout 1 never, lowest at step 2
    np.testing.assert_allclose(err, [0.04, 0.04])
    np.testing.assert_allclose(off, [0.06, 0.06])


def test_peg_landing_per_seed_separates_the_plan_from_the_scatter_and_the_bias_from_the_noise():
    """examples/studies/noise_peg_landing.py: rollouts landing symmetrically around a point 5 cm from the hole
    have a plan offset of 5 cm and a scatter of their distance to that point; an estimate error that is the
    same vector in every rollout is all bias, one that alternates in sign all scatter."""
    import numpy as np

    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_peg_landing.py"))
    off = np.array([[0.05, 0.01], [0.05, -0.01], [0.04, 0.0], [0.06, 0.0]])
    same = np.tile([0.0, 0.02], (4, 1))
    r = mod["per_seed"](same, off)
    np.testing.assert_allclose([r["plan_offset"], r["scatter"]], [0.05, 0.01])
    np.testing.assert_allclose([r["estimate_bias"], r["estimate_scatter"]], [0.02, 0.0], atol=1e-15)
    np.testing.assert_allclose(r["plan_offset_estimated"], np.hypot(0.05, 0.02))
    alternating = same * np.array([[1], [-1], [1], [-1]])
    r = mod["per_seed"](alternating, off)
    np.testing.assert_allclose([r["estimate_bias"], r["estimate_scatter"]], [0.0, 0.02], atol=1e-15)


def test_peg_table_filter_moves_only_estimates_inside_the_table_beside_the_opening(monkeypatch):
    """examples/studies/noise_peg_table_filter.py: with a linear ``h`` (the peg bottom is ``z`` itself) an estimate
    below the table top 5 cm beside the hole is lifted to the table top (to within the pseudo-measurement's
    weight), and one below the table top inside the opening, or above the table, is left as it is."""
    import numpy as np

    monkeypatch.syspath_prepend(str(EXAMPLES / "studies"))
    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_peg_table_filter.py"))
    target, table = mod["TARGET"], mod["TABLE_Z"]

    def measure(z, jacobian=True):
        return (z.copy(), np.broadcast_to(np.eye(3), z.shape[:-1] + (3, 3))) if jacobian else z.copy()

    z = np.array([target + [0.05, 0.0, 0.05],     # below the table top (target + 0.05 < table), beside the hole
                  target + [0.0, 0.002, 0.05],    # as low, inside the opening
                  target + [0.05, 0.0, 0.2]])     # above the table
    # no prior information; the update's information H^T H / r2 = I / 1e-2: variance 1e-2 in every coordinate
    out = mod["project"](z, measure, np.zeros((3, 3)), 1e-2, [0, 1, 2], outside=0.01, r=1e-8)
    assert abs(out[0, 2] - table) < 1e-5 and np.array_equal(out[0, :2], z[0, :2])
    assert np.array_equal(out[1:], z[1:])


def test_table_variant_lifts_only_states_inside_the_table_beside_the_opening(monkeypatch):
    """examples/studies/noise_unkept_variants.py ``--variant table``: with a kinematics whose peg bottom is the
    joint vector itself, a state below the table top beside the hole is moved onto the table top (its velocity
    untouched), one as low inside the opening and one above the table are left as they are."""
    import types

    import numpy as np

    monkeypatch.syspath_prepend(str(EXAMPLES / "studies"))
    mod = runpy.run_path(str(EXAMPLES / "studies" / "noise_unkept_variants.py"))
    target, table = runpy.run_path(str(EXAMPLES / "studies" / "noise_peg_landing.py"))["TARGET"], mod["TABLE_Z"]

    def measure(z, jacobian=True):
        z = np.atleast_2d(z)
        return (z.copy(), np.broadcast_to(np.eye(6), z.shape[:-1] + (6, 6))) if jacobian else z.copy()

    km = types.SimpleNamespace(nq=3, zidx=np.arange(6), measure=measure)
    x = np.array([[*(target + [0.05, 0.0, 0.05]), 1.0, 2.0, 3.0],
                  [*(target + [0.0, 0.002, 0.05]), 1.0, 2.0, 3.0],
                  [*(target + [0.05, 0.0, 0.2]), 1.0, 2.0, 3.0]])
    out = mod["lift_onto_table"](km, x, [0, 1, 2], 0.01)
    np.testing.assert_allclose(out[0], [*(target[:2] + [0.05, 0.0]), table, 1.0, 2.0, 3.0])
    assert np.array_equal(out[1:], x[1:])