"""Tests of soc_opt.noise.noisefit (docs/math.md §10.1): exact population correction, consistency, SSM-EM."""

from __future__ import annotations

import numpy as np
import pytest
from noise_oracle import closed_loop, condition, cov, random_pd, sample, stack

from soc_opt.bench.noisefit import bias_table, population_naive, problem, relative_errors, simulate
from soc_opt.models import LinearGaussianDynamics, NotPositiveDefiniteError, ShapeError
from soc_opt.noise.estimator import kalman_filter, measurement_noise
from soc_opt.noise.noisefit import (
    NoiseFitConfig,
    condition_joint,
    correct_joint,
    corrected_fit,
    estimate_noise_action_cov,
    naive_fit,
    noise_action_cov,
    smooth_states,
    ssm_em,
)


def _population(prob, *, gains=None, y_row=None):
    """Exact tuple moments of (s_k, a_k, s_{k+1}[, y_k]) and of (x_k, a_k, x_{k+1}[, y_k]) from the oracle."""
    dyn, pol = prob["dynamics"], prob["policy"]
    sys = {"A": dyn.A, "B": dyn.B, "c": dyn.c, "W": dyn.cov}
    filt = None
    if gains is not None:
        filt = {"A": dyn.A, "B": dyn.B, "c": dyn.c, "G": gains, "mu0": prob["mu0"]}
    cl = closed_loop(sys, prob["R"], prob["mu0"], prob["P0"], pol.K, pol.k, pol.cov, filt=filt, y_row=y_row)
    T = dyn.T
    out = {"mu": [], "Lam": [], "mu_true": [], "Lam_true": [], "X": []}
    for k in range(T):
        extra = [cl["y"][k]] if y_row is not None else []
        obs = stack([cl["s"][k], cl["a"][k], cl["s"][k + 1]] + extra)
        tru = stack([cl["x"][k], cl["a"][k], cl["x"][k + 1]] + extra)
        out["mu"].append(obs.const)
        out["Lam"].append(cov(obs))
        out["mu_true"].append(tru.const)
        out["Lam_true"].append(cov(tru))
        out["X"].append(cov(cl["eps"][k], cl["a"][k]))
    return {k: np.array(v) for k, v in out.items()}


def _y_row(T, n, m, W, rng):
    Ay = rng.standard_normal((T, 1, n))
    By = rng.standard_normal((T, 1, m))
    cy = rng.standard_normal((T, 1))
    joint = np.empty((T, n + 1, n + 1))
    for k in range(T):
        v = 0.02 * rng.standard_normal(n)
        joint[k] = np.block([[W[k], v[:, None]], [v[None], np.array([[0.3]])]])
        assert np.linalg.eigvalsh(joint[k])[0] > 0
    return {"Ay": Ay, "By": By, "cy": cy, "joint": joint}


# --------------------------------------------------------------------------- exact (population) checks


@pytest.mark.parametrize("filtered", [False, True])
def test_noise_action_covariance_is_R_K_or_R_G_K(filtered):
    prob = problem(seed=1, T=5)
    rng = np.random.default_rng(0)
    G = None
    if filtered:  # any predictor-corrector gains, not only Kalman's
        G = np.stack([random_pd(2, rng, 0.5) for _ in range(6)])
    pop = _population(prob, gains=G)
    np.testing.assert_allclose(noise_action_cov(prob["R"], prob["policy"].K, G), pop["X"], atol=1e-12)


@pytest.mark.parametrize("filtered", [False, True])
def test_correction_recovers_the_true_model_and_y_row_from_exact_moments(filtered):
    """On exact closed-loop moments the corrected regression is exact; naive and R-only are not."""
    prob = problem(seed=2, T=5)
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    n, m, T = dyn.n, dyn.m, dyn.T
    rng = np.random.default_rng(3)
    G = np.stack([random_pd(n, rng, 0.5) for _ in range(T + 1)]) if filtered else None
    yr = _y_row(T, n, m, dyn.cov, rng)
    pop = _population(prob, gains=G, y_row=yr)
    X = noise_action_cov(R, pol.K, G)
    cm = correct_joint(pop["mu"], pop["Lam"], n, m, R, X, min_reliability=1e-6)
    assert np.all(cm.floored == 0)
    # the corrected moments are the moments of the true tuple (x_k, a_k, x_{k+1}, y_k)
    np.testing.assert_allclose(cm.cov, pop["Lam_true"], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(cm.mean, pop["mu_true"], atol=1e-12)
    Ao, co, So = condition_joint(cm.mean, cm.cov, n + m)
    np.testing.assert_allclose(Ao[:, :n, :n], dyn.A, atol=1e-9)
    np.testing.assert_allclose(Ao[:, :n, n:], dyn.B, atol=1e-9)
    np.testing.assert_allclose(co[:, :n], dyn.c, atol=1e-9)
    np.testing.assert_allclose(Ao[:, n:, :n], yr["Ay"], atol=1e-9)
    np.testing.assert_allclose(Ao[:, n:, n:], yr["By"], atol=1e-9)
    np.testing.assert_allclose(co[:, n:], yr["cy"], atol=1e-9)
    np.testing.assert_allclose(So, yr["joint"], atol=1e-9)  # W, the (w, eta) cross term and Var(eta)
    # the naive regression and "subtract R from the s block only" are biased by a finite amount
    An, _, _ = condition_joint(pop["mu"], pop["Lam"], n + m)
    assert relative_errors(An[:, :n, :n], dyn.A) > 0.1
    cm0 = correct_joint(pop["mu"], pop["Lam"], n, m, R, np.zeros_like(X), min_reliability=1e-6)
    A0, _, _ = condition_joint(cm0.mean, cm0.cov, n + m)
    assert relative_errors(A0[:, :n, :], np.concatenate([dyn.A, dyn.B], 2)) > 0.05


def test_population_naive_limit_matches_the_oracle():
    prob = problem(seed=4, T=5)
    n, m = prob["dynamics"].n, prob["dynamics"].m
    pop = _population(prob)
    An, _, _ = condition_joint(pop["mu"], pop["Lam"], n + m)
    A_lim, B_lim = population_naive(prob)
    np.testing.assert_allclose(A_lim, An[:, :n, :n], atol=1e-10)
    np.testing.assert_allclose(B_lim, An[:, :n, n:], atol=1e-10)


# --------------------------------------------------------------------------- consistency (Monte Carlo)


def test_corrected_fit_is_consistent_where_the_naive_fit_is_not():
    prob = problem(seed=0)
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    X = noise_action_cov(R, pol.K)
    A_lim, _ = population_naive(prob)
    gap = relative_errors(A_lim, dyn.A)  # exact M -> inf error of the naive fit
    assert gap > 0.1
    errs_c, errs_n = [], []
    for M in (300, 30000):
        _, s, a = simulate(prob, M, np.random.default_rng([5, M]))
        errs_c.append(relative_errors(corrected_fit(s, a, R, X).A, dyn.A))
        errs_n.append(relative_errors(naive_fit(s, a).A, dyn.A))
    assert errs_c[1] < 0.1 * gap and errs_c[1] < errs_c[0]
    assert errs_n[1] > 0.8 * gap  # bounded away from zero, at its population limit


def test_filtered_sampler_needs_the_filter_gain_in_the_correction():
    """Exact population errors of the wrong corrections, then Monte Carlo: only X = R G^T K^T is consistent."""
    prob = problem(seed=0, filtered=True)
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    n, m = dyn.n, dyn.m
    AB = np.concatenate([dyn.A, dyn.B], 2)
    X_good = noise_action_cov(R, pol.K, prob["filter"].G)
    X_wrong = noise_action_cov(R, pol.K)  # treats the sampler as acting on s
    pop = _population(prob, gains=prob["filter"].G)

    def pop_err(X):
        if X is None:
            Ao, _, _ = condition_joint(pop["mu"], pop["Lam"], n + m)
        else:
            cm = correct_joint(pop["mu"], pop["Lam"], n, m, R, X, min_reliability=1e-6)
            Ao, _, _ = condition_joint(cm.mean, cm.cov, n + m)
        return relative_errors(Ao[:, :n, :], AB)

    assert pop_err(X_good) < 1e-12
    wrong_limit, naive_limit = pop_err(X_wrong), pop_err(None)
    assert wrong_limit > 0.01 and naive_limit > 0.1

    _, s, a = simulate(prob, 30000, np.random.default_rng(7))

    def err(fit):
        return relative_errors(np.concatenate([fit.A, fit.B], 2), AB)

    assert err(corrected_fit(s, a, R, X_good)) < 0.5 * wrong_limit
    assert err(corrected_fit(s, a, R, X_wrong)) > 0.5 * wrong_limit
    assert err(naive_fit(s, a)) > 0.8 * naive_limit


def test_ssm_em_is_consistent_and_never_decreases_the_likelihood():
    prob = problem(seed=0)
    dyn, R = prob["dynamics"], prob["R"]
    gap = relative_errors(population_naive(prob)[0], dyn.A)
    _, s, a = simulate(prob, 4000, np.random.default_rng(9))
    fit = ssm_em(s, a, R, NoiseFitConfig(em_tol=1e-7))  # starts from the naive fit
    assert np.all(np.diff(fit.loglik) >= -1e-9 * np.abs(fit.loglik[:-1]))
    assert fit.loglik[-1] > fit.loglik[0]
    assert relative_errors(fit.dynamics.A, dyn.A) < 0.15 * gap
    assert relative_errors(fit.dynamics.B, dyn.B) < 0.1
    np.testing.assert_allclose(fit.dynamics.cov.mean(0), dyn.cov.mean(0), atol=0.01)


def test_noise_action_cov_estimate_is_consistent_for_a_sampler_on_s():
    prob = problem(seed=3)
    R, pol = prob["R"], prob["policy"]
    M = 20000
    x, s, a = simulate(prob, M, np.random.default_rng(1))
    Xh = estimate_noise_action_cov(s, a, R)
    X = noise_action_cov(R, pol.K)
    T = pol.T
    for k in range(T):
        Css = np.cov(s[:, k].T, bias=True)
        se_K = np.sqrt(np.outer(np.diag(pol.cov[k]), np.diag(np.linalg.inv(Css))) / M)  # (m, n)
        se_X = R @ se_K.T  # R = rho^2 I: elementwise scaling
        assert np.all(np.abs(Xh[k] - X[k]) < 5 * se_X + 1e-15)


# --------------------------------------------------------------------------- smoother and PD rule


def test_smoother_equals_bruteforce_conditioning_on_all_measurements():
    rng = np.random.default_rng(11)
    n, m, T = 2, 1, 4
    from noise_oracle import random_ltv

    sys = random_ltv(n, m, T, rng)
    dyn = LinearGaussianDynamics(sys["A"], sys["B"], sys["c"], sys["W"])
    R, mu0, P0 = random_pd(n, rng, 0.3), rng.standard_normal(n), random_pd(n, rng, 0.5)
    actions = rng.standard_normal((T, m))
    cl = closed_loop(sys, R, mu0, P0, None, None, None, actions=actions)
    s_val = np.array(sample(cl["s"], rng))
    sm = smooth_states(kalman_filter(dyn, R, mu0, P0), s_val[None], actions[None])
    obs = stack(cl["s"])
    for k in range(T + 1):
        mean, C = condition(cl["x"][k], obs, s_val.ravel())
        np.testing.assert_allclose(sm.mean[0, k], mean, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(sm.cov[0, k], C, rtol=1e-8, atol=1e-11)
        if k < T:
            _, Cj = condition(stack([cl["x"][k + 1], cl["x"][k]]), obs, s_val.ravel())
            np.testing.assert_allclose(sm.cross[0, k], Cj[:n, n:], rtol=1e-8, atol=1e-11)


def test_reliability_floor_keeps_the_corrected_covariance_positive_definite():
    """Deterministic start state: Cov(x_0) = 0, so the correction at k = 0 is floored, and the fit stays finite."""
    prob = problem(seed=5)
    prob["P0"] = 1e-12 * np.eye(2)
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    _, s, a = simulate(prob, 200, np.random.default_rng(2))
    from soc_opt.noise.noisefit import sample_moments

    mu, Lam = sample_moments(s, a)
    X = noise_action_cov(R, pol.K)
    r_min = 0.05
    cm = correct_joint(mu, Lam, 2, 1, R, X, min_reliability=r_min)
    assert cm.floored[0] >= 1
    nz = 3
    for k in range(dyn.T):
        Czz, Czt = Lam[k, :nz, :nz], cm.cov[k, :nz, :nz]
        rel = np.linalg.eigvalsh(np.linalg.solve(np.linalg.cholesky(Czz), np.linalg.solve(np.linalg.cholesky(Czz), Czt).T))
        assert rel.min() >= r_min - 1e-10
    fit = corrected_fit(s, a, R, X, NoiseFitConfig(min_reliability=r_min))
    assert np.all(np.isfinite(fit.A)) and np.all(np.linalg.eigvalsh(fit.cov) > 0)


# --------------------------------------------------------------------------- bench and errors


def test_bias_table_reports_all_methods_and_the_naive_bias():
    rows = bias_table(Ms=(1000,), reps=2, seed=0, config=NoiseFitConfig(em_tol=1e-5))
    by = {r["method"]: r for r in rows}
    assert set(by) == {"naive", "corrected", "ssm_em"}
    assert by["naive"]["med_err_A"] > 0.8 * by["naive"]["naive_limit_A"]
    assert by["corrected"]["med_err_A"] < 0.5 * by["naive"]["med_err_A"]
    assert by["ssm_em"]["med_err_A"] < 0.5 * by["naive"]["med_err_A"]


def test_bad_inputs_are_rejected_by_name():
    prob = problem(seed=0, T=4)
    _, s, a = simulate(prob, 50, np.random.default_rng(0))
    R, K = prob["R"], prob["policy"].K
    X = noise_action_cov(R, K)
    with pytest.raises(ValueError, match="rho2"):
        measurement_noise(-0.1, 2)
    with pytest.raises(NotPositiveDefiniteError, match="measurement noise R"):
        corrected_fit(s, a, -R, X)
    with pytest.raises(NotPositiveDefiniteError, match="measurement noise R"):
        ssm_em(s, a, np.diag([0.1, -0.1]))
    with pytest.raises(ShapeError, match="noise-action covariance X"):
        corrected_fit(s, a, R, X[:, :, :0])
    with pytest.raises(ShapeError, match="actions a"):
        corrected_fit(s, a[:, :-1], R, X)
    with pytest.raises(ShapeError, match="measured states s"):
        naive_fit(s[0], a)
    with pytest.raises(ShapeError, match="filter gains G"):
        noise_action_cov(R, K, np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="at least 2 rollouts"):
        naive_fit(s[:1], a[:1])
    with pytest.raises(ValueError, match="min_reliability"):
        NoiseFitConfig(min_reliability=0.0)
    with pytest.raises(ShapeError, match="init"):
        ssm_em(s, a, R, init=LinearGaussianDynamics(prob["dynamics"].A[:2], prob["dynamics"].B[:2],
                                                     prob["dynamics"].c[:2], prob["dynamics"].cov[:2]))
