"""Adding a method or a noise estimator, with its own settings and saved state, is one new file plus one
registry line (docs/architecture.md, "How to add"): the toy ones of tests/toy_method.py and
tests/toy_estimator.py load their own TOML tables, run through the ordinary drivers, checkpoint, and
resume in a new process to the same end as an uninterrupted run."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from soc_opt import plugins
from soc_opt.config import ConfigError
from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.experiments.statefile import decode_state
from soc_opt.methods import registry
from soc_opt.methods.config import DPSOCConfig, LQRFLMConfig
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.strategy import resolve

ROOT = Path(__file__).resolve().parents[1]
TASK = {"T": 8}  # linear2d_short

SHOOT_TOML = """
[shoot]
iterations = 4
samples = 6
elite = 0.34
step = 0.8
"""
QUANTILE_TOML = """
[baseline]
iterations = 4
samples = 6
[baseline.noise]
estimator = "quantile"
[baseline.noise.quantile]
q = 0.25
"""


@pytest.fixture
def toy_method(monkeypatch):
    from toy_method import SHOOT

    monkeypatch.setitem(plugins.METHODS, SHOOT.name, SHOOT)  # the one registry line
    return SHOOT


@pytest.fixture
def toy_estimator(monkeypatch):
    from toy_estimator import QuantileState

    monkeypatch.setitem(plugins.ESTIMATORS, QuantileState.name, QuantileState)  # the one registry line
    QuantileState.calls.clear()
    return QuantileState


def test_a_plugins_own_table_is_refused_until_it_is_registered_then_loads_with_its_defaults(monkeypatch):
    with pytest.raises(ConfigError, match="unknown config key 'shoot' for DPSOCConfig"):
        DPSOCConfig.from_dict({"shoot": {"elite": 0.25}})
    with pytest.raises(ConfigError, match="unknown config key 'quantile'"):
        NoiseConfig.from_dict({"estimator": "quantile", "quantile": {"q": 0.25}})
    from toy_estimator import QuantileConfig, QuantileState
    from toy_method import SHOOT, ShootConfig

    monkeypatch.setitem(plugins.METHODS, SHOOT.name, SHOOT)
    monkeypatch.setitem(plugins.ESTIMATORS, QuantileState.name, QuantileState)
    cfg = DPSOCConfig.from_dict({"shoot": {"elite": 0.25}, "baseline": {"noise": {"quantile": {"q": 0.25}}}})
    assert cfg.shoot == ShootConfig(elite=0.25) and cfg.section("shoot").samples == ShootConfig().samples
    assert cfg.baseline.noise.quantile == QuantileConfig(q=0.25)
    assert DPSOCConfig().shoot == ShootConfig()  # unset: the plug-in's documented defaults
    # checked like any table: the key and the value named, with the table's path
    with pytest.raises(ConfigError, match=r"shoot\.elite: must be in \(0, 1\], got 2.0"):
        DPSOCConfig.from_dict({"shoot": {"elite": 2.0}})
    with pytest.raises(ConfigError, match=r"unknown config key 'bogus' in \[shoot\]"):
        DPSOCConfig.from_dict({"shoot": {"bogus": 1}})
    # written back as its own table, after the core sections; equal settings compare and hash equal
    tables = list(plugins.METHODS.settings())  # every registered method's table, in registration order
    assert list(cfg.to_dict())[-len(tables):] == tables and tables[-1] == "shoot"
    assert cfg.to_dict()["shoot"]["elite"] == 0.25
    assert DPSOCConfig.from_dict(cfg.to_dict()) == cfg
    noise = cfg.baseline.noise
    assert NoiseConfig.from_dict(noise.to_dict()) == noise and hash(NoiseConfig.from_dict(noise.to_dict())) == hash(noise)
    assert cfg.replace(shoot=ShootConfig()) == DPSOCConfig(baseline=cfg.baseline)


def test_a_registered_toy_estimator_with_its_own_options_drives_two_lqr_flm_iterations(toy_estimator, linear2d_short):
    noise = NoiseConfig(estimator="quantile", quantile={"q": 0.25})  # accepted: the name is in the table
    cfg = DPSOCConfig(baseline=LQRFLMConfig(iterations=2, samples=6, noise=noise))
    assert isinstance(resolve(linear2d_short, noise), toy_estimator)
    state = registry.run(linear2d_short, "lqr-flm", cfg, seed=1)
    assert state.iteration == 2 and len(toy_estimator.calls) == 2
    np.testing.assert_array_equal(toy_estimator.calls[-1], np.quantile(state.last_rollouts.s, 0.25, axis=0))
    toy_estimator.calls.clear()  # its default option, q = 0.5: the median
    median = registry.run(linear2d_short, "lqr-flm", cfg.replace(baseline=cfg.baseline.replace(
        noise=noise.replace(quantile={"q": 0.5}))), seed=1)
    np.testing.assert_array_equal(toy_estimator.calls[-1], np.quantile(median.last_rollouts.s, 0.5, axis=0))


def test_an_unregistered_name_is_refused_naming_the_known_ones():
    with pytest.raises(ValueError, match="estimator.*'quantile'"):
        NoiseConfig(estimator="quantile")
    with pytest.raises(ValueError, match="unknown method 'shoot'"):
        registry.get_method("shoot")


class _Interrupt(Exception):
    pass


def _interrupted_after(n):
    def on_iteration(st):
        if st.iteration == n:
            raise _Interrupt

    return on_iteration


_RESUME = """
import json, sys
from soc_opt.plugins import ESTIMATORS, METHODS
from toy_estimator import QuantileState
from toy_method import SHOOT
METHODS.register(SHOOT)  # the one registry line of each plug-in
ESTIMATORS.register(QuantileState)
from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.tasks import load_task
task = load_task("linear2d", overrides=json.loads(sys.argv[1]))
for method, toml, out in json.loads(sys.argv[2]):
    state = run_experiment(task, method, load_run_config("linear2d", toml, method=method), 3, out)
    print(method, type(state).__name__, state.iteration)
"""


def test_toy_plugins_checkpoint_after_two_iterations_and_resume_in_a_new_process_to_the_uninterrupted_end(
        toy_method, toy_estimator, linear2d_short, tmp_path):
    runs = []
    for method, text in (("shoot", SHOOT_TOML), ("lqr-flm", QUANTILE_TOML)):
        toml = tmp_path / f"{method}.toml"
        toml.write_text(text)
        cfg = load_run_config("linear2d", toml, method=method)
        whole = run_experiment(linear2d_short, method, cfg, 3, tmp_path / f"{method}-whole")
        assert whole.iteration == 4
        with pytest.raises(_Interrupt):  # stopped after two iterations: the checkpoint holds them
            run_experiment(linear2d_short, method, cfg, 3, tmp_path / method, on_iteration=_interrupted_after(2))
        saved = decode_state((tmp_path / method / "checkpoint.npz").read_bytes())
        assert saved.iteration == 2
        runs.append((method, str(toml), str(tmp_path / method), whole))
    assert type(saved).__name__ == "RunState" and type(runs[0][3]).__name__ == "ShootState"
    assert len(runs[0][3].elite_costs) == 4 and toy_estimator.calls  # each plug-in ran its own code

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])}
    out = subprocess.run([sys.executable, "-c", _RESUME, json.dumps(TASK), json.dumps([r[:3] for r in runs])],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["shoot ShootState 4", "lqr-flm RunState 4"]
    for method, _, path, whole in runs:
        resumed = decode_state((Path(path) / "checkpoint.npz").read_bytes())
        assert type(resumed) is type(whole) and resumed.iteration == 4
        for a, b in ((resumed.policy.K, whole.policy.K), (resumed.policy.k, whole.policy.k),
                     (resumed.policy.cov, whole.policy.cov)):
            np.testing.assert_array_equal(a, b)  # bit for bit
        assert [list(r.cost) for r in resumed.history] == [list(r.cost) for r in whole.history]
        assert resumed.rng_state == whole.rng_state
    shoot = decode_state((Path(runs[0][2]) / "checkpoint.npz").read_bytes())
    assert shoot.elite_costs == runs[0][3].elite_costs  # the method's own state came back


def test_a_run_recorded_before_an_estimator_was_registered_still_matches_unless_it_selects_it(toy_estimator):
    """An estimator registered later adds its table to every ``[baseline.noise]``; a run directory recorded
    before compares equal (the table is not in use there), one that selects it compares its options."""
    from soc_opt.experiments.rundir import differences

    recorded = {k: v for k, v in NoiseConfig().to_dict().items() if k != "quantile"}  # as recorded before
    assert "quantile" in NoiseConfig().to_dict()
    assert differences({"noise": recorded}, {"noise": NoiseConfig().to_dict()}) == []
    selecting = {"noise": {**recorded, "estimator": "quantile"}}
    assert differences(selecting, {"noise": NoiseConfig(estimator="quantile").to_dict()}) == []  # its defaults
    changed = {"noise": NoiseConfig(estimator="quantile", quantile={"q": 0.25}).to_dict()}
    assert differences(selecting, changed) == ["noise.quantile: (unset: {\"q\": 0.5} when recorded) -> {\"q\": 0.25}"]
