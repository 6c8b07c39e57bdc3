"""Tests of the E-step (docs/math.md §4): closed loop, Kalman filter, RTS smoother, moments.

The oracle is brute-force Gaussian conditioning: every variable of the trajectory
(states, actions, observations) is written as an affine map of independent noises
``(s_0 - mu0, w_0, eo_0, ..., w_{T-1}, eo_{T-1})`` straight from the augmented model
and the policy (the action is kept explicit, so the oracle does not use the closed-loop
formulas), the joint Gaussian of ``(s_0..s_T, y_0..y_{T-1})`` is formed and conditioned
on ``Y`` with dense linear algebra.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import block_diag
from scipy.stats import multivariate_normal

from soc_opt import lgssm
from soc_opt.estep import closed_loop, kalman_filter, log_likelihood, moments, smooth
from soc_opt.models import (
    AugmentedModel,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    ShapeError,
)
from soc_opt.testing import random_estep_instance

TOL = 1e-8


# --------------------------------------------------------------------------- instances


def sample_y(rng, model, policy, mu0, P0, M):
    """Observations ``(M, T)`` sampled by simulating states and actions explicitly."""
    n, T = model.n, model.T
    s = rng.multivariate_normal(mu0, P0, size=M)
    Y = np.empty((M, T))
    for t in range(T):
        a = s @ policy.K[t].T + policy.k[t] + rng.multivariate_normal(np.zeros(policy.m), policy.cov[t], size=M)
        z = np.concatenate([s, a], axis=1)
        zeta = z @ model.Ao[t].T + model.co[t] + rng.multivariate_normal(np.zeros(n + 1), model.So[t], size=M)
        s, Y[:, t] = zeta[:, :n], zeta[:, n]
    return Y


# --------------------------------------------------------------------------- oracle


def joint_gaussian(model, policy, mu0, P0):
    """Mean and covariance of ``v = (s_0, ..., s_T, y_0, ..., y_{T-1})``.

    Each variable is ``mean + L @ w`` with ``w = (x0, w_0, eo_0, ..., w_{T-1}, eo_{T-1})``
    independent: ``x0 ~ N(0, P0)``, ``w_k ~ N(0, Sigma_k)``, ``eo_k ~ N(0, So_k)``.
    """
    n, m, T = model.n, model.m, model.T
    d = n + T * (m + n + 1)
    W = block_diag(P0, *[block_diag(policy.cov[t], model.So[t]) for t in range(T)])
    s_mean, s_map = mu0.copy(), np.zeros((n, d))
    s_map[:, :n] = np.eye(n)
    means, maps, y_means, y_maps = [s_mean], [s_map], [], []
    for t in range(T):
        off = n + t * (m + n + 1)
        a_mean = policy.K[t] @ s_mean + policy.k[t]
        a_map = policy.K[t] @ s_map
        a_map[:, off : off + m] += np.eye(m)
        A, Bm = model.Ao[t][:, :n], model.Ao[t][:, n:]
        z_mean = A @ s_mean + Bm @ a_mean + model.co[t]
        z_map = A @ s_map + Bm @ a_map
        z_map[:, off + m : off + m + n + 1] += np.eye(n + 1)
        s_mean, s_map = z_mean[:n], z_map[:n]
        y_means.append(z_mean[n])
        y_maps.append(z_map[n])
        means.append(s_mean)
        maps.append(s_map)
    mean = np.concatenate(means + [np.array(y_means)])
    L = np.vstack(maps + [np.array(y_maps).reshape(T, d)])
    cov = L @ W @ L.T
    return mean, 0.5 * (cov + cov.T)


def oracle(model, policy, mu0, P0, y, n_obs=None):
    """Posterior of ``(s_0..s_T)`` given ``y_0..y_{n_obs-1}`` (default all) by dense conditioning.

    Returns ``(mean (T+1, n), joint_cov ((T+1) n, (T+1) n), loglik)``.
    """
    n, T = model.n, model.T
    n_obs = T if n_obs is None else n_obs
    mean, cov = joint_gaussian(model, policy, mu0, P0)
    ns = (T + 1) * n
    idx_y = ns + np.arange(n_obs)
    mu_s, mu_y = mean[:ns], mean[idx_y]
    C_ss, C_sy, C_yy = cov[:ns, :ns], cov[:ns][:, idx_y], cov[np.ix_(idx_y, idx_y)]
    yo = np.asarray(y, dtype=float)[:n_obs]
    post_mean = mu_s + C_sy @ np.linalg.solve(C_yy, yo - mu_y) if n_obs else mu_s
    post_cov = C_ss - C_sy @ np.linalg.solve(C_yy, C_sy.T) if n_obs else C_ss
    ll = multivariate_normal(mu_y, C_yy).logpdf(yo) if n_obs else 0.0
    return post_mean.reshape(T + 1, n), 0.5 * (post_cov + post_cov.T), float(ll)


def block(joint, n, i, j):
    return joint[i * n : (i + 1) * n, j * n : (j + 1) * n]


def oracle_smoothed(model, policy, mu0, P0, y):
    """Oracle ``(mean, cov, cross, loglik)`` in the layout of ``Smoothed`` for one sequence."""
    n, T = model.n, model.T
    mean, joint, ll = oracle(model, policy, mu0, P0, y)
    cov = np.stack([block(joint, n, t, t) for t in range(T + 1)])
    cross = np.stack([block(joint, n, t + 1, t) for t in range(T)]) if T else np.zeros((0, n, n))
    return mean, cov, cross, ll


def assert_close(actual, desired, name):
    desired = np.asarray(desired)
    scale = max(1.0, float(np.max(np.abs(desired), initial=0.0)))
    np.testing.assert_allclose(actual, desired, rtol=TOL, atol=TOL * scale, err_msg=name)


def check_against_oracle(model, policy, mu0, P0, y):
    sm = smooth(model, policy, y, mu0, P0)
    ys = np.atleast_2d(y)
    batched = np.ndim(y) == 2
    for i, yi in enumerate(ys):
        mean, cov, cross, ll = oracle_smoothed(model, policy, mu0, P0, yi)
        got = (sm.mean[i], sm.cov[i], sm.cross[i], sm.loglik[i]) if batched else (sm.mean, sm.cov, sm.cross, sm.loglik)
        assert_close(got[0], mean, "smoothed mean")
        assert_close(got[1], cov, "smoothed cov")
        assert_close(got[2], cross, "lag-one cross-covariance")
        assert_close(got[3], ll, "log p(Y)")
    return sm


# --------------------------------------------------------------------------- closed loop


def test_closed_loop_matches_per_step_marginalisation(rng):
    model, policy, _, _ = random_estep_instance(rng, 4, 2, 5)
    Mk, mk, Sk = closed_loop(model, policy)
    assert Mk.shape == (5, 5, 4) and mk.shape == (5, 5) and Sk.shape == (5, 5, 5)
    n = model.n
    for t in range(model.T):
        # zeta = Ao [s; K s + k + w] + co + eo: linear map of (s, w, eo)
        Ao = model.Ao[t]
        assert_close(Mk[t], Ao[:, :n] + Ao[:, n:] @ policy.K[t], "M_k")
        assert_close(mk[t], Ao[:, n:] @ policy.k[t] + model.co[t], "m_k")
        J = np.hstack([Ao[:, n:], np.eye(n + 1)])
        assert_close(Sk[t], J @ block_diag(policy.cov[t], model.So[t]) @ J.T, "S_k")
        np.testing.assert_array_equal(Sk[t], Sk[t].T)


def test_closed_loop_pd_for_singular_policy_covariance():
    rng = np.random.default_rng(1)
    model, policy, mu0, P0 = random_estep_instance(rng, 3, 2, 4)
    det = LinearGaussianPolicy(policy.K, policy.k, np.zeros_like(policy.cov), allow_singular=True)
    _, _, Sk = closed_loop(model, det)
    assert np.all(np.linalg.eigvalsh(Sk)[:, 0] > 0)
    assert_close(Sk, model.So, "S_k with Sigma = 0")
    check_against_oracle(model, det, mu0, P0, sample_y(rng, model, det, mu0, P0, 1)[0])


# --------------------------------------------------------------------------- smoother vs oracle


@pytest.mark.parametrize("seed,n,m,T,M", [(0, 3, 2, 5, 0), (1, 6, 3, 8, 0), (2, 2, 1, 1, 0), (3, 5, 2, 7, 3)])
def test_smoother_matches_bruteforce_conditioning(seed, n, m, T, M):
    rng = np.random.default_rng(seed)
    model, policy, mu0, P0 = random_estep_instance(rng, n, m, T)
    Y = sample_y(rng, model, policy, mu0, P0, max(M, 1))
    check_against_oracle(model, policy, mu0, P0, Y if M else Y[0])


@settings(max_examples=100, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 6),
    m=st.integers(1, 3),
    T=st.integers(1, 8),
    M=st.sampled_from([0, 1, 3]),
    cross=st.booleans(),
)
def test_smoother_matches_bruteforce_conditioning_random(seed, n, m, T, M, cross):
    rng = np.random.default_rng(seed)
    model, policy, mu0, P0 = random_estep_instance(rng, n, m, T, cross=cross)
    Y = sample_y(rng, model, policy, mu0, P0, max(M, 1))
    check_against_oracle(model, policy, mu0, P0, Y if M else Y[0])


def test_smoother_matches_oracle_for_arbitrary_observations():
    """Observations far from the model's predictions (e.g. the optimistic y = 1 mode)."""
    rng = np.random.default_rng(4)
    model, policy, mu0, P0 = random_estep_instance(rng, 4, 2, 6)
    check_against_oracle(model, policy, mu0, P0, np.ones(6))
    check_against_oracle(model, policy, mu0, P0, 5.0 * rng.normal(size=(2, 6)))


def test_action_noise_alone_correlates_state_and_observation_noise():
    """``So`` block-diagonal, but shared action noise (B Sigma By^T) still couples s_{k+1} and y_k."""
    rng = np.random.default_rng(5)
    model, policy, mu0, P0 = random_estep_instance(rng, 4, 3, 6, cross=False, policy_var=2.0)
    _, _, Sk = closed_loop(model, policy)
    assert np.abs(Sk[:, :4, 4]).max() > 0.1
    check_against_oracle(model, policy, mu0, P0, sample_y(rng, model, policy, mu0, P0, 2))


def test_state_observation_cross_block_matters():
    """Zeroing the s-y block of S_k (what an implementation ignoring it computes) changes the answer."""
    rng = np.random.default_rng(6)
    n, m, T = 4, 2, 6
    model, policy, mu0, P0 = random_estep_instance(rng, n, m, T, policy_var=1.0)
    y = sample_y(rng, model, policy, mu0, P0, 1)[0]
    truth = oracle_smoothed(model, policy, mu0, P0, y)

    # same closed loop expressed with a deterministic policy, S_k with its cross block dropped
    Bs = model.Ao[:, :, n:]
    S = model.So + np.einsum("tia,tab,tjb->tij", Bs, policy.cov, Bs)
    S_naive = S.copy()
    S_naive[:, :n, n] = 0.0
    S_naive[:, n, :n] = 0.0
    assert np.abs(S[:, :n, n]).max() > 0.1
    naive_model = AugmentedModel(model.Ao, model.co, S_naive, n)
    det = LinearGaussianPolicy(policy.K, policy.k, np.zeros_like(policy.cov), allow_singular=True)
    naive = smooth(naive_model, det, y, mu0, P0)

    assert np.abs(naive.mean - truth[0]).max() > 1e-2
    assert np.abs(naive.cov - truth[1]).max() > 1e-3
    assert abs(naive.loglik - truth[3]) > 1e-2
    # ... while the smoother is exact on both models
    check_against_oracle(model, policy, mu0, P0, y)
    check_against_oracle(naive_model, det, mu0, P0, y)


# --------------------------------------------------------------------------- filter


def test_filter_matches_conditioning_on_past_observations():
    rng = np.random.default_rng(7)
    model, policy, mu0, P0 = random_estep_instance(rng, 3, 2, 5)
    n, T = 3, 5
    Y = sample_y(rng, model, policy, mu0, P0, 2)
    f = kalman_filter(model, policy, Y, mu0, P0)
    assert isinstance(f, lgssm.Filtered)
    assert f.predicted_means.shape == (2, T + 1, n) and f.filtered_covariances.shape == (2, T, n, n)
    for i in range(2):
        for t in range(T + 1):
            mean, joint, _ = oracle(model, policy, mu0, P0, Y[i], n_obs=t)  # y_0..y_{t-1}
            assert_close(f.predicted_means[i, t], mean[t], f"predicted mean {t}")
            assert_close(f.predicted_covariances[i, t], block(joint, n, t, t), f"predicted cov {t}")
            if t < T:
                mean, joint, _ = oracle(model, policy, mu0, P0, Y[i], n_obs=t + 1)  # y_0..y_t
                assert_close(f.filtered_means[i, t], mean[t], f"filtered mean {t}")
                assert_close(f.filtered_covariances[i, t], block(joint, n, t, t), f"filtered cov {t}")
        assert_close(f.marginal_loglik[i], oracle(model, policy, mu0, P0, Y[i])[2], "filter log p(Y)")


def test_log_likelihood_equals_smoother_loglik():
    rng = np.random.default_rng(8)
    model, policy, mu0, P0 = random_estep_instance(rng, 3, 2, 6)
    Y = sample_y(rng, model, policy, mu0, P0, 3)
    ll = log_likelihood(model, policy, Y, mu0, P0)
    assert ll.shape == (3,)
    np.testing.assert_array_equal(ll, smooth(model, policy, Y, mu0, P0).loglik)
    single = log_likelihood(model, policy, Y[1], mu0, P0)
    assert isinstance(single, float)
    assert_close(single, ll[1], "single-sequence loglik")


# --------------------------------------------------------------------------- batching


def test_batched_equals_looped_single_sequences():
    rng = np.random.default_rng(9)
    model, policy, mu0, P0 = random_estep_instance(rng, 5, 2, 12)
    Y = sample_y(rng, model, policy, mu0, P0, 4)
    b = smooth(model, policy, Y, mu0, P0)
    assert b.batched
    assert b.mean.shape == (4, 13, 5) and b.cov.shape == (4, 13, 5, 5) and b.cross.shape == (4, 12, 5, 5)
    assert b.loglik.shape == (4,)
    for i in range(4):
        s = smooth(model, policy, Y[i], mu0, P0)
        assert not s.batched and isinstance(s.loglik, float)
        np.testing.assert_allclose(b.mean[i], s.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.cov[i], s.cov, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.cross[i], s.cross, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.loglik[i], s.loglik, rtol=1e-12)


# --------------------------------------------------------------------------- long horizon


def test_long_horizon_covariances_stay_positive_definite():
    rng = np.random.default_rng(10)
    n, m, T, M = 26, 7, 1000, 3
    model, policy, mu0, P0 = random_estep_instance(rng, n, m, T)
    Y = sample_y(rng, model, policy, mu0, P0, M)
    sm = smooth(model, policy, Y, mu0, P0)
    f = kalman_filter(model, policy, Y, mu0, P0)
    for arr in (sm.mean, sm.cov, sm.cross, sm.loglik, f.filtered_covariances, f.predicted_covariances):
        assert np.all(np.isfinite(arr))
    cov, cross = sm.cov[0], sm.cross[0]
    np.testing.assert_array_equal(cov, np.swapaxes(cov, 1, 2))
    assert np.linalg.eigvalsh(cov)[:, 0].min() > 0
    assert np.linalg.eigvalsh(f.filtered_covariances[0])[:, 0].min() > 0
    # joint covariance of (s_{k+1}, s_k) | Y is positive definite
    pair = np.block([[cov[1:], cross], [np.swapaxes(cross, 1, 2), cov[:-1]]])
    assert np.linalg.eigvalsh(0.5 * (pair + np.swapaxes(pair, 1, 2)))[:, 0].min() > 0
    # smoothing never increases uncertainty: P^s_k <= P^f_k
    gap = np.linalg.eigvalsh(f.filtered_covariances[0] - cov[:-1])[:, 0]
    assert gap.min() > -1e-10 * np.abs(cov).max()
    np.testing.assert_allclose(sm.loglik, f.marginal_loglik, rtol=0, atol=0)


# --------------------------------------------------------------------------- moments


def test_moments_match_bruteforce_moments():
    rng = np.random.default_rng(11)
    n, m, T, M = 3, 2, 4, 3
    model, policy, mu0, P0 = random_estep_instance(rng, n, m, T)
    Y = sample_y(rng, model, policy, mu0, P0, M)
    mom = moments(smooth(model, policy, Y, mu0, P0), Y)
    assert mom.count == M and mom.T == T and mom.n == n

    Szz, Szs, Sss = np.zeros((3, T, n + 1, n + 1))
    for i in range(M):
        mean, joint, _ = oracle(model, policy, mu0, P0, Y[i])
        for t in range(T):
            # second moments of (s_{t+1}, y_t, s_t, 1), y_t a constant given Y
            mu = np.concatenate([mean[t + 1], [Y[i, t]], mean[t], [1.0]])
            C = np.zeros((2 * n + 2, 2 * n + 2))
            C[:n, :n] = block(joint, n, t + 1, t + 1)
            C[:n, n + 1 : 2 * n + 1] = block(joint, n, t + 1, t)
            C[n + 1 : 2 * n + 1, :n] = block(joint, n, t, t + 1)
            C[n + 1 : 2 * n + 1, n + 1 : 2 * n + 1] = block(joint, n, t, t)
            E = C + np.outer(mu, mu)
            Szz[t] += E[: n + 1, : n + 1] / M
            Szs[t] += E[: n + 1, n + 1 :] / M
            Sss[t] += E[n + 1 :, n + 1 :] / M
    assert_close(mom.Szz, Szz, "Szz")
    assert_close(mom.Szs, Szs, "Szs")
    assert_close(mom.Sss, Sss, "Sss")
    np.testing.assert_array_equal(mom.Sss[:, n, n], 1.0)
    np.testing.assert_array_equal(mom.Sss, np.swapaxes(mom.Sss, 1, 2))
    np.testing.assert_array_equal(mom.Szz, np.swapaxes(mom.Szz, 1, 2))
    assert np.all(np.linalg.eigvalsh(mom.Sss)[:, 0] > 0)


def test_moments_single_sequence_equals_batch_of_one():
    rng = np.random.default_rng(12)
    model, policy, mu0, P0 = random_estep_instance(rng, 2, 1, 3)
    Y = sample_y(rng, model, policy, mu0, P0, 1)
    a = moments(smooth(model, policy, Y[0], mu0, P0), Y[0])
    b = moments(smooth(model, policy, Y, mu0, P0), Y)
    for f in ("Szz", "Szs", "Sss"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- errors


@pytest.fixture(scope="module")
def small():
    rng = np.random.default_rng(13)
    model, policy, mu0, P0 = random_estep_instance(rng, 3, 2, 5)
    return model, policy, np.zeros(5), mu0, P0


@pytest.mark.parametrize("fn", [smooth, kalman_filter, log_likelihood])
@pytest.mark.parametrize(
    "case,exc,msg",
    [
        ("y_length", ShapeError, "y must have shape"),
        ("y_batch_length", ShapeError, "y must have shape"),
        ("y_ndim", ShapeError, "y must have shape"),
        ("y_empty_batch", ShapeError, "y must hold at least one sequence"),
        ("y_nan", ValueError, "y contains NaN"),
        ("mu0_shape", ShapeError, "mu0"),
        ("P0_shape", ShapeError, "P0"),
        ("P0_not_pd", NotPositiveDefiniteError, "P0"),
        ("P0_not_symmetric", NotPositiveDefiniteError, "P0"),
        ("T_mismatch", ShapeError, "horizon T"),
        ("n_mismatch", ShapeError, "state dimension n"),
        ("m_mismatch", ShapeError, "action dimension m"),
        ("model_type", TypeError, "model must be an AugmentedModel"),
    ],
)
def test_invalid_inputs_raise_naming_the_array(small, fn, case, exc, msg):
    model, policy, y, mu0, P0 = small
    T, n, m = model.T, model.n, model.m
    if case == "y_length":
        y = np.zeros(T + 1)
    elif case == "y_batch_length":
        y = np.zeros((2, T - 1))
    elif case == "y_ndim":
        y = np.zeros((2, T, 1))
    elif case == "y_empty_batch":
        y = np.zeros((0, T))
    elif case == "y_nan":
        y = np.zeros(T)
        y[2] = np.nan
    elif case == "mu0_shape":
        mu0 = np.zeros(n + 1)
    elif case == "P0_shape":
        P0 = np.eye(n + 1)
    elif case == "P0_not_pd":
        P0 = np.diag([1.0] * (n - 1) + [-1e-3])
    elif case == "P0_not_symmetric":
        P0 = np.eye(n)
        P0[0, 1] = 0.5
    elif case == "T_mismatch":
        policy = LinearGaussianPolicy.zeros(T + 1, n, m)
    elif case == "n_mismatch":
        policy = LinearGaussianPolicy.zeros(T, n + 1, m)
    elif case == "m_mismatch":
        policy = LinearGaussianPolicy.zeros(T, n, m + 1)
    elif case == "model_type":
        model = model.dynamics()
    with pytest.raises(exc, match=msg):
        fn(model, policy, y, mu0, P0)


def test_closed_loop_rejects_mismatched_policy(small):
    model = small[0]
    with pytest.raises(ShapeError, match="policy action dimension m=3 does not match model action dimension m=2"):
        closed_loop(model, LinearGaussianPolicy.zeros(model.T, model.n, 3))


def test_smooth_documents_every_argument_in_an_args_section():
    import inspect
    import re

    doc = inspect.getdoc(smooth)
    assert "Args:" in doc
    args = doc.split("Args:", 1)[1]
    for name in inspect.signature(smooth).parameters:
        assert re.search(rf"^\s+{name}:", args, re.M), name
