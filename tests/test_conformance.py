"""The conformance checks (soc_opt/conformance.py): every built-in method and estimator passes them, so do
the toy plug-ins of tests/ (``toy_method``, ``toy_estimator`` and ``toy_hill``, the last written from
docs/architecture.md alone), and a plug-in that breaks a rule fails naming it."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from soc_opt import plugins
from soc_opt.conformance import check_estimator, check_method
from soc_opt.methods import registry

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def hill(monkeypatch):
    from toy_hill import HILL

    monkeypatch.setitem(plugins.METHODS, HILL.name, HILL)  # the one registration line
    return HILL


@pytest.mark.parametrize("name", ["lqr-flm", "dpsoc-em", "ilqg"])
def test_every_built_in_method_passes_the_conformance_check(name):
    check_method(plugins.METHODS.lookup(name))


@pytest.mark.parametrize("name", ["none", "kalman"])
def test_the_built_in_estimators_for_any_task_pass_the_conformance_check(name):
    check_estimator(plugins.ESTIMATORS.lookup(name))


@pytest.mark.slow
def test_the_kinematic_estimator_passes_the_conformance_check_on_the_peg():
    from soc_opt.tasks import load_task

    check_estimator(plugins.ESTIMATORS.lookup("kinematic"), task=load_task("peg", overrides={"T": 10, "rho2": 0.1}))


def test_the_toy_plugins_pass_the_conformance_check(hill, monkeypatch):
    from toy_estimator import QuantileConfig, QuantileState
    from toy_method import SHOOT

    monkeypatch.setitem(plugins.METHODS, SHOOT.name, SHOOT)
    monkeypatch.setitem(plugins.ESTIMATORS, QuantileState.name, QuantileState)
    check_method(hill)
    check_method(SHOOT)
    check_estimator(QuantileState, options=QuantileConfig(q=0.25))


def test_a_method_that_keeps_its_random_state_outside_its_state_fails_naming_the_rng(monkeypatch):
    from toy_hill import Hill

    class Leaky(Hill):
        """Hill, but each iteration also moves the feed-forward by a draw of a generator its state does not hold."""

        name = "leaky"
        sections = ("leaky",)
        rng = None

        def iterate(self, task, cfg, state):
            self.rng = np.random.default_rng(0) if self.rng is None else self.rng
            st = super().iterate(task, cfg, state)
            pol = st.policy
            return dataclasses.replace(st, policy=dataclasses.replace(pol, k=pol.k + self.rng.standard_normal(pol.k.shape)))

    leaky = Leaky()
    monkeypatch.setitem(plugins.METHODS, leaky.name, leaky)
    with pytest.raises(AssertionError, match="from a checkpoint of its state gives another policy"):
        check_method(leaky)


def test_a_plugin_is_checked_by_the_one_registration_api_whichever_way_it_is_added(monkeypatch):
    class NotAMethod:
        name = "broken"
        settings = None
        state_types = ()

    with pytest.raises(TypeError, match="Method protocol.*missing"):
        plugins.METHODS.register(NotAMethod())
    with pytest.raises(TypeError, match="Method protocol"):
        monkeypatch.setitem(plugins.METHODS, "broken", NotAMethod())
    with pytest.raises(TypeError, match="NoiseStrategy"):
        plugins.ESTIMATORS.register(NotAMethod)
    assert "broken" not in plugins.METHODS and "broken" not in plugins.ESTIMATORS
    assert registry.register == plugins.METHODS.register and registry.get_method == plugins.METHODS.lookup


_SCRIPT = """
import sys
from soc_opt.plugins import METHODS
from toy_hill import HILL
METHODS.register(HILL)  # the one registration line, from a script
from soc_opt import cli
from soc_opt.sweeps.spec import sweep_from_dict
spec = sweep_from_dict({"tasks": ["linear2d"], "methods": ["hill"], "seeds": 1, "common": {"task": {"T": 8}}},
                       base_dir=sys.argv[1])
print("sweep:", sorted({t.method for t in spec.trials}))
try:
    cli.main(["run", "--help"])
except SystemExit:
    pass
sys.exit(cli.main(["run", "linear2d", "--method", "hill", "--samples", "3", "--out", sys.argv[2]]))
"""


def test_a_method_registered_from_a_script_is_listed_by_the_cli_and_sweeps_and_refuses_a_flag_it_does_not_read(tmp_path):
    env = {"PYTHONPATH": str(ROOT / "tests"), "PATH": "/usr/bin:/bin"}
    res = subprocess.run([sys.executable, "-c", _SCRIPT, str(tmp_path), str(tmp_path / "run")], capture_output=True,
                         text=True, env=env, cwd=tmp_path, timeout=300)
    assert "sweep: ['hill']" in res.stdout, res.stderr
    assert "hill" in res.stdout.split("--method")[1].split("\n")[0], res.stdout  # the choices of --method
    assert res.returncode == 2 and "--samples does not apply to --method hill (it reads --iterations" in res.stderr
    assert not (tmp_path / "run").exists()


def test_the_toy_method_s_rows_have_no_kl_columns_and_its_final_evaluation_is_its_own(hill, tmp_path):
    from soc_opt.cli import main

    out = tmp_path / "run"
    toml = tmp_path / "hill.toml"
    toml.write_text("[hill]\nsamples = 3\n")
    assert main(["run", "linear2d", "--method", "hill", "--iterations", "2", "--config", str(toml), "--out", str(out)]) == 0
    header = (out / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "cost_mean" in header and not {"kl", "nu", "mult"} & set(header)
    rows = json.loads((out / "metrics.json").read_text())
    assert [r["iteration"] for r in rows] == [0, 1]
    with np.load(out / "final_eval.npz") as z:
        assert z["x"].shape[0] == 3  # [hill] samples, not [baseline]'s
