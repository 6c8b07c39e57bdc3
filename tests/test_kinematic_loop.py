"""The kinematic estimator in the loop (soc_opt/noise/kinematic/loop.py; its wiring in
soc_opt/methods/ and the [baseline.noise] knob, docs/math.md §11.3)."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from soc_opt.config import ConfigError
from soc_opt.methods import registry
from soc_opt.methods.config import DPSOCConfig, LQRFLMConfig
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
    paper = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=1)
    kin = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base.replace(noise=NoiseConfig(estimator="kinematic")),
                                                      i_switch=0), seed=1)
    assert isinstance(kin.policy, KinematicFilteredPolicy)
    np.testing.assert_array_equal(kin.policy.policy.K, paper.policy.K)
    np.testing.assert_array_equal(kin.policy.policy.k, paper.policy.k)
    for a, b in zip(kin.history, paper.history):
        np.testing.assert_array_equal(a.cost, b.cost)


def test_dpsoc_em_with_the_kinematic_estimator_returns_a_filtered_em_policy():
    task = load_task("peg", overrides={"T": 30})
    base = LQRFLMConfig(iterations=2, samples=8, init_var=1.0, noise=NoiseConfig(estimator="kinematic"))
    st = registry.run(task, "dpsoc-em", DPSOCConfig(baseline=base, i_switch=1), seed=0)
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
    st = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=0)
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
    st = registry.run(task, "dpsoc-em", DPSOCConfig(baseline=base, i_switch=1), seed=0)
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
        st = registry.run(task, method, DPSOCConfig(baseline=base, i_switch=i_switch), seed=0)
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
    st = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=0)
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
        runs = [registry.run(task, "lqr-flm", DPSOCConfig(baseline=LQRFLMConfig(iterations=2, samples=8, init_var=1.0,
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


def test_em_loglik_of_a_fixed_map_is_the_extended_kalman_pass_likelihood():
    """``em.loglik``: the likelihood a fixed map gives a batch is the first (extended-Kalman) pass of EM
    from that map, before any M-step."""
    from soc_opt.noise.kinematic import em, loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.model import KinematicModel

    task = load_task("peg", overrides={"rho2": 0.1, "T": 30})
    km = KinematicModel(task)
    pol = task.initial_policy(0.5)
    _, filt, _ = loop.learn(task, task.rollouts(pol, 6, np.random.default_rng(0)), pol, KinematicConfig())
    batch = task.rollouts(pol, 5, np.random.default_rng(2))
    first = em.fit(km, batch.s, batch.a, 0.1, KinematicConfig(relin=0, em_iters=0), filt.accel())
    assert em.loglik(km, filt.accel(), batch.s, batch.a, 0.1, KinematicConfig()) == first.loglik[0]


def _held_out_setting():
    """A batch, its predecessor, and sampling policies whose maps are the one learned from the
    predecessor and that map with its torque response reversed and its noise 100 times smaller."""
    from soc_opt.noise.kinematic import loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.model import KinematicModel

    task = load_task("peg", overrides={"rho2": 0.1, "T": 30})
    pol = task.initial_policy(0.5)
    previous = task.rollouts(pol, 6, np.random.default_rng(0))
    _, filt, _ = loop.learn(task, previous, pol, KinematicConfig())
    good = filt.accel()
    samplers = [KinematicFilteredPolicy(pol, filt),
                KinematicFilteredPolicy(pol, dataclasses.replace(filt, accel_B=-good.B, accel_S=0.01 * good.S))]
    return task, KinematicModel(task), previous, task.rollouts(pol, 6, np.random.default_rng(1)), samplers


def test_held_out_selection_keeps_the_start_whose_map_predicts_the_previous_batch_better():
    """``start_select = "previous"``: both EM starts run on the batch as before, and the map kept is the
    one with the higher likelihood of the previous batch (held out), whichever start it came from, not
    the one with the higher likelihood of the batch itself."""
    from soc_opt.noise.kinematic import em, loop
    from soc_opt.noise.kinematic.config import KinematicConfig

    task, km, previous, batch, samplers = _held_out_setting()
    cfg = KinematicConfig(start_select="previous", filter_start="kept")
    cold = em.fit(km, batch.s, batch.a, 0.1, cfg, None)
    picked = set()
    for sampler in samplers:
        warm = em.fit(km, batch.s, batch.a, 0.1, cfg, sampler.filter.accel())
        held = [em.loglik(km, r.accel, previous.s, previous.a, 0.1, cfg) for r in (warm, cold)]
        best = warm if held[0] >= held[1] else cold
        got, filt, diag = loop.learn(task, batch, sampler, cfg, previous)
        np.testing.assert_array_equal(got.s, km.measure(best.smoothed.mean, False))
        np.testing.assert_array_equal(filt.accel_B, best.accel.B)
        assert (diag["kin_heldout_sampler"], diag["kin_heldout_data"]) == tuple(held)
        assert diag["kin_start"] == ("sampler" if best is warm else "data")
        picked.add(diag["kin_start"])
    assert picked == {"sampler", "data"}  # the test exercises both outcomes


def test_held_out_selection_without_a_previous_batch_is_the_in_sample_rule():
    """With no previous batch (the first iteration) ``start_select = "previous"`` compares the starts on
    the batch itself, as ``"batch"`` does; with one, the two rules may differ but ``"batch"`` ignores it."""
    from soc_opt.noise.kinematic import loop
    from soc_opt.noise.kinematic.config import KinematicConfig

    task, _, previous, batch, samplers = _held_out_setting()
    for sampler in samplers:
        a, _, da = loop.learn(task, batch, sampler, KinematicConfig(start_select="previous"))
        b, _, db = loop.learn(task, batch, sampler, KinematicConfig(start_select="batch"), previous)
        np.testing.assert_array_equal(a.s, b.s)
        assert da["kin_start"] == db["kin_start"] and "kin_heldout_data" not in da and "kin_heldout_data" not in db


def test_the_loop_hands_each_iteration_the_batch_its_sampler_was_learned_from():
    """LQR-FLM and DPSOC-EM (through its EM phase) pass each estimate the batch sampled just before
    (the one the sampling policy's filter was learned from; none on the first), taken from the run
    state's ``last_rollouts``, which the checkpoint carries."""
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic_strategy import KinematicEstimator

    seen = []
    orig = KinematicEstimator.estimate

    def spy(self, prior, rollouts, fit_cfg, sampler, rng, previous=None):
        seen.append((rollouts, previous))
        return orig(self, prior, rollouts, fit_cfg, sampler, rng, previous)

    task = load_task("peg", overrides={"rho2": 0.1, "T": 20})
    nc = NoiseConfig(estimator="kinematic", kinematic=KinematicConfig(start_select="previous"))
    for method, i_switch in (("lqr-flm", 0), ("dpsoc-em", 1)):
        seen.clear()
        KinematicEstimator.estimate = spy
        try:
            registry.run(task, method, DPSOCConfig(baseline=LQRFLMConfig(iterations=3, samples=5, init_var=1.0,
                                                                          noise=nc), i_switch=i_switch), seed=0)
        finally:
            KinematicEstimator.estimate = orig
        assert seen[0][1] is None
        for (before, _), (_, prev) in zip(seen, seen[1:]):
            assert prev is before
        assert len(seen) == (3 if method == "lqr-flm" else 4)


def test_filter_from_the_sampler_start_keeps_its_own_line_while_the_learner_gets_the_kept_run():
    """``filter_start = "sampler"``: the online filter is built from the EM run started at the sampling
    policy's map (its map, transition and nominal trajectory), the learner's smoothed states come from
    the run ``start_select`` kept, whichever that is; ``"kept"`` builds both from the kept run."""
    from soc_opt.noise.kinematic import em, loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.filter import build_filter

    task, km, _, batch, samplers = _held_out_setting()
    cold = em.fit(km, batch.s, batch.a, 0.1, KinematicConfig(), None)
    kept_starts = set()
    for sampler in samplers:
        warm = em.fit(km, batch.s, batch.a, 0.1, KinematicConfig(), sampler.filter.accel())
        kept = warm if warm.loglik[-1] > cold.loglik[-1] else cold
        for where, source in (("sampler", warm), ("kept", kept)):
            cfg = KinematicConfig(filter_start=where)
            got, filt, diag = loop.learn(task, batch, sampler, cfg)
            np.testing.assert_array_equal(got.s, km.measure(kept.smoothed.mean, False))
            ref = build_filter(km, source.accel, em.z_model(km, source.accel, cfg), source.smoothed.mean.mean(axis=0),
                               0.1, online=True)
            for name in ("A", "Q", "zbar", "accel_B", "accel_S", "Lm"):
                np.testing.assert_array_equal(getattr(filt, name), getattr(ref, name))
            assert diag["kin_filter_start"] == ("sampler" if where == "sampler" else diag["kin_start"])
        kept_starts.add("sampler" if kept is warm else "data")
    assert kept_starts == {"sampler", "data"}  # with the data's run kept, the two settings differ


def test_data_start_select_keeps_the_batch_start_for_the_learner_and_the_sampler_line_for_the_filter():
    """``start_select = "data"``: the learner's smoothed states are always those of EM from the batch's own
    map, whatever the likelihoods; with ``filter_start = "sampler"`` the filter is the sampler-start run's."""
    from soc_opt.noise.kinematic import em, loop
    from soc_opt.noise.kinematic.config import KinematicConfig

    task, km, _, batch, samplers = _held_out_setting()
    cfg = KinematicConfig(start_select="data")
    cold = em.fit(km, batch.s, batch.a, 0.1, cfg, None)
    for sampler in samplers:
        warm = em.fit(km, batch.s, batch.a, 0.1, cfg, sampler.filter.accel())
        got, filt, diag = loop.learn(task, batch, sampler, cfg)
        np.testing.assert_array_equal(got.s, km.measure(cold.smoothed.mean, False))
        np.testing.assert_array_equal(filt.accel_B, warm.accel.B)
        assert diag["kin_start"] == "data" and diag["kin_filter_start"] == "sampler"


def test_parallel_starts_change_nothing_but_the_wall_time():
    """``parallel_starts`` (default on) runs the data's EM start in a forked process: the smoothed
    rollouts, the filter and the diagnostics equal those of the two starts run in turn."""
    from soc_opt.noise.kinematic import loop
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.parallel import can_fork

    if not can_fork():
        pytest.skip("needs fork and two CPUs")
    task, km, _, batch, samplers = _held_out_setting()
    for sampler in samplers:
        out = [loop.learn(task, batch, sampler, KinematicConfig(parallel_starts=p)) for p in (True, False)]
        np.testing.assert_array_equal(out[0][0].s, out[1][0].s)
        for name in ("A", "Q", "zbar", "accel_B", "accel_S", "Lm", "G"):
            np.testing.assert_array_equal(getattr(out[0][1], name), getattr(out[1][1], name))
        for key in ("kin_loglik_first", "kin_loglik_last", "kin_start", "kin_filter_start"):
            assert out[0][2][key] == out[1][2][key]
        np.testing.assert_array_equal(out[0][2]["posterior"][0], out[1][2]["posterior"][0])


SLIDER = Path(__file__).parent / "data" / "slider" / "slider.toml"


def test_slide_only_object_with_constant_coordinates_runs_for_several_iterations():
    """The puck only slides: the heights and vertical velocities of both points are exactly constant and
    each puck coordinate is its slide joint plus a constant.  With the mixture prior warm-started this
    stopped at the fourth iteration ("ill-defined empirical covariance", issue 34)."""
    task = load_task(SLIDER)
    base = LQRFLMConfig(iterations=4, samples=20, init_var=1.0, noise=NoiseConfig(estimator="kinematic"))
    assert base.fit.prior_warm_start
    st = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=0)
    assert [r.iteration for r in st.history] == [0, 1, 2, 3]
    assert all(np.isfinite(r.cost).all() for r in st.history)
    z = [task.state_labels.index(f"{p}.{c}") for p in ("tip", "puck_c") for c in ("z", "vz")]
    assert np.ptp(st.last_rollouts.x[..., z], axis=(0, 1)).max() == 0.0  # constant, exactly
    assert isinstance(st.policy, KinematicFilteredPolicy)


def test_gym_mujoco_task_runs_with_the_kinematic_estimator():
    task = load_task("gym:Reacher-v5", overrides={"T": 20})
    base = LQRFLMConfig(iterations=2, samples=4, init_var=1.0, noise=NoiseConfig(estimator="kinematic"))
    st = registry.run(task, "dpsoc-em", DPSOCConfig(baseline=base, i_switch=1), seed=0)
    assert "em" in [r.phase for r in st.history]
    assert isinstance(st.policy, KinematicFilteredPolicy)
    assert all(np.isfinite(r.cost).all() for r in st.history)


@pytest.mark.parametrize("task, reason", [
    ("linear2d", "task 'linear2d' is of kind 'linear', which has none"),
    (f"{SLIDER}::no-puck-joints", "joint 'puck_x' moves the site 'puck_c'"),
])
def test_a_task_the_estimator_cannot_model_is_refused_before_anything_is_written(tmp_path, capsys, task, reason):
    from soc_opt.cli import main

    if task.endswith("::no-puck-joints"):  # the slider with the puck's slide joints left out of the state
        text = SLIDER.read_text().replace('extra_joints = ["puck_x", "puck_y"]', "extra_joints = []")
        text = text.replace("q0 = [0.3, 0.6, 0.0, 0.0]", "q0 = [0.3, 0.6]").replace('model = "slider.xml"',
                                                                                   f'model = "{SLIDER.parent / "slider.xml"}"')
        task = tmp_path / "slider_no_puck_joints.toml"
        task.write_text(text)
    config = tmp_path / "kinematic.toml"
    config.write_text('[baseline]\niterations = 2\nsamples = 4\n[baseline.noise]\nestimator = "kinematic"\n')
    out = tmp_path / "run"
    assert main(["run", str(task), "--method", "lqr-flm", "--config", str(config), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("soc-opt: error: ") and reason in err[0]
    assert not out.exists()
