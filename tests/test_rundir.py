"""Run directory files (issue 18 item 7): permissions follow the umask, reopening a finished run
writes nothing (also on a read-only file system), and the initial policy is saved."""

from __future__ import annotations

import builtins
import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest

from soc_opt.cli import main
from soc_opt.experiments.run import load_run_config
from soc_opt.models import LinearGaussianPolicy
from soc_opt.tasks import load_task

ARGS = ["run", "linear2d", "--method", "lqr-flm", "--iterations", "2", "--samples", "4", "--progress", "lines"]


def _files(d: Path) -> dict:
    """Every file under ``d``: (size, mtime_ns, mode)."""
    return {str(p.relative_to(d)): (p.stat().st_size, p.stat().st_mtime_ns, stat.S_IMODE(p.stat().st_mode))
            for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    d = tmp_path_factory.mktemp("fin") / "run"
    old = os.umask(0o022)
    try:
        assert main([*ARGS, "--out", str(d)]) == 0
    finally:
        os.umask(old)
    return d


def test_run_files_are_readable_as_the_umask_allows(finished, tmp_path):
    modes = {name: mode for name, (_, _, mode) in _files(finished).items() if name != "lock"}
    assert modes and set(modes.values()) == {0o644}, modes
    old = os.umask(0o077)
    try:
        assert main([*ARGS, "--out", str(tmp_path / "private")]) == 0
    finally:
        os.umask(old)
    assert {m for n, (_, _, m) in _files(tmp_path / "private").items() if n != "lock"} == {0o600}


def test_the_initial_policy_is_saved_as_iteration_zero(finished):
    task = load_task("linear2d")
    cfg = load_run_config("linear2d", method="lqr-flm")
    initial = task.initial_policy(cfg.baseline.init_var)
    saved = LinearGaussianPolicy.load(finished / "policies" / "iter_000.npz")
    for name in ("K", "k", "cov"):
        np.testing.assert_array_equal(getattr(saved, name), getattr(initial, name))
    assert sorted(p.name for p in (finished / "policies").iterdir()) == ["iter_000.npz", "iter_001.npz",
                                                                         "iter_002.npz"]


def test_reopening_a_finished_run_writes_nothing(finished, capsys):
    before = _files(finished)
    assert main([*ARGS, "--out", str(finished)]) == 0
    assert "already finished (2 iterations)" in capsys.readouterr().out
    assert _files(finished) == before  # no figure re-rendered, no event file, no lock written


def _read_only(monkeypatch):
    """Every way soc_opt writes (open for writing, os.open with write flags, mkstemp, mkdir,
    rename, unlink, chmod) raises as on a read-only file system."""
    def refuse(*a, **k):
        raise OSError(30, "Read-only file system (test)")

    real_open, real_os_open = builtins.open, os.open

    def ro_open(file, mode="r", *a, **k):
        if any(c in mode for c in "wax+"):
            refuse()
        return real_open(file, mode, *a, **k)

    def ro_os_open(path, flags, *a, **k):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            refuse()
        return real_os_open(path, flags, *a, **k)

    monkeypatch.setattr(builtins, "open", ro_open)
    monkeypatch.setattr(os, "open", ro_os_open)
    for mod, name in ((tempfile, "mkstemp"), (os, "mkdir"), (os, "replace"), (os, "rename"), (os, "unlink"),
                      (os, "chmod"), (os, "link")):
        monkeypatch.setattr(mod, name, refuse)


def test_a_finished_run_opens_on_a_read_only_file_system(finished, monkeypatch, capsys):
    from soc_opt.experiments.run import finished_run, run_experiment

    before = _files(finished)
    task = load_task("linear2d")
    cfg = load_run_config("linear2d", method="lqr-flm", overrides={"iterations": 2, "samples": 4})
    _read_only(monkeypatch)
    assert main([*ARGS, "--out", str(finished)]) == 0, capsys.readouterr().err
    st = run_experiment(task, "lqr-flm", cfg, 0, finished, task_name="linear2d")
    assert st.iteration == 2 and finished_run(task, "lqr-flm", cfg, 0, finished, task_name="linear2d") is not None
    monkeypatch.undo()
    assert _files(finished) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="chmod does not stop root; the read-only path is tested above")
def test_a_finished_run_opens_in_a_directory_without_write_permission(finished, tmp_path):
    import shutil

    d = tmp_path / "ro"
    shutil.copytree(finished, d)
    for p in [d, *d.rglob("*")]:
        p.chmod(p.stat().st_mode & ~0o222)
    try:
        assert main([*ARGS, "--out", str(d)]) == 0
    finally:
        for p in [d, *d.rglob("*")]:
            p.chmod(p.stat().st_mode | 0o200)


def test_a_key_absent_from_the_record_is_a_difference_unless_its_absence_is_declared():
    """A key missing from a record is a difference (issue 31: a cut-down config.json must not match any
    configuration), except an option declared in ``IMPLIED_WHEN_ABSENT``: its absence implies its old value,
    and with its section not in use it implies nothing."""
    from soc_opt.config import IMPLIED_WHEN_ABSENT
    from soc_opt.experiments.rundir import differences
    from soc_opt.noise.aware import NoiseConfig

    assert IMPLIED_WHEN_ABSENT["kinematic.gains"] == ("nominal", {"estimator": "kinematic"})
    new = {"baseline": {"noise": NoiseConfig(estimator="kinematic").to_dict()}}
    old = {"baseline": {"noise": {k: v for k, v in new["baseline"]["noise"].items()}}}
    old["baseline"]["noise"]["kinematic"] = {k: v for k, v in new["baseline"]["noise"]["kinematic"].items()
                                             if k not in ("gains", "fit_moments", "w_floor")}
    diffs = differences(old, new)
    gains = [d for d in diffs if d.startswith("baseline.noise.kinematic.gains")]
    assert gains == ["baseline.noise.kinematic.gains: (unset: 'nominal' when recorded) -> 'online'"]
    assert [d for d in diffs if "w_floor" in d] == [
        f"baseline.noise.kinematic.w_floor: (not recorded) -> {new['baseline']['noise']['kinematic']['w_floor']}"]
    # the same record against a configuration with the implied values: only the undeclared key differs
    same = {"baseline": {"noise": NoiseConfig.from_dict(
        {"estimator": "kinematic", "kinematic": {"gains": "nominal", "fit_moments": "means"}}).to_dict()}}
    assert [d.split(":")[0] for d in differences(old, same)] == ["baseline.noise.kinematic.w_floor"]
    # with another estimator the kinematic section is not in use: its declared keys imply nothing
    paper_new = {"baseline": {"noise": NoiseConfig().to_dict()}}
    paper_old = {"baseline": {"noise": dict(paper_new["baseline"]["noise"], kinematic=old["baseline"]["noise"]["kinematic"])}}
    assert [d.split(":")[0] for d in differences(paper_old, paper_new)] == ["baseline.noise.kinematic.w_floor"]


def test_a_task_record_from_before_process_noise_matches_the_task_without_it():
    """``task.json`` of a run recorded before ``[process_noise]`` existed lacks the table: that is a task
    without process noise (docs/math.md §8.1), so it resumes against a task without it and not against
    one with it."""
    from soc_opt.experiments.rundir import _task_settings, differences
    from soc_opt.tasks import load_task

    new = _task_settings({"config": load_task("peg").config.to_dict()})
    old = {k: v for k, v in new.items() if k != "process_noise"}
    assert differences(old, new) == []
    noisy = _task_settings({"config": load_task("peg", overrides={"process_noise": {"start": 0.1}}).config.to_dict()})
    assert [d.split(":")[0] for d in differences(old, noisy)] == ["process_noise"]
