"""Tests of soc_opt.learning.fit (docs/math.md §2, §3).

Oracles: the known system matrices and the OLS / Wishart standard errors,
ridge regression written here with numpy, a direct re-implementation of the
NIW posterior + Gaussian conditioning with scipy densities, and exact moment
propagation of the closed loop for the Monte-Carlo check of ``cost_observations``.
Run with ``pytest -s`` to see the accuracy tables (also produced by
``soc_opt.bench.fit``).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from soc_opt.bench.fit import (
    convergence_table,
    few_sample_table,
    format_table,
    pendulum_table,
    summarize,
)
from soc_opt.config import ConfigError
from soc_opt.learning.fit import (
    FitConfig,
    MixturePrior,
    VBState,
    cost_observations,
    fit_augmented,
    fit_dynamics,
    prediction_error,
    tuples,
    update_prior,
)
from soc_opt.models import AugmentedModel, LinearGaussianPolicy, Rollouts, ShapeError
from soc_opt.testing import random_ltv_system, simulate_linear

N, MU, T = 6, 2, 50
ERRS = ("err_A", "err_B", "err_c", "err_W")
MSES = ("mse_ls", "mse_prior", "mse_ref", "mse_y_ls", "mse_y_prior", "components")


def _subset(ro: Rollouts, idx) -> Rollouts:
    return Rollouts(*(np.array(getattr(ro, f)[idx]) for f in ("x", "s", "a", "cost", "y")))


@pytest.fixture(scope="module")
def system():
    return random_ltv_system(np.random.default_rng(7), N, MU, T)


@pytest.fixture(scope="module")
def data(system):
    return simulate_linear(system, 40, np.random.default_rng(8), rho2=0.01)


# --------------------------------------------------------------------------- convergence to truth


def _ols_expected_sq_errors(ro: Rollouts, system: dict) -> dict:
    """Expected squared Frobenius errors (summed over steps) of OLS and of the ML residual covariance.

    Given the design ``Z_k = [s_k, a_k, 1]`` (independent of the step-k noise),
    ``E||Theta_hat - Theta||^2 = tr(W_k) tr((Z^T Z)^{-1})`` per block, and
    ``W_hat ~ Wishart(W, M-p)/M`` gives
    ``E||W_hat - W||^2 = (p/M)^2 ||W||^2 + (M-p)/M^2 (||W||^2 + tr(W)^2)``.
    """
    M, n, m = ro.M, ro.n, ro.m
    p = n + m + 1
    out = dict.fromkeys(ERRS, 0.0)
    for k in range(ro.T):
        Z = np.concatenate([ro.s[:, k], ro.a[:, k], np.ones((M, 1))], axis=1)
        G = np.diag(np.linalg.inv(Z.T @ Z))
        W = system["W"][k]
        trW = np.trace(W)
        out["err_A"] += trW * G[:n].sum()
        out["err_B"] += trW * G[n : n + m].sum()
        out["err_c"] += trW * G[-1]
        fro2 = np.sum(W * W)
        out["err_W"] += (p / M) ** 2 * fro2 + (M - p) / M**2 * (fro2 + trW**2)
    return out


def test_least_squares_error_matches_ols_standard_error():
    """At M=80 (no prior) the squared errors of A, B, c, W match their OLS/Wishart expectations."""
    ratios = {k: [] for k in ERRS}
    for seed in range(3):
        rng = np.random.default_rng(seed)
        sysm = random_ltv_system(rng, N, MU, T)
        ro = simulate_linear(sysm, 80, rng)
        dyn = fit_dynamics(ro, FitConfig(prior="none"))
        expect = _ols_expected_sq_errors(ro, sysm)
        got = {
            "err_A": np.sum((dyn.A - sysm["A"]) ** 2),
            "err_B": np.sum((dyn.B - sysm["B"]) ** 2),
            "err_c": np.sum((dyn.c - sysm["c"]) ** 2),
            "err_W": np.sum((dyn.cov - sysm["W"]) ** 2),
        }
        for k in ERRS:
            ratios[k].append(got[k] / expect[k])
    print("\nLS squared error / OLS expectation (3 seeds):", {k: np.round(v, 3).tolist() for k, v in ratios.items()})
    # each ratio is a sum of >= 300 roughly chi-square terms (relative sd <= ~10%); the
    # seed average must be within ~4 sd of 1
    for k in ERRS:
        assert 0.7 < np.mean(ratios[k]) < 1.35, (k, ratios[k])


def test_fit_converges_to_true_system_as_M_grows():
    rows = convergence_table(Ms=(5, 10, 20, 80), seeds=(0, 1, 2), n=N, m=MU, T=T)
    table = summarize(rows, ERRS, ("prior", "M"))
    print("\nrelative Frobenius errors vs truth (mean of 3 seeds):\n" + format_table(table))
    for prior in ("none", "mixture"):
        sel = [r for r in table if r["prior"] == prior]
        for key in ERRS:
            errs = [r[key] for r in sel]
            assert all(b < a for a, b in zip(errs, errs[1:])), (prior, key, errs)
        last = sel[-1]
        assert last["M"] == 80
        assert last["err_A"] < 0.06 and last["err_B"] < 0.06 and last["err_c"] < 0.2 and last["err_W"] < 0.35, last
    ls80 = next(r for r in table if r["prior"] == "none" and r["M"] == 80)
    mix80 = next(r for r in table if r["prior"] == "mixture" and r["M"] == 80)
    for key in ERRS:  # the prior's weight (1 pseudo-sample) vanishes as M grows
        assert mix80[key] < 1.05 * ls80[key], (key, mix80[key], ls80[key])


@pytest.mark.slow
def test_fit_converges_more_seeds_and_M():
    rows = convergence_table(Ms=(5, 10, 20, 40, 80, 160), seeds=tuple(range(6)), n=N, m=MU, T=T)
    table = summarize(rows, ERRS, ("prior", "M"))
    print("\nrelative Frobenius errors vs truth (mean of 6 seeds):\n" + format_table(table))
    for prior in ("none", "mixture"):
        sel = [r for r in table if r["prior"] == prior]
        for key in ERRS:
            errs = [r[key] for r in sel]
            assert all(b < a for a, b in zip(errs, errs[1:])), (prior, key, errs)


# --------------------------------------------------------------------------- few samples / nonlinear


def test_mixture_prior_beats_least_squares_with_few_samples():
    rows = few_sample_table(Ms=(3, 5, 7), seeds=(0, 1, 2), n=N, m=MU, T=T)
    table = summarize(rows, MSES, ("M",))
    print("\nheld-out one-step MSE, linear system, M < n+m = 8 (mean of 3 seeds):\n" + format_table(table))
    for r in table:
        assert r["mse_prior"] < r["mse_ls"], r
        assert r["mse_y_prior"] < r["mse_y_ls"], r


def test_mixture_prior_beats_least_squares_on_pendulum():
    rows = pendulum_table(Ms=(2, 3, 5), seeds=(0, 1, 2))
    table = summarize(rows, MSES, ("M",))
    print("\nheld-out one-step MSE, pendulum (n=2, m=1) (mean of 3 seeds):\n" + format_table(table))
    for r in table:
        assert r["mse_prior"] < r["mse_ls"], r
    rows = pendulum_table(Ms=(3,), seeds=(0, 1, 2), M_earlier=20)
    table = summarize(rows, MSES, ("M", "M_earlier"))
    print("with a buffer of 20 earlier rollouts:\n" + format_table(table))
    for r in table:
        assert r["mse_prior"] < r["mse_ls"], r


# --------------------------------------------------------------------------- least squares = ridge


def _ridge(Z: np.ndarray, y: np.ndarray, lam: float):
    """Ridge of y on centred Z with penalty M*lam, unpenalised intercept -> (coef, intercept)."""
    M = Z.shape[0]
    zm, ym = Z.mean(0), y.mean(0)
    Zc, yc = Z - zm, y - ym
    coef = np.linalg.solve(Zc.T @ Zc + M * lam * np.eye(Z.shape[1]), Zc.T @ yc)
    return coef, ym - zm @ coef


def test_least_squares_y_row_is_ridge_regression(data):
    cfg = FitConfig(prior="none", reg=1e-3)
    model = fit_augmented(data, cfg)
    n, m = data.n, data.m
    sa = np.concatenate([data.s[:, :-1], data.a], axis=-1)
    lam = cfg.reg * sa.reshape(-1, n + m).var(axis=0).mean()
    for k in range(data.T):
        coef, icpt = _ridge(sa[:, k], data.y[:, k], lam)
        np.testing.assert_allclose(model.Ao[k, n], coef, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(model.co[k, n], icpt, rtol=1e-8, atol=1e-10)


def test_least_squares_y_row_is_lstsq_with_tiny_reg(data):
    model = fit_augmented(data, FitConfig(prior="none", reg=1e-13))
    n = data.n
    for k in range(data.T):
        Z = np.concatenate([data.s[:, k], data.a[:, k], np.ones((data.M, 1))], axis=1)
        beta, *_ = np.linalg.lstsq(Z, data.y[:, k], rcond=None)
        np.testing.assert_allclose(model.Ao[k, n], beta[:-1], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(model.co[k, n], beta[-1], rtol=1e-6, atol=1e-9)


def test_least_squares_state_rows_equal_fit_dynamics(data):
    cfg = FitConfig(prior="none")
    aug, dyn = fit_augmented(data, cfg), fit_dynamics(data, cfg)
    d2 = aug.dynamics()
    for a, b in ((d2.A, dyn.A), (d2.B, dyn.B), (d2.c, dyn.c), (d2.cov, dyn.cov)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_training_prediction_error_equals_residual_variance(data):
    """With 1/M normalisation the mean squared training residual is tr(W_hat)/n (tiny ridge)."""
    dyn = fit_dynamics(data, FitConfig(prior="none", reg=1e-13))
    np.testing.assert_allclose(
        prediction_error(dyn, data), np.trace(dyn.cov, axis1=1, axis2=2) / data.n, rtol=1e-6
    )


@settings(max_examples=20, deadline=None)
@given(
    n=st.integers(1, 3),
    m=st.integers(1, 2),
    M=st.integers(2, 12),
    seed=st.integers(0, 10_000),
)
def test_least_squares_matches_ridge_for_random_shapes(n, m, M, seed):
    rng = np.random.default_rng(seed)
    Tn = 3
    x = rng.standard_normal((M, Tn + 1, n))
    a = rng.standard_normal((M, Tn, m))
    y = rng.uniform(0.1, 1.0, (M, Tn))
    ro = Rollouts(x=x, s=x, a=a, cost=-np.log(y), y=y)
    cfg = FitConfig(prior="none", reg=1e-2)
    model = fit_augmented(ro, cfg)
    sa = np.concatenate([x[:, :-1], a], axis=-1)
    lam = cfg.reg * sa.reshape(-1, n + m).var(axis=0).mean()
    zeta = np.concatenate([x[:, 1:], y[..., None]], axis=-1)
    for k in range(Tn):
        coef, icpt = _ridge(sa[:, k], zeta[:, k], lam)
        np.testing.assert_allclose(model.Ao[k], coef.T, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(model.co[k], icpt, rtol=1e-7, atol=1e-9)
        assert np.linalg.eigvalsh(model.So[k])[0] > 0


# --------------------------------------------------------------------------- NIW posterior oracle


def _oracle_fit(ro: Rollouts, prior: MixturePrior, cfg: FitConfig):
    """docs/math.md §2 steps 2-4 written out step by step with scipy densities and np.linalg.solve."""
    X = tuples(ro)
    M, Tn, D = X.shape
    nz = ro.n + ro.m
    lam = cfg.reg * X[..., :nz].reshape(-1, nz).var(axis=0).mean()
    Ao, co, So = [], [], []
    for k in range(Tn):
        Xk = X[:, k]
        dens = np.stack(
            [w * multivariate_normal(mu, S).pdf(Xk) for w, mu, S in zip(prior.weights, prior.means, prior.covariances)],
            axis=1,
        ).reshape(M, -1)
        resp = dens / dens.sum(axis=1, keepdims=True)
        wk = resp.mean(axis=0)
        mu0 = sum(w * mu for w, mu in zip(wk, prior.means))
        S0 = sum(w * (S + np.outer(mu - mu0, mu - mu0)) for w, mu, S in zip(wk, prior.means, prior.covariances))
        mue = Xk.mean(axis=0)
        Le = (Xk - mue).T @ (Xk - mue) / M
        mu_k = (cfg.k0 * mu0 + M * mue) / (cfg.k0 + M)
        Lam = (cfg.n0 * S0 + M * Le + cfg.k0 * M / (cfg.k0 + M) * np.outer(mue - mu0, mue - mu0)) / (M + cfg.n0)
        Lam[:nz, :nz] += lam * np.eye(nz)
        A = np.linalg.solve(Lam[:nz, :nz], Lam[:nz, nz:]).T
        Ao.append(A)
        co.append(mu_k[nz:] - A @ mu_k[:nz])
        So.append(Lam[nz:, nz:] - A @ Lam[:nz, nz:])
    return np.array(Ao), np.array(co), np.array(So)


@pytest.mark.parametrize("k0,n0", [(1.0, 1.0), (3.0, 0.5)])
def test_mixture_posterior_matches_direct_niw_computation(data, k0, n0):
    cfg = FitConfig(k0=k0, n0=n0, n_components=5)
    ro = _subset(data, slice(0, 5))
    prior = update_prior(None, data, cfg, np.random.default_rng(0))
    model = fit_augmented(ro, cfg, prior)
    Ao, co, So = _oracle_fit(ro, prior, cfg)
    np.testing.assert_allclose(model.Ao, Ao, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(model.co, co, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(model.So, So, rtol=1e-7, atol=1e-10)


def test_prior_with_vanishing_strength_reduces_to_least_squares(data):
    prior = update_prior(None, data, FitConfig(n_components=4), np.random.default_rng(0))
    weak = fit_augmented(data, FitConfig(k0=1e-10, n0=1e-10), prior)
    ls = fit_augmented(data, FitConfig(prior="none"))
    np.testing.assert_allclose(weak.Ao, ls.Ao, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(weak.So, ls.So, rtol=1e-6, atol=1e-10)


def test_prior_none_config_ignores_given_prior(data):
    prior = update_prior(None, data, FitConfig(n_components=4), np.random.default_rng(0))
    a = fit_augmented(data, FitConfig(prior="none"), prior)
    b = fit_augmented(data, FitConfig(prior="none"))
    np.testing.assert_array_equal(a.Ao, b.Ao)


def _loop_fit(ro: Rollouts, prior: MixturePrior, cfg: FitConfig, include_y: bool = True):
    """The NIW posterior + conditioning step by step and component by component (log densities,
    scipy triangular/Cholesky solves): the reference for the batched implementation."""
    X = tuples(ro, include_y)
    M, Tn, D = X.shape
    nz = ro.n + ro.m
    lam = cfg.reg * X[..., :nz].reshape(-1, nz).var(axis=0).mean()
    w, mus, Ss = prior.weights, prior.means[:, :D], prior.covariances[:, :D, :D]
    out = {"mu0": [], "S0": [], "Ao": [], "co": [], "So": []}
    for k in range(Tn):
        Xk = X[:, k]
        logp = np.empty((M, len(w)))
        for c in range(len(w)):
            L = np.linalg.cholesky(Ss[c])
            r = solve_triangular(L, (Xk - mus[c]).T, lower=True)
            logp[:, c] = np.log(w[c]) - 0.5 * (r * r).sum(0) - np.log(np.diag(L)).sum()
        wk = np.exp(logp - logsumexp(logp, axis=1, keepdims=True)).mean(axis=0)
        mu0 = np.zeros(D)
        for c in range(len(w)):
            mu0 += wk[c] * mus[c]
        S0 = np.zeros((D, D))
        for c in range(len(w)):
            S0 += wk[c] * (Ss[c] + np.outer(mus[c] - mu0, mus[c] - mu0))
        mue = Xk.mean(axis=0)
        Le = (Xk - mue).T @ (Xk - mue) / M
        mu_k = (cfg.k0 * mu0 + M * mue) / (cfg.k0 + M)
        Lam = (cfg.n0 * S0 + M * Le + cfg.k0 * M / (cfg.k0 + M) * np.outer(mue - mu0, mue - mu0)) / (M + cfg.n0)
        Lam = 0.5 * (Lam + Lam.T)
        Lam[:nz, :nz] += lam * np.eye(nz)
        A = cho_solve(cho_factor(Lam[:nz, :nz], lower=True), Lam[:nz, nz:]).T
        So = Lam[nz:, nz:] - A @ Lam[:nz, nz:]
        for key, v in (("mu0", mu0), ("S0", S0), ("Ao", A), ("co", mu_k[nz:] - A @ mu_k[:nz]),
                       ("So", 0.5 * (So + So.T))):
            out[key].append(v)
    return {k: np.array(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def prior6(data):
    prior = update_prior(None, data, FitConfig(n_components=6), np.random.default_rng(0))
    assert prior.n_components >= 2
    return prior


@pytest.mark.parametrize("include_y", [True, False])
def test_batched_posterior_matches_per_step_loop_to_1e10(data, prior6, include_y):
    cfg = FitConfig(n_components=6, k0=2.0, n0=1.5)
    ro = _subset(data, slice(0, 5))  # M = 5 < n+m: the prior matters
    prior = prior6
    ref = _loop_fit(ro, prior, cfg, include_y)
    mu0, S0 = prior.step_prior(tuples(ro, include_y), include_y)
    if include_y:
        model = fit_augmented(ro, cfg, prior)
        Ao, co, So = model.Ao, model.co, model.So
    else:
        dyn = fit_dynamics(ro, cfg, prior)
        Ao, co, So = np.concatenate([dyn.A, dyn.B], axis=2), dyn.c, dyn.cov
    # no eigenvalue floor was active (else the comparison would test the floor, not the algebra)
    assert np.linalg.eigvalsh(ref["So"])[:, 0].min() > 1e-6
    for got, key in ((mu0, "mu0"), (S0, "S0"), (Ao, "Ao"), (co, "co"), (So, "So")):
        scale = np.abs(ref[key]).max()
        np.testing.assert_allclose(got, ref[key], rtol=1e-10, atol=1e-10 * scale, err_msg=key)


def test_batched_responsibilities_match_per_component_densities(data, prior6):
    prior = prior6
    X = tuples(data).reshape(-1, prior.dim)[:300]
    dens = np.stack([w * multivariate_normal(mu, S).pdf(X)
                     for w, mu, S in zip(prior.weights, prior.means, prior.covariances)], axis=1)
    np.testing.assert_allclose(prior.responsibilities(X), dens / dens.sum(1, keepdims=True), rtol=1e-8, atol=1e-12)


# --------------------------------------------------------------------------- warm start


def _affine(ro: Rollouts, a: float, b: float) -> Rollouts:
    """States mapped to ``a s + b`` (actions and ``y`` unchanged)."""
    return Rollouts(x=a * ro.x + b, s=a * ro.s + b, a=np.array(ro.a), cost=np.array(ro.cost), y=np.array(ro.y))


def _affine_prior(p: MixturePrior, a: float, b: float) -> MixturePrior:
    """``p`` expressed in the units of :func:`_affine` (the ``s`` and ``s'`` columns of the tuples)."""
    n, m = p.n, p.m
    D = p.dim
    f = np.ones(D)
    f[:n] = f[n + m : 2 * n + m] = a
    g = np.zeros(D)
    g[:n] = g[n + m : 2 * n + m] = b
    cov = lambda S: S * f[:, None] * f[None, :]  # noqa: E731
    vb = p.vb._replace(means=p.vb.means * f + g, covariances=cov(p.vb.covariances))
    return MixturePrior(p.weights, p.means * f + g, cov(p.covariances), p.buffer * f + g, n, m, vb=vb)


def _close(x, y, rtol, name=""):
    np.testing.assert_allclose(x, y, rtol=rtol, atol=rtol * np.abs(y).max(), err_msg=name)


def test_warm_start_continues_the_same_vb_iteration(data):
    """30 VB iterations, then 10 more warm-started, equal 40 iterations in one go (same
    initialisation, same data): the stored posterior is the state of the iteration."""
    ro = _affine(_subset(data, slice(0, 10)), 7.0, 3.0)  # standardisation far from the identity
    # tol tiny: never "converged", so fixed iteration counts; min_weight 0: every component carried over
    cfg = FitConfig(n_components=5, buffer_size=0, tol=1e-300, min_weight=0.0)
    p30 = update_prior(None, ro, cfg.replace(max_iter=30), np.random.default_rng(0))
    warm = update_prior(p30, ro, cfg.replace(max_iter=10), np.random.default_rng(1))
    p40 = update_prior(None, ro, cfg.replace(max_iter=40), np.random.default_rng(0))
    assert (p30.n_iter, warm.n_iter, p40.n_iter) == (30, 10, 40)
    assert not np.allclose(p30.vb.means, p40.vb.means, rtol=1e-6)  # the 10 iterations did move it
    for x, y, name in zip(warm.vb, p40.vb, VBState._fields):
        _close(x, y, 1e-8, name)


def test_warm_start_is_equivariant_to_rescaled_states(data):
    """Warm-starting on states ``a s + b`` from the prior mapped to those units gives the mapped
    result of warm-starting on ``s``: the stored posterior is in original units and is carried
    through each fit's own standardisation."""
    cfg = FitConfig(n_components=4, buffer_size=400)
    r1, r2 = _subset(data, slice(0, 6)), _subset(data, slice(6, 12))
    p1 = update_prior(None, r1, cfg, np.random.default_rng(0))
    p2 = update_prior(p1, r2, cfg, np.random.default_rng(1))
    ref = _affine_prior(p2, 5.0, -2.0)
    got = update_prior(_affine_prior(p1, 5.0, -2.0), _affine(r2, 5.0, -2.0), cfg, np.random.default_rng(1))
    assert got.n_iter == p2.n_iter
    for x, y, name in zip(got.vb, ref.vb, VBState._fields):
        _close(x, y, 1e-7, name)


def test_warm_start_carries_over_only_the_kept_components(data):
    cfg = FitConfig(n_components=12, min_weight=0.08)
    r1, r2 = _subset(data, slice(0, 4)), _subset(data, slice(4, 8))
    p1 = update_prior(None, r1, cfg, np.random.default_rng(0))
    assert p1.n_components < 12  # VB emptied some components
    assert p1.vb.means.shape[0] == p1.n_components
    p2 = update_prior(p1, r2, cfg, np.random.default_rng(1))
    assert p2.vb.means.shape[0] == p2.n_components <= p1.n_components


def test_warm_start_flag_off_reproduces_cold_start(data):
    cfg = FitConfig(n_components=4, buffer_size=200)
    r1, r2 = _subset(data, slice(0, 4)), _subset(data, slice(4, 8))
    p1 = update_prior(None, r1, cfg, np.random.default_rng(0))
    assert p1.vb is not None and p1.vb.means.shape[0] == 4
    no_vb = MixturePrior(p1.weights, p1.means, p1.covariances, p1.buffer, p1.n, p1.m)
    cold = update_prior(p1, r2, cfg.replace(prior_warm_start=False), np.random.default_rng(5))
    ref = update_prior(no_vb, r2, cfg, np.random.default_rng(5))  # nothing to warm-start from
    warm = update_prior(p1, r2, cfg, np.random.default_rng(5))
    for f in ("weights", "means", "covariances", "buffer"):
        np.testing.assert_array_equal(getattr(cold, f), getattr(ref, f))
    np.testing.assert_array_equal(warm.buffer, cold.buffer)
    assert warm.n_iter != cold.n_iter or not np.array_equal(warm.vb.means, cold.vb.means)


def test_warm_start_is_deterministic_and_leaves_previous_prior_unchanged(data):
    cfg = FitConfig(n_components=4, buffer_size=200)
    r1, r2 = _subset(data, slice(0, 4)), _subset(data, slice(4, 8))
    p1 = update_prior(None, r1, cfg, np.random.default_rng(0))
    before = [np.array(a) for a in p1.vb] + [np.array(p1.means)]
    a = update_prior(p1, r2, cfg, np.random.default_rng(2))
    b = update_prior(p1, r2, cfg, np.random.default_rng(2))
    for x, y in zip(a.vb, b.vb):
        np.testing.assert_array_equal(x, y)
    for x, y in zip(before, list(p1.vb) + [p1.means]):
        np.testing.assert_array_equal(x, y)


def test_warm_start_with_other_component_count_starts_cold(data):
    r1, r2 = _subset(data, slice(0, 4)), _subset(data, slice(4, 8))
    p1 = update_prior(None, r1, FitConfig(n_components=4), np.random.default_rng(0))
    cfg = FitConfig(n_components=3)
    a = update_prior(p1, r2, cfg, np.random.default_rng(1))
    b = update_prior(p1, r2, cfg.replace(prior_warm_start=False), np.random.default_rng(1))
    np.testing.assert_array_equal(a.means, b.means)
    assert a.vb.means.shape[0] == 3


def test_prior_with_vb_state_pickles_and_validates_shapes(data):
    import pickle

    p = update_prior(None, _subset(data, slice(0, 4)), FitConfig(n_components=3), np.random.default_rng(0))
    q = pickle.loads(pickle.dumps(p))
    for x, y in zip(p.vb, q.vb):
        np.testing.assert_array_equal(x, y)
    bad = p.vb._replace(means=p.vb.means[:, :-1])
    with pytest.raises(ShapeError, match="vb means"):
        MixturePrior(p.weights, p.means, p.covariances, p.buffer, p.n, p.m, vb=bad)
    with pytest.raises(TypeError, match="VBState"):
        MixturePrior(p.weights, p.means, p.covariances, p.buffer, p.n, p.m, vb=tuple(p.vb))
    assert isinstance(q.vb, VBState)
    # the stored posterior (original units) carries the pruned mixture's components
    keep = p.vb.weight_concentration / p.vb.weight_concentration.sum() >= FitConfig().min_weight
    np.testing.assert_allclose(p.vb.means[keep], p.means, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(p.vb.covariances[keep], p.covariances, rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------- prior object / buffer / determinism


def test_prior_fields_and_pruning(data):
    cfg = FitConfig(n_components=8)
    prior = update_prior(None, data, cfg, np.random.default_rng(0))
    D = 2 * data.n + data.m + 1
    assert 1 <= prior.n_components <= 8
    assert prior.means.shape == (prior.n_components, D)
    assert prior.covariances.shape == (prior.n_components, D, D)
    assert np.isclose(prior.weights.sum(), 1.0) and np.all(prior.weights >= cfg.min_weight)
    assert np.all(np.linalg.eigvalsh(prior.covariances)[:, 0] > 0)
    # the mixture reproduces the data mean
    np.testing.assert_allclose(prior.weights @ prior.means, tuples(data).reshape(-1, D).mean(0), atol=0.05)


def test_buffer_is_bounded_and_keeps_newest(data):
    cfg = FitConfig(n_components=3, buffer_size=130)
    r1, r2 = _subset(data, slice(0, 2)), _subset(data, slice(2, 4))
    p1 = update_prior(None, r1, cfg, np.random.default_rng(0))
    assert p1.buffer.shape[0] == min(130, 2 * data.T)
    p2 = update_prior(p1, r2, cfg, np.random.default_rng(0))
    D = 2 * data.n + data.m + 1
    allt = np.concatenate([p1.buffer, tuples(r2).reshape(-1, D)])
    assert p2.buffer.shape == (130, D)
    np.testing.assert_array_equal(p2.buffer, allt[-130:])
    np.testing.assert_array_equal(p2.buffer[-2 * data.T :], tuples(r2).reshape(-1, D))
    p0 = update_prior(None, r1, cfg.replace(buffer_size=0), np.random.default_rng(0))
    assert p0.buffer.shape == (0, D)


def test_same_seed_gives_same_fit(data):
    cfg = FitConfig(n_components=6)
    ro = _subset(data, slice(0, 5))
    pa = update_prior(None, data, cfg, np.random.default_rng(3))
    pb = update_prior(None, data, cfg, np.random.default_rng(3))
    for f in ("weights", "means", "covariances", "buffer"):
        np.testing.assert_array_equal(getattr(pa, f), getattr(pb, f))
    ma, mb = fit_augmented(ro, cfg, pa), fit_augmented(ro, cfg, pb)
    np.testing.assert_array_equal(ma.Ao, mb.Ao)
    np.testing.assert_array_equal(ma.So, mb.So)
    # rng=None falls back to config.seed
    pc = update_prior(None, data, cfg.replace(seed=11))
    pd = update_prior(None, data, cfg.replace(seed=11))
    np.testing.assert_array_equal(pc.means, pd.means)


# --------------------------------------------------------------------------- validation / degenerate data


def test_fewer_than_two_rollouts_is_an_error(data):
    one = _subset(data, slice(0, 1))
    for f in (fit_augmented, fit_dynamics):
        with pytest.raises(ValueError, match="at least 2 rollouts"):
            f(one, FitConfig(prior="none"))


def test_prior_shape_mismatch_is_an_error(data):
    prior = update_prior(None, data, FitConfig(n_components=3), np.random.default_rng(0))
    rng = np.random.default_rng(1)
    x = rng.standard_normal((4, 6, 2))
    a = rng.standard_normal((4, 5, 1))
    y = np.full((4, 5), 0.5)
    small = Rollouts(x=x, s=x, a=a, cost=-np.log(y), y=y)
    with pytest.raises(ShapeError, match="n=6, m=2"):
        fit_augmented(small, FitConfig(), prior)
    with pytest.raises(ShapeError, match="n=6, m=2"):
        fit_dynamics(small, FitConfig(), prior)
    with pytest.raises(ShapeError, match="n=6, m=2"):
        update_prior(prior, small, FitConfig(), rng)


def test_nan_in_rollouts_is_rejected(data):
    s = np.array(data.s)
    s[1, 3, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        Rollouts(x=data.x, s=s, a=data.a, cost=data.cost, y=data.y)


def test_few_rollouts_least_squares_gives_pd_noise(data):
    ro = _subset(data, slice(0, 3))  # M=3 < n+m=8
    for prior in ("none", "mixture"):
        cfg = FitConfig(prior=prior, n_components=4)
        p = update_prior(None, ro, cfg, np.random.default_rng(0)) if prior == "mixture" else None
        model = fit_augmented(ro, cfg, p)
        assert np.all(np.isfinite(model.Ao))
        assert np.all(np.linalg.eigvalsh(model.So)[:, 0] > 0)
        dyn = fit_dynamics(ro, cfg, p)
        assert np.all(np.linalg.eigvalsh(dyn.cov)[:, 0] > 0)


def test_constant_state_component_is_regularised(data):
    x = np.array(data.x)
    x[..., 0] = 5.0
    y = np.ones_like(data.y)  # constant observation row too
    ro = Rollouts(x=x, s=x, a=data.a, cost=np.zeros_like(y), y=y)
    for prior in ("none", "mixture"):
        cfg = FitConfig(prior=prior, n_components=4)
        p = update_prior(None, ro, cfg, np.random.default_rng(0)) if prior == "mixture" else None
        model = fit_augmented(ro, cfg, p)
        assert np.all(np.isfinite(model.Ao)) and np.all(np.linalg.eigvalsh(model.So)[:, 0] > 0)
        # the constant component is predicted exactly (to the regulariser)
        np.testing.assert_allclose(prediction_error(model, ro, "y"), 0.0, atol=1e-8)


def _related(ro: Rollouts, shift: float, M: slice = slice(None)) -> Rollouts:
    """``ro``'s rollouts ``M``, states shifted by ``shift``, with ``x_1 = 2 x_0 + 1`` exactly (two varying
    coordinates in an exact linear relation) and ``x_2 = 0.25`` (a constant coordinate)."""
    x = np.array(ro.x[M]) + shift
    x[..., 1] = 2.0 * x[..., 0] + 1.0
    x[..., 2] = 0.25
    return Rollouts(x=x, s=x, a=ro.a[M], cost=ro.cost[M], y=ro.y[M])


def test_degenerate_directions_are_the_exact_relations_between_varying_coordinates(data):
    from soc_opt.learning.mixture import Subspace, standardisation, varying_columns

    X = tuples(_related(data, 0.0)).reshape(-1, 2 * N + MU + 1)
    center, scale = standardisation(X)
    varying = varying_columns(X.std(axis=0), center)
    assert not varying[2] and not varying[N + MU + 2]  # the constant coordinate, in s and s'
    sub = Subspace.of((X - center) / scale, varying, 1e-6)
    assert sub.null.shape[1] == 2  # x_1 = 2 x_0 + 1 in s and in s'
    assert sub.rank + sub.null.shape[1] == X.shape[1]
    np.testing.assert_allclose(sub.basis.T @ sub.null, 0.0, atol=1e-12)
    for off in (0, N + MU):  # each null direction lies in the span of (x_0, x_1) of s or of s'
        w = sub.null[[off, off + 1]]
        assert np.linalg.norm(w) > 1 - 1e-9 or np.linalg.norm(w) < 1e-9
    Zd = tuples(data).reshape(-1, 2 * N + MU + 1)
    c, sc = standardisation(Zd)
    assert Subspace.of((Zd - c) / sc, varying_columns(Zd.std(axis=0), c), 1e-6) is None


def test_warm_start_survives_a_component_left_without_tuples_on_related_coordinates(data):
    """A warm-started component that gets no tuples keeps sklearn's covariance prior, which is singular
    along an exact relation between coordinates: VB failed ("ill-defined empirical covariance").  Fitted
    on the non-degenerate directions, the prior keeps the relation in its means and is positive definite."""
    cfg = FitConfig(n_components=4, buffer_size=0)
    two = _related(data, 0.0, slice(0, 20))
    far = _related(data, 30.0, slice(20, 40))
    both = Rollouts(x=np.concatenate([two.x, far.x]), s=np.concatenate([two.s, far.s]), a=data.a,
                    cost=data.cost, y=data.y)
    first = update_prior(None, both, cfg, np.random.default_rng(0))
    prior = update_prior(first, two, cfg, np.random.default_rng(1))  # the far cluster's components get nothing
    assert prior.vb is not None and prior.n_components >= 1
    np.testing.assert_allclose(prior.means[:, 1], 2.0 * prior.means[:, 0] + 1.0, atol=1e-9)
    np.testing.assert_allclose(prior.means[:, 2], 0.25, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(prior.covariances)[:, 0] > 0)
    again = update_prior(prior, two, cfg, np.random.default_rng(2))  # and a warm start from it
    dyn = fit_dynamics(two, cfg, again)
    assert np.all(np.isfinite(dyn.A)) and np.all(np.linalg.eigvalsh(dyn.cov)[:, 0] > 0)


def test_config_toml_and_validation(tmp_path):
    f = tmp_path / "fit.toml"
    f.write_text('[fit]\nprior = "none"\nn_components = 5\nk0 = 2.0\nprior_warm_start = false\n')
    cfg = FitConfig.from_toml(f, table="fit")
    assert cfg.prior == "none" and cfg.n_components == 5 and cfg.k0 == 2.0 and cfg.n0 == 1.0
    assert cfg.prior_warm_start is False
    assert FitConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="prior"):
        FitConfig.from_dict({"prior": "gmm"})
    with pytest.raises(ConfigError, match="unknown config key"):
        FitConfig.from_dict({"strength": 1.0})
    with pytest.raises(ConfigError, match="k0"):
        FitConfig.from_dict({"k0": 0})


# --------------------------------------------------------------------------- cost observations


def _closed_loop_y_moments(model: AugmentedModel, policy: LinearGaussianPolicy, mu0, P0):
    """Exact mean and variance of y_k under the model and the policy, by moment propagation."""
    n = model.n
    mu, P = mu0.copy(), P0.copy()
    mean, var = [], []
    for k in range(model.T):
        Kk, kk, Sk = policy.K[k], policy.k[k], policy.cov[k]
        J = np.vstack([np.eye(n), Kk])
        zm = np.concatenate([mu, Kk @ mu + kk])
        Zc = J @ P @ J.T
        Zc[n:, n:] += Sk
        zm_next = model.Ao[k] @ zm + model.co[k]
        C = model.Ao[k] @ Zc @ model.Ao[k].T + model.So[k]
        mean.append(zm_next[n])
        var.append(C[n, n])
        mu, P = zm_next[:n], C[:n, :n]
    return np.array(mean), np.array(var)


@pytest.fixture(scope="module")
def small_model(system):
    ro = simulate_linear(system, 30, np.random.default_rng(3))
    model = fit_augmented(ro, FitConfig(prior="none"))
    rng = np.random.default_rng(4)
    policy = LinearGaussianPolicy(
        0.1 * rng.standard_normal((T, MU, N)), 0.2 * rng.standard_normal((T, MU)), np.broadcast_to(0.5 * np.eye(MU), (T, MU, MU))
    )
    return ro, model, policy


def test_cost_observation_modes_shapes(small_model):
    ro, model, policy = small_model
    mu0, P0 = np.zeros(N), np.eye(N)
    Y = cost_observations("model", ro, model, policy, mu0, P0, np.random.default_rng(0))
    assert Y.shape == (ro.M, T)
    Y = cost_observations("model", ro, model, policy, mu0, P0, np.random.default_rng(0), n_samples=7)
    assert Y.shape == (7, T)
    Ym = cost_observations("measured", ro)
    assert Ym.shape == (ro.M, T)
    np.testing.assert_array_equal(Ym, ro.y)
    Yo = cost_observations("optimistic", ro, model)
    assert Yo.shape == (1, T) and np.all(Yo == 1.0)
    with pytest.raises(ValueError, match="'bogus'"):
        cost_observations("bogus", ro, model, policy, mu0, P0, np.random.default_rng(0))
    with pytest.raises(ShapeError):
        cost_observations("model", ro, model, LinearGaussianPolicy.zeros(T - 1, N, MU), mu0, P0, np.random.default_rng(0))


def test_model_cost_observations_match_model_moments(small_model):
    ro, model, policy = small_model
    mu0, P0 = 0.3 * np.ones(N), 0.5 * np.eye(N)
    S = 4000
    Y = cost_observations("model", ro, model, policy, mu0, P0, np.random.default_rng(5), n_samples=S)
    mean, var = _closed_loop_y_moments(model, policy, mu0, P0)
    # 5 standard errors per step (T=50 steps, two statistics each)
    z_mean = (Y.mean(0) - mean) / np.sqrt(var / S)
    z_var = (Y.var(0, ddof=1) - var) / (var * np.sqrt(2.0 / (S - 1)))
    assert np.max(np.abs(z_mean)) < 5, np.max(np.abs(z_mean))
    assert np.max(np.abs(z_var)) < 5, np.max(np.abs(z_var))


def test_model_cost_observations_are_reproducible(small_model):
    ro, model, policy = small_model
    args = (ro, model, policy, np.zeros(N), np.eye(N))
    a = cost_observations("model", *args, np.random.default_rng(9))
    b = cost_observations("model", *args, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)


def test_prediction_error_validation(small_model):
    ro, model, _ = small_model
    with pytest.raises(ValueError, match="AugmentedModel"):
        prediction_error(model.dynamics(), ro, "y")
    assert prediction_error(model, ro).shape == (T,)
    assert prediction_error(model, ro, "y").shape == (T,)
    with pytest.raises(ValueError, match="target"):
        prediction_error(model, ro, "both")
