"""Tests for soc_opt/models.py: shape and covariance validation, sampling."""

import numpy as np
import pytest

from soc_opt.models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    Rollouts,
    ShapeError,
)
from soc_opt.testing import random_quadratic_cost, random_trajectory


def _policy(T=3, n=4, m=2, var=0.5):
    return LinearGaussianPolicy(np.ones((T, m, n)), np.zeros((T, m)), np.broadcast_to(var * np.eye(m), (T, m, m)))


def test_policy_shapes_and_immutability():
    p = _policy()
    assert (p.T, p.n, p.m) == (3, 4, 2)
    with pytest.raises(ValueError):
        p.K[0, 0, 0] = 1.0


def test_policy_rejects_wrong_offset_shape_naming_it():
    with pytest.raises(ShapeError, match=r"policy k must have shape \(3, 2\)"):
        LinearGaussianPolicy(np.zeros((3, 2, 4)), np.zeros((3, 3)), np.broadcast_to(np.eye(2), (3, 2, 2)))


def test_policy_rejects_non_pd_covariance_naming_the_step():
    cov = np.broadcast_to(np.eye(2), (3, 2, 2)).copy()
    cov[1] = np.diag([1.0, -1.0])
    with pytest.raises(NotPositiveDefiniteError, match=r"policy cov\[1\] is not positive definite"):
        LinearGaussianPolicy(np.zeros((3, 2, 4)), np.zeros((3, 2)), cov)


def test_policy_rejects_non_symmetric_covariance():
    cov = np.broadcast_to(np.eye(2), (3, 2, 2)).copy()
    cov[2, 0, 1] = 0.5
    with pytest.raises(NotPositiveDefiniteError, match=r"policy cov\[2\] is not symmetric"):
        LinearGaussianPolicy(np.zeros((3, 2, 4)), np.zeros((3, 2)), cov)


def test_policy_rejects_nan_naming_the_array():
    K = np.zeros((3, 2, 4))
    K[1, 1, 2] = np.nan
    with pytest.raises(ValueError, match=r"policy K contains NaN"):
        LinearGaussianPolicy(K, np.zeros((3, 2)), np.broadcast_to(np.eye(2), (3, 2, 2)))


def test_sampled_actions_have_the_policy_mean_and_covariance(rng):
    T, n, m = 2, 3, 2
    cov = np.array([[[2.0, 0.5], [0.5, 1.0]]] * T)
    p = LinearGaussianPolicy(rng.standard_normal((T, m, n)), rng.standard_normal((T, m)), cov)
    s = rng.standard_normal(n)
    N = 200_000
    a = p.sample_action(1, np.broadcast_to(s, (N, n)), rng)
    mean = p.K[1] @ s + p.k[1]
    se = np.sqrt(np.diag(cov[1]) / N)
    assert np.all(np.abs(a.mean(0) - mean) < 5 * se)
    # covariance: standard error of a sample variance is about sqrt(2/N) * variance
    assert np.allclose(np.cov(a.T), cov[1], atol=5 * np.sqrt(2 / N) * 2.0)


def test_singular_policy_allowed_only_on_request():
    with pytest.raises(NotPositiveDefiniteError):
        LinearGaussianPolicy(np.zeros((2, 1, 2)), np.zeros((2, 1)), np.zeros((2, 1, 1)))
    p = LinearGaussianPolicy(np.zeros((2, 1, 2)), np.zeros((2, 1)), np.zeros((2, 1, 1)), allow_singular=True)
    assert np.all(p.chol == 0)


def test_augmented_model_splits_state_and_action_columns():
    T, n, m = 2, 3, 2
    Ao = np.arange(T * (n + 1) * (n + m), dtype=float).reshape(T, n + 1, n + m)
    model = AugmentedModel(Ao, np.zeros((T, n + 1)), np.broadcast_to(np.eye(n + 1), (T, n + 1, n + 1)), n)
    assert model.m == m
    assert np.array_equal(model.As, Ao[:, :, :n]) and np.array_equal(model.Bs, Ao[:, :, n:])
    dyn = model.dynamics()
    assert isinstance(dyn, LinearGaussianDynamics) and dyn.B.shape == (T, n, m)


def test_augmented_model_rejects_wrong_row_count():
    with pytest.raises(ShapeError, match="augmented Ao"):
        AugmentedModel(np.zeros((2, 3, 5)), np.zeros((2, 4)), np.broadcast_to(np.eye(4), (2, 4, 4)), 3)


def test_quadratic_cost_evaluates_the_stage_formula():
    rng = np.random.default_rng(1)
    T, n, m = 3, 2, 1
    cost = random_quadratic_cost(rng, n, m, T, normalize=False, floor=0.0, c0=np.arange(T, dtype=float))
    C, c = cost.C, cost.c
    s, a = random_trajectory(rng, n, m, T)
    z = np.concatenate([s[:T], a], axis=1)
    expected = [0.5 * z[t] @ C[t] @ z[t] + z[t] @ c[t] + t for t in range(T)]
    assert np.allclose(cost(s, a), expected)


def test_rollouts_reject_mismatched_shapes_naming_the_array():
    M, T, n, m = 2, 3, 2, 1
    with pytest.raises(ShapeError, match="rollouts y"):
        Rollouts(np.zeros((M, T + 1, n)), np.zeros((M, T + 1, n)), np.zeros((M, T, m)), np.zeros((M, T)),
                 np.zeros((M, T + 1)))


def test_policy_saved_and_loaded_through_npz_is_the_same_policy(tmp_path):
    pol = _policy(T=4, n=3, m=2)
    pol.save(tmp_path / "p.npz")
    back = LinearGaussianPolicy.load(tmp_path / "p.npz")
    for name in ("K", "k", "cov"):
        np.testing.assert_array_equal(getattr(back, name), getattr(pol, name))


def test_loading_a_run_directorys_best_policy_ignores_its_extra_arrays(tmp_path):
    pol = _policy()
    np.savez_compressed(tmp_path / "best_policy.npz", **pol.to_dict(), mean_cost=1.5, iteration=3)
    np.testing.assert_array_equal(LinearGaussianPolicy.load(tmp_path / "best_policy.npz").K, pol.K)
    np.savez_compressed(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ShapeError, match="not a policy file.*K, k, cov"):
        LinearGaussianPolicy.load(tmp_path / "other.npz")
