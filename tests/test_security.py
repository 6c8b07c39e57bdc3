"""Opening files the project reads back never runs code (issue 18 item 1).

Crafted files with a payload (a pickle whose ``__reduce__`` creates a marker file, an ``.npz``
holding an object array with the same payload, state files whose JSON names types or nodes
outside the schema, or points an array outside its buffer) are put in every position the
project reads: ``checkpoint.npz``, ``checkpoint.prev.npz``, the old ``checkpoint.pkl`` /
``checkpoint.prev.pkl`` / ``fork_state.pkl``, ``fork_state.npz``, ``config.json`` / ``task.json``
and policy files (``LinearGaussianPolicy.load``).  The real entry points (``soc-opt run``,
``soc-opt compare``, ``soc-opt convert-checkpoint`` without ``--trust``, the library loaders)
must refuse them with a one-line error naming the file, and the marker must never appear.
The library holds no unpickling call outside ``soc_opt.experiments.convert_checkpoint`` (checked by
reading the sources).
"""

from __future__ import annotations

import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_statefile import Payload, bad_files

from soc_opt.cli import main

ARGS = ["--method", "lqr-flm", "--iterations", "2", "--samples", "4", "--progress", "lines"]
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A genuine finished run directory (2 iterations) to plant files in."""
    d = tmp_path_factory.mktemp("genuine") / "run"
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 0
    return d


def _plant(finished, tmp_path, name, data) -> Path:
    d = tmp_path / "run"
    shutil.copytree(finished, d)
    (d / name).write_bytes(data)
    return d


def _error(capsys) -> str:
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("soc-opt: error:"), lines
    return lines[0]


@pytest.mark.parametrize("kind", list(bad_files("m")))
def test_a_crafted_last_checkpoint_is_refused_by_soc_opt_run(finished, tmp_path, capsys, kind):
    marker = tmp_path / "marker"
    d = _plant(finished, tmp_path, "checkpoint.npz", bad_files(marker)[kind])
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    err = _error(capsys)
    assert "checkpoint.npz" in err and "--restart" in err
    assert not marker.exists()


@pytest.mark.parametrize("kind", ["pickle", "npz with an object array", "unknown type", "layout outside its buffer"])
def test_a_crafted_previous_checkpoint_is_neither_loaded_for_the_hint_nor_with_the_flag(finished, tmp_path, capsys,
                                                                                        kind):
    marker = tmp_path / "marker"
    d = _plant(finished, tmp_path, "checkpoint.prev.npz", bad_files(marker)[kind])
    (d / "checkpoint.npz").write_bytes(b"damaged")
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    assert "no intact previous checkpoint" in _error(capsys)
    assert main(["run", "linear2d", *ARGS, "--out", str(d), "--previous-checkpoint"]) == 2
    assert "checkpoint.prev.npz" in _error(capsys)
    assert not marker.exists()


@pytest.mark.parametrize("name", ["checkpoint.pkl", "checkpoint.prev.pkl"])
@pytest.mark.parametrize("method", ["lqr-flm", "dpsoc-em", "ilqg"])
def test_an_old_pickle_checkpoint_alone_is_refused_with_the_conversion_command(tmp_path, capsys, name, method):
    marker = tmp_path / "marker"
    d = tmp_path / "run"
    d.mkdir()
    (d / name).write_bytes(pickle.dumps(Payload(marker)))
    assert main(["run", "linear2d", "--method", method, "--iterations", "5", "--out", str(d)]) == 2
    err = _error(capsys)
    assert name in err and f"soc-opt convert-checkpoint --trust '{d}'" in err
    assert not marker.exists()
    assert sorted(p.name for p in d.iterdir()) == [name]  # nothing written before the refusal


def test_convert_checkpoint_refuses_without_trust_and_runs_nothing(tmp_path, capsys):
    marker = tmp_path / "marker"
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "checkpoint.pkl").write_bytes(pickle.dumps(Payload(marker)))
    assert main(["convert-checkpoint", str(tmp_path / "run")]) == 2
    assert "--trust" in _error(capsys)
    assert not marker.exists() and (tmp_path / "run" / "checkpoint.pkl").exists()


def test_a_crafted_fork_state_is_never_loaded_by_soc_opt_compare(tmp_path, capsys):
    marker = tmp_path / "marker"
    out = tmp_path / "cmp"
    (out / "seed_0").mkdir(parents=True)
    (out / "compare.json").write_text('{"format": "soc_opt compare"}')  # a compare directory
    (out / "seed_0" / "fork_state.pkl").write_bytes(pickle.dumps(Payload(marker)))
    cmp_args = ["compare", "linear2d", "--seeds", "1", "--iterations", "2", "--samples", "4", "--i-switch", "1",
                "--progress", "lines", "--out", str(out)]
    assert main(cmp_args) == 2
    err = _error(capsys)
    assert "fork_state.pkl" in err and "convert-checkpoint --trust" in err
    assert not marker.exists()
    # a crafted fork_state.npz counts as damaged: it is recomputed, never loaded
    (out / "seed_0" / "fork_state.pkl").unlink()
    for kind, data in bad_files(marker).items():
        (out / "seed_0" / "fork_state.npz").write_bytes(data)
        shutil.rmtree(out / "seed_0" / "lqr-flm", ignore_errors=True)
        shutil.rmtree(out / "seed_0" / "dpsoc-em", ignore_errors=True)
        assert main(cmp_args) == 0, kind
        assert not marker.exists(), kind
        capsys.readouterr()


@pytest.mark.parametrize("content", ['[1, 2]', '{"method": "lqr-flm", "config": 5}', '{"config": {"baseline": []}}'])
def test_a_config_json_of_unexpected_types_is_refused_naming_it(finished, tmp_path, capsys, content):
    d = _plant(finished, tmp_path, "config.json", content.encode())
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    assert "config.json" in _error(capsys)


def test_a_policy_file_with_an_object_array_is_refused_by_the_loader(tmp_path):
    from soc_opt.models import LinearGaussianPolicy

    marker = tmp_path / "marker"
    obj = np.array([Payload(marker)], dtype=object)
    np.savez(tmp_path / "policy.npz", K=obj, k=obj, cov=obj)
    with pytest.raises(ValueError, match="pickle"):
        LinearGaussianPolicy.load(tmp_path / "policy.npz")
    assert not marker.exists()


def test_no_library_module_unpickles_except_the_trusted_converter():
    pattern = re.compile(r"(cloud)?pickle\.loads?\(|allow_pickle\s*=\s*True|pickle\.Unpickler|joblib\.load|"
                         r"np\.load\([^)]*allow_pickle\s*=\s*True")
    hits = [f"{p.relative_to(ROOT)}:{i}" for p in sorted((ROOT / "soc_opt").rglob("*.py"))
            for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert hits == ["soc_opt/experiments/convert_checkpoint.py:" + str(_unpickler_line())]


def _unpickler_line() -> int:
    lines = (ROOT / "soc_opt" / "experiments" / "convert_checkpoint.py").read_text().splitlines()
    return next(i for i, ln in enumerate(lines, 1) if "pickle.Unpickler" in ln)


def test_convert_checkpoint_with_trust_turns_a_genuine_old_run_into_one_that_resumes(finished, tmp_path, capsys):
    """An old-format run (pickle of a real state, with the old header) converts and reads back."""
    import hashlib

    from soc_opt.experiments.rundir import decode_checkpoint

    d = tmp_path / "old"
    shutil.copytree(finished, d)
    state = decode_checkpoint(d / "checkpoint.npz")
    for new, old in (("checkpoint.npz", "checkpoint.pkl"), ("checkpoint.prev.npz", "checkpoint.prev.pkl")):
        payload = pickle.dumps(decode_checkpoint(d / new))
        (d / old).write_bytes(b"soc_opt checkpoint v1\n" + hashlib.sha256(payload).hexdigest().encode() + b"\n"
                              + payload)
        (d / new).unlink()
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    assert "convert-checkpoint" in _error(capsys)
    assert main(["convert-checkpoint", "--trust", str(d)]) == 0
    assert "2 checkpoints converted" in capsys.readouterr().out
    assert not list(d.glob("*.pkl"))
    back = decode_checkpoint(d / "checkpoint.npz")
    np.testing.assert_array_equal(back.policy.K, state.policy.K)
    assert back.iteration == state.iteration and back.rng_state == state.rng_state
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 0
    assert "already finished" in capsys.readouterr().out


def test_convert_checkpoint_finds_the_classes_of_the_retired_algorithms_module(finished, tmp_path, capsys):
    """Pickles written before the methods package name their run-state and configuration classes
    ``soc_opt.algorithms.<Class>``; that module is gone (issue 33) and the converter still finds them."""
    from soc_opt.experiments.rundir import decode_checkpoint

    d = tmp_path / "old"
    shutil.copytree(finished, d)
    state = decode_checkpoint(d / "checkpoint.npz")
    for new, old in (("checkpoint.npz", "checkpoint.pkl"), ("checkpoint.prev.npz", "checkpoint.prev.pkl")):
        payload = pickle.dumps(decode_checkpoint(d / new), protocol=0)  # GLOBAL opcodes: "module\nname\n"
        assert b"csoc_opt.methods.state\nRunState\n" in payload
        for name in (b"RunState", b"IterationRecord", b"BestPolicy", b"PreviousStep", b"EMDiagnostics"):
            payload = payload.replace(b"csoc_opt.methods.state\n" + name + b"\n", b"csoc_opt.algorithms\n" + name + b"\n")
        (d / old).write_bytes(payload)
        (d / new).unlink()
    assert b"csoc_opt.algorithms\nRunState\n" in (d / "checkpoint.pkl").read_bytes()
    assert main(["convert-checkpoint", "--trust", str(d)]) == 0
    assert "2 checkpoints converted" in capsys.readouterr().out
    assert "soc_opt.algorithms" not in sys.modules  # found through the converter's table, not an import
    back = decode_checkpoint(d / "checkpoint.npz")
    np.testing.assert_array_equal(back.policy.K, state.policy.K)
    assert back.iteration == state.iteration and back.rng_state == state.rng_state


# ------------------------------------------------------------------ issue 31: the file system, bounded reads, contracts
# Each test below failed on the main branch before issue 31 (the behaviour it checks did not exist).

import io  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

from soc_opt.experiments import statefile  # noqa: E402

SWEEP = ROOT / "problems" / "sweeps" / "linear2d_small.toml"


def _outside(tmp_path, names) -> dict[Path, bytes]:
    """Files outside every directory soc_opt is given (link targets), with their bytes."""
    victim = tmp_path / "victim"
    victim.mkdir(exist_ok=True)
    out = {}
    for n in names:
        p = victim / n
        p.write_bytes(f"the user's own {n}\n".encode())
        out[p] = p.read_bytes()
    return out


def _unchanged(files_before: dict[Path, bytes]) -> None:
    for p, data in files_before.items():
        assert p.exists() and not p.is_symlink() and p.read_bytes() == data, p


def _unfinished(finished, tmp_path, name="run") -> Path:
    """A copy of the finished run set back one iteration (its previous checkpoint as the last one)."""
    d = tmp_path / name
    shutil.copytree(finished, d)
    shutil.copyfile(d / "checkpoint.prev.npz", d / "checkpoint.npz")
    return d


def test_figures_written_where_links_were_planted_leave_the_link_targets_unchanged(finished, tmp_path, capsys):
    names = ["cost_per_iteration.png", "ee_trajectories.png", "filmstrip.png", "final_eval.npz", "metrics.csv"]
    targets = _outside(tmp_path, names)
    d = _unfinished(finished, tmp_path)
    for p in targets:
        (d / p.name).unlink(missing_ok=True)
        (d / p.name).symlink_to(p)
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 0
    _unchanged(targets)
    for n in names:  # the run's own files replaced the links
        assert (d / n).is_file() and not (d / n).is_symlink() and (d / n).stat().st_size > 0


COMPARE_ARGS = ["compare", "linear2d", "--seeds", "1", "--iterations", "2", "--samples", "4", "--i-switch", "1",
                "--progress", "lines"]


@pytest.mark.parametrize("where", ["compare", "sweep"])
def test_reports_rewritten_where_links_were_planted_leave_the_link_targets_unchanged(tmp_path, capsys, where):
    d = tmp_path / where
    if where == "compare":
        args = [*COMPARE_ARGS, "--out", str(d)]
        names = ["summary.json", "report.md", "actions.png", "cost_per_iteration.png", "seed_0/lqr-flm/final_eval.npz"]
    else:
        args = ["sweep", str(SWEEP), "--out", str(d), "--workers", "1"]
        names = ["report.md", "summary.csv", "trials.csv", "status.json"]
    assert main(args) == 0  # a finished directory; running again rewrites its report
    targets = _outside(tmp_path, [n.replace("/", "_") for n in names])
    for n, p in zip(names, targets):
        (d / n).unlink()
        (d / n).symlink_to(p)
    assert main(args) == 0
    _unchanged(targets)
    for n in names:
        assert (d / n).is_file() and not (d / n).is_symlink() and (d / n).stat().st_size > 0


@pytest.mark.parametrize("where", ["run", "compare", "sweep"])
def test_a_lock_planted_as_a_link_is_refused_and_its_target_keeps_its_bytes(finished, tmp_path, capsys, where):
    targets = _outside(tmp_path, ["lock"])
    d = tmp_path / where
    if where == "run":
        shutil.copytree(finished, d)
        (d / "checkpoint.npz").unlink()  # not finished: the run takes its lock
        args = ["run", "linear2d", *ARGS, "--out", str(d)]
    elif where == "compare":
        d.mkdir()
        (d / "compare.json").write_text('{"format": "soc_opt compare"}')
        args = ["compare", "linear2d", "--seeds", "1", "--iterations", "2", "--samples", "4", "--i-switch", "1",
                "--progress", "lines", "--out", str(d)]
    else:
        d.mkdir()
        (d / "sweep.json").write_text('{"name": "linear2d_small", "trials": []}')
        args = ["sweep", str(SWEEP), "--out", str(d), "--workers", "1"]
    (d / "lock").unlink(missing_ok=True)
    (d / "lock").symlink_to(next(iter(targets)))
    assert main(args) == 2
    err = _error(capsys)
    assert "lock" in err and "symbolic link" in err
    _unchanged(targets)


@pytest.mark.parametrize("restart", [False, True])
def test_a_policies_folder_planted_as_a_link_is_refused_and_nothing_in_its_target_is_written_or_deleted(
        finished, tmp_path, capsys, restart):
    elsewhere = tmp_path / "users_policies"
    elsewhere.mkdir()
    own = {elsewhere / "iter_000.npz": b"mine 0", elsewhere / "iter_005.npz": b"mine 5", elsewhere / "notes.txt": b"x"}
    for p, data in own.items():
        p.write_bytes(data)
    d = _unfinished(finished, tmp_path)
    shutil.rmtree(d / "policies")
    (d / "policies").symlink_to(elsewhere, target_is_directory=True)
    assert main(["run", "linear2d", *ARGS, "--out", str(d), *(["--restart"] if restart else [])]) == 2
    err = _error(capsys)
    assert "policies" in err and "symbolic link" in err
    assert sorted(elsewhere.iterdir()) == sorted(own)
    _unchanged(own)


USER_FILES = {"config.json": b'{"my": "settings"}', "task.json": b"{}", "metrics.csv": b"a,b\n1,2\n",
              "best_policy.npz": b"npz", "lock": b"my lock", "costs.npz": b"c", "policy.npz": b"p",
              "final_eval.npz": b"e", "summary.json": b"{}", "report.md": b"# mine", "policies/iter_001.npz": b"i"}


def _user_folder(tmp_path) -> tuple[Path, dict[Path, bytes]]:
    d = tmp_path / "mine"
    for name, data in USER_FILES.items():
        (d / name).parent.mkdir(parents=True, exist_ok=True)
        (d / name).write_bytes(data)
    return d, {d / n: data for n, data in USER_FILES.items()}


@pytest.mark.parametrize("command", ["run", "run --restart", "run --method ilqg", "compare", "compare --restart", "sweep"])
def test_out_on_a_folder_that_is_not_a_run_directory_is_refused_and_nothing_in_it_changes(tmp_path, capsys, command):
    d, before = _user_folder(tmp_path)
    words = command.split()
    if words[0] == "run":
        base = ARGS if "ilqg" not in words else ["--iterations", "2", "--progress", "lines"]
        args = ["run", "linear2d", *base, *words[1:], "--out", str(d)]
    elif words[0] == "compare":
        args = ["compare", "linear2d", "--seeds", "1", "--iterations", "2", "--samples", "4", "--i-switch", "1",
                "--progress", "lines", *words[1:], "--out", str(d)]
    else:
        args = ["sweep", str(SWEEP), "--out", str(d), "--workers", "1"]
    assert main(args) == 2
    err = _error(capsys)
    assert str(d) in err and "not empty" in err
    _unchanged(before)
    assert sorted(p for p in d.rglob("*")) == sorted({*before, d / "policies"})


#: A small launcher runs the command and reports its child's peak with ``resource.getrusage``: a process
#: forked from pytest itself would inherit pytest's peak (Linux keeps the pre-exec high-water mark).
_LAUNCH = """
import resource, subprocess, sys
p = subprocess.run([sys.executable, "-m", "soc_opt.cli", *sys.argv[1:]])
print("RSS", p.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""
#: Peak resident memory allowed for a refused resume (a whole linear2d run peaks near 250 MB here).
RSS_BOUND_MB = 600


def _peak_mb(args) -> tuple[int, float, str]:
    p = subprocess.run([sys.executable, "-c", _LAUNCH, *args], capture_output=True, text=True, timeout=600)
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("RSS")][-1].split()
    return int(line[1]), int(line[2]) / 1024, p.stderr


def _rewrite(path: Path, edit_tree=None, extra: dict | None = None, deflate_zero_member: tuple | None = None):
    """Rewrite a genuine state file: ``edit_tree(tree)`` changes its structure, the checksum is recomputed
    (whoever writes the file can), ``deflate_zero_member = (name, n_bytes)`` adds a deflated member of zeros."""
    import zipfile

    with np.load(path) as f:
        members = {k: f[k] for k in f.files}
    tree = json.loads(members.pop("__tree__").tobytes())
    members.pop("__sha256__")
    if edit_tree is not None:
        edit_tree(tree)
    tree_b = json.dumps(tree).encode()
    digest = statefile._digest(tree_b, members)
    np.savez(path, **members, **(extra or {}), __tree__=np.frombuffer(tree_b, np.uint8),
             __sha256__=np.frombuffer(digest.encode(), np.uint8))
    if deflate_zero_member is not None:
        name, n = deflate_zero_member
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (n // 8,)})
        with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as zf:
            with zf.open(name, "w", force_zip64=True) as w:
                w.write(header.getvalue())
                chunk = bytes(64 << 20)
                for _ in range(n // len(chunk)):
                    w.write(chunk)


def test_a_checkpoint_with_a_deflated_2_gib_member_is_refused_before_inflating_it(finished, tmp_path):
    d = _unfinished(finished, tmp_path)
    _rewrite(d / "checkpoint.npz", deflate_zero_member=("a999.npy", 2 << 30))
    assert (d / "checkpoint.npz").stat().st_size < 8 << 20  # a few MB on disk
    rc, peak, err = _peak_mb(["run", "linear2d", *ARGS, "--out", str(d)])
    assert peak < RSS_BOUND_MB, f"peak resident memory {peak:.0f} MB"  # measured first: what failed before issue 31
    assert rc == 2 and "checkpoint.npz" in err and "a999.npy" in err, err


def test_a_state_with_a_zero_stride_view_of_a_trillion_elements_is_refused_without_expanding_it(finished, tmp_path):
    d = _unfinished(finished, tmp_path)

    def broadcast_K(tree):
        node = tree["state"]["fields"]["policy"]["fields"]["K"]
        node["shape"], node["strides"] = [10**6, 10**6], [0, 0]

    _rewrite(d / "checkpoint.npz", broadcast_K)
    rc, peak, err = _peak_mb(["run", "linear2d", *ARGS, "--out", str(d)])
    assert peak < RSS_BOUND_MB, f"peak resident memory {peak:.0f} MB"
    assert rc == 2 and "checkpoint.npz" in err and "more than" in err, err
    assert not list((d / "policies").glob("iter_*[!0-9].npz"))


def test_a_config_json_cut_down_to_its_keys_does_not_accept_another_configuration(finished, tmp_path, capsys):
    d = _unfinished(finished, tmp_path)
    rec = json.loads((d / "config.json").read_text())
    (d / "config.json").write_text(json.dumps({"method": rec["method"], "seed": rec["seed"], "config": {}}))
    rows = (d / "metrics.csv").read_text()
    args = [a if a != "4" else "6" for a in ARGS]  # --samples 6 instead of 4
    assert main(["run", "linear2d", *args, "--out", str(d)]) == 2
    err = _error(capsys)
    assert "different configuration" in err and "(not recorded)" in err
    assert (d / "metrics.csv").read_text() == rows


@pytest.mark.parametrize("field,value,says", [
    ("iteration", -3, "iteration -3"), ("iteration", float("inf"), "iteration"), ("iteration", 10**9, "outside"),
    ("mult", float("nan"), "mult"), ("mult", "large", "mult"), ("em_done", "yes", "em_done"), ("rng_state", {"x": 1}, "rng_state"),
])
def test_a_schema_valid_state_with_invalid_values_is_refused_naming_the_field(finished, tmp_path, capsys, field,
                                                                                value, says):
    d = _unfinished(finished, tmp_path)

    def edit(tree):
        tree["state"]["fields"][field] = value

    _rewrite(d / "checkpoint.npz", edit)
    before = sorted(p.name for p in (d / "policies").iterdir())
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    err = _error(capsys)
    assert "checkpoint.npz" in err and says in err, err
    assert "already finished" not in err
    assert sorted(p.name for p in (d / "policies").iterdir()) == before


def test_a_second_sweep_on_the_same_directory_stops_at_once_naming_the_holder(tmp_path, capsys):
    from soc_opt.experiments.rundir import lock_directory

    out = tmp_path / "sweep"
    with lock_directory(out, what="sweep directory"):
        assert main(["sweep", str(SWEEP), "--out", str(out), "--workers", "1"]) == 2
        err = _error(capsys)
    assert f"process {os.getpid()}" in err and "sweep directory" in err
    assert sorted(p.name for p in out.iterdir()) == ["lock"]


DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize("name", ["config.json", "task.json"])
def test_a_100k_deep_json_in_a_run_directory_is_refused_naming_the_file(finished, tmp_path, capsys, name):
    d = _unfinished(finished, tmp_path)
    (d / name).write_text('{"a": ' + DEEP + "}")
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    assert name in _error(capsys)


def test_a_100k_deep_structure_in_a_checkpoint_is_refused_naming_it(finished, tmp_path, capsys):
    d = _unfinished(finished, tmp_path)
    raw = json.dumps({"format": statefile.FORMAT, "version": statefile.VERSION, "state": 0})
    deep = raw.replace("0}", DEEP + "}").encode()
    (d / "checkpoint.npz").write_bytes(_raw_state(deep))
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    err = _error(capsys)
    assert "checkpoint.npz" in err and "nested" in err


def _raw_state(tree_b: bytes, arrays: dict | None = None) -> bytes:
    arrays = arrays or {}
    buf = io.BytesIO()
    np.savez(buf, **arrays, __tree__=np.frombuffer(tree_b, np.uint8),
             __sha256__=np.frombuffer(statefile._digest(tree_b, arrays).encode(), np.uint8))
    return buf.getvalue()


@pytest.mark.parametrize("kind", ["a 100k-deep TOML array", "a result.json of wrong types"])
def test_a_hostile_sweep_file_or_result_is_refused_in_one_line_naming_it(tmp_path, capsys, kind):
    out = tmp_path / "sweep"
    sweep_file, name = SWEEP, "result.json"
    if kind == "a 100k-deep TOML array":
        sweep_file, name = tmp_path / "deep.toml", "deep.toml"
        sweep_file.write_text('name = "deep"\ntasks = ' + DEEP + "\n")
    else:
        from soc_opt.sweeps.runner import prepare_out
        from soc_opt.sweeps.spec import load_sweep

        spec = load_sweep(SWEEP)
        prepare_out(spec, out)
        (out / spec.trials[0].relpath / "result.json").write_text('{"status": "done", "final_cost": "low"}')
    assert main(["sweep", str(sweep_file), "--out", str(out), "--workers", "1"]) == 2
    assert name in _error(capsys)


@pytest.mark.parametrize("name", ["result.json", "trial.json", "progress.json"])
def test_a_100k_deep_trial_record_reads_as_absent_and_never_raises(tmp_path, name):
    from soc_opt.sweeps.runner import prepare_out
    from soc_opt.sweeps.spec import load_sweep, read_json

    spec = load_sweep(SWEEP)
    out = tmp_path / "sweep"
    prepare_out(spec, out)
    path = out / spec.trials[0].relpath / name
    path.write_text('{"status": "done", "x": ' + DEEP + "}")
    assert read_json(path) is None
    states = prepare_out(spec, out)  # the trial is pending: run again, its record rewritten
    assert states[spec.trials[0].id] == "pending"


@pytest.mark.parametrize("kind", ["shape 10^30", "a member that is not a .npy array"])
def test_a_state_file_with_an_impossible_layout_or_foreign_member_is_refused_naming_it(finished, tmp_path, capsys, kind):
    import zipfile

    d = _unfinished(finished, tmp_path)
    if kind == "shape 10^30":
        def edit(tree):
            tree["state"]["fields"]["policy"]["fields"]["K"]["shape"] = [10**30, 1]
        _rewrite(d / "checkpoint.npz", edit)
    else:
        with zipfile.ZipFile(d / "checkpoint.npz", "a") as zf:
            zf.writestr("readme.txt", "hello")
    assert main(["run", "linear2d", *ARGS, "--out", str(d)]) == 2
    err = _error(capsys)
    assert "checkpoint.npz" in err and ("invalid shape" if kind == "shape 10^30" else "readme.txt") in err
