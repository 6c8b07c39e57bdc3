"""Errors in variables (soc_opt/noise/eiv.py, docs/math.md §13.1): a linear plant without process noise,
sensor noise only.  The oracle is the plant itself (its ``A, B`` and ``W = 0``)."""

import numpy as np
import pytest

from soc_opt.config import ConfigError
from soc_opt.learning import fit
from soc_opt.models import LinearGaussianDynamics, LinearGaussianPolicy
from soc_opt.noise.aware import NoiseConfig, loop_filter, noise_model
from soc_opt.noise.eiv import eiv_fit
from soc_opt.noise.estimator import FilteredPolicy
from soc_opt.noise.strategy import resolve
from soc_opt.tasks import load_task

PLANT = """
name = "eiv_plant"
kind = "linear"
T = 8
rho2 = 0.1
[linear]
system = "matrices"
A = [[0.9, 0.3, 0.0], [-0.3, 0.9, 0.1], [0.0, -0.1, 0.95]]
B = [[1.0, 0.2, 0.0], [0.0, 0.8, 0.3], [0.1, 0.0, 1.2]]
process_var = 0.0
x0 = [1.0, -0.5, 0.2]
[[cost]]
type = "quadratic"
target = [0.0, 0.0, 0.0]
Qs = 1.0
Qa = 0.1
"""


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """The plant, and 1000 rollouts of a feedback policy acting on a Kalman filter of it (so the
    actions are correlated with the sensor noise: the least-squares ``B`` is biased too)."""
    path = tmp_path_factory.mktemp("eiv") / "plant.toml"
    path.write_text(PLANT)
    task = load_task(path)
    T, n, m = task.T, task.n, task.m
    A, B = np.broadcast_to(task.A, (T, n, n)).copy(), np.broadcast_to(task.B, (T, n, m)).copy()
    true = LinearGaussianDynamics(A, B, np.zeros((T, n)), np.broadcast_to(1e-6 * np.eye(n), (T, n, n)).copy())
    noise = noise_model(task)
    kf = loop_filter(true, noise, NoiseConfig(estimator="kalman"))
    gains = LinearGaussianPolicy(np.broadcast_to(-0.4 * task.B.T, (T, m, n)).copy(), np.zeros((T, m)),
                                 np.broadcast_to(np.eye(m), (T, m, m)).copy())
    sampler = FilteredPolicy(gains, kf)
    rollouts = task.rollouts(sampler, 1000, np.random.default_rng(1))
    return task, true, noise, sampler, rollouts


def _b_error(model, true) -> float:
    """Mean over steps of ``||B_k - B||_F / ||B||_F``."""
    return float(np.mean(np.linalg.norm(model.B - true.B, axis=(1, 2)) / np.linalg.norm(true.B, axis=(1, 2))))


def _w_ratio(model, noise) -> float:
    """Mean over steps of ``tr W_k / tr R``."""
    return float(np.mean(np.trace(model.cov, axis1=1, axis2=2)) / np.trace(noise.R))


def test_eiv_fit_attributes_the_sensor_noise_to_the_sensor(plant):
    task, true, noise, _, ro = plant
    ls = fit.fit_dynamics(ro, fit.FitConfig(prior="none"))
    eiv = eiv_fit(ro, ls, noise.R, noise.mu0, noise.P0).model
    # least squares believes in process noise that is sensor noise (about R + A R A^T) and is off in B
    assert _w_ratio(ls, noise) > 1.0
    assert _b_error(ls, true) > 0.035
    # the latent-state fit puts it back on the sensor: B within a few percent, W near zero
    assert _b_error(eiv, true) < 0.025
    assert _w_ratio(eiv, noise) < 0.02


@pytest.mark.parametrize("correction, b_max, w_max", [("eiv", 0.025, 0.02)])
def test_loop_fit_with_latent_states_recovers_the_plant(plant, correction, b_max, w_max):
    """Through the loop's learner (mixture prior, NIW posterior) with ``fit_correction = "eiv"``; the paper's
    fit and the shorter ``"ssm_em"`` are measured beside it and miss ``W`` (the property that fails on them)."""
    task, true, noise, sampler, ro = plant
    fc = fit.FitConfig()
    models = {}
    for corr in ("none", "ssm_em", correction):
        strategy = resolve(task, NoiseConfig(estimator="kalman", fit_correction=corr))
        est = strategy.estimate(None, ro, fc, sampler, np.random.default_rng(0))
        models[corr] = strategy.fit(ro, fc, est, sampler)
    assert _b_error(models[correction], true) < b_max
    assert _w_ratio(models[correction], noise) < w_max
    assert _w_ratio(models["none"], noise) > 1.0
    assert _w_ratio(models["ssm_em"], noise) > 2 * w_max  # 20 plain EM iterations stop far from W = 0


def test_eiv_loglik_never_decreases_and_squarem_gets_further_than_plain_em(plant):
    _, _, noise, _, ro = plant
    ls = fit.fit_dynamics(ro, fit.FitConfig(prior="none"))
    fast = eiv_fit(ro, ls, noise.R, noise.mu0, noise.P0, max_iter=30, tol=0.0)
    slow = eiv_fit(ro, ls, noise.R, noise.mu0, noise.P0, max_iter=30, tol=0.0, accelerate=False)
    for res in (fast, slow):
        assert np.all(np.diff(res.loglik) >= -1e-9 * np.abs(res.loglik[1:]))
    assert fast.loglik[-1] > slow.loglik[-1]
    # both move towards the same maximiser: plain EM given many more E-steps ends next to SQUAREM's point
    long = eiv_fit(ro, ls, noise.R, noise.mu0, noise.P0, max_iter=300, tol=0.0, accelerate=False)
    assert abs(long.loglik[-1] - fast.loglik[-1]) < abs(slow.loglik[-1] - fast.loglik[-1])


def test_eiv_is_the_least_squares_fit_when_the_sensor_is_exact(plant):
    """``R -> 0``: the states are the measurements and maximum likelihood is least squares."""
    task, true, _, _, ro = plant
    exact = ro.__class__(x=ro.x, s=ro.x, a=ro.a, cost=ro.cost, y=ro.y)
    ls = fit.fit_dynamics(exact, fit.FitConfig(prior="none", reg=1e-12))
    R = 1e-10 * np.eye(task.n)
    eiv = eiv_fit(exact, ls, R, np.asarray(task.x0, float), 1e-10 * np.eye(task.n), reg=1e-12).model
    np.testing.assert_allclose(eiv.B[1:], ls.B[1:], atol=1e-4)
    np.testing.assert_allclose(eiv.B[1:], true.B[1:], atol=1e-4)


def test_kinematic_estimator_takes_eiv_and_refuses_the_other_corrections():
    NoiseConfig(estimator="kinematic", fit_correction="eiv")
    for corr in ("moments", "ssm_em"):
        with pytest.raises(ConfigError, match="fit_correction"):
            NoiseConfig(estimator="kinematic", fit_correction=corr)


def test_eiv_does_not_pool_over_time():
    with pytest.raises(ConfigError, match="time_window"):
        NoiseConfig(estimator="kalman", fit_correction="eiv", time_window=2)
