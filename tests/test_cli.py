"""Tests for soc_opt/cli.py: configuration errors are caught before any simulation."""

import numpy as np
import pytest

from soc_opt.cli import main
from soc_opt.config import ConfigError
from soc_opt.experiments.run import load_run_config


def test_unknown_config_key_is_rejected_naming_it(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[baseline]\niteratons = 3\n")
    assert main(["run", "linear2d", "--config", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "iteratons" in err and "baseline" in err
    assert not (tmp_path / "o").exists()


def test_wrong_type_is_rejected_naming_the_key(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text('[em]\nn_em = "two"\n')
    assert main(["compare", "linear2d", "--config", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "em.n_em" in capsys.readouterr().err


def test_missing_task_file_is_named(tmp_path, capsys):
    missing = tmp_path / "nope.toml"
    assert main(["run", str(missing), "--out", str(tmp_path / "o")]) == 2
    assert "nope.toml" in capsys.readouterr().err


def test_task_with_missing_model_file_is_named(tmp_path, capsys):
    p = tmp_path / "task.toml"
    p.write_text('name = "x"\nT = 5\nmodel = "missing_arm.xml"\n')
    assert main(["run", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "missing_arm.xml" in capsys.readouterr().err


def test_invalid_switch_point_is_rejected():
    with pytest.raises(ConfigError, match="i_switch"):
        load_run_config("linear2d", overrides={"iterations": 3, "i_switch": 5})


def test_paper_flag_sets_the_paper_scale():
    cfg = load_run_config("peg", paper=True)
    assert (cfg.baseline.iterations, cfg.baseline.samples, cfg.i_switch) == (14, 20, 4)
    # the rest of the task's default file is kept
    assert cfg.baseline.init_var == load_run_config("peg").baseline.init_var


def test_flags_override_the_paper_scale_and_lqr_flm_ignores_the_switch():
    cfg = load_run_config("linear2d", paper=True, overrides={"iterations": 3, "samples": None},
                          method="lqr-flm")
    # i_switch (4) lies outside a 3-iteration run, which only DPSOC-EM would use it for
    assert (cfg.baseline.iterations, cfg.baseline.samples, cfg.i_switch) == (3, 20, 4)
    with pytest.raises(ConfigError, match="i_switch"):
        load_run_config("linear2d", paper=True, overrides={"iterations": 3}, method="dpsoc-em")


def test_config_doc_lists_every_field(capsys):
    assert main(["config-doc"]) == 0
    out = capsys.readouterr().out
    for key in ("`[em.mstep]`", "`clarabel_tol`", "`[baseline.kl]`", "`seed_offset`", "`mu_restart`"):
        assert key in out


# ----------------------------------------------------------------- issue 13: errors, iLQG, numbering

SMALL = ["--iterations", "2", "--samples", "4"]


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("soc-opt: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("key,value", [("baseline", "kl_budget = nan"), ("baseline", "init_var = inf"),
                                       ("em", "cov_floor_scale = -inf"), ("baseline.step_size", "min_gap = nan")])
def test_nan_or_inf_in_the_config_is_refused_before_anything_is_written(tmp_path, capsys, key, value):
    p = tmp_path / "bad.toml"
    p.write_text(f"i_switch = 0\n[{key}]\n{value}\n")
    out = tmp_path / "o"
    assert main(["run", "linear2d", "--config", str(p), "--out", str(out)] + SMALL) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"{key}.{value.split()[0]}" in line and "finite" in line
    assert not out.exists()
    p.write_text("i_switch = 0\n")  # the corrected rerun is not blocked by anything
    assert main(["run", "linear2d", "--config", str(p), "--out", str(out)] + SMALL) == 0


def test_a_run_directory_of_another_seed_or_method_is_one_error_line_saying_what_differs(tmp_path, capsys):
    out = str(tmp_path / "o")
    assert main(["run", "linear2d", "--method", "lqr-flm", "--seed", "0", "--out", out] + SMALL) == 0
    capsys.readouterr()
    assert main(["run", "linear2d", "--method", "lqr-flm", "--seed", "1", "--out", out] + SMALL) == 2
    assert "seed: 0 -> 1" in _one_error_line(capsys.readouterr().err)
    cfg = tmp_path / "c.toml"
    cfg.write_text("i_switch = 1\n")
    assert main(["run", "linear2d", "--method", "dpsoc-em", "--config", str(cfg), "--out", out] + SMALL) == 2
    assert "method: 'lqr-flm' -> 'dpsoc-em'" in _one_error_line(capsys.readouterr().err)


def test_lqr_flm_accepts_a_config_file_with_one_iteration(tmp_path, capsys):
    p = tmp_path / "one.toml"
    p.write_text("[baseline]\niterations = 1\nsamples = 4\n")  # i_switch keeps its default, 4
    assert main(["run", "linear2d", "--method", "lqr-flm", "--config", str(p), "--out", str(tmp_path / "o")]) == 0
    assert main(["run", "linear2d", "--method", "dpsoc-em", "--config", str(p), "--out", str(tmp_path / "e")]) == 2
    assert "i_switch" in _one_error_line(capsys.readouterr().err)


def test_run_ends_with_the_returned_policy_scored_sampled_and_with_its_mean_action(tmp_path, capsys):
    """docs/math.md §12.3: ``soc-opt run`` evaluates what the method returns (the last accepted policy)
    on fresh rollouts, sampled and with its mean action; iLQG says it was scored without noise."""
    from soc_opt.experiments.rundir import decode_checkpoint
    from soc_opt.models import LinearGaussianPolicy

    p = tmp_path / "c.toml"
    p.write_text("[baseline]\niterations = 3\nsamples = 4\n[ilqg]\niterations = 2\n")
    out = tmp_path / "o"
    assert main(["run", "linear2d", "--method", "lqr-flm", "--config", str(p), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    line = next(ln for ln in text.splitlines() if ln.startswith("final policy = "))
    state = decode_checkpoint(out / "checkpoint.npz")
    assert f"the last accepted policy (iteration {state.accepted.iteration})" in line
    assert "sampled cost" in line and "mean action cost" in line
    saved = LinearGaussianPolicy.load(out / "final_policy.npz")
    np.testing.assert_array_equal(saved.K, state.accepted.policy.K)
    with np.load(out / "final_eval_mean_action.npz") as f:
        assert f["a"].shape[0] == 4
    assert main(["run", "linear2d", "--method", "ilqg", "--config", str(p), "--out", str(tmp_path / "i")]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("final policy = "))
    assert "scored without sensor noise" in line


def test_ilqg_writes_a_resumable_run_directory_and_reads_the_shared_config(tmp_path, capsys):
    import csv

    shared = tmp_path / "shared.toml"
    shared.write_text("i_switch = 1\n[baseline]\niterations = 3\nsamples = 4\n[em]\nn_em = 1\n"
                      "[ilqg]\niterations = 5\nmu_init = 1e-6\n")
    out = tmp_path / "o"
    args = ["run", "linear2d", "--method", "ilqg", "--config", str(shared), "--out", str(out)]
    assert main(args + ["--iterations", "1"]) == 0
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert [r["iteration"] for r in rows] == ["0"]  # --iterations overrides [ilqg] iterations = 5
    assert "metric_min_distance" in rows[0] and float(rows[0]["cost_mean"]) > 0
    for name in ("config.json", "task.json", "checkpoint.npz", "best_policy.npz", "policies/iter_001.npz"):
        assert (out / name).exists(), name
    capsys.readouterr()
    assert main(args + ["--iterations", "1"]) == 0
    assert "already finished (1 iterations)" in capsys.readouterr().out
    assert main(args + ["--iterations", "2"]) == 2  # a different run: refused, not overwritten
    assert "ilqg.iterations: 1 -> 2" in _one_error_line(capsys.readouterr().err)
    assert main(args + ["--samples", "3"]) == 2
    assert "--samples does not apply to --method ilqg" in _one_error_line(capsys.readouterr().err)


THREE_LINK = """
<mujoco>
  <option gravity="0 0 0"/>
  <worldbody>
    <body name="l1"><joint name="j1" type="hinge" axis="0 0 1"/><geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.03"/>
      <body name="l2" pos="0.5 0 0"><joint name="j2" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"/>
        <body name="l3" pos="0.4 0 0"><joint name="wrist" type="hinge" axis="0 0 1"/>
          <geom type="capsule" fromto="0 0 0 0.1 0 0" size="0.02"/></body>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="j1"/><motor joint="j2"/></actuator>
</mujoco>
"""


def test_ilqg_on_a_state_missing_joints_is_one_error_line_before_anything_is_written(tmp_path, capsys):
    (tmp_path / "arm.xml").write_text(THREE_LINK)
    (tmp_path / "task.toml").write_text('name = "arm"\nT = 5\nmodel = "arm.xml"\n[state]\njoints = ["j1", "j2"]\n'
                                        '[[cost]]\ntype = "torque"\n')
    out = tmp_path / "o"
    assert main(["run", str(tmp_path / "task.toml"), "--method", "ilqg", "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "'wrist'" in line and "state.extra_joints" in line
    assert not out.exists()


def test_console_counts_iterations_like_metrics_csv_and_labels_times(tmp_path, capsys):
    import csv
    import re

    out = tmp_path / "o"
    assert main(["run", "linear2d", "--method", "lqr-flm", "--out", str(out)] + SMALL) == 0
    console = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("[lqr-flm")]
    printed = [int(re.search(r"iter\s+(\d+) ", ln).group(1)) for ln in console]
    assert printed == [int(r["iteration"]) for r in csv.DictReader(open(out / "metrics.csv"))] == [0, 1]
    for ln in console:  # every duration carries its label
        assert re.findall(r"\d+(?:\.\d+)?s\b", ln) and all(
            re.search(rf"(time|total) {re.escape(t)}", ln) for t in re.findall(r"\d+(?:\.\d+)?s\b", ln))


def test_unexpected_errors_are_one_line_and_debug_shows_the_traceback_with_the_same_exit_status(
        tmp_path, capsys, monkeypatch):
    import soc_opt.experiments.run as experiment

    def boom(*a, **k):
        raise RuntimeError("deliberate\nfailure")

    monkeypatch.setattr(experiment, "run_experiment", boom)
    args = ["run", "linear2d", "--method", "lqr-flm", "--out", str(tmp_path / "o")] + SMALL
    assert main(args) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "RuntimeError: deliberate failure" in line and "--debug" in line
    assert main(["--debug"] + args) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and 'raise RuntimeError("deliberate' in err
    assert err.rstrip().splitlines()[-1].startswith("soc-opt: error: RuntimeError: deliberate failure")


def test_a_second_run_on_a_directory_in_use_is_refused_naming_the_first(tmp_path, capsys):
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "o"
    args = ["run", "linear2d", "--method", "lqr-flm", "--iterations", "30", "--samples", "4", "--out", str(out)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    first = subprocess.Popen([sys.executable, "-m", "soc_opt.cli"] + args + ["--progress", "lines"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        for line in first.stdout:  # wait until it is running
            if line.startswith("[lqr-flm seed 0] iter"):
                break
        else:
            raise AssertionError(first.stderr.read())
        assert main(args) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert f"in use by process {first.pid}" in line
    finally:
        first.send_signal(signal.SIGKILL)
        first.communicate()


# --------------------------------------------------------------------------- issue 18: every knob does what it says


def _linear_task(tmp_path, name: str, init_var: float | None):
    """A copy of linear2d under another name (so no default run configuration applies)."""
    from soc_opt.tasks.loading import BUILTIN_TASKS, problems_dir

    text = (problems_dir() / BUILTIN_TASKS["linear2d"]).read_text().replace('name = "linear2d"', f'name = "{name}"')
    if init_var is not None:
        text = text.replace("init_var = 1.0", f"init_var = {init_var!r}")
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return p


def _metrics_rows(out):
    import csv

    with open(out / "metrics.csv") as f:
        return [{k: v for k, v in r.items() if not k.startswith("time_")} for r in csv.DictReader(f)]


def _recorded_init_var(out) -> float:
    import json

    return json.loads((out / "config.json").read_text())["config"]["baseline"]["init_var"]


def test_task_file_init_var_sets_the_initial_policy_and_is_recorded(tmp_path, capsys):
    args = ["run", "--method", "lqr-flm", "--iterations", "1", "--samples", "4", "--progress", "lines"]
    small = _linear_task(tmp_path, "small", 0.01)
    big = _linear_task(tmp_path, "big", 100.0)
    assert main(args[:1] + [str(small)] + args[1:] + ["--out", str(tmp_path / "small")]) == 0
    assert main(args[:1] + [str(big)] + args[1:] + ["--out", str(tmp_path / "big")]) == 0
    assert (_recorded_init_var(tmp_path / "small"), _recorded_init_var(tmp_path / "big")) == (0.01, 100.0)
    cost = {k: float(_metrics_rows(tmp_path / k)[0]["cost_mean"]) for k in ("small", "big")}
    assert cost["small"] != cost["big"]
    # oracle: the task file's value acts exactly as the same value in [baseline] of --config
    cfg = tmp_path / "cfg.toml"
    cfg.write_text("[baseline]\ninit_var = 0.01\n")
    plain = _linear_task(tmp_path, "plain", None)
    assert main(args[:1] + [str(plain)] + args[1:] + ["--config", str(cfg), "--out", str(tmp_path / "cfg")]) == 0
    assert _metrics_rows(tmp_path / "cfg") == _metrics_rows(tmp_path / "small")


def test_baseline_init_var_of_the_run_configuration_overrides_the_task_file(tmp_path, capsys):
    big = _linear_task(tmp_path, "big", 100.0)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text("[baseline]\ninit_var = 0.01\n")
    assert main(["run", str(big), "--method", "lqr-flm", "--iterations", "1", "--samples", "4",
                 "--config", str(cfg), "--out", str(tmp_path / "o")]) == 0
    assert _recorded_init_var(tmp_path / "o") == 0.01


def test_run_takes_i_switch_and_a_bad_switch_point_gets_a_hint_naming_the_flag_and_file(tmp_path, capsys):
    assert main(["run", "linear2d", "--iterations", "2", "--samples", "4", "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "i_switch must be in [0, iterations=2), got 4" in line
    assert "--i-switch" in line and "experiments/linear2d.toml" in line
    assert not (tmp_path / "o").exists()
    assert main(["run", "linear2d", "--iterations", "2", "--samples", "4", "--i-switch", "0",
                 "--out", str(tmp_path / "o")]) == 0
    import json

    assert json.loads((tmp_path / "o" / "config.json").read_text())["config"]["i_switch"] == 0


def test_help_shows_the_defaults_including_the_method():
    from soc_opt.cli import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices
    text = " ".join(sub["run"].format_help().split())
    assert "(default: dpsoc-em)" in text and "--i-switch" in text and "(default: auto)" in text
    assert "(default: 0)" in text  # --seed
    assert "(default: 3)" in " ".join(sub["sweep"].format_help().split())  # --max-retries
    assert "(default: None)" not in text and "(default: False)" not in text


@pytest.mark.parametrize("text, named", [("init_var = -1.0", "baseline.init_var: must be > 0 or None, got -1.0"),
                                         ("kl_budget = 0.0", "baseline.kl_budget: must be > 0, got 0.0")])
def test_non_positive_baseline_values_are_named_with_file_key_and_value(tmp_path, capsys, text, named):
    p = tmp_path / "bad.toml"
    p.write_text(f"[baseline]\n{text}\n")
    assert main(["run", "linear2d", "--config", str(p), "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(p) in line and named in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("key, value", [("mass", "-1.0"), ("tau", "0.0")])
def test_non_positive_linear_mass_or_tau_is_named_with_file_key_and_value(tmp_path, capsys, key, value):
    p = _linear_task(tmp_path, "lin", None)
    p.write_text(p.read_text().replace("[linear]\n", f"[linear]\n{key} = {value}\n").replace(
        "mass = 1.0\n", "" if key == "mass" else "mass = 1.0\n").replace(
        "tau = 0.2 ", "" if key == "tau" else "tau = 0.2 ", 1))
    assert main(["run", str(p), "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(p) in line and f"linear.{key}: must be positive, got {value}" in line
    assert not (tmp_path / "o").exists()


def test_as_written_turns_step_acceptance_off_and_does_not_apply_to_ilqg(tmp_path, capsys):
    import json

    out = tmp_path / "o"
    args = ["run", "linear2d", "--method", "lqr-flm", "--iterations", "2", "--samples", "4", "--out", str(out)]
    assert main(args + ["--as-written"]) == 0
    cfg = json.loads((out / "config.json").read_text())["config"]
    assert cfg["baseline"]["acceptance"]["enabled"] is False
    rows = json.loads((out / "metrics.json").read_text())
    assert all("accepted" not in r for r in rows)
    capsys.readouterr()
    assert main(["run", "linear2d", "--method", "ilqg", "--as-written", "--out", str(tmp_path / "i")]) == 2
    assert "--as-written does not apply to --method ilqg" in capsys.readouterr().err


@pytest.mark.parametrize("errno_", [13, 30])  # EACCES (a folder of another user), EROFS (a read-only file system)
def test_an_unfinished_run_in_a_folder_soc_opt_cannot_write_is_one_line_naming_the_lock_file(tmp_path, capsys,
                                                                                            monkeypatch, errno_):
    """Issue 48 item 10: the refusal names the directory and its lock file in full, not ``'lock'``.  The
    refusal of the write is injected at the system call (the suite may run as root, whom permissions
    do not stop)."""
    import os
    import shutil

    out = tmp_path / "o"
    args = ["run", "linear2d", "--method", "lqr-flm", "--iterations", "2", "--samples", "4", "--out", str(out)]
    assert main(args) == 0
    shutil.copyfile(out / "checkpoint.prev.npz", out / "checkpoint.npz")  # one iteration left
    real_open = os.open

    def read_only(path, flags, *a, **kw):
        if path == "lock" and flags & os.O_CREAT:
            raise OSError(errno_, os.strerror(errno_), path)
        return real_open(path, flags, *a, **kw)

    monkeypatch.setattr(os, "open", read_only)
    capsys.readouterr()
    assert main(args) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(out / "lock") in line and "not writable" in line and os.strerror(errno_) in line, line


def test_output_read_by_a_pipe_that_closes_early_ends_quietly_like_a_pipe_stage(tmp_path):
    """`soc-opt sweep FILE --dry-run | head -2`: the reader goes away; no "BrokenPipeError" line, exit 141."""
    import subprocess
    import sys

    sweep = tmp_path / "s.toml"
    sweep.write_text('tasks = ["linear2d"]\nmethods = ["lqr-flm", "dpsoc-em"]\nseeds = 3000\n')
    p = subprocess.Popen([sys.executable, "-m", "soc_opt.cli", "sweep", str(sweep), "--dry-run"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.readline()
    p.stdout.close()  # the reader is gone before most of the 6000 lines (more than a pipe holds) are written
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141 and "BrokenPipeError" not in err and "error" not in err, err
