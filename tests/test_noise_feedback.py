"""What the policy's gains act on under sensor noise (docs/math.md §13.2; soc_opt/noise/aware.py
``calibration``, ``calibrated_gains``, ``open_loop_gains``; ``shaped_gains`` in soc_opt/methods/lqr_flm/iteration.py)
and the acceptance test on the estimated cost (§13.3)."""

import numpy as np
import pytest

from soc_opt.config import ConfigError
from soc_opt.methods import registry
from soc_opt.methods.config import AcceptanceConfig, DPSOCConfig, LQRFLMConfig
from soc_opt.methods.lqr_flm import acceptance_cost
from soc_opt.methods.state import record
from soc_opt.models import LinearGaussianPolicy
from soc_opt.noise.aware import NoiseConfig, calibrated_gains, calibration, gains, open_loop_gains
from soc_opt.tasks import load_task


def test_calibration_is_the_identity_when_the_estimate_is_the_state():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 12, 3))
    np.testing.assert_allclose(calibration(x, x, window=2, ridge=0.0), np.broadcast_to(np.eye(3), (12, 3, 3)), atol=1e-12)


def test_calibration_recovers_the_shrinkage_of_an_estimate_with_independent_noise():
    """``xhat = x + e`` with ``e`` independent of ``x``: the regression of ``x`` on ``xhat`` is ``S (S + P)^-1``."""
    rng = np.random.default_rng(1)
    S = np.array([[1.0, 0.3], [0.3, 0.5]])
    P = np.array([[0.5, 0.0], [0.0, 2.0]])
    M, T = 4000, 6
    x = rng.multivariate_normal(np.zeros(2), S, size=(M, T))
    xhat = x + rng.multivariate_normal(np.zeros(2), P, size=(M, T))
    G = calibration(x, xhat, window=5, ridge=0.0)
    expected = S @ np.linalg.inv(S + P)
    for k in range(T):
        np.testing.assert_allclose(G[k], expected, atol=0.03)


def test_calibrated_gains_keep_the_mean_action_along_the_plan():
    rng = np.random.default_rng(2)
    T, m, n = 5, 2, 3
    pol = LinearGaussianPolicy(rng.normal(size=(T, m, n)), rng.normal(size=(T, m)), np.broadcast_to(np.eye(m), (T, m, m)).copy())
    G = rng.uniform(0.2, 0.9, size=(T + 1, n, n))
    mu = rng.normal(size=(T + 1, n))
    new = calibrated_gains(pol, G, mu)
    np.testing.assert_allclose(new.K, pol.K @ G[:-1])
    np.testing.assert_allclose(np.einsum("tij,tj->ti", new.K, mu[:-1]) + new.k,
                               np.einsum("tij,tj->ti", pol.K, mu[:-1]) + pol.k, atol=1e-12)
    np.testing.assert_array_equal(new.cov, pol.cov)


def test_open_loop_gains_have_no_feedback_and_the_plans_mean_actions():
    T, m, n = 4, 2, 3
    pol = LinearGaussianPolicy(np.ones((T, m, n)), np.zeros((T, m)), np.broadcast_to(np.eye(m), (T, m, m)).copy())
    a = np.arange(T * m, dtype=float).reshape(T, m)
    new = open_loop_gains(pol, a)
    assert not new.K.any()
    np.testing.assert_array_equal(new.k, a)
    np.testing.assert_array_equal(new.cov, pol.cov)


def test_feedback_is_a_checked_option():
    with pytest.raises(ConfigError, match="feedback"):
        NoiseConfig(feedback="partial")
    assert not NoiseConfig(feedback="open_loop").paper


def _run(task, noise, method="lqr-flm", acceptance=AcceptanceConfig(), i_switch=0, iterations=2):
    base = LQRFLMConfig(iterations=iterations, samples=8, init_var=1.0, noise=noise, acceptance=acceptance)
    return registry.run(task, method, DPSOCConfig(baseline=base, i_switch=i_switch), seed=0)


@pytest.mark.parametrize("method", ["lqr-flm", "dpsoc-em"])
def test_open_loop_feedback_samples_policies_without_gains(method):
    task = load_task("peg", overrides={"T": 30})
    st = _run(task, NoiseConfig(estimator="kinematic", feedback="open_loop"), method, i_switch=1, iterations=3)
    assert not gains(st.policy).K.any()
    assert np.isfinite(gains(st.policy).k).all()


def test_calibrated_feedback_shrinks_gains_under_noise_and_is_the_plain_loop_without_it():
    task = load_task("peg", overrides={"T": 30})
    cal = _run(task, NoiseConfig(estimator="kinematic", feedback="calibrated"))
    plain = _run(task, NoiseConfig(estimator="kinematic"))
    assert np.isfinite(gains(cal.policy).K).all()
    # the first step is taken from the same batch and model: only the gains differ, and they are smaller
    assert np.linalg.norm(gains(cal.policy).K) < np.linalg.norm(gains(plain.policy).K)
    task0 = load_task("peg", overrides={"T": 30, "rho2": 0.0})
    a = _run(task0, NoiseConfig(estimator="kinematic", feedback="calibrated"))
    b = _run(task0, NoiseConfig(estimator="kinematic"))
    np.testing.assert_array_equal(gains(a.policy).K, gains(b.policy).K)


def test_estimated_acceptance_cost_reads_the_learners_states():
    task = load_task("peg", overrides={"T": 30})
    ro = task.rollouts(task.initial_policy(), 6, np.random.default_rng(0))
    rec = record(0, "baseline", task, ro)
    learned = ro.__class__(x=ro.x, s=ro.x, a=ro.a, cost=task.cost(ro.x, ro.a), y=ro.y)
    c, se = acceptance_cost(AcceptanceConfig(cost="estimated"), rec, learned)
    total = learned.total_cost()
    assert c == pytest.approx(total.mean()) and se == pytest.approx(total.std(ddof=1) / np.sqrt(6))
    assert c != pytest.approx(acceptance_cost(AcceptanceConfig(), rec)[0])
    with pytest.raises(ValueError, match="estimated"):
        acceptance_cost(AcceptanceConfig(cost="estimated"), rec)


@pytest.mark.parametrize("method", ["lqr-flm", "dpsoc-em"])
def test_runs_judge_steps_on_the_smoothed_cost_with_the_kinematic_estimator(method):
    task = load_task("peg", overrides={"T": 30})
    st = _run(task, NoiseConfig(estimator="kinematic"), method, AcceptanceConfig(cost="estimated"), i_switch=1,
              iterations=3)
    for rec in st.history[1:]:
        if "test_cost" in rec.extra:
            # the smoothed states' cost is far below the measured one (whose noise adds about rho^2 tr C_ss)
            assert rec.extra["test_cost"] < 0.5 * float(np.mean(rec.cost_measured))
