"""Tests for soc_opt/methods/ (lqr_flm, dpsoc_em, ilqg, registry): LQR-FLM, DPSOC-EM, model-based iLQG (docs/math.md §7)."""

import numpy as np
import pytest

from soc_opt import lqg
from soc_opt.learning import fit
from soc_opt.methods import registry
from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
from soc_opt.methods.ilqg import ILQGConfig, ilqg
from soc_opt.methods.registry import check_config
from soc_opt.tasks import load_task

# Documented in docs/choices.md: LQR-FLM needs 3 iterations (10 samples each) on this problem.
LQR_FLM_ITERATIONS_TO_5_PERCENT = 3


def test_lqr_flm_reaches_known_model_lqr_cost_within_5_percent():
    """Unknown linear-Gaussian dynamics (no sensor noise): LQR-FLM vs LQR on the true model."""
    task = load_task("linear2d", overrides={"rho2": 0.0, "T": 30})
    dyn = task.linearize()
    cost = task.cost_expansion(np.zeros((task.T + 1, task.n)), np.zeros((task.T, task.m)))
    J_lqr = lqg.expected_cost(dyn, cost, lqg.lqr(dyn, cost, task.mu0, task.P0), task.mu0, task.P0).sum()
    base = LQRFLMConfig(iterations=LQR_FLM_ITERATIONS_TO_5_PERCENT, samples=10, kl_budget=0.5, init_var=10.0,
                        fit=fit.FitConfig(prior="none"))
    state = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=0)
    J = lqg.expected_cost(dyn, cost, state.policy, task.mu0, task.P0).sum()
    assert J >= J_lqr * (1 - 1e-9)  # LQR is optimal on the true model
    assert J <= 1.05 * J_lqr


def test_lqr_flm_lowers_the_cost_on_linear2d():
    task = load_task("linear2d", overrides={"T": 20})
    base = LQRFLMConfig(iterations=4, samples=8, kl_budget=0.5, init_var=10.0)
    state = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=1)
    costs = [np.mean(r.cost) for r in state.history]
    assert costs[-1] < costs[0]
    assert state.best.mean_cost == min(costs)
    assert state.best.iteration == int(np.argmin(costs))


@pytest.mark.parametrize("y_mode", ["model", "measured", "optimistic"])
def test_dpsoc_em_runs_its_em_phase_at_the_switch(y_mode):
    task = load_task("linear2d", overrides={"T": 15})
    cfg = DPSOCConfig(i_switch=2, baseline=LQRFLMConfig(iterations=3, samples=6, init_var=10.0),
                      em=EMConfig(n_em=2, y_mode=y_mode))
    state = registry.run(task, "dpsoc-em", cfg, seed=0)
    phases = [(r.iteration, r.phase) for r in state.history]
    assert phases == [(0, "baseline"), (1, "baseline"), (2, "em"), (2, "em"), (2, "baseline")]
    em = [r for r in state.history if r.phase == "em"]
    # each EM recursion maximises the surrogate for its own smoothed moments
    for r in em:
        assert r.em.surrogate_new >= r.em.surrogate_old - 1e-9 * abs(r.em.surrogate_old)
    assert [r.em.recursion for r in em] == [0, 1]
    assert all(r.em is None for r in state.history if r.phase == "baseline")
    assert state.em_done


def test_em_update_respects_the_covariance_floor_and_raises_the_surrogate():
    from soc_opt.methods.dpsoc_em import em_update

    task = load_task("linear2d", overrides={"T": 15})
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=1, samples=8), em=EMConfig(cov_floor_scale=0.5))
    rng = np.random.default_rng(0)
    policy = task.initial_policy(2.0)
    ro = task.rollouts(policy, 8, rng)
    prior = fit.update_prior(None, ro, cfg.baseline.fit, rng)
    new, diag = em_update(task, cfg, policy, ro, prior, rng)
    gap = np.linalg.eigvalsh(np.asarray(new.cov) - 0.5 * np.asarray(policy.cov))
    assert gap.min() >= -1e-9
    assert diag.surrogate_new >= diag.surrogate_old


def test_dpsoc_em_and_lqr_flm_share_the_iterations_before_the_switch():
    task = load_task("linear2d", overrides={"T": 15})
    cfg = DPSOCConfig(i_switch=2, baseline=LQRFLMConfig(iterations=3, samples=6, init_var=10.0))
    a = registry.run(task, "lqr-flm", cfg, seed=4)
    b = registry.run(task, "dpsoc-em", cfg, seed=4)
    for ra, rb in zip(a.history[:2], b.history[:2]):
        np.testing.assert_array_equal(ra.cost, rb.cost)


def test_ilqg_lowers_the_cost_at_every_accepted_iteration_on_the_arm():
    task = load_task("peg", overrides={"T": 30})
    seen = []
    policy, costs = ilqg(task, cfg=ILQGConfig(iterations=4), on_iteration=lambda it, J, mu: seen.append(J))
    assert len(costs) >= 2, "iLQG accepted no step"
    assert all(b < a for a, b in zip(costs, costs[1:]))
    assert seen == costs[1:]
    assert policy.K.shape == (task.T, task.m, task.n)


def test_ilqg_linearises_with_its_finite_difference_step(monkeypatch):
    """``[ilqg] fd_eps`` is the step ``task.linearize`` receives (a linear task, whose linearisation is exact,
    is called without one)."""
    from soc_opt.methods import ilqg as ilqg_mod

    task = load_task("peg", overrides={"T": 5})
    seen = []
    real = task.linearize
    monkeypatch.setattr(task, "linearize", lambda x, u, cov=0.0, eps=1e-6: seen.append(eps) or real(x, u, cov, eps))
    st = ilqg_mod.initial_ilqg_state(task, ILQGConfig(fd_eps=3e-3))
    ilqg_mod.ilqg_iteration(task, ILQGConfig(fd_eps=3e-3), st)
    assert seen == [3e-3]
    lin = load_task("linear2d", overrides={"T": 5})
    st = ilqg_mod.initial_ilqg_state(lin, ILQGConfig())
    assert ilqg_mod.ilqg_iteration(lin, ILQGConfig(), st).history[-1].accepted


@pytest.fixture(scope="module")
def door_ilqg():
    """25 iterations of iLQG on the door from zero torques at rho^2 = 0.1 (the door's own; iLQG's model is
    noise free, so the iterates are those at any rho^2): ``(task, cfg, state)``, shared by the two tests
    below (the run is ~50 CPU seconds, most of the door's share of the suite)."""
    from soc_opt.methods.ilqg import run_ilqg

    task = load_task("door", overrides={"rho2": 0.1})
    cfg = ILQGConfig(iterations=25)
    return task, cfg, run_ilqg(task, cfg)


def test_ilqg_opens_the_door_from_zero_actions(door_ilqg):
    """With the default finite-difference step iLQG opens the door from zero torques (min hinge <= -0.95);
    with 1e-6 the contact Jacobians (norm up to 7e13) stop it near -0.5 (docs/results/acceptance.md §5).
    (``ilqg`` is ``run_ilqg`` from a fresh start returning ``(st.policy, st.costs)``; tested on the arm above.)"""
    task, _, st = door_ilqg
    policy, costs = st.policy, list(st.costs)
    ro = task.rollouts(policy.mean_policy(), 1, np.random.default_rng(0), noise=False)
    assert task.metrics(ro)["min_hinge"] <= -0.95
    assert costs[-1] < 5.0


def test_ilqg_acting_on_its_kalman_filter_opens_the_door_under_the_paper_s_sensor_noise(door_ilqg):
    """At rho^2 = 0.1 the iterate's feedback on the raw measurement does not move the door; read on the
    Kalman filter of its own linearisation (known start) its mean action opens it (docs/results/acceptance.md §5)."""
    from soc_opt.methods.ilqg import filtered_policy
    from soc_opt.noise.aware import mean_action

    task, cfg, st = door_ilqg
    fp = filtered_policy(task, st, cfg)
    assert (fp.T, fp.n, fp.m) == (task.T, task.n, task.m)
    np.testing.assert_array_equal(fp.filter.mu0, st.x[0])
    raw = task.metrics(task.rollouts(st.policy.mean_policy(), 10, np.random.default_rng(3)))["min_hinge"]
    filt = task.metrics(task.rollouts(mean_action(fp), 10, np.random.default_rng(3)))["min_hinge"]
    assert raw > -0.3 and filt <= -0.95, (raw, filt)


def test_unknown_method_is_rejected():
    task = load_task("linear2d", overrides={"T": 5})
    with pytest.raises(ValueError, match="unknown method"):
        registry.run(task, "ppo", DPSOCConfig(baseline=LQRFLMConfig(iterations=1, samples=2), i_switch=0))


def test_dpsoc_em_rejects_a_switch_outside_the_run_before_sampling():
    cfg = DPSOCConfig(i_switch=14, baseline=LQRFLMConfig(iterations=14))
    with pytest.raises(ValueError, match="i_switch"):
        check_config("dpsoc-em", cfg)
    check_config("lqr-flm", cfg)  # the baseline never switches
    task = load_task("linear2d", overrides={"T": 5})
    with pytest.raises(ValueError, match="i_switch"):
        registry.run(task, "dpsoc-em", cfg.replace(baseline=LQRFLMConfig(iterations=1, samples=2)), seed=0)
    with pytest.raises(ValueError, match=r"i_switch: must be in \[0, 10000\]"):
        DPSOCConfig(i_switch=-1)


def test_em_records_keep_the_metrics_columns_in_their_order():
    """metrics.csv columns of an EM record: the batch's prior-fit time, recursion index, diagnostics, then
    the phase timings."""
    task = load_task("linear2d", overrides={"T": 10})
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=1, samples=4, init_var=10.0))
    state = registry.run(task, "dpsoc-em", cfg, seed=0)
    em = next(r for r in state.history if r.phase == "em")
    keys = list(em.summary())
    em_block = ["time_prior", "em_recursion", "surrogate_old", "surrogate_new", "loglik_old", "loglik_new",
                "time_fit_augmented", "time_estep", "time_mstep"]
    start = keys.index("time_rollouts") + 1
    assert keys[start:start + len(em_block)] == em_block
    # then the step-acceptance columns of the batch (docs/math.md §12), if any
    assert set(keys[start + len(em_block):]) <= {"test_cost", "test_cost_se", "accept_threshold", "accepted",
                                                 "accepted_iteration"}
    assert em.summary()["surrogate_new"] == em.em.surrogate_new


def test_em_update_passes_its_mstep_config_to_the_m_step(monkeypatch):
    from soc_opt import mstep
    from soc_opt.methods.dpsoc_em import em_update
    from soc_opt.mstep import recipe

    task = load_task("linear2d", overrides={"T": 10})
    mcfg = mstep.MStepConfig(eig_tol=1e-11, feas_tol=1e-8)
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=1, samples=6), em=EMConfig(mstep=mcfg))
    seen = []
    original = recipe.maximize

    def spy(*args, **kwargs):
        seen.append(kwargs.get("config"))
        return original(*args, **kwargs)

    monkeypatch.setattr(recipe, "maximize", spy)  # the M-step recipe's call
    rng = np.random.default_rng(0)
    policy = task.initial_policy(2.0)
    em_update(task, cfg, policy, task.rollouts(policy, 6, rng), None, rng)
    assert seen == [mcfg]


def test_loop_kl_tolerance_comes_from_the_config_with_the_loop_default():
    """A partial [baseline.kl] table keeps the loop's tolerance (1e-6), not the library's (1e-10)."""
    cfg = DPSOCConfig.from_dict({"baseline": {"kl": {"max_backward": 400}}})
    assert cfg.baseline.kl.kl_rtol == LQRFLMConfig().kl.kl_rtol == 1e-6
    assert lqg.KLStepConfig().kl_rtol == 1e-10
    assert isinstance(cfg.baseline.kl, lqg.KLStepConfig)
    assert DPSOCConfig.from_dict({"baseline": {"kl": {"kl_rtol": 1e-8}}}).baseline.kl.kl_rtol == 1e-8


def test_paper_scale_is_the_default_scale():
    from soc_opt.methods.config import PAPER, with_paper_scale

    cfg = DPSOCConfig()
    assert (cfg.baseline.iterations, cfg.baseline.samples, cfg.i_switch) == tuple(PAPER) == (14, 20, 4)
    small = DPSOCConfig(i_switch=1, baseline=LQRFLMConfig(iterations=3, samples=5))
    assert with_paper_scale(small) == DPSOCConfig()


def test_every_run_config_knob_round_trips_through_toml_tables():
    """The run configuration holds every sub-config: to_dict -> from_dict is the identity."""
    from soc_opt import mstep

    cfg = DPSOCConfig(
        i_switch=1,
        baseline=LQRFLMConfig(iterations=3, kl_method="casadi", kl=LQRFLMConfig().kl.replace(eta_init=2.0)),
        em=EMConfig(mstep=mstep.MStepConfig(solver="SCS", exact_max_iter=7)),
    )
    back = DPSOCConfig.from_dict(cfg.to_dict())
    assert back == cfg
    assert back.em.mstep.solver == "SCS" and back.evaluation.seed_offset == 10_000


def test_ilqg_warm_start_begins_at_the_policy_s_noise_free_mean_actions(tmp_path):
    """``[ilqg] init_policy``: the first iterate is the open-loop rollout of the policy's mean action."""
    from soc_opt.config import ConfigError
    from soc_opt.methods.ilqg import ILQGConfig, initial_ilqg_state, warm_start_actions
    from soc_opt.models import LinearGaussianPolicy

    task = load_task("linear2d", overrides={"T": 12})
    pol = task.initial_policy(1.0)
    pol = LinearGaussianPolicy(pol.K, pol.k + 0.3, pol.cov)
    path = tmp_path / "p.npz"
    pol.save(path)
    cfg = ILQGConfig(init_policy=str(path))
    u = warm_start_actions(task, cfg.init_policy)
    ro = task.rollouts(pol.mean_policy(), 1, np.random.default_rng(0), noise=False)
    np.testing.assert_array_equal(u, ro.a[0])
    st = initial_ilqg_state(task, cfg, u)
    np.testing.assert_allclose(st.x, ro.x[0], rtol=1e-12, atol=1e-12)
    with pytest.raises(ConfigError, match="init_policy: no such file"):
        ILQGConfig(init_policy=str(tmp_path / "missing.npz"))
    other = load_task("linear2d", overrides={"T": 7})
    with pytest.raises(ConfigError, match="needs"):
        warm_start_actions(other, str(path))
