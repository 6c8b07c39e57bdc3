"""Tests of soc_opt.noise.estimator (docs/math.md §10.2) against brute-force Gaussian conditioning."""

from __future__ import annotations

import numpy as np
import pytest
from noise_oracle import closed_loop, condition, cov, random_ltv, random_pd, sample, stack
from scipy.stats import multivariate_normal

from soc_opt import lqg
from soc_opt.models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    QuadraticCost,
    ShapeError,
)
from soc_opt.noise.estimator import (
    FilteredPolicy,
    KalmanFilter,
    cost_correction,
    filter_pass,
    filter_states,
    filter_step,
    filtered_cost,
    initial_estimate,
    innovation_augmented,
    innovation_dynamics,
    kalman_filter,
    measurement_noise,
)


def _system(n=2, m=1, T=4, seed=0):
    rng = np.random.default_rng(seed)
    sys = random_ltv(n, m, T, rng)
    dyn = LinearGaussianDynamics(sys["A"], sys["B"], sys["c"], sys["W"])
    R = random_pd(n, rng, 0.3)
    mu0 = rng.standard_normal(n)
    P0 = random_pd(n, rng, 0.5)
    return rng, sys, dyn, R, mu0, P0


def _policy(T, n, m, rng, var=0.2):
    K = 0.4 * rng.standard_normal((T, m, n))
    k = rng.standard_normal((T, m))
    S = np.stack([random_pd(m, rng, var) for _ in range(T)])
    return LinearGaussianPolicy(K, k, S)


def _filt_dict(kf):
    return {"A": kf.A, "B": kf.B, "c": kf.c, "G": kf.G, "mu0": kf.mu0}


# --------------------------------------------------------------------------- the filter


@pytest.mark.parametrize("singular", [False, True])
def test_filter_equals_bruteforce_conditioning_on_measurements(singular):
    """xhat_k = E[x_k | s_0..s_k], P_k, P^-_k and log p(s | a) from the full joint Gaussian (fixed actions)."""
    n, m, T = 3, 2, 4
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=1)
    if singular:  # PSD (rank-deficient) W and P0 are allowed when R > 0
        v = rng.standard_normal((n, 1))
        P0 = v @ v.T
        sys["W"] = np.broadcast_to(v @ v.T * 0.1, (T, n, n)).copy()
        dyn = LinearGaussianDynamics(sys["A"], sys["B"], sys["c"], sys["W"])
    actions = rng.standard_normal((T, m))
    cl = closed_loop(sys, R, mu0, P0, None, None, None, actions=actions)
    kf = kalman_filter(dyn, R, mu0, P0)
    for trial in range(3):
        s_val = np.array(sample(cl["s"], rng))
        fp = filter_pass(kf, s_val, actions)
        for k in range(T + 1):
            obs = stack(cl["s"][: k + 1])
            mean, C = condition(cl["x"][k], obs, s_val[: k + 1].ravel())
            np.testing.assert_allclose(fp.mean[k], mean, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(kf.P[k], C, rtol=1e-8, atol=1e-10)
            if k > 0:
                pm, Cm = condition(cl["x"][k], stack(cl["s"][:k]), s_val[:k].ravel())
                np.testing.assert_allclose(fp.pred_mean[k], pm, rtol=1e-9, atol=1e-9)
                np.testing.assert_allclose(kf.P_pred[k], Cm, rtol=1e-8, atol=1e-10)
        all_s = stack(cl["s"])
        ll = multivariate_normal(all_s.const, cov(all_s)).logpdf(s_val.ravel())
        np.testing.assert_allclose(fp.loglik, ll, rtol=1e-10)


def test_online_filter_step_equals_batch_and_is_causal():
    n, m, T = 2, 1, 6
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=2)
    kf = kalman_filter(dyn, R, mu0, P0)
    M = 5
    s = rng.standard_normal((M, T + 1, n))
    a = rng.standard_normal((M, T, m))
    batch = filter_states(kf, s, a)
    xh = filter_step(kf, 0, s[:, 0])
    np.testing.assert_allclose(xh, batch[:, 0], atol=1e-12)
    for k in range(1, T + 1):
        xh = filter_step(kf, k, s[:, k], xh, a[:, k - 1])
        np.testing.assert_allclose(xh, batch[:, k], atol=1e-12)
    # one sequence at a time gives the same numbers (leading axes are batch axes)
    np.testing.assert_allclose(filter_states(kf, s[3], a[3]), batch[3], atol=1e-12)
    # causality: changing s_{j..T} and a_{j-1..} leaves xhat_0..xhat_{j-1} unchanged
    j = 3
    s2, a2 = s.copy(), a.copy()
    s2[:, j:] += 10.0
    a2[:, j - 1 :] -= 5.0
    out = filter_states(kf, s2, a2)
    np.testing.assert_array_equal(out[:, :j], batch[:, :j])
    assert np.all(np.abs(out[:, j] - batch[:, j]) > 1e-6)


def test_filter_without_measurement_noise_returns_the_measurements():
    n, m, T = 3, 1, 5
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=3)
    kf = kalman_filter(dyn, measurement_noise(0.0, n), mu0, P0)
    s = rng.standard_normal((4, T + 1, n))
    a = rng.standard_normal((4, T, m))
    np.testing.assert_allclose(kf.G, np.broadcast_to(np.eye(n), kf.G.shape), atol=1e-12)
    np.testing.assert_allclose(filter_states(kf, s, a), s, atol=1e-12)


def test_deterministic_start_keeps_the_prior_mean():
    n, m, T = 2, 1, 3
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=4)
    kf = kalman_filter(dyn, R, mu0, np.zeros((n, n)))
    np.testing.assert_allclose(kf.G[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(filter_step(kf, 0, rng.standard_normal((3, n))), np.broadcast_to(mu0, (3, n)))
    _, c0 = initial_estimate(kf)
    np.testing.assert_allclose(c0, 0.0, atol=1e-15)


def test_filter_gain_identities_hold():
    """G_k R = P_k and G_k S_k G_k^T = P^-_k - P_k (used by the innovation form and the y row)."""
    n, m, T = 3, 2, 5
    _, _, dyn, R, mu0, P0 = _system(n, m, T, seed=5)
    kf = kalman_filter(dyn, R, mu0, P0)
    np.testing.assert_allclose(kf.G @ R, kf.P, atol=1e-12)
    np.testing.assert_allclose(kf.G @ kf.S @ np.swapaxes(kf.G, 1, 2), kf.P_pred - kf.P, atol=1e-12)


def test_filter_roundtrips_through_dict():
    _, _, dyn, R, mu0, P0 = _system(seed=6)
    kf = kalman_filter(dyn, R, mu0, P0)
    kf2 = KalmanFilter.from_dict(kf.to_dict())
    for name in ("A", "B", "c", "W", "R", "mu0", "P0", "G", "P", "P_pred", "S"):
        np.testing.assert_array_equal(getattr(kf2, name), getattr(kf, name))


# --------------------------------------------------------------------------- filtered closed loop


def test_innovation_form_reproduces_the_exact_estimate_marginals_and_cost():
    """The Markov model in xhat gives the exact E[xhat_k], Cov(xhat_k), and E[l(x, a)] with the correction."""
    n, m, T = 3, 2, 5
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=7)
    kf = kalman_filter(dyn, R, mu0, P0)
    pol = _policy(T, n, m, rng)
    cl = closed_loop(sys, R, mu0, P0, pol.K, pol.k, pol.cov, filt=_filt_dict(kf))
    m0, c0 = initial_estimate(kf)
    marg = lqg.forward(innovation_dynamics(kf), pol, m0, c0)
    Cs = np.stack([random_pd(n + m, rng) for _ in range(T)])
    cost = QuadraticCost(Cs, rng.standard_normal((T, n + m)), n, rng.standard_normal(T))
    exact_cost = np.empty(T)
    for k in range(T + 1):
        xh = cl["xhat"][k]
        np.testing.assert_allclose(marg.mean[k], xh.const, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(marg.cov[k], cov(xh), rtol=1e-9, atol=1e-10)
        err = cl["x"][k] - xh
        # the estimation error is independent of the estimate, with covariance P_k
        np.testing.assert_allclose(cov(err, xh), 0.0, atol=1e-10)
        np.testing.assert_allclose(cov(err), kf.P[k], rtol=1e-9, atol=1e-11)
        if k < T:
            z = stack([cl["x"][k], cl["a"][k]])
            Cz = cov(z)
            exact_cost[k] = 0.5 * np.trace(cost.C[k] @ Cz) + 0.5 * z.const @ cost.C[k] @ z.const + cost.c[k] @ z.const + cost.c0[k]
    via_innovation = lqg.expected_cost(innovation_dynamics(kf), filtered_cost(kf, cost), pol, m0, c0)
    np.testing.assert_allclose(via_innovation, exact_cost, rtol=1e-9)
    without = lqg.expected_cost(innovation_dynamics(kf), cost, pol, m0, c0)
    np.testing.assert_allclose(exact_cost - without, cost_correction(kf, cost), rtol=1e-8)
    assert np.all(cost_correction(kf, cost) > 0)


def test_augmented_model_in_xhat_equals_the_exact_regression_of_the_filtered_loop():
    """(xhat_{k+1}, y_k) | (xhat_k, a_k): same Ao, co; noise covariance with the filter-error terms."""
    n, m, T = 2, 2, 4
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=8)
    Ay = rng.standard_normal((T, 1, n))
    By = rng.standard_normal((T, 1, m))
    cy = rng.standard_normal((T, 1))
    joint = np.empty((T, n + 1, n + 1))
    for k in range(T):
        F = rng.standard_normal((n + 1, n + 1)) * 0.3
        joint[k] = F @ F.T + 0.05 * np.eye(n + 1)
    sys["W"] = joint[:, :n, :n].copy()
    dyn = LinearGaussianDynamics(sys["A"], sys["B"], sys["c"], sys["W"])
    model = AugmentedModel(
        np.concatenate([np.concatenate([sys["A"], sys["B"]], 2), np.concatenate([Ay, By], 2)], 1),
        np.concatenate([sys["c"], cy], 1), joint, n,
    )
    kf = kalman_filter(dyn, R, mu0, P0)
    pol = _policy(T, n, m, rng, var=0.5)
    cl = closed_loop(sys, R, mu0, P0, pol.K, pol.k, pol.cov, filt=_filt_dict(kf),
                     y_row={"Ay": Ay, "By": By, "cy": cy, "joint": joint})
    aug = innovation_augmented(model, kf)
    for k in range(T):
        z = stack([cl["xhat"][k], cl["a"][k]])
        zeta = stack([cl["xhat"][k + 1], cl["y"][k]])
        Czz = cov(z)
        coef = np.linalg.solve(Czz, cov(z, zeta)).T
        resid = cov(zeta) - coef @ Czz @ coef.T
        np.testing.assert_allclose(aug.Ao[k], coef, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(aug.co[k], zeta.const - coef @ z.const, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(aug.So[k], resid, rtol=1e-8, atol=1e-10)
    # the state block of the xhat-frame noise is the innovation-form process noise
    np.testing.assert_allclose(aug.So[:, :n, :n], innovation_dynamics(kf).cov, atol=1e-12)


# --------------------------------------------------------------------------- errors


def test_negative_or_invalid_rho2_is_rejected_by_name():
    with pytest.raises(ValueError, match="rho2"):
        measurement_noise(-0.1, 3)
    with pytest.raises(ValueError, match="rho2"):
        measurement_noise(float("nan"), 3)
    with pytest.raises(ValueError, match="rho2"):
        measurement_noise("a lot", 3)


def test_bad_noise_model_is_rejected_by_name():
    n, m, T = 2, 1, 3
    _, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=9)
    with pytest.raises(NotPositiveDefiniteError, match="measurement noise R"):
        kalman_filter(dyn, np.diag([0.1, -0.1]), mu0, P0)
    with pytest.raises(NotPositiveDefiniteError, match="measurement noise R"):
        kalman_filter(dyn, np.array([[0.1, 0.05], [0.0, 0.1]]), mu0, P0)  # not symmetric
    with pytest.raises(NotPositiveDefiniteError, match="P0"):
        kalman_filter(dyn, R, mu0, -np.eye(n))
    with pytest.raises(NotPositiveDefiniteError, match="dynamics cov"):
        LinearGaussianDynamics(sys["A"], sys["B"], sys["c"], -sys["W"])
    with pytest.raises(NotPositiveDefiniteError, match=r"S\[0\]"):  # R = 0 and P0 = 0: s_0 carries no noise model
        kalman_filter(dyn, np.zeros((n, n)), mu0, np.zeros((n, n)))
    with pytest.raises(ShapeError, match="measurement noise R"):
        kalman_filter(dyn, np.eye(n + 1), mu0, P0)
    with pytest.raises(ShapeError, match="mu0"):
        kalman_filter(dyn, R, np.zeros(n + 1), P0)


def test_bad_filter_inputs_are_rejected_by_name():
    n, m, T = 2, 1, 3
    rng, sys, dyn, R, mu0, P0 = _system(n, m, T, seed=10)
    kf = kalman_filter(dyn, R, mu0, P0)
    with pytest.raises(ShapeError, match="s_k"):
        filter_step(kf, 0, np.zeros(n + 1))
    with pytest.raises(ValueError, match="needs the previous estimate"):
        filter_step(kf, 1, np.zeros(n))
    with pytest.raises(ValueError, match="k = 0"):
        filter_step(kf, 0, np.zeros(n), np.zeros(n), np.zeros(m))
    with pytest.raises(ShapeError, match="a_0"):
        filter_step(kf, 1, np.zeros(n), np.zeros(n), np.zeros(m + 1))
    with pytest.raises(ValueError, match="filter step k"):
        filter_step(kf, T + 1, np.zeros(n))
    with pytest.raises(ShapeError, match="actions a"):
        filter_states(kf, np.zeros((4, T + 1, n)), np.zeros((4, T + 1, m)))
    with pytest.raises(ShapeError, match="measurements s"):
        filter_states(kf, np.zeros((4, T, n)), np.zeros((4, T, m)))
    with pytest.raises(ShapeError, match="filter has"):
        FilteredPolicy(LinearGaussianPolicy.zeros(T + 1, n, m), kf)
    other = kalman_filter(LinearGaussianDynamics(sys["A"] * 0.5, sys["B"], sys["c"], sys["W"]), R, mu0, P0)
    model = AugmentedModel(
        np.concatenate([np.concatenate([sys["A"], sys["B"]], 2), np.ones((T, 1, n + m))], 1),
        np.zeros((T, n + 1)), np.broadcast_to(np.eye(n + 1), (T, n + 1, n + 1)) * 0.1, n,
    )
    with pytest.raises(ValueError, match="not built from this model"):
        innovation_augmented(model, other)
