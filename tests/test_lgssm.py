"""The Gaussian core (soc_opt.lgssm) against brute-force conditioning of the joint Gaussian."""

from __future__ import annotations

import numpy as np
import pytest

from soc_opt import lgssm
from soc_opt.models import ShapeError


def _spd(rng, *shape, scale=0.3, floor=0.05):
    d = shape[-1]
    L = scale * rng.standard_normal(shape)
    return L @ np.swapaxes(L, -1, -2) + floor * np.eye(d)


def _instance(rng, M=3, T=4, n=3, p=1, K=None, correlated=True, per_sequence=False):
    """A random model; ``per_sequence``: emission weights and covariances per sequence."""
    K = T if K is None else K
    lead = (M,) if per_sequence else ()
    F = 0.8 * rng.standard_normal((T, n, n)) / np.sqrt(n)
    b = rng.standard_normal((M, T, n))
    H = rng.standard_normal(lead + (K, p, n))
    d = rng.standard_normal((K, p))
    # joint noise covariance of (w_k, v_k), so that the cross block is consistent
    Sj = _spd(rng, *(lead + (K, n + p, n + p)))
    Q = Sj[..., :T, :n, :n] if not per_sequence else Sj[0, :T, :n, :n]
    R = Sj[..., :, n:, n:]
    C = Sj[..., :T, :n, n:] if correlated else None
    if not correlated:
        Sj[..., :n, n:] = 0.0
        Sj[..., n:, :n] = 0.0
    if per_sequence:  # Q is shared: rebuild per-sequence joint blocks with the shared Q
        Sj[..., :T, :n, :n] = Q
        if correlated:  # keep each joint block PD: shrink the cross block
            C = 0.3 * Sj[..., :T, :n, n:]
            Sj[..., :T, :n, n:] = C
            Sj[..., :T, n:, :n] = np.swapaxes(C, -1, -2)
    params = lgssm.Params(lgssm.Initial(rng.standard_normal(n), _spd(rng, n, n)),
                          lgssm.Dynamics(F, b, Q), lgssm.Emissions(H, d, R), C)
    y = rng.standard_normal((M, K, p))
    return params, y


def _seq(params: lgssm.Params, i: int, M: int) -> lgssm.Params:
    """Sequence ``i``'s own shared-matrix model."""
    def pick(x, shared_ndim):
        x = np.asarray(x)
        return x[i] if x.ndim == shared_ndim + 1 else x

    ini, dyn, em = params.initial, params.dynamics, params.emissions
    return lgssm.Params(lgssm.Initial(pick(ini.mean, 1), pick(ini.cov, 2)),
                        lgssm.Dynamics(pick(dyn.weights, 3), pick(dyn.bias, 2), pick(dyn.cov, 3)),
                        lgssm.Emissions(pick(em.weights, 3), pick(em.bias, 2), pick(em.cov, 3)),
                        None if params.noise_cross_cov is None else pick(params.noise_cross_cov, 3))


def _brute_force(params: lgssm.Params, y: np.ndarray):
    """Condition the joint Gaussian of ``(z_0..z_T, y_0..y_{K-1})`` on one sequence ``y (K, p)``."""
    ini, dyn, em = params.initial, params.dynamics, params.emissions
    F, b, Q = dyn.weights, dyn.bias, dyn.cov
    H, d, R = em.weights, em.bias, em.cov
    T, n = F.shape[0], F.shape[1]
    K, p = y.shape
    C = np.zeros((T, n, p)) if params.noise_cross_cov is None else params.noise_cross_cov
    blocks = [ini.cov] + [np.block([[Q[k], C[k]], [C[k].T, R[k]]]) for k in range(T)] + ([R[T]] if K == T + 1 else [])
    dims = [b_.shape[0] for b_ in blocks]
    N = sum(dims)
    Sig = np.zeros((N, N))
    off = np.cumsum([0] + dims)
    for i, blk in enumerate(blocks):
        Sig[off[i]:off[i + 1], off[i]:off[i + 1]] = blk
    Az = np.zeros((T + 1, n, N))
    Az[0][:, :n] = np.eye(n)
    mz = np.zeros((T + 1, n))
    mz[0] = ini.mean
    Ay = np.zeros((K, p, N))
    my = np.zeros((K, p))
    for k in range(K):
        Ay[k] = H[k] @ Az[k]
        my[k] = H[k] @ mz[k] + d[k]
        if k < T:
            Ay[k][:, off[k + 1] + n:off[k + 2]] += np.eye(p)
        else:
            Ay[k][:, off[T + 1]:] += np.eye(p)
        if k < T:
            Az[k + 1] = F[k] @ Az[k]
            Az[k + 1][:, off[k + 1]:off[k + 1] + n] += np.eye(n)
            mz[k + 1] = F[k] @ mz[k] + b[k]
    if K == T:
        pass
    Az2, Ay2 = Az.reshape(-1, N), Ay.reshape(-1, N)
    Szz, Szy, Syy = Az2 @ Sig @ Az2.T, Az2 @ Sig @ Ay2.T, Ay2 @ Sig @ Ay2.T
    r = y.reshape(-1) - my.reshape(-1)
    G = np.linalg.solve(Syy, Szy.T).T
    mean = (mz.reshape(-1) + G @ r).reshape(T + 1, n)
    cov = (Szz - G @ Szy.T).reshape(T + 1, n, T + 1, n)
    _, logdet = np.linalg.slogdet(Syy)
    ll = -0.5 * (r.size * np.log(2 * np.pi) + logdet + r @ np.linalg.solve(Syy, r))
    covs = np.stack([cov[k, :, k] for k in range(T + 1)])
    cross = np.stack([cov[k + 1, :, k] for k in range(T)])
    return mean, covs, cross, ll


CASES = [
    dict(p=1, K="T", correlated=True, per_sequence=False),
    dict(p=1, K="T+1", correlated=False, per_sequence=False),
    dict(p=2, K="T", correlated=True, per_sequence=False),
    dict(p=2, K="T+1", correlated=True, per_sequence=False),
    dict(p=2, K="T+1", correlated=False, per_sequence=True),
    dict(p=1, K="T", correlated=True, per_sequence=True),
    dict(p=4, K="T+1", correlated=False, per_sequence=True),  # p > n: the update in information form
    dict(p=4, K="T", correlated=True, per_sequence=False),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_smoother_matches_brute_force_conditioning(case):
    rng = np.random.default_rng(7)
    M, T = 3, 4
    K = T if case["K"] == "T" else T + 1
    params, y = _instance(rng, M=M, T=T, n=3, p=case["p"], K=K, correlated=case["correlated"],
                          per_sequence=case["per_sequence"])
    post = lgssm.rts_smoother(params, y)
    filt = lgssm.kalman_filter(params, y)
    assert post.smoothed_means.shape == (M, T + 1, 3)
    shared = not case["per_sequence"]
    assert post.smoothed_covariances.shape == ((T + 1, 3, 3) if shared else (M, T + 1, 3, 3))
    for i in range(M):
        mean, cov, cross, ll = _brute_force(_seq(params, i, M), y[i])
        np.testing.assert_allclose(post.smoothed_means[i], mean, atol=1e-9)
        np.testing.assert_allclose(post.smoothed_covariances if shared else post.smoothed_covariances[i], cov, atol=1e-9)
        np.testing.assert_allclose(post.smoothed_cross_covariances if shared else post.smoothed_cross_covariances[i], cross, atol=1e-9)
        np.testing.assert_allclose(post.marginal_loglik[i], ll, atol=1e-9)
        np.testing.assert_allclose(filt.marginal_loglik[i], ll, atol=1e-9)
        np.testing.assert_allclose(lgssm.log_likelihood(params, y)[i], ll, atol=1e-9)


def test_filter_last_step_matches_smoother_and_prefix_conditioning():
    """The filtered moments at step k are the brute-force posterior given y_0..y_k only."""
    rng = np.random.default_rng(3)
    params, y = _instance(rng, M=2, T=4, n=3, p=2, K=5, correlated=True)
    filt = lgssm.kalman_filter(params, y)
    post = lgssm.rts_smoother(params, y)
    np.testing.assert_allclose(filt.filtered_means[:, -1], post.smoothed_means[:, -1], atol=1e-12)
    # prefix: a model with the first k+1 steps
    k = 2
    ini, dyn, em = params.initial, params.dynamics, params.emissions
    sub = lgssm.Params(ini, lgssm.Dynamics(dyn.weights[:k], dyn.bias[:, :k], dyn.cov[:k]),
                       lgssm.Emissions(em.weights[:k + 1], em.bias[:k + 1], em.cov[:k + 1]), params.noise_cross_cov[:k])
    for i in range(2):
        mean, cov, _, _ = _brute_force(_seq(sub, i, 2), y[i, :k + 1])
        np.testing.assert_allclose(filt.filtered_means[i, k], mean[k], atol=1e-9)
        np.testing.assert_allclose(filt.filtered_covariances[k], cov[k], atol=1e-9)


@pytest.mark.parametrize("p", [2, 4])
def test_extended_filter_with_the_model_linearisation_is_the_linear_filter(p):
    rng = np.random.default_rng(5)
    M, T = 3, 4
    params, y = _instance(rng, M=M, T=T, n=3, p=p, K=T + 1, correlated=False)
    H, d = params.emissions.weights, params.emissions.bias
    seen = []

    def linearize(k, m):
        seen.append(m.copy())
        return np.broadcast_to(H[k], (M,) + H[k].shape), np.broadcast_to(d[k], (M,) + d[k].shape)

    ext = lgssm.rts_smoother(params, y, linearize=linearize)
    lin = lgssm.rts_smoother(params, y)
    assert ext.smoothed_covariances.shape == (M, T + 1, 3, 3)
    np.testing.assert_allclose(ext.smoothed_means, lin.smoothed_means, atol=1e-12)
    np.testing.assert_allclose(ext.smoothed_covariances,
                               np.broadcast_to(lin.smoothed_covariances, ext.smoothed_covariances.shape), atol=1e-12)
    np.testing.assert_allclose(ext.marginal_loglik, lin.marginal_loglik, atol=1e-10)
    filt = lgssm.kalman_filter(params, y)
    np.testing.assert_allclose(np.stack(seen[: T + 1], 1), filt.predicted_means[:, : T + 1], atol=1e-12)


def test_shapes_are_checked():
    rng = np.random.default_rng(0)
    params, y = _instance(rng, M=2, T=3, n=2, p=1)
    with pytest.raises(ShapeError):
        lgssm.rts_smoother(params, y[:, :2])
    with pytest.raises(ShapeError):
        lgssm.rts_smoother(params, y[0])
    with pytest.raises(TypeError):
        lgssm.rts_smoother(tuple(params), y)
