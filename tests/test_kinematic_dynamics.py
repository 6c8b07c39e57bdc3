"""Tests for soc_opt/noise/kinematic/dynamics.py (docs/math.md §11.3 (a)): the structured transition in
the task's coordinates predicts the joint rows as the filter does and the site rows as MuJoCo's
forward kinematics to first order, ignores the site columns, and swaps into the augmented model."""

import numpy as np
import pytest

from soc_opt.config import ConfigError
from soc_opt.learning import fit
from soc_opt.models import Rollouts, ShapeError
from soc_opt.noise.kinematic import em, loop
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.dynamics import structured_dynamics, with_dynamics
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.noise.kinematic_strategy import posterior_correction
from soc_opt.tasks import load_task


@pytest.fixture(scope="module")
def peg():
    task = load_task("peg")
    ro = task.rollouts(task.initial_policy(0.3), 8, np.random.default_rng(4))
    smoothed, filt, _ = loop.learn(task, ro, task.initial_policy(0.3), KinematicConfig())
    return task, ro, smoothed, filt


def test_joint_rows_are_the_filters_prediction_and_site_columns_are_ignored(peg):
    task, ro, _, filt = peg
    dyn = structured_dynamics(filt, 1e-6)
    rng = np.random.default_rng(0)
    k = 37
    x = ro.x[0, k] + 0.01 * rng.standard_normal(task.n)
    a = ro.a[0, k]
    pred = dyn.A[k] @ x + dyn.B[k] @ a + dyn.c[k]
    z = x[filt.zidx]
    np.testing.assert_allclose(pred[filt.zidx], filt.A[k] @ z + filt.Bz[k] @ a + filt.cz[k], atol=1e-10)
    sites = np.setdiff1d(np.arange(task.n), filt.zidx)
    assert sites.size > 0
    np.testing.assert_array_equal(dyn.A[:, :, sites], 0.0)


def test_site_rows_match_forward_kinematics_to_second_order(peg):
    task, ro, _, filt = peg
    dyn = structured_dynamics(filt, 1e-6)
    km = KinematicModel(task)
    k = 50
    rng = np.random.default_rng(1)
    direction = rng.standard_normal(filt.zidx.size)
    errs = []
    for eps in (0.02, 0.01):
        z = filt.zbar[k] + eps * direction / np.linalg.norm(direction)
        x = np.zeros(task.n)
        x[filt.zidx] = z
        a = ro.a[:, k].mean(0)
        z1 = filt.A[k] @ z + filt.Bz[k] @ a + filt.cz[k]
        errs.append(np.max(np.abs(dyn.A[k] @ x + dyn.B[k] @ a + dyn.c[k] - km.measure(z1, False))))
    # the error is the linearisation of h along zbar_{k+1}: it falls ~4x when the distance halves
    assert errs[1] < 0.35 * errs[0]


def test_process_noise_has_the_filters_rank_plus_the_floor(peg):
    task, _, _, filt = peg
    dyn = structured_dynamics(filt, 1e-6)
    nz = filt.zidx.size
    assert np.all(np.linalg.eigvalsh(dyn.cov) >= 1e-6 - 1e-12)
    # without the floor: rank nz, and on the joint block exactly the filter's Q
    W = dyn.cov - 1e-6 * np.eye(task.n)
    assert set(np.linalg.matrix_rank(W, tol=1e-12 * np.abs(W).max())) == {nz}
    np.testing.assert_allclose(W[:, filt.zidx][:, :, filt.zidx], filt.Q, atol=1e-15)
    with pytest.raises(ValueError, match="w_floor"):
        structured_dynamics(filt, 0.0)


def test_with_dynamics_keeps_the_cost_rows_of_the_augmented_fit(peg):
    task, _, smoothed, filt = peg
    model = fit.fit_augmented(smoothed, fit.FitConfig(prior="none"))
    dyn = structured_dynamics(filt, 1e-6)
    out = with_dynamics(model, dyn)
    n = task.n
    np.testing.assert_array_equal(out.dynamics().A, dyn.A)
    np.testing.assert_array_equal(out.dynamics().cov, dyn.cov)
    np.testing.assert_array_equal(out.Ao[:, n], model.Ao[:, n])
    np.testing.assert_array_equal(out.co[:, n], model.co[:, n])
    np.testing.assert_array_equal(out.So[:, n, n], model.So[:, n, n])
    np.testing.assert_array_equal(out.So[:, :n, n], 0.0)
    with pytest.raises(ShapeError, match="do not match"):
        with_dynamics(model, structured_dynamics(filt, 1e-6).__class__(dyn.A[:-1], dyn.B[:-1], dyn.c[:-1], dyn.cov[:-1]))


def test_structured_dynamics_needs_the_kinematic_filter():
    with pytest.raises(ConfigError, match="dynamics"):
        KinematicConfig(dynamics="structured", filter="fit")
    assert KinematicConfig(dynamics="structured").dynamics == "structured"


# --------------------------------------------------------------------------- fit_moments = "posterior"


def _sigma_rollouts(mean, cov, a):
    """Rollouts whose tuples have, per source rollout, the given mean trajectory ``(M, T+1, n)`` and joint
    covariance ``cov (M, (T+1) n, (T+1) n)``: ``2D`` symmetric points ``mean +- sqrt(D) L e_j`` each."""
    M, T1, n = mean.shape
    D = T1 * n
    pts, acts = [], []
    for i in range(M):
        L = np.linalg.cholesky(cov[i])
        for sign in (1.0, -1.0):
            for j in range(D):
                pts.append(mean[i] + sign * np.sqrt(D) * L[:, j].reshape(T1, n))
                acts.append(a[i])
    s = np.array(pts)
    a2 = np.array(acts)
    return Rollouts(x=s, s=s, a=a2, cost=np.zeros((s.shape[0], T1 - 1)), y=np.ones((s.shape[0], T1 - 1)))


def test_posterior_fit_equals_the_fit_on_points_carrying_the_posterior_covariances():
    rng = np.random.default_rng(5)
    M, T, n, m = 6, 2, 3, 2
    mean = rng.standard_normal((M, T + 1, n))
    a = rng.standard_normal((M, T, m))
    G = rng.standard_normal((M, (T + 1) * n, (T + 1) * n))
    cov = 0.05 * G @ np.swapaxes(G, -1, -2) / n + 0.01 * np.eye((T + 1) * n)
    Px = np.stack([cov[:, k * n:(k + 1) * n, k * n:(k + 1) * n].mean(0) for k in range(T + 1)])
    Cx = np.stack([cov[:, (k + 1) * n:(k + 2) * n, k * n:(k + 1) * n].mean(0) for k in range(T)])
    cfg = fit.FitConfig(prior="none", reg=1e-13)  # ridge negligible (it scales with the data)
    means = Rollouts(x=mean, s=mean, a=a, cost=np.zeros((M, T)), y=np.ones((M, T)))
    got = fit.fit_dynamics(means, cfg, correct=posterior_correction(Px, Cx, n, m, 1.0))
    want = fit.fit_dynamics(_sigma_rollouts(mean, cov, a), cfg)
    for g, w in zip((got.A, got.B, got.c, got.cov), (want.A, want.B, want.c, want.cov)):
        np.testing.assert_allclose(g, w, atol=1e-9)
    # the means alone: a different model (the posterior (co)variances matter)
    plain = fit.fit_dynamics(means, cfg)
    assert np.max(np.abs(plain.A - want.A)) > 1e-3


def test_posterior_moments_carry_the_smoother_covariances_through_h(peg):
    task, ro, _, _ = peg
    km = KinematicModel(task)
    res = em.fit(km, ro.s[:3], ro.a[:3], float(task.rho2), KinematicConfig(), None)
    sm = res.smoothed
    Px, Cx = loop.posterior_moments(sm)
    H = sm.lin[1]
    i, k = 2, 40
    one_x = H[i, k] @ sm.cov[i, k] @ H[i, k].T
    np.testing.assert_allclose(Px[k], np.mean([H[j, k] @ sm.cov[j, k] @ H[j, k].T for j in range(3)], 0), atol=1e-14)
    np.testing.assert_allclose(Cx[k], np.mean([H[j, k + 1] @ sm.cross[j, k] @ H[j, k].T for j in range(3)], 0),
                               atol=1e-14)
    # the joint rows of h are z itself: the joint block of H P H^T is P
    np.testing.assert_allclose(one_x[np.ix_(km.zidx, km.zidx)], sm.cov[i, k], atol=1e-15)
    assert Px.shape == (task.T + 1, task.n, task.n) and Cx.shape == (task.T, task.n, task.n)


def test_posterior_fit_in_the_loop_has_more_process_noise_than_the_means_fit(peg):
    task, ro, _, _ = peg
    from soc_opt.noise.aware import NoiseConfig
    from soc_opt.noise.strategy import resolve

    cfgs = {fm: NoiseConfig(estimator="kinematic", kinematic=KinematicConfig(fit_moments=fm)) for fm in ("means", "posterior")}
    fcfg = fit.FitConfig(prior="none")
    W = {}
    for fm, ncfg in cfgs.items():
        strat = resolve(task, ncfg)
        est = strat.estimate(None, ro, fcfg, task.initial_policy(0.3), np.random.default_rng(0))
        assert (est.moments is None) == (fm == "means")
        W[fm] = strat.fit(est.data(ro), fcfg, est, task.initial_policy(0.3)).cov
    # the smoothed means understate the spread of the states: the posterior fit's noise is larger
    assert np.mean(np.trace(W["posterior"], axis1=1, axis2=2)) > np.mean(np.trace(W["means"], axis1=1, axis2=2))


# --------------------------------------------------------------------------- structured_prior


def _sigma_points(mu, S):
    """``2d`` points with mean ``mu (d,)`` and (population) covariance ``S (d, d)`` exactly."""
    d = mu.size
    L = np.linalg.cholesky(S)
    return np.concatenate([mu + np.sqrt(d) * L.T, mu - np.sqrt(d) * L.T])


def _random_moments(rng, T, d):
    mu = rng.standard_normal((T, d))
    G = rng.standard_normal((T, d, d))
    return mu, G @ np.swapaxes(G, -1, -2) / d + 0.1 * np.eye(d)


def _random_dynamics(rng, T, n, m):
    from soc_opt.models import LinearGaussianDynamics

    G = rng.standard_normal((T, n, n))
    return LinearGaussianDynamics(rng.standard_normal((T, n, n)), rng.standard_normal((T, n, m)),
                                  rng.standard_normal((T, n)), G @ np.swapaxes(G, -1, -2) / n + 0.05 * np.eye(n))


@pytest.mark.parametrize("with_y", [False, True])
def test_structured_prior_equals_the_moments_of_data_pooled_with_tuples_of_the_transition(with_y):
    from soc_opt.noise.kinematic.dynamics import structured_prior

    rng = np.random.default_rng(11)
    T, n, m, count, strength = 3, 3, 2, 21.0, 7.0
    nz, d = n + m, 2 * n + m + int(with_y)
    mu, Lam = _random_moments(rng, T, d)
    dyn = _random_dynamics(rng, T, n, m)
    got_mu, got_Lam = structured_prior(dyn, strength, count)(mu, Lam)
    F = np.concatenate([dyn.A, dyn.B], -1)
    for k in range(T):
        data = _sigma_points(mu[k], Lam[k])
        # pseudo-tuples: the data's (x, a[, y]) moments, x' from the transition with independent noise W
        keep = np.r_[np.arange(nz), np.arange(nz + n, d)]
        zy = _sigma_points(mu[k, keep], Lam[k][np.ix_(keep, keep)])
        w = _sigma_points(np.zeros(n), dyn.cov[k])
        pseudo = np.zeros((zy.shape[0] * w.shape[0], d))
        for i, p in enumerate(zy):
            rows = slice(i * w.shape[0], (i + 1) * w.shape[0])
            pseudo[rows, keep] = p
            pseudo[rows, nz:nz + n] = F[k] @ p[:nz] + dyn.c[k] + w
        pooled = np.concatenate([data, pseudo])
        weights = np.r_[np.full(len(data), count / len(data)), np.full(len(pseudo), strength / len(pseudo))]
        np.testing.assert_allclose(got_mu[k], np.average(pooled, axis=0, weights=weights), atol=1e-10)
        np.testing.assert_allclose(got_Lam[k], np.cov(pooled.T, aweights=weights, bias=True), atol=1e-10)


def test_structured_prior_regression_is_the_weighted_mean_of_the_data_and_the_transition():
    from soc_opt.noise.kinematic.dynamics import structured_prior

    rng = np.random.default_rng(12)
    T, n, m, count = 4, 3, 2, 20.0
    mu, Lam = _random_moments(rng, T, 2 * n + m)
    dyn = _random_dynamics(rng, T, n, m)
    A0, c0, _ = fit._condition(mu, Lam, n + m, 1e-12)
    for strength, w in ((0.0, 0.0), (20.0, 0.5), (60.0, 0.75), (1e12, 1.0)):
        A, c, S = fit._condition(*structured_prior(dyn, strength, count)(mu, Lam), n + m, 1e-12)
        F = np.concatenate([dyn.A, dyn.B], -1)
        np.testing.assert_allclose(A, (1 - w) * A0 + w * F, atol=1e-8)
        np.testing.assert_allclose(c, (1 - w) * c0 + w * dyn.c, atol=1e-8)
    np.testing.assert_allclose(S, dyn.cov, atol=1e-6)  # all prior: the transition's own noise


def test_structured_prior_leaves_data_from_the_transition_unchanged():
    from soc_opt.noise.kinematic.dynamics import structured_prior

    rng = np.random.default_rng(13)
    T, n, m = 2, 3, 2
    nz = n + m
    mu_z, Szz = _random_moments(rng, T, nz)
    dyn = _random_dynamics(rng, T, n, m)
    F = np.concatenate([dyn.A, dyn.B], -1)
    mu = np.concatenate([mu_z, np.einsum("tij,tj->ti", F, mu_z) + dyn.c], -1)
    Lam = np.block([[Szz, Szz @ np.swapaxes(F, -1, -2)], [F @ Szz, F @ Szz @ np.swapaxes(F, -1, -2) + dyn.cov]])
    got_mu, got_Lam = structured_prior(dyn, 13.0, 20.0)(mu, Lam)
    np.testing.assert_allclose(got_mu, mu, atol=1e-12)
    np.testing.assert_allclose(got_Lam, Lam, atol=1e-10)


def test_structured_prior_rejects_bad_weights_shapes_and_configurations():
    from soc_opt.noise.kinematic.dynamics import structured_prior

    rng = np.random.default_rng(14)
    dyn = _random_dynamics(rng, 2, 3, 2)
    with pytest.raises(ValueError, match="strength"):
        structured_prior(dyn, -1.0, 20.0)
    with pytest.raises(ShapeError, match="do not fit"):
        structured_prior(dyn, 1.0, 20.0)(*_random_moments(rng, 2, 6))
    with pytest.raises(ConfigError, match="structured_prior"):
        KinematicConfig(structured_prior=5.0, dynamics="structured")
    with pytest.raises(ConfigError, match="structured_prior"):
        KinematicConfig(structured_prior=5.0, filter="fit")
    with pytest.raises(ConfigError, match="structured_prior"):
        KinematicConfig(structured_prior=-1.0)


def test_structured_prior_in_the_loop_pulls_the_fit_towards_the_transition(peg):
    task, ro, _, _ = peg
    from soc_opt.noise.aware import NoiseConfig
    from soc_opt.noise.strategy import resolve

    fcfg = fit.FitConfig(prior="none")
    models = {}
    for sp in (0.0, 20.0):
        strat = resolve(task, NoiseConfig(estimator="kinematic", kinematic=KinematicConfig(structured_prior=sp)))
        est = strat.estimate(None, ro, fcfg, task.initial_policy(0.3), np.random.default_rng(0))
        models[sp] = strat.fit(est.data(ro), fcfg, est, task.initial_policy(0.3))
    target = structured_dynamics(est.filter, KinematicConfig().w_floor)
    # M = 8 rollouts against 20 pseudo-tuples: the B of the fit moves most of the way to the transition's
    far = np.linalg.norm(models[0.0].B - target.B)
    near = np.linalg.norm(models[20.0].B - target.B)
    assert near < 0.5 * far
