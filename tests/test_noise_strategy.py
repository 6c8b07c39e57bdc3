"""Tests for soc_opt/noise_strategy.py: ``[baseline.noise]`` resolved to one strategy per run."""

import numpy as np
import pytest

from soc_opt.config import ConfigError
from soc_opt.learning.fit import FitConfig
from soc_opt.noise import aware as noise_aware
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.estimator import FilteredPolicy
from soc_opt.noise.strategy import Estimates, KalmanEstimator, MeasuredState, resolve, strategy_class
from soc_opt.tasks import load_task


@pytest.fixture(scope="module")
def sampled():
    task = load_task("linear2d", overrides={"T": 8})
    rng = np.random.default_rng(3)
    pol = task.initial_policy(1.0)
    ro = task.rollouts(pol, 12, rng)
    return task, pol, ro


def test_resolve_gives_one_object_per_task_and_configuration(sampled):
    task = sampled[0]
    a = resolve(task, NoiseConfig())
    assert a is resolve(task, NoiseConfig())
    assert isinstance(a, MeasuredState)
    assert isinstance(resolve(task, NoiseConfig(estimator="kalman")), KalmanEstimator)
    assert resolve(load_task("linear2d", overrides={"T": 8}), NoiseConfig()) is not a


def test_every_registered_estimator_resolves_to_its_class():
    for name in noise_aware.ESTIMATORS:
        assert strategy_class(name).name == name
    with pytest.raises(ConfigError, match="estimator"):
        strategy_class("nope")


def test_paper_strategy_is_the_plain_fit_and_model(sampled):
    from soc_opt.learning import fit

    task, pol, ro = sampled
    s = resolve(task, NoiseConfig())
    cfg = FitConfig(prior="none")
    est = s.estimate(None, ro, cfg, pol, np.random.default_rng(0))
    assert est == Estimates() and est.data(ro) is ro
    dyn = s.fit(ro, cfg, est, pol)
    ref = fit.fit_dynamics(ro, cfg, None)
    np.testing.assert_array_equal(dyn.A, ref.A)
    np.testing.assert_array_equal(s.expansion_point(ro, dyn), ro.s.mean(axis=0))
    cost = task.cost_expansion(ro.s.mean(axis=0), ro.a.mean(axis=0))
    local, wrap = s.lqg_model(dyn, cost, est)
    np.testing.assert_array_equal(local.mu0, task.mu0)
    np.testing.assert_array_equal(local.P0, task.P0)
    assert wrap(pol) is pol and s.gains(pol) is pol


def test_kalman_strategy_wraps_the_policy_with_the_filter_of_the_fit(sampled):
    task, pol, ro = sampled
    s = resolve(task, NoiseConfig(estimator="kalman"))
    dyn = s.fit(ro, FitConfig(prior="none"), Estimates(), pol)
    cost = task.cost_expansion(ro.s.mean(axis=0), ro.a.mean(axis=0))
    local, wrap = s.lqg_model(dyn, cost, Estimates())
    wrapped = wrap(pol)
    assert isinstance(wrapped, FilteredPolicy) and wrapped.policy is pol
    kf = noise_aware.loop_filter(dyn, noise_aware.noise_model(task), s.cfg)
    np.testing.assert_array_equal(wrapped.filter.G, kf.G)
    assert s.gains(wrapped) is pol
