"""Tests for soc_opt/sweep.py, soc_opt/sweep_runner.py and soc_opt/sweep_report.py.

Oracles: the grid is compared with ``itertools.product`` of its axes; each trial's files with an
ordinary ``run_experiment`` run in this process; interrupted sweeps with an uninterrupted one;
the aggregated means and standard deviations with numpy on the per-trial results.
"""

import csv
import io
import itertools
import json
import logging
import os
import signal
import threading
import time

import numpy as np
import pytest

from soc_opt.cli import main
from soc_opt.experiments.run import run_experiment
from soc_opt.experiments.rundir import decode_checkpoint
from soc_opt.linalg import single_thread_blas
from soc_opt.methods.state import IterationRecord, RunState
from soc_opt.sweeps.runner import ProgressBoard, run_sweep
from soc_opt.sweeps.spec import SweepError, TrialDiverged, load_sweep, sweep_from_dict
from soc_opt.sweeps.trial import check_finite
from soc_opt.tasks import BUILTIN_TASKS, load_task
from soc_opt.tasks.loading import problems_dir

# the Ray tests run in one pytest-xdist worker, one after the other (`make test` uses --dist loadgroup):
# two local Ray clusters at once on a 2-core machine only slow each other down
pytestmark = pytest.mark.xdist_group("ray")

SMALL = {
    "name": "small",
    "tasks": ["linear2d"],
    "methods": ["lqr-flm", "dpsoc-em"],
    "seeds": [0, 1],
    "common": {"i_switch": 1, "baseline": {"iterations": 3, "samples": 5}, "task": {"T": 15}},
}


def _quiet_board(n):
    return ProgressBoard(n, stream=io.StringIO(), live=False)


# --------------------------------------------------------------------------- grid expansion


def test_grid_is_the_product_of_tasks_settings_methods_and_seeds(tmp_path):
    own = tmp_path / "mytask.toml"
    src = (problems_dir() / BUILTIN_TASKS["linear2d"]).read_text()
    own.write_text(src.replace('name = "linear2d"', 'name = "mytask"'))
    data = {
        "tasks": ["linear2d", "mytask.toml"],
        "methods": ["lqr-flm", "dpsoc-em"],
        "seeds": 3,
        "common": {"i_switch": 1, "baseline": {"iterations": 3, "samples": 5}},
        "grid": {"task": {"rho2": [0.1, 0.01]}, "em": {"y_mode": ["model", "measured"]}},
    }
    spec = sweep_from_dict(data, base_dir=tmp_path, source="s.toml")
    settings = [f"rho2={r},y_mode={y}" for r, y in itertools.product(["0.1", "0.01"], ["model", "measured"])]
    expected = list(itertools.product(["linear2d", "mytask"], settings, ["lqr-flm", "dpsoc-em"], [0, 1, 2]))
    assert [(t.task_label, t.setting, t.method, t.seed) for t in spec.trials] == expected
    assert len({t.relpath for t in spec.trials}) == 48
    for t in spec.trials:
        rho2, y_mode = t.setting.split(",")
        assert t.task_overrides == {"rho2": float(rho2.split("=")[1])}
        assert t.config.em.y_mode == y_mode.split("=")[1]
        assert (t.config.baseline.iterations, t.config.baseline.samples, t.config.i_switch) == (3, 5, 1)
        # precedence: the task's default algorithm file (problems/experiments/linear2d.toml sets
        # init_var = 10) below [common]; a task without a default file gets the class defaults
        assert t.config.baseline.init_var == (10.0 if t.task_label == "linear2d" else 1.0)
        assert t.eval_samples == 5
    assert spec.trials[-1].task.endswith("mytask.toml") and os.path.isabs(spec.trials[-1].task)


def test_settings_entries_cross_the_grid_and_may_not_repeat_its_keys():
    data = dict(SMALL, settings=[{"name": "a", "em": {"n_em": 2}}, {"name": "b"}],
                grid={"task": {"rho2": [0.1, 0.01]}})
    spec = sweep_from_dict(data)
    assert [s.name for s in spec.settings] == ["a,rho2=0.1", "a,rho2=0.01", "b,rho2=0.1", "b,rho2=0.01"]
    n_em = {t.setting: t.config.em.n_em for t in spec.trials}
    assert n_em == {"a,rho2=0.1": 2, "a,rho2=0.01": 2, "b,rho2=0.1": 1, "b,rho2=0.01": 1}
    # [common] and the setting's task tables are merged (T from common, rho2 from the grid)
    assert {tuple(sorted(t.task_overrides.items())) for t in spec.trials} == {(("T", 15), ("rho2", 0.1)),
                                                                               (("T", 15), ("rho2", 0.01))}
    bad = dict(SMALL, settings=[{"name": "a", "task": {"rho2": 0.5}}], grid={"task": {"rho2": [0.1]}})
    with pytest.raises(ValueError, match="task.rho2"):
        sweep_from_dict(bad)


def test_settings_record_their_entry_and_grid_values():
    data = dict(SMALL, settings=[{"name": "a", "em": {"n_em": 2}}, {"name": "b"}],
                grid={"task": {"rho2": [0.1, 0.01]}})
    spec = sweep_from_dict(data)
    assert [(s.group, s.grid) for s in spec.settings] == [
        ("a", (("rho2", 0.1),)), ("a", (("rho2", 0.01),)), ("b", (("rho2", 0.1),)), ("b", (("rho2", 0.01),))]
    assert [(s.group, s.grid) for s in sweep_from_dict(SMALL).settings] == [("", ())]


def test_report_plots_quantities_against_a_single_numeric_grid_key(tmp_path):
    from soc_opt.sweeps.report import versus_key, write_report
    from soc_opt.sweeps.spec import RESULT

    data = dict(SMALL, settings=[{"name": "a"}, {"name": "b"}], grid={"task": {"rho2": [0.0, 0.01, 0.1]}})
    spec = sweep_from_dict(data)
    status = {}
    for i, t in enumerate(spec.trials):
        (tmp_path / t.relpath).mkdir(parents=True)
        res = {"final_cost": float(i), "state_spread": 1.0, "action_spread": 1.0, "best_cost": float(i),
               "metrics": {"final_distance": 0.1 * i}, "cost_per_iteration": [3.0, 2.0, float(i)]}
        (tmp_path / t.relpath / RESULT).write_text(json.dumps(res))
        status[t.id] = {"state": "done"}
    assert versus_key(spec) == "rho2"
    md = write_report(spec, tmp_path, status).read_text()
    assert (tmp_path / "versus_rho2_linear2d.png").stat().st_size > 0
    assert "versus_rho2_linear2d.png" in md
    two_keys = dict(SMALL, grid={"task": {"rho2": [0.0, 0.1]}, "em": {"y_mode": ["model", "measured"]}})
    assert versus_key(sweep_from_dict(two_keys)) is None
    assert versus_key(sweep_from_dict(dict(SMALL, grid={"em": {"y_mode": ["model", "measured"]}}))) is None


def test_baseline_trials_clamp_the_unused_switch_point_and_dpsoc_trials_reject_it():
    data = dict(SMALL, common={"baseline": {"iterations": 2}})  # default i_switch is 4
    spec = sweep_from_dict(dict(data, methods=["lqr-flm"]))
    assert {t.config.i_switch for t in spec.trials} == {1}
    with pytest.raises(ValueError, match="i_switch"):
        sweep_from_dict(data)


@pytest.mark.parametrize("text, named", [
    ('seed = [0]\n', "'seed'"),
    ('[grid]\nem.y_mod = ["model"]\n', "y_mod"),
    ('[common.baseline]\niteratons = 3\n', "iteratons"),
    ('[common.task]\nrhoo = 0.1\n', "rhoo"),
    ('[[settings]]\nname = "x"\nbaseline = { fit = { priorr = "none" } }\n', "priorr"),
    ('[grid]\ntask.rho2 = 0.1\n', "grid.task.rho2"),
    ('[common]\nem = { n_em = "two" }\n', "em.n_em"),
    ('[common]\niterations = 3\n', "'iterations'"),
])
def test_sweep_file_with_an_unknown_key_is_rejected_before_any_trial_starts(tmp_path, capsys, text, named):
    f = tmp_path / "bad.toml"
    f.write_text('tasks = ["linear2d"]\nmethods = ["lqr-flm"]\nseeds = [0]\n' + text)
    out = tmp_path / "out"
    assert main(["sweep", str(f), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert named in err and "bad.toml" in err
    assert not out.exists()


@pytest.mark.parametrize("tasks, methods, named", [
    ('["linear2d", "linear3d"]', '["lqr-flm"]', "linear3d"),
    ('["linear2d"]', '["lqr-flm", "ilqg"]', "ilqg"),
])
def test_sweep_file_with_an_unknown_task_or_method_is_rejected_naming_it(tmp_path, capsys, tasks, methods, named):
    f = tmp_path / "bad.toml"
    f.write_text(f"tasks = {tasks}\nmethods = {methods}\nseeds = 2\n")
    out = tmp_path / "out"
    assert main(["sweep", str(f), "--out", str(out)]) == 2
    assert named in capsys.readouterr().err
    assert not out.exists()


def test_the_example_sweep_file_is_valid():
    spec = load_sweep(os.path.join(os.path.dirname(__file__), "..", "problems", "sweeps", "linear2d_small.toml"))
    assert len(spec.trials) == len(spec.settings) * 2 * 2 and spec.name == "linear2d_small"


def test_the_paper_scale_peg_sweep_has_the_trials_of_the_paper_comparison():
    spec = load_sweep(os.path.join(os.path.dirname(__file__), "..", "problems", "sweeps", "peg_paper.toml"))
    assert [(t.method, t.seed) for t in spec.trials] == [(m, s) for m in ("lqr-flm", "dpsoc-em") for s in range(5)]
    for t in spec.trials:
        assert (t.config.baseline.iterations, t.config.baseline.samples, t.config.i_switch) == (14, 20, 4)


@pytest.mark.parametrize("task", ["peg", "door"])
def test_the_noise_sweep_files_cross_six_variants_with_four_noise_levels(task):
    """paper, noise-aware (§10), kinematic (§11), kinematic with the filter from the EM run the learner keeps (its
    fourth round), with EM from the sampler's map only (its third round) and on the smoothed means alone (its second
    round) x rho^2 in {0, 0.001, 0.01, 0.1} x 2 methods x 10 seeds."""
    spec = load_sweep(os.path.join(os.path.dirname(__file__), "..", "problems", "sweeps", f"noise_{task}.toml"))
    assert len(spec.settings) == 24 and len(spec.trials) == 24 * 2 * 10
    noise = {(s.group, s.grid[0][1]) for s in spec.settings}
    groups = ("paper", "noise-aware", "kinematic", "kinematic-r4", "kinematic-warm", "kinematic-means")
    assert noise == {(g, r) for g in groups for r in (0.0, 0.001, 0.01, 0.1)}
    expected = {"paper": "none", "noise-aware": "kalman", "kinematic": "kinematic", "kinematic-r4": "kinematic",
                "kinematic-warm": "kinematic", "kinematic-means": "kinematic"}
    for t in spec.trials:
        est = t.config.baseline.noise.estimator
        group = t.setting.split(",")[0]
        assert est == expected[group]
        if est == "kinematic":
            kin = t.config.baseline.noise.kinematic
            assert kin.fit_moments == ("means" if group == "kinematic-means" else "posterior")
            assert kin.warm_start and kin.restart_from_data == (group in ("kinematic", "kinematic-r4"))
            assert kin.filter_start == ("sampler" if group == "kinematic" else "kept")
        assert t.task_overrides["rho2"] in (0.0, 0.001, 0.01, 0.1) and t.config.baseline.iterations == 14


@pytest.mark.parametrize("name, settings, rho2", [
    ("acceptance_free", ("paper", "paper-as-written"), 0.0),
    ("acceptance_noise", ("paper", "paper-as-written", "kinematic", "kinematic-as-written", "kinematic-var4"), 0.1)])
def test_the_acceptance_sweeps_pair_each_setting_with_the_paper_as_written(name, settings, rho2):
    """Issue 30's sweeps: door and peg, seeds 100-109 (not used for tuning), paper scale; a setting named
    ``*-as-written`` turns step acceptance off, every other keeps it on (docs/results/acceptance.md)."""
    spec = load_sweep(os.path.join(os.path.dirname(__file__), "..", "problems", "sweeps", f"{name}.toml"))
    assert tuple(s.group for s in spec.settings) == settings
    assert len(spec.trials) == 2 * len(settings) * 2 * 10 and set(spec.seeds) == set(range(100, 110))
    for t in spec.trials:
        group = t.setting.split(",")[0]
        assert t.config.baseline.acceptance.enabled == (not group.endswith("as-written"))
        assert t.config.baseline.noise.estimator == ("kinematic" if group.startswith("kinematic") else "none")
        assert t.config.baseline.init_var == (4.0 if group == "kinematic-var4" else 1.0)
        assert t.task_overrides["rho2"] == rho2 and (t.config.baseline.iterations, t.config.baseline.samples) == (14, 20)


def test_non_finite_sampled_cost_is_a_diverging_trial():
    def state(cost):
        rec = IterationRecord(iteration=2, phase="baseline", cost=np.array(cost), cost_measured=np.array(cost),
                              kl=0.0, nu=0.0, mult=1.0, metrics={}, timings={})
        return RunState(iteration=3, policy=None, mult=1.0, prior=None, rng_state={}, history=(rec,))

    check_finite(state([1.0, 2.0]))
    with pytest.raises(TrialDiverged, match="iteration 3"):
        check_finite(state([1.0, np.inf]))
    with pytest.raises(TrialDiverged):
        check_finite(state([np.nan, 1.0]))


def _first_cost(trial_dir):
    with open(trial_dir / "metrics.csv") as f:
        return float(next(csv.DictReader(f))["cost_mean"])


def test_a_grid_over_task_init_var_gives_trials_with_that_initial_covariance(tmp_path):
    from soc_opt.sweeps.trial import run_trial

    data = {"tasks": ["linear2d"], "methods": ["lqr-flm"], "seeds": [0],
            "common": {"baseline": {"iterations": 1, "samples": 4}, "task": {"T": 10}},
            "grid": {"task": {"init_var": [0.01, 100.0]}}}
    spec = sweep_from_dict(data)
    # the sweep's task.init_var wins over linear2d's default run configuration ([baseline] init_var = 10)
    assert [t.config.baseline.init_var for t in spec.trials] == [0.01, 100.0]
    costs = []
    for t in spec.trials:
        res = run_trial(t, tmp_path / t.relpath)
        assert res["status"] == "done", res
        recorded = json.loads((tmp_path / t.relpath / "config.json").read_text())["config"]["baseline"]["init_var"]
        assert recorded == t.task_overrides["init_var"]
        costs.append(_first_cost(tmp_path / t.relpath))
    assert costs[0] != costs[1]
    # oracle: the trial equals a run of the task with that init_var in its task configuration
    task = load_task("linear2d", overrides={"T": 10, "init_var": 0.01})
    cfg = spec.trials[0].config.replace(baseline=spec.trials[0].config.baseline.replace(init_var=None))
    run_experiment(task, "lqr-flm", cfg, 0, tmp_path / "plain")
    assert _first_cost(tmp_path / "plain") == costs[0]


def test_sweep_rejects_setting_both_task_and_baseline_init_var(tmp_path):
    data = {"tasks": ["linear2d"], "methods": ["lqr-flm"], "seeds": [0],
            "common": {"baseline": {"init_var": 2.0}}, "grid": {"task": {"init_var": [0.01, 100.0]}}}
    with pytest.raises(SweepError, match="task.init_var and baseline.init_var"):
        sweep_from_dict(data)


def test_sweep_accepts_gym_tasks(tmp_path):
    from soc_opt.sweeps.trial import run_trial

    data = {"tasks": ["gym:Reacher-v5"], "methods": ["lqr-flm"], "seeds": [0],
            "common": {"baseline": {"iterations": 1, "samples": 3}, "task": {"T": 5, "gym": {"reset_seed": 3}}}}
    (trial,) = sweep_from_dict(data).trials
    assert trial.task == "gym:Reacher-v5" and trial.id == "gym-Reacher-v5/default/lqr-flm/seed_0"
    res = run_trial(trial, tmp_path / trial.relpath)
    assert res["status"] == "done", res
    assert np.isfinite(res["final_cost"]) and "return" in res["metrics"]
    task_json = json.loads((tmp_path / trial.relpath / "task.json").read_text())
    assert task_json["config"]["gym"]["reset_seed"] == 3
    bad = {**data, "common": {**data["common"], "task": {"gym": {"kwargs": {"reward_dist_weight": "x"}}}}}
    with pytest.raises(SweepError, match="gym.kwargs.reward_dist_weight = 'x'"):
        sweep_from_dict(bad)


# --------------------------------------------------------------------------- on a local Ray


@pytest.fixture(scope="module")
def local_ray():
    import ray

    ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def reference(local_ray, tmp_path_factory):
    """The small sweep, uninterrupted."""
    out = tmp_path_factory.mktemp("sweep") / "ref"
    spec = sweep_from_dict(SMALL)
    stream = io.StringIO()
    res = run_sweep(spec, out, board=ProgressBoard(len(spec.trials), stream=stream, live=False))
    return spec, out, res, stream.getvalue()


def _metrics(path):
    with open(path / "metrics.csv") as f:
        return [{k: v for k, v in row.items() if not k.startswith("time_")} for row in csv.DictReader(f)]


def _same_metrics(spec, out_a, out_b):
    for t in spec.trials:
        a, b = _metrics(out_a / t.relpath), _metrics(out_b / t.relpath)
        assert a == b, t.id
        ra = json.loads((out_a / t.relpath / "result.json").read_text())
        rb = json.loads((out_b / t.relpath / "result.json").read_text())
        assert (ra["final_cost"], ra["metrics"]) == (rb["final_cost"], rb["metrics"]), t.id


def test_small_sweep_trials_are_ordinary_runs_of_each_method(reference, tmp_path):
    spec, out, res, log = reference
    assert res["counts"] == {"pending": 0, "running": 0, "done": 4, "failed": 0}
    status = json.loads((out / "status.json").read_text())
    assert {v["state"] for v in status["trials"].values()} == {"done"}
    for t in spec.trials:
        assert f"[done] {t.id}" in log
        task = load_task(t.task, overrides=t.task_overrides)
        with single_thread_blas():
            run_experiment(task, t.method, t.config, t.seed, tmp_path / t.id)
        assert _metrics(out / t.relpath) == _metrics(tmp_path / t.id), t.id
        assert json.loads((out / t.relpath / "config.json").read_text()) == json.loads(
            (tmp_path / t.id / "config.json").read_text())
    assert "4/4 finished" in log


def test_sweep_report_holds_mean_and_std_over_seeds(reference):
    spec, out, res, _ = reference
    for name in ("report.md", "summary.csv", "trials.csv", "final_linear2d.png", "cost_linear2d.png"):
        assert (out / name).stat().st_size > 0, name
    with open(out / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["setting"], r["method"]) for r in rows] == [("default", "lqr-flm"), ("default", "dpsoc-em")]
    for r in rows:
        vals = [json.loads((out / t.relpath / "result.json").read_text())["final_cost"]
                for t in spec.trials if t.method == r["method"]]
        assert len(vals) == 2 == int(r["seeds_done"])
        assert float(r["final_cost_mean"]) == pytest.approx(np.mean(vals), rel=1e-12)
        assert float(r["final_cost_std"]) == pytest.approx(np.std(vals), rel=1e-12)
    md = (out / "report.md").read_text()
    assert "| default | dpsoc-em | 2 |" in md and "final_linear2d.png" in md


def test_sweep_trials_score_the_returned_policy_sampled_and_with_its_mean_action(reference):
    """docs/math.md §12.3: the final evaluation is of the method's returned policy (the last accepted
    one), on fresh rollouts, with its exploration covariance and with its mean action K s + k."""
    from soc_opt.experiments.compare import evaluate_policy
    from soc_opt.methods.registry import get_method
    from soc_opt.noise.aware import mean_action

    spec, out, _, _ = reference
    t = spec.trials[0]
    res = json.loads((out / t.relpath / "result.json").read_text())
    state = decode_checkpoint(out / t.relpath / "checkpoint.npz")
    task = load_task(t.task, overrides=t.task_overrides)
    policy = get_method(t.method).final_policy(t.config, state)
    assert policy is state.accepted.policy
    with single_thread_blas():
        ro = evaluate_policy(task, mean_action(policy), t.eval_samples, t.seed)
    assert res["final_cost_mean_action"] == pytest.approx(float(np.mean(task.true_cost(ro).sum(-1))), rel=1e-9)
    assert set(res["metrics_mean_action"]) == set(res["metrics"])
    assert {"final_vs_last_worse", "final_vs_last_ratio", "rejected_steps"} <= set(res)


def test_sweep_report_judges_the_claims_paired_over_seeds(reference):
    from soc_opt.experiments.report import paired_test

    spec, out, _, _ = reference
    md = (out / "report.md").read_text()
    assert "## Claims: DPSOC-EM against LQR-FLM, paired over seeds" in md
    with open(out / "claims.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3
    res = {(t.method, t.seed): json.loads((out / t.relpath / "result.json").read_text()) for t in spec.trials}
    cost = paired_test([res["lqr-flm", s]["final_cost"] for s in (0, 1)], [res["dpsoc-em", s]["final_cost"] for s in (0, 1)])
    row = next(r for r in rows if "cost" in r["claim"])
    assert float(row["diff_mean"]) == pytest.approx(cost["diff_mean"], rel=1e-12)
    assert row["verdict"] == cost["verdict"] and (row["held"] == "True") == (cost["verdict"] == "lower")
    with open(out / "trials.csv") as f:
        assert "final_cost_mean_action" in next(csv.DictReader(f))


def test_a_trial_to_run_records_its_whole_spec_and_a_finished_one_keeps_its_record(tmp_path):
    """trial.json of a trial that has not finished is rewritten with the spec it runs with (a record
    written by an older soc_opt may lack options added since); a finished trial's record is kept."""
    from soc_opt.sweeps.runner import prepare_out
    from soc_opt.sweeps.spec import read_json, write_json

    spec = sweep_from_dict({"name": "rec", "tasks": ["linear2d"], "methods": ["lqr-flm"], "seeds": 2})
    prepare_out(spec, tmp_path)
    done, pending = (tmp_path / t.relpath for t in spec.trials)
    for d in (done, pending):
        rec = read_json(d / "trial.json")
        del rec["config"]["baseline"]["noise"]["kinematic"]["gains"]  # as written before the option existed
        write_json(d / "trial.json", rec)
    write_json(done / "result.json", {"status": "done", "final_cost": 1.0, "state_spread": 0.1, "action_spread": 0.2})
    states = prepare_out(spec, tmp_path)
    assert sorted(states.values()) == ["done", "pending"]
    assert "gains" not in read_json(done / "trial.json")["config"]["baseline"]["noise"]["kinematic"]
    assert read_json(pending / "trial.json")["config"]["baseline"]["noise"]["kinematic"]["gains"] == "online"


def test_rerunning_a_finished_sweep_skips_every_trial(reference):
    spec, out, _, _ = reference
    before = {t.id: (out / t.relpath / "result.json").stat().st_mtime_ns for t in spec.trials}
    stream = io.StringIO()
    res = run_sweep(spec, out, board=ProgressBoard(len(spec.trials), stream=stream, live=False))
    assert res["counts"]["done"] == 4
    assert {t.id: (out / t.relpath / "result.json").stat().st_mtime_ns for t in spec.trials} == before
    assert "finished earlier" in stream.getvalue()


def test_failed_trial_is_recorded_and_the_sweep_goes_on(local_ray, tmp_path):
    # init_var = 1e300: the first rollouts explode and the KL step cannot reach its budget
    data = dict(SMALL, methods=["lqr-flm"], seeds=[0],
                settings=[{"name": "ok"}, {"name": "wild", "baseline": {"init_var": 1e300}}])
    spec = sweep_from_dict(data)
    res = run_sweep(spec, tmp_path, board=_quiet_board(2))
    states = {tid: v["state"] for tid, v in res["status"].items()}
    assert states == {"linear2d/ok/lqr-flm/seed_0": "done", "linear2d/wild/lqr-flm/seed_0": "failed"}
    err = res["status"]["linear2d/wild/lqr-flm/seed_0"]["error"]
    assert "BudgetUnreachable" in err and "not reachable" in err  # a SolverError, named by its class
    assert "Traceback" in (tmp_path / "trials/linear2d/wild/lqr-flm/seed_0/error.txt").read_text()
    assert "## Failed trials" in (tmp_path / "report.md").read_text()


def _killer(target, marker):
    def hook(trial_id, state, trial_dir):
        if trial_id == target and state.iteration == 2 and not os.path.exists(marker):
            with open(marker + ".tmp", "w") as f:
                f.write(str(os.getpid()))
            os.replace(marker + ".tmp", marker)
            time.sleep(120)  # the test kills this worker process here
    return hook


def _kill_when_marked(marker, killed):
    t0 = time.time()
    while not os.path.exists(marker):
        if time.time() - t0 > 120:
            return
        time.sleep(0.05)
    os.kill(int(open(marker).read()), signal.SIGKILL)
    killed.append(True)


def _sweep_with_a_kill(spec, out, target, max_retries):
    marker = str(out) + ".pid"
    killed = []
    watcher = threading.Thread(target=_kill_when_marked, args=(marker, killed), daemon=True)
    watcher.start()
    res = run_sweep(spec, out, max_retries=max_retries, on_iteration=_killer(target, marker),
                    board=_quiet_board(len(spec.trials)))
    watcher.join(timeout=5)
    assert killed == [True]
    return res


def test_worker_killed_mid_trial_is_retried_from_its_checkpoint(reference, tmp_path):
    spec, ref_out, _, _ = reference
    target = "linear2d/default/dpsoc-em/seed_1"
    res = _sweep_with_a_kill(spec, tmp_path / "k", target, max_retries=3)
    assert res["counts"]["done"] == 4
    result = json.loads((tmp_path / "k" / spec.trials[3].relpath / "result.json").read_text())
    assert spec.trials[3].id == target
    assert (result["attempt"], result["resumed_from"]) == (2, 2)
    _same_metrics(spec, ref_out, tmp_path / "k")


def test_worker_killed_past_its_retries_fails_and_a_rerun_resumes_it(reference, tmp_path):
    spec, ref_out, _, _ = reference
    target = "linear2d/default/lqr-flm/seed_0"
    res = _sweep_with_a_kill(spec, tmp_path / "k", target, max_retries=0)
    assert res["status"][target]["state"] == "failed" and res["counts"]["done"] == 3
    assert (tmp_path / "k" / spec.trials[0].relpath / "error.txt").exists()
    res = run_sweep(spec, tmp_path / "k", board=_quiet_board(len(spec.trials)))
    assert res["counts"]["done"] == 4
    result = json.loads((tmp_path / "k" / spec.trials[0].relpath / "result.json").read_text())
    assert result["resumed_from"] == 2
    _same_metrics(spec, ref_out, tmp_path / "k")


@pytest.mark.parametrize("path", sorted((problems_dir() / "sweeps").glob("*.toml")), ids=lambda p: p.stem)
def test_every_committed_sweep_file_loads_and_is_named_after_its_file(path):
    """Every sweep a document cites as a command (docs/results/*.md) is a valid sweep whose output directory
    ``runs/sweep-NAME`` is the one the documents name, with at least one trial."""
    spec = load_sweep(str(path))
    assert spec.name == path.stem and len(spec.trials) >= 1


def test_the_cap_sweep_varies_only_the_door_cap_on_the_tuning_seeds():
    """``cap_tuning.toml`` (docs/results/acceptance.md §4): the door without noise, step acceptance on, tuning seeds
    200-209, the door experiment's cap of 10 against 30 and none (the library default 1e4); acceptance on, floor and
    initial variance those of the default setting."""
    spec = load_sweep(str(problems_dir() / "sweeps" / "cap_tuning.toml"))
    assert set(spec.seeds) == set(range(200, 210)) and {t.task for t in spec.trials} == {"door"}
    caps = {t.setting.split(",")[0]: t.config.baseline.step_size.mult_max for t in spec.trials}
    assert caps == {"default": 10.0, "cap30": 30.0, "uncapped": 1e4}
    base = next(t.config for t in spec.trials if t.setting.startswith("default"))
    for t in spec.trials:
        assert t.config.baseline.acceptance.enabled and t.task_overrides["rho2"] == 0.0
        assert t.config.baseline.step_size.mult_min == base.baseline.step_size.mult_min
        assert t.config.baseline.init_var == base.baseline.init_var


# ------------------------------------------------------------------ issue 48 items 7 and 9: grids and names are bounded


def test_a_1_kb_sweep_file_asking_for_10_to_the_20_settings_is_refused_within_the_memory_bound(tmp_path):
    from test_reading import HOSTILE_RSS_MB, peak_run

    grid = "".join(f"baseline.fit.k{i} = [{', '.join(str(v) for v in range(10))}]\n" for i in range(20))
    path = tmp_path / "grid.toml"
    path.write_text('tasks = ["linear2d"]\nmethods = ["lqr-flm"]\nseeds = 1\n[grid]\n' + grid)
    assert path.stat().st_size < 1300
    rc, peak, err = peak_run(["sweep", path, "--dry-run"])
    assert peak < HOSTILE_RSS_MB, f"peak resident memory {peak:.0f} MB"
    assert rc == 2 and str(path) in err and "100000000000000000000 settings" in err, err


@pytest.mark.parametrize("text,named", [
    ('seeds = 100000', "seeds: expected a count in [1, 10000]"),
    ('seeds = 100\n[grid]\ntask.rho2 = [' + ", ".join(str((i + 1) / 1000) for i in range(200)) + "]", "= 20000 trials"),
    ('seeds = 1\neval_samples = 1000000000', "eval_samples: expected an integer in [1, 10000]"),
])
def test_a_sweep_asking_for_too_many_trials_or_samples_is_refused_naming_the_key(tmp_path, capsys, text, named):
    path = tmp_path / "big.toml"
    path.write_text(f'tasks = ["linear2d"]\nmethods = ["lqr-flm"]\n{text}\n')
    assert main(["sweep", str(path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and named in err, err


@pytest.mark.parametrize("name", ["../../escape", "/abs", ".hidden", "a/b", "x" * 101])
def test_a_sweep_name_that_would_leave_runs_is_refused_before_anything_is_written(tmp_path, capsys, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "named.toml"
    path.write_text(f'name = "{name}"\ntasks = ["linear2d"]\nmethods = ["lqr-flm"]\nseeds = 1\n')
    assert main(["sweep", str(path), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "name:" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["named.toml"]


def test_a_setting_name_of_dots_stays_one_folder_of_the_sweep():
    spec = sweep_from_dict({**SMALL, "settings": [{"name": ".."}, {"name": "."}]})
    assert {t.relpath.parts[2] for t in spec.trials} == {"_.", "_"}
    assert all(".." not in t.relpath.parts for t in spec.trials)
