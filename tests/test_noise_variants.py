"""Tests for the noise-aware variants in the loop (docs/math.md §10; soc_opt/noise_aware.py, the
estimator in task rollouts, the fit hook, and their wiring in soc_opt/methods/)."""

import dataclasses
import types

import numpy as np
import pytest

from soc_opt import estep, lqg, mstep
from soc_opt.config import ConfigError
from soc_opt.learning import fit
from soc_opt.methods import registry
from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
from soc_opt.methods.dpsoc_em import em_update
from soc_opt.methods.lqr_flm import initial_state, lqr_flm_iteration
from soc_opt.models import LinearGaussianDynamics, LinearGaussianPolicy, NotPositiveDefiniteError
from soc_opt.noise import aware as noise_aware
from soc_opt.noise import noisefit
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.estimator import FilteredPolicy, filter_states, kalman_filter, measurement_noise
from soc_opt.noise.noisefit import smooth_states
from soc_opt.tasks import load_task


def _random_policy(task, rng, gain=0.3, var=2.0):
    K = gain * rng.standard_normal((task.T, task.m, task.n))
    k = rng.standard_normal((task.T, task.m))
    return LinearGaussianPolicy(K, k, np.broadcast_to(var * np.eye(task.m), (task.T, task.m, task.m)).copy())


def _noisy_filter(task, rng):
    """A filter of a model that is not the task's (so that xhat differs clearly from s and x)."""
    dyn = task.linearize() if hasattr(task, "A") else None
    T, n, m = task.T, task.n, task.m
    A = np.broadcast_to(np.eye(n), (T, n, n)) if dyn is None else dyn.A * 0.9
    B = 0.05 * rng.standard_normal((T, n, m)) if dyn is None else dyn.B
    W = np.broadcast_to(0.02 * np.eye(n), (T, n, n))
    R = measurement_noise(max(task.rho2, 0.05), n)
    return kalman_filter(LinearGaussianDynamics(A, B, np.zeros((T, n)), W), R, task.mu0, 1e-3 * np.eye(n))


# --------------------------------------------------------------------------- default = the paper


def _paper_iteration(task, cfg, state):
    """The paper's LQR-FLM iteration recomposed from its primitives (docs/math.md §7), independent of the loop."""
    rng = np.random.default_rng()
    rng.bit_generator.state = state.rng_state
    ro = task.rollouts(state.policy, cfg.samples, rng)
    prior = fit.update_prior(state.prior, ro, cfg.fit, rng)
    dyn = fit.fit_dynamics(ro, cfg.fit, prior)
    cost = task.cost_expansion(ro.s.mean(axis=0), ro.a.mean(axis=0))
    model = lqg.LocalModel(dyn, cost, task.mu0, task.P0)
    mult = state.mult
    if state.prev is not None:
        pred, act = lqg.laplace_improvements(state.prev.reference, state.policy, state.prev.model, model)
        mult = lqg.adapt_multiplier(mult, pred, act, cfg.step_size)
    res = lqg.kl_step(dyn, cost, state.policy, cfg.kl_budget * task.T * mult, task.mu0, task.P0, config=cfg.kl)
    return res.policy, mult, ro


def test_default_config_is_the_paper_loop_bit_for_bit():
    task = load_task("linear2d", overrides={"T": 10})
    cfg = LQRFLMConfig(iterations=3, samples=6, init_var=10.0)
    assert cfg.noise == NoiseConfig() and cfg.noise.paper
    state = initial_state(task, cfg, seed=2)
    for _ in range(3):
        policy, mult, ro = _paper_iteration(task, cfg, state)
        state = lqr_flm_iteration(task, cfg, state)
        assert isinstance(state.policy, LinearGaussianPolicy)
        for name in ("K", "k", "cov"):
            assert np.array_equal(getattr(state.policy, name), getattr(policy, name))
        assert state.mult == mult
        assert np.array_equal(state.last_rollouts.s, ro.s)


def test_default_em_update_is_the_paper_recursion_bit_for_bit():
    task = load_task("linear2d", overrides={"T": 10})
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=1, samples=8))
    policy = _random_policy(task, np.random.default_rng(3), gain=0.05)
    ro = task.rollouts(policy, 8, np.random.default_rng(4))
    prior = fit.update_prior(None, ro, cfg.baseline.fit, np.random.default_rng(5))
    new, _ = em_update(task, cfg, policy, ro, prior, np.random.default_rng(6))
    # recomposed: fit augmented model, Y from the model, E-step, M-step (paper Algorithm 1)
    rng = np.random.default_rng(6)
    model = fit.fit_augmented(ro, cfg.baseline.fit, prior)
    Y = fit.cost_observations("model", ro, model, policy, task.mu0, task.P0, rng)
    sm = estep.smooth(model, policy, Y, task.mu0, task.P0)
    cons = mstep.MStepConstraints(cov_floor=(0.5 * np.asarray(policy.cov)).tolist())
    ref = mstep.maximize(model, estep.moments(sm, Y), constraints=cons, previous=policy, config=cfg.em.mstep, min_norm=False).policy
    assert isinstance(new, LinearGaussianPolicy)
    for name in ("K", "k", "cov"):
        assert np.array_equal(getattr(new, name), getattr(ref, name))


# --------------------------------------------------------------------------- rollouts with the filter


def test_linear_rollouts_of_a_filtered_policy_act_on_the_online_filter_estimate():
    task = load_task("linear2d", overrides={"T": 12})
    rng = np.random.default_rng(0)
    pol = _random_policy(task, rng)
    kf = _noisy_filter(task, rng)
    ro = task.rollouts(FilteredPolicy(pol, kf), 5, np.random.default_rng(7))
    # independent: the batch filter over the recorded measurements and actions, and the same draws
    xhat = filter_states(kf, ro.s, ro.a)
    draws = task.draw_noise(5, np.random.default_rng(7))
    a = np.einsum("tij,mtj->mti", pol.K, xhat[:, :-1]) + pol.k + np.einsum("tij,mtj->mti", pol.chol, draws.w)
    np.testing.assert_allclose(ro.a, a, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(ro.s, ro.x + draws.eps)
    x_next = ro.x[:, :-1] @ task.A.T + ro.a @ task.B.T + task.c + draws.xi
    np.testing.assert_allclose(ro.x[:, 1:], x_next, rtol=1e-12, atol=1e-12)
    assert np.abs(xhat - ro.s).max() > 1e-2  # the filter does something here


def test_linear_rollouts_of_a_plain_policy_use_the_measured_state_with_the_same_draws():
    task = load_task("linear2d", overrides={"T": 12})
    pol = _random_policy(task, np.random.default_rng(1))
    ro = task.rollouts(pol, 4, np.random.default_rng(8))
    d = task.draw_noise(4, np.random.default_rng(8))
    x = np.empty_like(ro.x)
    x[:, 0] = task.x0
    a = np.empty_like(ro.a)
    for k in range(task.T):
        s = x[:, k] + d.eps[:, k]
        a[:, k] = s @ pol.K[k].T + pol.k[k] + d.w[:, k] @ pol.chol[k].T
        x[:, k + 1] = x[:, k] @ task.A.T + a[:, k] @ task.B.T + task.c + d.xi[:, k]
    np.testing.assert_array_equal(ro.a, a)
    np.testing.assert_array_equal(ro.x, x)


def test_mujoco_rollouts_of_a_filtered_policy_act_on_the_online_filter_estimate():
    task = load_task("peg", overrides={"T": 8})
    rng = np.random.default_rng(2)
    pol = _random_policy(task, rng, gain=0.01, var=0.05)
    kf = _noisy_filter(task, rng)
    fpol = FilteredPolicy(pol, kf)
    ro = task.rollouts(fpol, 3, np.random.default_rng(9), workers=2)
    xhat = filter_states(kf, ro.s, ro.a)
    draws = task.draw_noise(3, np.random.default_rng(9))
    a = np.einsum("tij,mtj->mti", pol.K, xhat[:, :-1]) + pol.k + np.einsum("tij,mtj->mti", pol.chol, draws.w)
    np.testing.assert_allclose(ro.a, a, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(ro.s, ro.x + draws.eps)
    # the filter with the identity gain (R = 0) gives the plain policy's rollouts
    ident = kalman_filter(kf.dynamics(), np.zeros((task.n, task.n)), task.mu0, np.eye(task.n))
    assert np.allclose(ident.G, np.eye(task.n))
    ro_id = task.rollouts(FilteredPolicy(pol, ident), 3, np.random.default_rng(9))
    ro_plain = task.rollouts(pol, 3, np.random.default_rng(9))
    np.testing.assert_allclose(ro_id.x, ro_plain.x, rtol=1e-9, atol=1e-9)


def test_filtered_policy_round_trips_through_an_npz_file(tmp_path):
    task = load_task("linear2d", overrides={"T": 6})
    rng = np.random.default_rng(3)
    fpol = FilteredPolicy(_random_policy(task, rng), _noisy_filter(task, rng))
    np.savez_compressed(tmp_path / "p.npz", **fpol.to_dict())
    back = FilteredPolicy.from_dict(np.load(tmp_path / "p.npz"))
    for name in ("K", "k", "cov"):
        assert np.array_equal(getattr(back.policy, name), getattr(fpol.policy, name))
    for name in ("A", "B", "c", "W", "R", "mu0", "P0", "G", "P"):
        np.testing.assert_allclose(getattr(back.filter, name), getattr(fpol.filter, name), rtol=1e-12, atol=1e-15)


# --------------------------------------------------------------------------- corrected fit


@pytest.mark.parametrize("filtered", [False, True])
def test_corrected_fit_in_fit_dynamics_recovers_the_system_where_the_naive_fit_does_not(filtered):
    """Oracle: the task's true (A, B).  Least squares (no prior), many rollouts, feedback sampler.

    The start states are spread (``x_0 ~ N(0, I)``) so that every direction of ``x_k`` is excited at
    every step (from the task's fixed start a chain of integrators leaves directions with a variance
    far below ``rho2`` for many steps, where neither fit can identify ``A``).
    """
    task = load_task("linear2d", overrides={"T": 10, "rho2": 0.1})
    rng = np.random.default_rng(4)
    pol = _random_policy(task, rng, gain=0.1, var=4.0)
    sampler = FilteredPolicy(pol, _noisy_filter(task, rng)) if filtered else pol
    M = 4000
    x0 = np.random.default_rng(11).standard_normal((M, task.n))
    ro = task.rollouts(sampler, M, np.random.default_rng(5), x0=x0)
    cfg = fit.FitConfig(prior="none")
    noise = noise_aware.noise_model(task)
    X = noise_aware.sampler_noise_action_cov(sampler, noise.R)
    hook = noise_aware.moment_correction(noise.R, X, task.n, task.m, 0.05)
    naive = fit.fit_dynamics(ro, cfg)
    corr = fit.fit_dynamics(ro, cfg, correct=hook)
    same = noise_aware.fit_local(ro, cfg, None, NoiseConfig(fit_correction="moments"), noise, sampler)
    np.testing.assert_array_equal(same.A, corr.A)

    def err(d):
        F = np.concatenate([d.A, d.B], axis=2)
        F0 = np.concatenate([task.A, task.B], axis=1)
        return np.linalg.norm(F - F0, axis=(1, 2)) / np.linalg.norm(F0)

    assert np.median(err(corr)) < 0.04
    assert np.median(err(naive)) > 3 * np.median(err(corr))
    # the corrected noise covariance has R removed; the naive one carries it (trace ~ 1 here)
    tr = lambda d: np.median(np.trace(d.cov, axis1=1, axis2=2))  # noqa: E731
    assert tr(naive) > 0.5 and tr(corr) < 0.1 * tr(naive)


def test_ssm_em_fit_is_closer_to_the_system_than_the_naive_fit_with_the_mixture_prior():
    """Oracle: the true A.  20 rollouts with the mixture prior (the loop's fitting path)."""
    task = load_task("linear2d", overrides={"T": 20, "rho2": 0.1})
    rng = np.random.default_rng(3)
    pol = _random_policy(task, rng, gain=0.1, var=4.0)
    x0 = rng.standard_normal((20, task.n))
    ro = task.rollouts(pol, 20, rng, x0=x0)
    cfg = fit.FitConfig()
    prior = fit.update_prior(None, ro, cfg, np.random.default_rng(8))
    noise = noise_aware.noise_model(task)
    naive = fit.fit_dynamics(ro, cfg, prior)
    em = noise_aware.fit_local(ro, cfg, prior, NoiseConfig(fit_correction="ssm_em"), noise, pol)
    err = lambda d: np.median(np.linalg.norm(d.A[task.T // 2:] - task.A, axis=(1, 2)))  # noqa: E731
    assert err(em) < 0.75 * err(naive)
    # the augmented variant (DPSOC-EM) fits the same state rows plus the y row
    aug = noise_aware.fit_local(ro, cfg, prior, NoiseConfig(fit_correction="ssm_em"), noise, pol, include_y=True)
    assert aug.Ao.shape == (task.T, task.n + 1, task.n + task.m)
    assert err(aug.dynamics()) < 0.75 * err(naive)


@pytest.mark.parametrize("h", [0, 1, 3, 50])
def test_pooled_moments_are_the_moments_of_the_union_of_the_windows_tuples(h):
    rng = np.random.default_rng(5)
    M, T, d = 7, 9, 4
    Xs = rng.standard_normal((M, T, d)) + np.arange(T)[None, :, None] * rng.standard_normal(d)
    mu = Xs.mean(axis=0)
    Lam = np.einsum("mti,mtj->tij", Xs - mu, Xs - mu) / M
    pm, pL = noise_aware.pool_moments(mu, Lam, h)
    for k in range(T):
        pts = Xs[:, max(0, k - h): min(T, k + h + 1)].reshape(-1, d)  # the oracle: pool the tuples
        np.testing.assert_allclose(pm[k], pts.mean(axis=0), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(pL[k], np.cov(pts.T, bias=True), rtol=1e-12, atol=1e-12)
    X = rng.standard_normal((T, 3, 2))
    pX = noise_aware.pool_noise_action_cov(X, h)
    np.testing.assert_allclose(pX[T // 2], X[max(0, T // 2 - h): T // 2 + h + 1].mean(axis=0), rtol=1e-12)


@pytest.mark.parametrize("h", [1, 3, 50])
def test_anchored_pooling_keeps_the_steps_mean_and_the_windows_second_moments_about_it(h):
    rng = np.random.default_rng(6)
    M, T, d = 7, 9, 4
    Xs = rng.standard_normal((M, T, d)) + (np.arange(T)[None, :, None] ** 2) * rng.standard_normal(d)
    mu = Xs.mean(axis=0)
    Lam = np.einsum("mti,mtj->tij", Xs - mu, Xs - mu) / M
    am, aL = noise_aware.pool_moments(mu, Lam, h, "anchored")
    np.testing.assert_array_equal(am, mu)
    for k in range(T):
        pts = Xs[:, max(0, k - h): min(T, k + h + 1)].reshape(-1, d) - mu[k]  # oracle: about step k's mean
        np.testing.assert_allclose(aL[k], pts.T @ pts / len(pts), rtol=1e-12, atol=1e-12)
    # conditioning the anchored moments gives a model through step k's own means
    Ao, co, _ = noisefit.condition_joint(am, aL, 2, 1e-12)
    np.testing.assert_allclose(np.einsum("tij,tj->ti", Ao, mu[:, :2]) + co, mu[:, 2:], rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="pool mode"):
        noise_aware.pool_moments(mu, Lam, h, "median")


def test_smoothed_expansion_point_is_the_mean_smoothed_state_and_closer_to_the_truth():
    task = load_task("linear2d", overrides={"rho2": 0.1})
    rng = np.random.default_rng(3)
    ro = task.rollouts(_random_policy(task, rng, gain=0.0, var=1.0), 5, rng)
    dyn, noise = task.linearize(), noise_aware.noise_model(task)
    cfg = NoiseConfig(estimator="kalman", expand_at="smoothed")
    got = noise_aware.expansion_point(ro, dyn, noise, cfg)
    kf = noise_aware.loop_filter(dyn, noise, cfg)
    np.testing.assert_allclose(got, smooth_states(kf, ro.s, ro.a).mean.mean(axis=0), rtol=1e-12)
    np.testing.assert_array_equal(noise_aware.expansion_point(ro, dyn, noise, NoiseConfig()), ro.s.mean(axis=0))
    truth = ro.x.mean(axis=0)
    assert np.linalg.norm(got - truth) < 0.5 * np.linalg.norm(ro.s.mean(axis=0) - truth)


def test_prior_on_smoothed_states_buffers_the_smoothed_tuples_and_the_loop_uses_it():
    task = load_task("linear2d", overrides={"T": 12, "rho2": 0.1})
    cfg = LQRFLMConfig(iterations=2, samples=8, init_var=10.0,
                       noise=NoiseConfig(estimator="kalman", fit_correction="ssm_em", prior_data="smoothed"))
    st = lqr_flm_iteration(task, cfg, initial_state(task, cfg, seed=0))
    st2 = lqr_flm_iteration(task, cfg, st)  # the sampler now has a filter: it smooths with its model
    ro = st2.last_rollouts
    f = st.policy.filter
    den = noise_aware.denoise(ro, LinearGaussianDynamics(f.A, f.B, f.c, f.W), noise_aware.noise_model(task), cfg.noise)
    want = fit.tuples(den, True).reshape(-1, 2 * task.n + task.m + 1)
    buf = st2.prior.buffer
    np.testing.assert_allclose(buf[-len(want):], want, rtol=1e-12, atol=1e-12)
    assert not np.allclose(buf[-len(want):, : task.n], fit.tuples(ro, True).reshape(len(want), -1)[:, : task.n])
    # the smoothed tuples are closer to the true ones than the measured ones (a model fitted from
    # 8 rollouts: 0.18 against 0.26 mean absolute error here)
    true_t = fit.tuples(dataclasses.replace(ro, s=ro.x), True).reshape(len(want), -1)
    assert (np.abs(want - true_t)[:, : task.n].mean()
            < np.abs(fit.tuples(ro, True).reshape(len(want), -1) - true_t)[:, : task.n].mean())
    assert isinstance(st2.policy, FilteredPolicy) and np.isfinite(st2.policy.policy.K).all()


# --------------------------------------------------------------------------- the loop with the estimator


def test_estimator_at_zero_noise_is_the_identity_filter_and_reproduces_the_paper_loop():
    task = load_task("linear2d", overrides={"T": 10, "rho2": 0.0})
    base = LQRFLMConfig(iterations=2, samples=6, init_var=10.0)
    paper = registry.run(task, "lqr-flm", DPSOCConfig(baseline=base, i_switch=0), seed=1)
    cfg = DPSOCConfig(baseline=base.replace(noise=NoiseConfig(estimator="kalman")), i_switch=0)
    kal = registry.run(task, "lqr-flm", cfg, seed=1)
    assert isinstance(kal.policy, FilteredPolicy)
    np.testing.assert_allclose(kal.policy.filter.G, np.broadcast_to(np.eye(task.n), kal.policy.filter.G.shape),
                               atol=1e-12)
    np.testing.assert_allclose(kal.policy.policy.K, paper.policy.K, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(kal.policy.policy.k, paper.policy.k, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose([np.mean(r.cost) for r in kal.history], [np.mean(r.cost) for r in paper.history],
                               rtol=1e-9)


def test_kalman_iteration_saves_the_filter_of_its_fit_and_steps_on_the_innovation_form():
    task = load_task("linear2d", overrides={"T": 10})
    cfg = LQRFLMConfig(iterations=2, samples=8, init_var=10.0, fit=fit.FitConfig(prior="none"),
                       noise=NoiseConfig(estimator="kalman"))
    st = lqr_flm_iteration(task, cfg, initial_state(task, cfg, seed=0))
    noise = noise_aware.noise_model(task)
    dyn = fit.fit_dynamics(st.last_rollouts, cfg.fit)
    kf = noise_aware.loop_filter(dyn, noise, cfg.noise)
    np.testing.assert_array_equal(st.policy.filter.A, dyn.A)
    np.testing.assert_allclose(st.policy.filter.G, kf.G, rtol=1e-12, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(st.policy.filter.W) >= 1e-3 * 0.1 * (1 - 1e-9))  # the W floor
    # the step's model is the innovation form of that filter, its cost corrected by 1/2 tr(C_xx P_k)
    cost = task.cost_expansion(st.last_rollouts.s.mean(0), st.last_rollouts.a.mean(0))
    np.testing.assert_allclose(st.prev.model.dynamics.cov, kf.G[1:] @ kf.S[1:] @ np.swapaxes(kf.G[1:], 1, 2),
                               rtol=1e-10, atol=1e-15)
    corr = 0.5 * np.einsum("tij,tji->t", cost.C[:, : task.n, : task.n], kf.P[: task.T])
    np.testing.assert_allclose(st.prev.model.cost.c0, cost.c0 + corr, rtol=1e-12)
    assert np.all(corr > 0)
    st2 = lqr_flm_iteration(task, cfg, st)  # samples the filtered policy, adapts the step
    assert isinstance(st2.policy, FilteredPolicy) and st2.mult != st.mult


@pytest.mark.parametrize("filtered", [False, True])
def test_the_loop_fits_with_the_noise_action_cov_of_the_policy_that_sampled(filtered):
    task = load_task("linear2d", overrides={"T": 10})
    cfg = LQRFLMConfig(iterations=1, samples=40, fit=fit.FitConfig(prior="none"),
                       noise=NoiseConfig(fit_correction="moments"))
    rng = np.random.default_rng(2)
    gains_ = _random_policy(task, rng, gain=0.2, var=4.0)
    kf = _noisy_filter(task, rng)
    sampler = FilteredPolicy(gains_, kf) if filtered else gains_
    st = lqr_flm_iteration(task, cfg, dataclasses.replace(initial_state(task, cfg, seed=1), policy=sampler))
    R = 0.1 * np.eye(task.n)
    Kt = np.swapaxes(gains_.K, 1, 2)
    X = R @ np.swapaxes(kf.G[: task.T], 1, 2) @ Kt if filtered else R @ Kt  # docs/noise.md §7
    want = fit.fit_dynamics(st.last_rollouts, cfg.fit,
                            correct=noise_aware.moment_correction(R, X, task.n, task.m, cfg.noise.min_reliability))
    got = st.prev.model.dynamics  # estimator "none": the KL step ran on the fit itself
    for name in ("A", "B", "c", "cov"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    naive = fit.fit_dynamics(st.last_rollouts, cfg.fit)
    assert not np.allclose(got.A, naive.A)


def test_dpsoc_em_with_the_estimator_runs_its_em_phase_on_the_filtered_loop():
    task = load_task("linear2d", overrides={"T": 12})
    base = LQRFLMConfig(iterations=3, samples=8, init_var=10.0,
                        noise=NoiseConfig(estimator="kalman", fit_correction="ssm_em"))
    cfg = DPSOCConfig(i_switch=1, baseline=base, em=EMConfig(n_em=1))
    state = registry.run(task, "dpsoc-em", cfg, seed=0)
    em = [r for r in state.history if r.phase == "em"]
    assert len(em) == 1
    assert em[0].em.surrogate_new >= em[0].em.surrogate_old - 1e-9 * abs(em[0].em.surrogate_old)
    assert isinstance(state.policy, FilteredPolicy)


# --------------------------------------------------------------------------- bad input


def test_noise_config_rejects_unknown_values_with_the_key_named():
    with pytest.raises(ConfigError, match="noise.estimator"):
        LQRFLMConfig.from_dict({"noise": {"estimator": "ekf"}})
    with pytest.raises(ConfigError, match="noise.fit_correction"):
        LQRFLMConfig.from_dict({"noise": {"fit_correction": "tls"}})
    with pytest.raises(ValueError, match="filter_w_floor"):
        NoiseConfig(filter_w_floor=-1.0)
    with pytest.raises(ValueError, match="estep_p0_jitter"):
        NoiseConfig(estep_p0_jitter=0.0)
    with pytest.raises(ValueError, match="min_reliability"):
        NoiseConfig(min_reliability=0.0)
    with pytest.raises(ValueError, match="time_window"):
        NoiseConfig(time_window=-1, fit_correction="moments")
    with pytest.raises(ValueError, match="time_window: .* needs fit_correction"):
        NoiseConfig(time_window=5)
    with pytest.raises(ConfigError, match="noise.expand_at"):
        LQRFLMConfig.from_dict({"noise": {"expand_at": "true"}})
    with pytest.raises(ConfigError, match="noise.pool"):
        LQRFLMConfig.from_dict({"noise": {"pool": "median", "fit_correction": "ssm_em"}})
    with pytest.raises(ValueError, match="prior_data: 'smoothed' .* needs fit_correction = 'ssm_em'"):
        NoiseConfig(prior_data="smoothed", fit_correction="moments")
    assert not NoiseConfig(expand_at="smoothed").paper
    cfg = LQRFLMConfig.from_dict({"noise": {"estimator": "kalman", "fit_correction": "ssm_em", "time_window": 50}})
    assert cfg.noise.label == "kalman + ssm_em, window 50" and not cfg.noise.paper


def test_negative_noise_and_a_non_psd_noise_model_get_clear_errors():
    with pytest.raises(ConfigError, match="rho2"):
        load_task("linear2d", overrides={"rho2": -0.1})
    bad = types.SimpleNamespace(name="bad", n=2, rho2=0.5, mu0=np.zeros(2), P0=0.1 * np.eye(2))
    with pytest.raises(NotPositiveDefiniteError, match="task.P0 - rho2 I"):
        noise_aware.noise_model(bad)
    neg = types.SimpleNamespace(name="neg", n=2, rho2=-1.0, mu0=np.zeros(2), P0=np.eye(2))
    with pytest.raises(ValueError, match="rho2"):
        noise_aware.noise_model(neg)
    # no measurement noise and a known start: S_0 = P0 + R is singular
    T, n, m = 3, 2, 1
    dyn = LinearGaussianDynamics(np.broadcast_to(np.eye(n), (T, n, n)), np.ones((T, n, m)), np.zeros((T, n)),
                                 np.broadcast_to(np.eye(n), (T, n, n)))
    zero = noise_aware.NoiseModel(np.zeros((n, n)), np.zeros(n), np.zeros((n, n)))
    with pytest.raises(NotPositiveDefiniteError, match=r"estimator = 'kalman' \(iteration 3\).*S\[0\]"):
        noise_aware.loop_filter(dyn, zero, NoiseConfig(estimator="kalman"), " (iteration 3)")
