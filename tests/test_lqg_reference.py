"""Tests of soc_opt.noise.lqg_reference (docs/math.md §10.3): exact closed-loop moments, Monte Carlo, R -> 0, optimality."""

from __future__ import annotations

import numpy as np
import pytest
from noise_oracle import closed_loop, cov, random_ltv, random_pd, stack

from soc_opt import lqg
from soc_opt.models import LinearGaussianDynamics, LinearGaussianPolicy, NotPositiveDefiniteError, QuadraticCost, ShapeError
from soc_opt.noise.estimator import (
    FilteredPolicy,
    filtered_cost,
    initial_estimate,
    innovation_dynamics,
    kalman_filter,
    measurement_noise,
)
from soc_opt.noise.lqg_reference import closed_loop_moments, expected_cost, simulate, task_reference
from soc_opt.noise.lqg_reference import lqg as lqg_solve


def _problem(n=3, m=2, T=6, seed=0):
    rng = np.random.default_rng(seed)
    sys = random_ltv(n, m, T, rng)
    dyn = LinearGaussianDynamics(sys["A"], sys["B"], sys["c"], sys["W"])
    Cs = np.zeros((T, n + m, n + m))
    for k in range(T):
        Cs[k, :n, :n] = random_pd(n, rng)
        Cs[k, n:, n:] = 0.1 * random_pd(m, rng)
    target = rng.standard_normal(n) * 2
    c = np.zeros((T, n + m))
    c[:, :n] = -(Cs[:, :n, :n] @ target)
    cost = QuadraticCost(Cs, c, n)
    R = random_pd(n, rng, 0.3)
    mu0 = rng.standard_normal(n)
    P0 = random_pd(n, rng, 0.5)
    return rng, sys, dyn, cost, R, mu0, P0


def _exact_cost(cl, cost, T, n):
    out = np.empty(T)
    for k in range(T):
        z = stack([cl["x"][k], cl["a"][k]])
        out[k] = 0.5 * np.trace(cost.C[k] @ cov(z)) + 0.5 * z.const @ cost.C[k] @ z.const + cost.c[k] @ z.const + cost.c0[k]
    return out


def test_closed_loop_moments_equal_bruteforce_with_a_mismatched_filter():
    """(x_k, xhat_k) moments and E[l(x, a)] of a stochastic policy whose filter model and prior are wrong."""
    n, m, T = 3, 2, 5
    rng, sys, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=1)
    wrong = LinearGaussianDynamics(sys["A"] * 0.8, sys["B"] + 0.1, sys["c"] - 0.2, sys["W"] * 3)
    kf = kalman_filter(wrong, 2.0 * R, mu0 + 0.5, 0.3 * P0)
    pol = LinearGaussianPolicy(0.3 * rng.standard_normal((T, m, n)), rng.standard_normal((T, m)),
                               np.stack([random_pd(m, rng, 0.3) for _ in range(T)]))
    fpol = FilteredPolicy(pol, kf)
    cl = closed_loop(sys, R, mu0, P0, pol.K, pol.k, pol.cov,
                     filt={"A": kf.A, "B": kf.B, "c": kf.c, "G": kf.G, "mu0": kf.mu0})
    mom = closed_loop_moments(dyn, R, fpol, mu0, P0)
    for k in range(T + 1):
        z = stack([cl["x"][k], cl["xhat"][k]])
        np.testing.assert_allclose(mom.mean[k], z.const, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(mom.cov[k], cov(z), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(expected_cost(dyn, cost, R, fpol, mu0, P0), _exact_cost(cl, cost, T, n), rtol=1e-9)


def test_lqg_cost_equals_the_innovation_form_cost():
    """Two independent paths: the 2n-dim propagation and LQR-style moments of the Markov model in xhat."""
    n, m, T = 3, 2, 8
    _, _, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=2)
    sol = lqg_solve(dyn, cost, R, mu0, P0)
    kf = sol.policy.filter
    m0, c0 = initial_estimate(kf)
    other = lqg.expected_cost(innovation_dynamics(kf), filtered_cost(kf, cost), sol.policy.policy, m0, c0)
    np.testing.assert_allclose(sol.stage_cost, other, rtol=1e-9)
    np.testing.assert_allclose(sol.total, sol.stage_cost.sum())


def test_lqg_cost_matches_monte_carlo_of_the_closed_loop():
    n, m, T = 3, 2, 8
    rng, _, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=3)
    sol = lqg_solve(dyn, cost, R, mu0, P0)
    M = 20000
    smp = simulate(dyn, R, sol.policy, mu0, P0, M, np.random.default_rng(11))
    per = cost(smp.x, smp.a)  # (M, T) stage costs on the true states
    se = per.std(axis=0, ddof=1) / np.sqrt(M)
    assert np.all(np.abs(per.mean(axis=0) - sol.stage_cost) < 4.0 * se)
    tot = per.sum(axis=1)
    assert abs(tot.mean() - sol.total) < 4.0 * tot.std(ddof=1) / np.sqrt(M)
    # the online estimates of the simulation are the batch filter's
    from soc_opt.noise.estimator import filter_states

    np.testing.assert_allclose(filter_states(sol.policy.filter, smp.s, smp.a), smp.xhat, atol=1e-10)


def test_lqg_cost_tends_to_the_perfect_state_lqr_cost_as_noise_vanishes():
    n, m, T = 3, 2, 6
    _, _, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=4)
    pol = lqg.lqr(dyn, cost, mu0, P0)
    lqr_cost = lqg.expected_cost(dyn, cost, pol, mu0, P0).sum()
    exact0 = lqg_solve(dyn, cost, np.zeros((n, n)), mu0, P0).total
    np.testing.assert_allclose(exact0, lqr_cost, rtol=1e-10)
    gaps = [lqg_solve(dyn, cost, r * np.eye(n), mu0, P0).total - lqr_cost for r in (1e-8, 1e-6, 1e-4, 1e-2, 1.0)]
    assert gaps[0] < 1e-6 * abs(lqr_cost)
    # more measurement noise never helps (a noisier sensor can be simulated from a cleaner one)
    assert all(g >= -1e-9 * abs(lqr_cost) for g in gaps)
    assert all(b >= a - 1e-9 * abs(lqr_cost) for a, b in zip(gaps, gaps[1:]))


def test_lqg_is_optimal_among_filtered_linear_policies():
    """Perturbed gains, perturbed offsets, or a filter with the wrong noise level all cost more."""
    n, m, T = 3, 2, 6
    rng, _, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=5)
    sol = lqg_solve(dyn, cost, R, mu0, P0)
    base = sol.total
    pol, kf = sol.policy.policy, sol.policy.filter
    for _ in range(10):
        dK = 0.05 * rng.standard_normal(pol.K.shape)
        dk = 0.05 * rng.standard_normal(pol.k.shape)
        p2 = LinearGaussianPolicy(pol.K + dK, pol.k + dk, pol.cov, allow_singular=True)
        assert expected_cost(dyn, cost, R, FilteredPolicy(p2, kf), mu0, P0).sum() > base
    for scale in (0.0, 0.1, 10.0):  # scale 0: the policy acts on the raw measurements (G = I)
        kf2 = kalman_filter(dyn, scale * R, mu0, P0 + (1e-3 * np.eye(n) if scale == 0 else 0))
        assert expected_cost(dyn, cost, R, FilteredPolicy(pol, kf2), mu0, P0).sum() > base


def test_linear2d_reference_lies_between_perfect_states_and_raw_measurements():
    from soc_opt.tasks import load_task

    task = load_task("linear2d")
    sol = task_reference(task)
    dyn = task.linearize()
    n = task.n
    cost = task.cost_expansion(np.broadcast_to(task.mu0, (task.T + 1, n)).copy(), np.zeros((task.T, task.m)))
    Z = np.zeros((n, n))
    pol = sol.policy.policy
    perfect = lqg.expected_cost(dyn, cost, pol, task.mu0, Z).sum()
    R = measurement_noise(task.rho2, n)
    raw = expected_cost(dyn, cost, R, FilteredPolicy(pol, kalman_filter(dyn, Z, task.mu0, 1e-6 * np.eye(n))), task.mu0, Z).sum()
    assert perfect <= sol.total <= raw
    smp = simulate(dyn, R, sol.policy, task.mu0, Z, 4000, np.random.default_rng(0))
    tot = task.cost(smp.x, smp.a).sum(axis=1)
    assert abs(tot.mean() - sol.total) < 4.0 * tot.std(ddof=1) / np.sqrt(len(tot))
    # the noise sweep: rho^2 = 0 is the perfect-state LQR cost, and the cost grows with rho^2
    sweep = [task_reference(load_task("linear2d", overrides={"rho2": r})).total for r in (0.0, 0.001, 0.01, 0.1)]
    np.testing.assert_allclose(sweep[0], perfect, rtol=1e-12)
    assert all(b > a for a, b in zip(sweep, sweep[1:]))
    np.testing.assert_allclose(sweep[-1], sol.total, rtol=1e-12)


def test_bad_reference_inputs_are_rejected_by_name():
    n, m, T = 2, 1, 3
    rng, sys, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=6)
    with pytest.raises(NotPositiveDefiniteError, match="measurement noise R"):
        lqg_solve(dyn, cost, -R, mu0, P0)
    with pytest.raises(NotPositiveDefiniteError, match="P0"):
        lqg_solve(dyn, cost, R, mu0, -P0)
    sol = lqg_solve(dyn, cost, R, mu0, P0)
    with pytest.raises(NotPositiveDefiniteError, match="measurement noise R"):
        closed_loop_moments(dyn, -R, sol.policy, mu0, P0)
    with pytest.raises(ShapeError, match="mu0"):
        closed_loop_moments(dyn, R, sol.policy, np.zeros(n + 1), P0)
    short = LinearGaussianDynamics(sys["A"][:2], sys["B"][:2], sys["c"][:2], sys["W"][:2])
    with pytest.raises(ShapeError, match="filtered policy"):
        closed_loop_moments(short, R, sol.policy, mu0, P0)
    with pytest.raises(ValueError, match="number of rollouts"):
        simulate(dyn, R, sol.policy, mu0, P0, 0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="rho2"):
        measurement_noise(-1e-3, n)


def test_kl_step_runs_unchanged_on_the_filtered_loop():
    """docs/math.md §10.2: the KL step on the innovation form predicts the true closed-loop cost of its policy."""
    n, m, T = 3, 2, 6
    rng, _, dyn, cost, R, mu0, P0 = _problem(n, m, T, seed=7)
    kf = kalman_filter(dyn, R, mu0, P0)
    m0, c0 = initial_estimate(kf)
    ref = LinearGaussianPolicy(0.2 * rng.standard_normal((T, m, n)), rng.standard_normal((T, m)),
                               np.broadcast_to(np.eye(m), (T, m, m)).copy())
    lqg_cost = lqg_solve(dyn, cost, R, mu0, P0).total
    previous = np.inf
    for nu in (0.5, 2.0, 8.0):
        res = lqg.kl_step(innovation_dynamics(kf), filtered_cost(kf, cost), ref, nu, m0, c0)
        np.testing.assert_allclose(res.kl.sum(), nu, rtol=1e-4)
        true_cost = expected_cost(dyn, cost, R, FilteredPolicy(res.policy, kf), mu0, P0).sum()
        np.testing.assert_allclose(res.expected_cost, true_cost, rtol=1e-9)
        assert lqg_cost <= true_cost < previous  # a larger budget gets closer to the LQG optimum
        previous = true_cost
