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
