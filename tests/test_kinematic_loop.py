"""The kinematic estimator in the loop (soc_opt/noise/kinematic/loop.py; its wiring in
soc_opt/algorithms.py and the [baseline.noise] knob, docs/math.md §11.3)."""

import numpy as np
import pytest

from soc_opt.algorithms import DPSOCConfig, LQRFLMConfig, run_algorithm
from soc_opt.config import ConfigError
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
from soc_opt.tasks import load_task


def test_config_selects_the_kinematic_estimator_and_names_conflicts():
    cfg = NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"segments": 20, "em_iters": 3}})
    assert cfg.kinematic.segments == 20 and cfg.kinematic.em_iters == 3 and not cfg.paper
    with pytest.raises(ConfigError, match="fit_correction = 'ssm_em'"):
        NoiseConfig.from_dict({"estimator": "kinematic", "fit_correction": "ssm_em"})
    with pytest.raises(ConfigError, match="segments"):
        NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"segments": 0}})
    with pytest.raises(ConfigError, match="unknown config key"):
        NoiseConfig.from_dict({"kinematic": {"segmnts": 3}})


def test_at_zero_noise_the_kinematic_loop_is_the_paper_loop():
    """rho^2 = 0: smoothed states = measured, filter = identity, same start: the paper's iterations."""
    task = load_task("peg", overrides={"rho2": 0.0, "T": 30})
    base = LQRFLMConfig(iterations=2, samples=6, init_var=1.0)
    paper = run_algorithm(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=1)
    kin = run_algorithm(task, "lqr-flm", DPSOCConfig(baseline=base.replace(noise=NoiseConfig(estimator="kinematic")),
                                                      i_switch=0), seed=1)
    assert isinstance(kin.policy, KinematicFilteredPolicy)
    np.testing.assert_array_equal(kin.policy.policy.K, paper.policy.K)
    np.testing.assert_array_equal(kin.policy.policy.k, paper.policy.k)
    for a, b in zip(kin.history, paper.history):
        np.testing.assert_array_equal(a.cost, b.cost)


def test_dpsoc_em_with_the_kinematic_estimator_returns_a_filtered_em_policy():
    task = load_task("peg", overrides={"T": 30})
    base = LQRFLMConfig(iterations=2, samples=8, init_var=1.0, noise=NoiseConfig(estimator="kinematic"))
    st = run_algorithm(task, "dpsoc-em", DPSOCConfig(baseline=base, i_switch=1), seed=0)
    phases = [r.phase for r in st.history]
    assert "em" in phases
    assert isinstance(st.policy, KinematicFilteredPolicy)
    em_rec = st.history[phases.index("em")]
    assert "estimator" in em_rec.timings and np.isfinite(em_rec.em.loglik_new)
    ro = task.rollouts(st.policy, 2, np.random.default_rng(0))
    assert np.isfinite(ro.x).all()


def test_innovation_kl_model_runs_the_kl_step_on_the_innovation_form():
    task = load_task("peg", overrides={"T": 30})
    noise = NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"kl_model": "innovation"}})
    base = LQRFLMConfig(iterations=2, samples=8, init_var=1.0, noise=noise)
    st = run_algorithm(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=0)
    assert isinstance(st.policy, KinematicFilteredPolicy)
    # the innovation form's initial distribution is that of the estimate, not the known start
    assert not np.allclose(st.prev.model.P0, 1e-6 * np.eye(task.n))
    with pytest.raises(ConfigError, match="kl_model"):
        NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"kl_model": "lqg"}})



def test_the_kinematic_strategy_keeps_no_per_iteration_state():
    """The batch's smoothed rollouts and filter travel in the Estimates and the run state, not on the
    (memoised, run-wide) strategy object: iterating leaves its attributes as resolved."""
    from soc_opt.noise.kinematic_strategy import KinematicEstimator
    from soc_opt.noise.strategy import resolve

    task = load_task("peg", overrides={"T": 30})
    noise = NoiseConfig(estimator="kinematic")
    strategy = resolve(task, noise)
    assert isinstance(strategy, KinematicEstimator)
    base = LQRFLMConfig(iterations=2, samples=6, init_var=1.0, noise=noise)
    st = run_algorithm(task, "dpsoc-em", DPSOCConfig(baseline=base, i_switch=1), seed=0)
    assert isinstance(st.policy, KinematicFilteredPolicy)
    assert resolve(task, noise) is strategy
    assert set(vars(strategy)) == {"task", "cfg", "_noise"}
    assert strategy.task is task and strategy.cfg is noise


def test_fit_filter_acts_on_the_kalman_filter_of_the_smoothed_state_fit():
    """``filter = "fit"``: the learner still fits on the kinematic smoother's states, but the policy acts
    on the §10.2 Kalman filter of that fit (a plain FilteredPolicy, not the structured EKF), for both
    methods; the KL step runs on the innovation form (its start is the estimate's, not the known one)."""
    from soc_opt.noise.estimator import FilteredPolicy, KalmanFilter

    task = load_task("peg", overrides={"T": 30})
    noise = NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"filter": "fit"}})
    base = LQRFLMConfig(iterations=2, samples=8, init_var=1.0, noise=noise)
    for method, i_switch in (("lqr-flm", 0), ("dpsoc-em", 1)):
        st = run_algorithm(task, method, DPSOCConfig(baseline=base, i_switch=i_switch), seed=0)
        assert type(st.policy) is FilteredPolicy and isinstance(st.policy.filter, KalmanFilter)
        assert (st.policy.filter.T, st.policy.filter.n, st.policy.filter.m) == (30, task.n, task.m)
        assert not np.allclose(st.prev.model.P0, 1e-6 * np.eye(task.n))
        ro = task.rollouts(st.policy, 2, np.random.default_rng(0))
        assert np.isfinite(ro.x).all()
    with pytest.raises(ConfigError, match="filter"):
        NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"filter": "ekf"}})


def test_structured_dynamics_gives_gains_on_the_joint_state_only():
    """``dynamics = "structured"``: the KL step's model ignores the site columns of x, so from the
    initial policy (no gains) the new gains act on zhat alone; the KL step ran on that model."""
    task = load_task("peg", overrides={"T": 30})
    noise = NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"dynamics": "structured"}})
    base = LQRFLMConfig(iterations=2, samples=8, init_var=1.0, noise=noise)
    st = run_algorithm(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=0)
    zidx = st.policy.filter.zidx
    sites = np.setdiff1d(np.arange(task.n), zidx)
    K = st.policy.policy.K
    assert np.abs(K[:, :, zidx]).max() > 0.0
    np.testing.assert_allclose(K[:, :, sites], 0.0, atol=1e-9 * np.abs(K).max())
    np.testing.assert_array_equal(st.prev.model.dynamics.A[:, :, sites], 0.0)


def test_posterior_moments_change_the_fit_not_the_zero_noise_loop():
    """``fit_moments = "posterior"`` is a different fit at rho^2 > 0 and the paper's loop at rho^2 = 0."""
    noise = NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"fit_moments": "posterior"}})
    plain = NoiseConfig.from_dict({"estimator": "kinematic", "kinematic": {"fit_moments": "means"}})
    for rho2, same in ((0.0, True), (0.1, False)):
        task = load_task("peg", overrides={"rho2": rho2, "T": 30})
        runs = [run_algorithm(task, "lqr-flm", DPSOCConfig(baseline=LQRFLMConfig(iterations=2, samples=8, init_var=1.0,
                                                                                   noise=nc), i_switch=0), seed=1)
                for nc in (noise, plain)]
        assert np.array_equal(runs[0].policy.policy.K, runs[1].policy.policy.K) == same
