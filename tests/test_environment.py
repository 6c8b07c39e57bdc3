"""The environment recorded in a run directory (soc_opt/experiments/environment.py): what it holds,
how differences are listed, and that a run resumed in another environment says so."""

import json
import subprocess
import sys

import numpy as np

from soc_opt.experiments.environment import environment, environment_differences
from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.tasks import load_task


def test_the_record_names_the_versions_this_process_runs():
    import mujoco
    import scipy

    env = environment()
    assert env["packages"]["numpy"] == np.__version__
    assert env["packages"]["scipy"] == scipy.__version__
    assert env["packages"]["mujoco"] == mujoco.__version__
    assert env["python"].count(".") == 2
    assert json.loads(json.dumps(env)) == env                     # stored as JSON as is


def test_the_record_names_the_path_of_the_compiled_kernels(monkeypatch):
    """``kernels``: ``numba <version>`` when the compiled kernels run, ``numpy`` otherwise
    (soc_opt.compiled); a run resumed on the other path says so, like any other difference."""
    from soc_opt import compiled

    monkeypatch.setenv(compiled.ENV, "numpy")
    env = environment()
    assert env["kernels"].startswith("numpy")
    if compiled.available():
        monkeypatch.setenv(compiled.ENV, "numba")
        assert environment()["kernels"].startswith("numba ")
        assert any(d.startswith("kernels: numpy") for d in environment_differences(env, environment()))


def test_the_blas_record_does_not_depend_on_what_else_the_process_imported():
    """cvxpy loads SCS, whose wheel bundles a BLAS of its own; a run that never solves with CVXPY does not
    import it, so two processes of one run (a sweep's worker, the resume) may differ in that alone.  The
    record names numpy's and scipy's BLAS, before and after."""
    code = ("import json; from soc_opt.experiments.environment import environment; a = environment()['blas']; "
            "import cvxpy; print(json.dumps([a, environment()['blas']]))")
    before, after = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                              check=True).stdout)
    assert before == after and before


def test_differences_list_each_changed_entry_and_nothing_for_an_old_record():
    env = environment()
    other = json.loads(json.dumps(env))
    other["packages"]["mujoco"] = "0.0.1"
    other["blas"] = ["OpenBLAS 0.0 Prescott"]
    diffs = environment_differences(other, env)
    assert sorted(d.split(":")[0] for d in diffs) == ["blas", "mujoco"]
    assert f"mujoco: 0.0.1 -> {env['packages']['mujoco']}" in diffs
    assert environment_differences(env, env) == []
    assert environment_differences(None, env) == []               # a run from before the record
    odd = environment_differences({"packages": [1, 2], "blas": 5}, env)   # hand-edited: read, not raised on
    assert [d.split(":")[0] for d in odd] == ["blas", "packages"]


def test_a_run_records_its_environment_and_a_resume_elsewhere_says_so(tmp_path):
    task = load_task("linear2d")
    cfg = load_run_config("linear2d", method="lqr-flm", overrides={"iterations": 3, "samples": 4})

    def resumed(out, mujoco_version=None):
        """Notes printed when the run in ``out`` resumes from the checkpoint before its last."""
        first = run_experiment(task, "lqr-flm", cfg, 0, out)
        meta = json.loads((out / "config.json").read_text())
        assert meta["environment"] == environment()
        if mujoco_version is not None:
            meta["environment"]["packages"]["mujoco"] = mujoco_version
            (out / "config.json").write_text(json.dumps(meta))
        lines = []
        st = run_experiment(task, "lqr-flm", cfg, 0, out, progress=lines.append, previous_checkpoint=True)
        assert any("resuming" in str(x) for x in lines)
        np.testing.assert_array_equal(st.policy.K, first.policy.K)
        return [str(x) for x in lines if "another environment" in str(x)]

    assert resumed(tmp_path / "here") == []
    notes = resumed(tmp_path / "elsewhere", "0.0.1")
    assert len(notes) == 1 and "mujoco: 0.0.1 -> " in notes[0]
