"""Fault injection on runs and configurations (issue 13): every fault must end in a clear error
or in a resumed run identical to the uninterrupted one, losing at most the unfinished iteration.

Faults: NaN/inf in every numeric config field; damaged and missing checkpoints; the task TOML and
the MJCF (and an included file) edited between a kill and the resume; two concurrent writers;
SIGKILL at random times and in the middle of random file writes; a simulation diverging mid-run.

The runs are small ``linear2d`` runs (mixture prior, DPSOC-EM with its EM phase); runs that are
killed or compete for a directory are child processes (fresh interpreters: forking this process
with its BLAS and thread pools running can deadlock the child).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import typing
from pathlib import Path

import numpy as np
import pytest

from soc_opt.config import Config, ConfigError
from soc_opt.config_doc import config_tables
from soc_opt.experiments.run import CheckpointError, RunDirectoryError, load_run_config, run_experiment
from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
from soc_opt.tasks import LinearTask, SimulationError, TaskConfig, load_task
from soc_opt.tasks.config import TERM_TYPES, LinearConfig, MetricConfig

CFG = DPSOCConfig(i_switch=1, baseline=LQRFLMConfig(iterations=4, samples=6, kl_budget=1.0), em=EMConfig(n_em=1))
SEED = 3


@pytest.fixture(scope="module")
def task():
    return load_task("linear2d", overrides={"T": 15})


@pytest.fixture(scope="module")
def reference(task, tmp_path_factory):
    """Uninterrupted runs of both methods: ``{method: (directory, seconds)}``."""
    out = {}
    for method in ("lqr-flm", "dpsoc-em"):
        d = tmp_path_factory.mktemp("ref") / method
        t0 = time.perf_counter()
        run_experiment(task, method, CFG, SEED, d)
        out[method] = (d, time.perf_counter() - t0)
    return out


def _run_files(d: Path) -> dict:
    """The results of a run directory: metrics without timings, every policy, sample and best arrays."""
    rows = json.loads((d / "metrics.json").read_text())
    out = {"metrics": [{k: v for k, v in r.items() if not k.startswith("time")} for r in rows]}
    for p in sorted(d.glob("policies/*.npz")) + sorted(d.glob("samples/*.npz")) + [d / "best_policy.npz"]:
        with np.load(p) as f:
            out[str(p.relative_to(d))] = {k: f[k] for k in f.files}
    return out


def assert_same_run(a: Path, b: Path) -> None:
    ra, rb = _run_files(a), _run_files(b)
    assert ra.keys() == rb.keys()
    assert ra["metrics"] == rb["metrics"]
    for key in ra:
        if key != "metrics":
            for name in ra[key]:
                np.testing.assert_array_equal(ra[key][name], rb[key][name], err_msg=f"{key}:{name}")


# ----------------------------------------------------------------- NaN/inf in every numeric field


def _depth(tp) -> int | None:
    """0 for a float field, 1 for a list of floats, 2 for a list of lists; None if not numeric-float."""
    if tp is float:
        return 0
    args = [a for a in typing.get_args(tp) if a is not type(None) and a is not Ellipsis]
    if typing.get_origin(tp) is tuple:
        inner = _depth(args[0]) if args else None
        return None if inner is None else inner + 1
    depths = [d for d in map(_depth, args) if d is not None]
    return min(depths) if depths else None


def _float_fields(cls: type[Config]):
    """``(name, depth)`` of every float field of ``cls`` (nested configs are visited separately)."""
    hints = typing.get_type_hints(cls)
    for name in cls.__dataclass_fields__:
        depth = _depth(hints[name])
        if depth is not None:
            yield name, depth


def _wrap(value, depth):
    for _ in range(depth):
        value = [value]
    return value


RUN_FIELDS = [(table, name, depth) for table, cls in config_tables(DPSOCConfig) for name, depth in _float_fields(cls)]


def test_the_field_enumeration_covers_every_run_config_table():
    tables = {t for t, _, _ in RUN_FIELDS}
    assert {"baseline", "baseline.fit", "baseline.kl", "em", "em.mstep", "ilqg"} <= tables
    assert ("ilqg", "alphas", 1) in RUN_FIELDS and ("baseline", "kl_budget", 0) in RUN_FIELDS


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
@pytest.mark.parametrize("table,name,depth", RUN_FIELDS, ids=[f"{t}.{n}" for t, n, _ in RUN_FIELDS])
def test_nonfinite_run_config_value_is_refused_naming_the_key(tmp_path, table, name, depth, bad):
    p = tmp_path / "c.toml"
    value = "[" * depth + bad + "]" * depth
    p.write_text(f"[{table}]\n{name} = {value}\n" if table else f"{name} = {value}\n")
    with pytest.raises(ConfigError, match=rf"{table + '.' if table else ''}{name}(\[0\])*: must be a finite number"):
        load_run_config("linear2d", p)


TASK_BASE = {"name": "t", "T": 5, "kind": "linear"}
TASK_FIELDS = (
    [("", n, lst) for n, lst in _float_fields(TaskConfig)]
    + [("linear", n, lst) for n, lst in _float_fields(LinearConfig)]
    + [("metric", n, lst) for n, lst in _float_fields(MetricConfig)]
    + [(f"cost:{typ}", n, lst) for typ, cls in TERM_TYPES.items() for n, lst in _float_fields(cls)]
)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("table,name,depth", TASK_FIELDS, ids=[f"{t}.{n}" for t, n, _ in TASK_FIELDS])
def test_nonfinite_task_config_value_is_refused_naming_the_key(table, name, depth, bad):
    value = _wrap(bad, depth)
    data = dict(TASK_BASE)
    if table.startswith("cost:"):
        data["cost"] = [{"type": table[5:], name: value}]
        where = rf"cost\[0\]\.{name}"
    elif table:
        data[table] = {name: value}
        where = rf"{table}\.{name}"
    else:
        data[name] = value
        where = name
    with pytest.raises(ConfigError, match=rf"{where}(\[0\])*: must be a finite number"):
        TaskConfig.from_dict(data)


# ----------------------------------------------------------------- damaged checkpoints


class _Kill(Exception):
    pass


def _stop_after(n):
    def cb(st):
        if st.iteration == n:
            raise _Kill

    return cb


def _damage(kind: str, d: Path) -> None:
    ck = d / "checkpoint.npz"
    data = ck.read_bytes()
    if kind == "empty":
        ck.write_bytes(b"")
    elif kind == "truncated":
        ck.write_bytes(data[: len(data) // 2])
    elif kind == "bit flip":  # in the stored arrays (a flip in zip metadata such as a time stamp is harmless)
        i = len(data) // 2
        ck.write_bytes(data[:i] + bytes([data[i] ^ 1]) + data[i + 1:])
    elif kind == "garbage":
        ck.write_bytes(b"not a checkpoint at all")


@pytest.mark.parametrize("kind", ["empty", "truncated", "bit flip", "garbage"])
def test_damaged_checkpoint_is_reported_and_the_previous_one_resumes_identically(task, reference, tmp_path, kind):
    d = tmp_path / "r"
    with pytest.raises(_Kill):
        run_experiment(task, "dpsoc-em", CFG, SEED, d, on_iteration=_stop_after(3))
    _damage(kind, d)
    with pytest.raises(CheckpointError) as err:
        run_experiment(task, "dpsoc-em", CFG, SEED, d)
    msg = str(err.value)
    assert "checkpoint.npz" in msg and "--previous-checkpoint" in msg and "--restart" in msg
    assert "2 iterations done" in msg and "\n" not in msg
    assert _resume_in_a_new_process("dpsoc-em", d, previous=True) == "done"
    assert_same_run(d, reference["dpsoc-em"][0])


def test_both_checkpoints_damaged_leaves_restart_which_reproduces_the_run(task, reference, tmp_path):
    d = tmp_path / "r"
    with pytest.raises(_Kill):
        run_experiment(task, "lqr-flm", CFG, SEED, d, on_iteration=_stop_after(2))
    (d / "checkpoint.prev.npz").write_bytes(b"")
    _damage("truncated", d)
    with pytest.raises(CheckpointError, match="no intact previous checkpoint: rerun with --restart"):
        run_experiment(task, "lqr-flm", CFG, SEED, d)
    run_experiment(task, "lqr-flm", CFG, SEED, d, restart=True)
    assert_same_run(d, reference["lqr-flm"][0])


def test_a_deleted_checkpoint_falls_back_to_the_previous_one(task, reference, tmp_path):
    d = tmp_path / "r"
    with pytest.raises(_Kill):
        run_experiment(task, "lqr-flm", CFG, SEED, d, on_iteration=_stop_after(3))
    (d / "checkpoint.npz").unlink()
    assert _resume_in_a_new_process("lqr-flm", d) == "done"
    assert_same_run(d, reference["lqr-flm"][0])


# ----------------------------------------------------------------- edited task between kill and resume

ARM = """<mujoco>
  <option timestep="0.01" gravity="0 0 0"/>
  <include file="links.xml"/>
  <actuator><motor name="m1" joint="j1"/><motor name="m2" joint="j2"/></actuator>
</mujoco>"""
LINKS = """<mujoco><worldbody>
  <body name="l1"><joint name="j1" type="hinge" axis="0 0 1" damping="0.1"/>
    <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="1"/>
    <body name="l2" pos="0.5 0 0"><joint name="j2" type="hinge" axis="0 0 1" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="0.5"/><site name="tip" pos="0.4 0 0"/></body>
  </body>
</worldbody></mujoco>"""
ARM_TOML = """name = "arm"
T = 6
model = "arm.xml"
q0 = [0.3, 0.5]
rho2 = 0.01
init_var = 0.1
[state]
joints = ["j1", "j2"]
sites = ["tip"]
[[cost]]
type = "point"
sites = ["tip"]
target = [0.2, 0.6, 0.0]
[[cost]]
type = "torque"
wu = 0.01
"""


@pytest.mark.parametrize("edit,expected", [
    (("task.toml", "target = [0.2, 0.6", "target = [0.3, 0.6"), r"task\.cost\[0\]\.target"),
    (("arm.xml", 'timestep="0.01"', 'timestep="0.02"'), r"model file arm\.xml changed"),
    (("links.xml", 'damping="0.1"', 'damping="0.5"'), r"model file links\.xml changed"),
])
def test_edited_task_or_mjcf_between_kill_and_resume_is_refused_naming_it(tmp_path, edit, expected):
    (tmp_path / "arm.xml").write_text(ARM)
    (tmp_path / "links.xml").write_text(LINKS)
    (tmp_path / "task.toml").write_text(ARM_TOML)
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=2, samples=3))
    out = tmp_path / "run"
    with pytest.raises(_Kill):
        run_experiment(load_task(tmp_path / "task.toml"), "lqr-flm", cfg, 0, out, on_iteration=_stop_after(1))
    name, old, new = edit
    (tmp_path / name).write_text((tmp_path / name).read_text().replace(old, new))
    with pytest.raises(RunDirectoryError, match=expected):
        run_experiment(load_task(tmp_path / "task.toml"), "lqr-flm", cfg, 0, out)
    (tmp_path / name).write_text((tmp_path / name).read_text().replace(new, old))  # undo: resumes
    assert run_experiment(load_task(tmp_path / "task.toml"), "lqr-flm", cfg, 0, out).iteration == 2


# ----------------------------------------------------------------- child processes

#: A child run: loads the module's task and config, optionally SIGKILLs itself halfway through its
#: j-th file write (leaving a partial temporary file), says "ready", optionally waits for a line on
#: stdin, then runs and reports "done" or "refused <message>".
CHILD = r"""
import json, os, signal, sys
from pathlib import Path
args = json.loads(sys.argv[1])
import soc_opt.experiments.rundir as rundir
from soc_opt.methods.config import DPSOCConfig
from soc_opt.experiments.run import RunDirectoryError, run_experiment
from soc_opt.tasks import load_task
task = load_task(args.get("task", "linear2d"), overrides=args["task_overrides"])
cfg = DPSOCConfig.from_dict(args["cfg"])
class Stop(Exception):
    pass
def stop(st):
    if st.iteration == args["stop_after"]:
        raise Stop
if args["kill_at_write"]:
    real, count = rundir.atomic_write_bytes, [0]
    def write(path, data):
        count[0] += 1
        if count[0] == args["kill_at_write"]:
            Path(path).with_name(f".{Path(path).name}.tmp-killed").write_bytes(data[: len(data) // 2])
            os.kill(os.getpid(), signal.SIGKILL)
        real(path, data)
    rundir.atomic_write_bytes = write
print("ready", flush=True)
if args["wait"]:
    sys.stdin.readline()
try:
    run_experiment(task, args["method"], cfg, args["seed"], args["out"], previous_checkpoint=args["previous"],
                   on_iteration=stop if args["stop_after"] else None)
    print("done", flush=True)
except Stop:
    print("stopped", flush=True)
except RunDirectoryError as e:
    print("refused", e, flush=True)
"""
ROOT = Path(__file__).resolve().parents[1]


def _child(method: str, out: Path, kill_at_write: int | None = None, wait: bool = False, *, cfg=CFG,
           previous: bool = False, stop_after: int | None = None, task_overrides=None, seed=SEED,
           task: str = "linear2d") -> subprocess.Popen:
    args = {"cfg": cfg.to_dict(), "method": method, "seed": seed, "out": str(out), "kill_at_write": kill_at_write,
            "wait": wait, "previous": previous, "stop_after": stop_after, "task": task,
            "task_overrides": {"T": 15} if task_overrides is None else task_overrides}
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    p = subprocess.Popen([sys.executable, "-c", CHILD, json.dumps(args)], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert p.stdout.readline().strip() == "ready", p.stderr.read()
    return p


def _resume_in_a_new_process(method: str, d: Path, **kw) -> str:
    """Run ``method`` on ``d`` in a fresh interpreter (never the one that wrote the checkpoint);
    its last stdout line ("done", "stopped" or "refused ...")."""
    p = _child(method, d, **kw)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    return out.strip().splitlines()[-1]


# ----------------------------------------------------------------- resume in a new process


@pytest.mark.parametrize("method,iterations", [("lqr-flm", 6), pytest.param("dpsoc-em", 10, marks=pytest.mark.slow)])
def test_every_iteration_in_its_own_process_equals_the_uninterrupted_run(tmp_path, method, iterations):
    """Issue 18: the default linear2d run (step adaptation on) stopped after every iteration and
    resumed in a new process each time; with pickle checkpoints the step-size multiplier drifted by
    1e-16 after a resume (the previous step's arrays lost their layout), here from iteration 2 on."""
    cfg = load_run_config("linear2d", method=method, overrides={"iterations": iterations})
    ref, d = tmp_path / "ref", tmp_path / "chain"
    assert _resume_in_a_new_process(method, ref, cfg=cfg, task_overrides={}, seed=0) == "done"
    for k in range(1, cfg.baseline.iterations):
        assert _resume_in_a_new_process(method, d, cfg=cfg, task_overrides={}, seed=0, stop_after=k) == "stopped"
    assert _resume_in_a_new_process(method, d, cfg=cfg, task_overrides={}, seed=0) == "done"
    assert_same_run(d, ref)


@pytest.mark.parametrize("method, seed", [("lqr-flm", 4), ("dpsoc-em", 3)])  # seeds on which a step is rejected
def test_a_run_with_the_rank_test_and_partial_recovery_resumed_in_new_processes_equals_the_uninterrupted_run(
        tmp_path, method, seed):
    """Issue 47: the rank test reads the accepted batch's costs from the checkpoint (``AcceptedPolicy.costs``)
    and recovery its remembered multiplier; a strict rank test (kappa = eps = 0) rejects steps on linear2d,
    and a run stopped after every iteration and resumed each time in a new process equals the uninterrupted
    one."""
    cfg = load_run_config("linear2d", method=method, overrides={"iterations": 7, "samples": 6})
    cfg = cfg.replace(i_switch=2, baseline=cfg.baseline.replace(acceptance=cfg.baseline.acceptance.replace(
        kappa=0.0, eps=0.0, test="rank", recover=True, recover_fraction=0.5)))
    ref, d = tmp_path / "ref", tmp_path / "chain"
    assert _resume_in_a_new_process(method, ref, cfg=cfg, task_overrides={}, seed=seed) == "done"
    rows = json.loads((ref / "metrics.json").read_text())
    assert any(r.get("accepted") == 0.0 for r in rows), "the strict rank test should reject a step"
    for k in range(1, cfg.baseline.iterations):
        assert _resume_in_a_new_process(method, d, cfg=cfg, task_overrides={}, seed=seed, stop_after=k) == "stopped"
    assert _resume_in_a_new_process(method, d, cfg=cfg, task_overrides={}, seed=seed) == "done"
    assert_same_run(d, ref)


@pytest.mark.parametrize("method", ["lqr-flm", "dpsoc-em"])
def test_a_run_with_rejected_steps_resumed_in_new_processes_equals_the_uninterrupted_run(tmp_path, method):
    """Issue 30: the last accepted policy, its step and the multiplier's ceiling are in the checkpoint; a
    strict acceptance test (kappa = eps = 0) rejects steps on linear2d, and a run stopped after every
    iteration and resumed each time in a new process equals the uninterrupted one."""
    cfg = load_run_config("linear2d", method=method, overrides={"iterations": 7, "samples": 6})
    cfg = cfg.replace(i_switch=2, baseline=cfg.baseline.replace(
        acceptance=cfg.baseline.acceptance.replace(kappa=0.0, eps=0.0)))
    ref, d = tmp_path / "ref", tmp_path / "chain"
    assert _resume_in_a_new_process(method, ref, cfg=cfg, task_overrides={}, seed=4) == "done"
    rows = json.loads((ref / "metrics.json").read_text())
    assert any(r.get("accepted") == 0.0 for r in rows), "the strict test should reject a step"
    for k in range(1, cfg.baseline.iterations):
        assert _resume_in_a_new_process(method, d, cfg=cfg, task_overrides={}, seed=4, stop_after=k) == "stopped"
    assert _resume_in_a_new_process(method, d, cfg=cfg, task_overrides={}, seed=4) == "done"
    assert_same_run(d, ref)


@pytest.mark.parametrize("method, start_select", [("lqr-flm", "batch"), ("dpsoc-em", "batch"), ("lqr-flm", "previous")])
def test_a_kinematic_estimator_run_resumed_in_new_processes_equals_the_uninterrupted_run(tmp_path, method,
                                                                                      start_select):
    """Issues 18 x 19: the kinematic filter is stored as data (no MuJoCo model in the checkpoint) and
    bound again to the task's model by the rollouts of the resumed process (``for_task``); with
    ``start_select = "previous"`` the resumed process judges the EM starts on the previous batch, which
    it reads from the checkpoint (``last_rollouts``)."""
    text = (ROOT / "docs/results/noise/peg_kinematic.toml").read_text()
    text = text.replace("[baseline.noise.kinematic]", f'[baseline.noise.kinematic]\nstart_select = "{start_select}"', 1)
    (tmp_path / "cfg.toml").write_text(text)
    cfg = load_run_config("peg", tmp_path / "cfg.toml", method=method,
                          overrides={"iterations": 3, "samples": 6, **({"i_switch": 1} if method == "dpsoc-em" else {})})
    assert cfg.baseline.noise.kinematic.start_select == start_select
    kw = {"cfg": cfg, "task": "peg", "task_overrides": {"T": 25}, "seed": 0}
    ref, d = tmp_path / "ref", tmp_path / "chain"
    assert _resume_in_a_new_process(method, ref, **kw) == "done"
    for k in range(1, cfg.baseline.iterations):
        assert _resume_in_a_new_process(method, d, stop_after=k, **kw) == "stopped"
    assert _resume_in_a_new_process(method, d, **kw) == "done"
    assert_same_run(d, ref)


# ----------------------------------------------------------------- concurrent writers


def test_two_concurrent_writers_one_is_refused_and_the_other_finishes_identically(reference, tmp_path):
    d = tmp_path / "r"
    procs = [_child("dpsoc-em", d, wait=True) for _ in range(2)]
    for p in procs:  # both start at once
        p.stdin.write("go\n")
        p.stdin.flush()
    outs = {p.pid: p.communicate(timeout=600)[0].strip() for p in procs}
    done = [pid for pid, o in outs.items() if o == "done"]
    refused = [o for o in outs.values() if o.startswith("refused")]
    assert len(done) == 1 and len(refused) == 1, outs
    assert f"in use by process {done[0]}" in refused[0]
    assert_same_run(d, reference["dpsoc-em"][0])


# ----------------------------------------------------------------- SIGKILL at random points


def _kill_and_resume(task, reference, tmp_path, runs: int, seed: int) -> list[str]:
    """``runs`` children killed with SIGKILL, by a timer or halfway through a file write (chosen
    at random), each resumed here; every resumed directory must equal the uninterrupted one."""
    rng = np.random.default_rng(seed)
    log = []
    for i in range(runs):
        method = ("lqr-flm", "dpsoc-em")[i % 2]
        ref_dir, seconds = reference[method]
        d = tmp_path / f"run{i}"
        by_write = i % 3 == 2
        p = _child(method, d, kill_at_write=int(rng.integers(1, 31)) if by_write else None)
        if not by_write:
            time.sleep(float(rng.uniform(0.05, 1.0)) * seconds)
            p.send_signal(signal.SIGKILL)
        p.communicate(timeout=600)
        done = json.loads((d / "metrics.json").read_text()) if (d / "metrics.json").exists() else []
        log.append(f"{method}: killed ({'mid-write' if by_write else 'timer'}, exit {p.returncode}) "
                   f"with {len(done)} iterations written")
        assert _resume_in_a_new_process(method, d) == "done"
        assert_same_run(d, ref_dir)
        assert not list(d.glob(".*.tmp-*")), "temporary files of the killed writes were left behind"
    print("\n".join(log))
    return log


def test_sigkill_at_random_points_then_resume_equals_the_uninterrupted_run(task, reference, tmp_path):
    _kill_and_resume(task, reference, tmp_path, runs=3, seed=0)


@pytest.mark.slow
def test_sigkill_at_random_points_in_ten_runs(task, reference, tmp_path):
    _kill_and_resume(task, reference, tmp_path, runs=10, seed=1)


# ----------------------------------------------------------------- a simulation diverging mid-run


class DivergingTask(LinearTask):
    """linear2d whose rollouts blow up from the ``fail_at``-th call on."""

    def __init__(self, config, fail_at):
        super().__init__(config)
        self.calls = 0
        self.fail_at = fail_at

    def rollouts(self, *args, **kw):
        self.calls += 1
        if self.calls >= self.fail_at:
            raise SimulationError(f"sample 2 diverged at control step 7 (call {self.calls})")
        return super().rollouts(*args, **kw)


def test_a_diverging_simulation_keeps_the_finished_iterations_and_says_so(task, reference, tmp_path, capsys,
                                                                           monkeypatch):
    from soc_opt.cli import main

    d = tmp_path / "r"
    with pytest.raises(SimulationError, match="diverged") as err:
        run_experiment(DivergingTask(task.config, fail_at=3), "lqr-flm", CFG, SEED, d)
    assert "keeps 2 finished iterations" in " ".join(err.value.__notes__)
    assert len(json.loads((d / "metrics.json").read_text())) == 2
    # the same fault through the command line: one line, exit status 2
    import soc_opt.tasks

    monkeypatch.setattr(soc_opt.tasks, "load_task", lambda *a, **k: DivergingTask(task.config, fail_at=1))
    (tmp_path / "cfg.toml").write_text("i_switch = 1\n[baseline]\niterations = 4\nsamples = 6\nkl_budget = 1.0\n")
    assert main(["run", "linear2d", "--method", "lqr-flm", "--config", str(tmp_path / "cfg.toml"),
                 "--seed", str(SEED), "--out", str(d)]) == 2
    err_lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err_lines) == 1 and err_lines[0].startswith("soc-opt: error: sample 2 diverged")
    assert "keeps 2 finished iterations" in err_lines[0]
    run_experiment(task, "lqr-flm", CFG, SEED, d)  # without the fault: resumes to the same run
    assert_same_run(d, reference["lqr-flm"][0])
