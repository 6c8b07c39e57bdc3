"""Adding a method or a noise estimator is one new file plus one registry entry (docs/architecture.md):
the toy ones of tests/toy_method.py and tests/toy_estimator.py run through the ordinary drivers."""

import csv

import numpy as np
import pytest

from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.methods import registry
from soc_opt.methods.config import DPSOCConfig, LQRFLMConfig
from soc_opt.noise import aware
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.strategy import resolve


@pytest.fixture
def toy_method(monkeypatch):
    from toy_method import ELITE_MEAN

    monkeypatch.setitem(registry.METHODS, ELITE_MEAN.name, ELITE_MEAN)  # the one registry entry
    return ELITE_MEAN


@pytest.fixture
def toy_estimator(monkeypatch):
    monkeypatch.setitem(aware.ESTIMATORS, "median", "toy_estimator:MedianState")  # the one registry entry
    from toy_estimator import MedianState

    MedianState.calls.clear()
    return MedianState


def test_a_registered_toy_method_runs_two_iterations_in_a_run_directory(toy_method, linear2d_short, tmp_path):
    cfg = load_run_config("linear2d", overrides={"iterations": 2, "samples": 6}, method=toy_method.name)
    lines = []
    state = run_experiment(linear2d_short, toy_method.name, cfg, 3, tmp_path / "run", progress=lines.append)
    assert state.iteration == 2 and len(state.history) == 2
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    assert [int(r["iteration"]) for r in rows] == [0, 1]
    assert lines and all(line.startswith("[elite-mean seed 3]") for line in lines)
    # the feed-forward moved to the elite mean; the gains did not change
    np.testing.assert_array_equal(state.policy.K, linear2d_short.initial_policy(cfg.baseline.init_var).K)
    assert not np.allclose(state.policy.k, linear2d_short.initial_policy(cfg.baseline.init_var).k)
    # resuming a finished run is a no-op with the same result
    again = run_experiment(linear2d_short, toy_method.name, cfg, 3, tmp_path / "run")
    np.testing.assert_array_equal(again.policy.k, state.policy.k)


def test_a_registered_toy_estimator_drives_two_lqr_flm_iterations(toy_estimator, linear2d_short):
    noise = NoiseConfig(estimator="median")  # accepted: the name is in the table
    cfg = DPSOCConfig(baseline=LQRFLMConfig(iterations=2, samples=6, noise=noise))
    strategy = resolve(linear2d_short, noise)
    assert isinstance(strategy, toy_estimator)
    state = registry.run(linear2d_short, "lqr-flm", cfg, seed=1)
    assert state.iteration == 2 and len(toy_estimator.calls) == 2
    np.testing.assert_array_equal(toy_estimator.calls[-1], np.median(state.last_rollouts.s, axis=0))
    paper = registry.run(linear2d_short, "lqr-flm", cfg.replace(baseline=cfg.baseline.replace(noise=NoiseConfig())),
                         seed=1)
    assert not np.array_equal(paper.policy.k, state.policy.k)  # the expansion point made a difference


def test_an_unregistered_name_is_refused_naming_the_known_ones():
    with pytest.raises(ValueError, match="estimator"):
        NoiseConfig(estimator="median")
    with pytest.raises(ValueError, match="unknown method 'elite-mean'"):
        registry.get_method("elite-mean")
