"""The kinematic estimator in the loop (soc_opt/noise/kinematic/loop.py; its wiring in
soc_opt/algorithms.py and the [baseline.noise] knob, docs/math.md §11.3)."""

import dataclasses

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


def test_cold_start_smoothing_does_not_depend_on_the_sampling_policys_map():
    """``warm_start = false``: EM starts from the data's own initial map, so the smoothed states of a
    batch are the same whichever filter drew it; warm-started (alone), they depend on its map."""
    from soc_opt.noise.kinematic import loop
    from soc_opt.noise.kinematic.config import KinematicConfig

    task = load_task("peg", overrides={"rho2": 0.1, "T": 30})
    pol = task.initial_policy(0.5)
    first = task.rollouts(pol, 6, np.random.default_rng(0))
    _, filt, _ = loop.learn(task, first, pol, KinematicConfig())
    batch = task.rollouts(pol, 6, np.random.default_rng(1))
    with_map = KinematicFilteredPolicy(pol, filt)
    for warm, same in ((False, True), (True, False)):
        cfg = KinematicConfig(warm_start=warm, restart_from_data=False)
        a, _, _ = loop.learn(task, batch, with_map, cfg)
        b, _, _ = loop.learn(task, batch, pol, cfg)
        assert np.array_equal(a.s, b.s) == same


def test_restart_keeps_the_em_start_with_the_higher_likelihood():
    """``restart_from_data`` (default): EM from the sampler's map and from the data's own map, the run
    with the higher final ``log p(s | a)`` kept, whichever it is."""
    from soc_opt.noise.kinematic import em, loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.model import AccelMap, KinematicModel

    task = load_task("peg", overrides={"rho2": 0.1, "T": 30})
    km = KinematicModel(task)
    pol = task.initial_policy(0.5)
    batch = task.rollouts(pol, 6, np.random.default_rng(1))
    _, filt, _ = loop.learn(task, task.rollouts(pol, 6, np.random.default_rng(0)), pol, KinematicConfig())
    good = filt.accel()
    # a poor start: the learned map with its torque response reversed and its noise 100 times smaller
    bad = AccelMap(-good.B, good.D, good.c, 0.01 * good.S)
    cfg = KinematicConfig()
    assert cfg.warm_start and cfg.restart_from_data
    cold = em.fit(km, batch.s, batch.a, 0.1, cfg, None)
    picked = set()
    for accel in (good, bad):
        sampler = KinematicFilteredPolicy(pol, dataclasses.replace(filt, accel_B=accel.B, accel_D=accel.D,
                                                                   accel_c=accel.c, accel_S=accel.S))
        warm = em.fit(km, batch.s, batch.a, 0.1, cfg, sampler.filter.accel())
        best = warm if warm.loglik[-1] > cold.loglik[-1] else cold
        got, _, diag = loop.learn(task, batch, sampler, cfg)
        np.testing.assert_array_equal(got.s, km.measure(best.smoothed.mean, False))
        assert diag["kin_loglik_last"] == max(warm.loglik[-1], cold.loglik[-1])
        picked.add(diag["kin_start"])
    assert picked == {"sampler", "data"}  # the test exercises both outcomes
