"""Tests for soc_opt/noise/kinematic/smoother.py (docs/math.md §11.2): exact at rho^2 = 0, equal to
the dense Gaussian posterior of the linearised model, and better than the raw measurement."""

import math

import numpy as np
import pytest

from soc_opt.models import ShapeError
from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.noise.kinematic.smoother import LinearGaussianZ, smooth
from soc_opt.tasks import load_task


@pytest.fixture(scope="module")
def peg():
    task = load_task("peg")
    km = KinematicModel(task)
    ro = task.rollouts(task.initial_policy(1.0), 4, np.random.default_rng(3))
    return task, km, ro


def _short(km, ro, T, rng):
    """A random transition in z over the first T steps (non-trivial D, B, c, S)."""
    cfg = KinematicConfig()
    acc = em.initial_map(km, ro.s, 0.1, 1e-4)
    nq, m = km.nq, km.m
    D = 0.3 * rng.standard_normal((km.T, nq, km.nz))
    B = 0.5 * rng.standard_normal((km.T, nq, m))
    acc = type(acc)(B, D, rng.standard_normal((km.T, nq)), acc.S)
    lg = em.z_model(km, acc, cfg)
    return LinearGaussianZ(lg.A[:T], lg.Bz[:T], lg.cz[:T], lg.Q[:T], lg.z0, 1e-2 * np.eye(km.nz))


def test_rho2_zero_returns_the_measured_states(peg):
    task, km, ro = peg
    acc = em.initial_map(km, ro.x, 0.0, 1e-4)
    sm = smooth(km, em.z_model(km, acc, KinematicConfig()), ro.x, ro.a, np.zeros((km.n, km.n)))
    np.testing.assert_array_equal(sm.mean, km.z_of(ro.x))
    assert not sm.cov.any() and not sm.cross.any()
    np.testing.assert_allclose(km.measure(sm.mean, False), ro.x, rtol=0, atol=1e-12)


def test_equals_dense_gaussian_posterior_of_the_linearised_model(peg):
    """Brute force: the joint Gaussian of z_0..z_T and the measurements, conditioned densely."""
    task, km, ro = peg
    rng = np.random.default_rng(0)
    T, M, r2, nz, n = 4, 2, 0.1, km.nz, km.n
    lg = _short(km, ro, T, rng)
    s, a = ro.s[:M, : T + 1], ro.a[:M, :T]
    zl = km.z_of(ro.x[:M, : T + 1]) + 0.05 * rng.standard_normal((M, T + 1, nz))
    sm = smooth(km, lg, s, a, r2 * np.eye(n), zl)
    hx, H = km.measure(zl)
    for i in range(M):
        # z = mean + L w: the linear map from (z_0 noise, process noises) to the stacked z
        N = (T + 1) * nz
        mean = np.zeros(N)
        cov = np.zeros((N, N))
        mean[:nz], cov[:nz, :nz] = lg.z0, lg.P0
        for k in range(T):
            sk, sn = slice(k * nz, (k + 1) * nz), slice((k + 1) * nz, (k + 2) * nz)
            mean[sn] = lg.A[k] @ mean[sk] + lg.Bz[k] @ a[i, k] + lg.cz[k]
            cov[sn, :] = lg.A[k] @ cov[sk, :]
            cov[:, sn] = cov[sn, :].T
            cov[sn, sn] = lg.A[k] @ cov[sk, sk] @ lg.A[k].T + lg.Q[k]
        Hb = np.zeros(((T + 1) * n, N))
        off = np.zeros((T + 1) * n)
        for k in range(T + 1):
            Hb[k * n:(k + 1) * n, k * nz:(k + 1) * nz] = H[i, k]
            off[k * n:(k + 1) * n] = hx[i, k] - H[i, k] @ zl[i, k]
        Sy = Hb @ cov @ Hb.T + r2 * np.eye(len(off))
        y = s[i].ravel()
        ey = y - off - Hb @ mean
        Kg = cov @ Hb.T @ np.linalg.inv(Sy)
        pm = mean + Kg @ ey
        pc = cov - Kg @ Hb @ cov
        np.testing.assert_allclose(sm.mean[i].ravel(), pm, rtol=0, atol=1e-8)
        for k in range(T + 1):
            np.testing.assert_allclose(sm.cov[i, k], pc[k * nz:(k + 1) * nz, k * nz:(k + 1) * nz], atol=1e-9)
        for k in range(T):
            np.testing.assert_allclose(sm.cross[i, k], pc[(k + 1) * nz:(k + 2) * nz, k * nz:(k + 1) * nz], atol=1e-9)
        ll = -0.5 * (len(y) * math.log(2 * math.pi) + np.linalg.slogdet(Sy)[1] + ey @ np.linalg.solve(Sy, ey))
        assert sm.loglik[i] == pytest.approx(ll, rel=1e-9)


def test_smoothed_states_beat_the_raw_measurement(peg):
    task, km, ro = peg
    res = em.fit(km, ro.s, ro.a, task.rho2, KinematicConfig())
    xs = km.measure(res.smoothed.mean, False)
    err = lambda e: np.sqrt(np.mean(e ** 2))  # noqa: E731
    q, p = km.zidx[: km.nq], task.layout["site_pos"]
    assert err(xs[..., q] - ro.x[..., q]) < 0.25 * err(ro.s[..., q] - ro.x[..., q])
    assert err(xs[..., p] - ro.x[..., p]) < 0.25 * err(ro.s[..., p] - ro.x[..., p])


def test_bad_shapes_are_named(peg):
    task, km, ro = peg
    lg = em.z_model(km, em.initial_map(km, ro.s, 0.1, 1e-4), KinematicConfig())
    with pytest.raises(ShapeError, match="smoother"):
        smooth(km, lg, ro.s[:, :50], ro.a, 0.1 * np.eye(km.n))
    with pytest.raises(ShapeError, match="z_lin"):
        smooth(km, lg, ro.s, ro.a, 0.1 * np.eye(km.n), np.zeros((1, 2, 3)))
