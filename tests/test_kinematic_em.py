"""Tests for soc_opt/noise/kinematic/em.py (docs/math.md §11.2): the likelihood never decreases, the
M-step is least squares on exact states, the first round's noise follows the second differences."""

import numpy as np
import pytest

from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.noise.kinematic.smoother import smooth
from soc_opt.parallel import can_fork
from soc_opt.tasks import load_task


@pytest.fixture(scope="module", params=["peg", "door"])
def data(request):
    task = load_task(request.param)
    km = KinematicModel(task)
    ro = task.rollouts(task.initial_policy(1.0), 6, np.random.default_rng(5))
    return task, km, ro


@pytest.mark.parametrize("segments,prior", [(1, 0.0), (10, 0.0), (100, 0.0)])
def test_em_likelihood_never_decreases(data, segments, prior):
    task, km, ro = data
    cfg = KinematicConfig(em_iters=5, segments=segments, prior_strength=prior)
    res = em.fit(km, ro.s, ro.a, 0.1, cfg)
    ll = res.loglik
    assert ll.shape == (6,)
    assert np.all(np.diff(ll) >= -1e-8 * np.abs(ll[:-1])), ll


def test_mstep_on_exact_states_is_least_squares():
    """rho^2 = 0: the smoothed states are the measured ones, the M-step is ordinary least squares.
    (Peg: every regressor varies; on door the hinge is still under the initial policy, so the
    normal equations are singular up to the ridge.)"""
    task = load_task("peg")
    km = KinematicModel(task)
    ro = task.rollouts(task.initial_policy(1.0), 6, np.random.default_rng(5))
    cfg = KinematicConfig()
    lg = em.z_model(km, em.initial_map(km, ro.x, 0.0, 1e-4), cfg)
    sm = smooth(km, lg, ro.x, ro.a, np.zeros((km.n, km.n)))
    acc = em.mstep(sm, ro.a, km.dt, km.nq, 1, 0.0, 1e-12)
    z = km.z_of(ro.x)
    u = (z[:, 1:, km.nq:] - z[:, :-1, km.nq:]) / km.dt
    X = np.concatenate([ro.a, z[:, :-1], np.ones(ro.a.shape[:2] + (1,))], axis=-1).reshape(-1, km.m + km.nz + 1)
    W = np.linalg.lstsq(X, u.reshape(-1, km.nq), rcond=None)[0].T
    Wk = np.concatenate([acc.B[0], acc.D[0], acc.c[0][:, None]], axis=1)
    fit_ls, fit_em = X @ W.T, X @ Wk.T
    np.testing.assert_allclose(fit_em, fit_ls, rtol=0, atol=1e-6 * np.abs(fit_ls).max())
    res = u.reshape(-1, km.nq) - fit_ls
    np.testing.assert_allclose(acc.S[0], res.T @ res / len(res), rtol=1e-6, atol=1e-8 * np.abs(res).max() ** 2)


def test_prior_pulls_segments_towards_the_time_invariant_map(data):
    task, km, ro = data
    res = em.fit(km, ro.s, ro.a, 0.1, KinematicConfig(em_iters=1))
    sm = res.smoothed
    pooled = em.mstep(sm, ro.a, km.dt, km.nq, 1, 0.0, 1e-4)
    free = em.mstep(sm, ro.a, km.dt, km.nq, 100, 0.0, 1e-4)
    strong = em.mstep(sm, ro.a, km.dt, km.nq, 100, 1e7, 1e-4)
    d = lambda x: np.abs(x.B - pooled.B).max()  # noqa: E731
    assert d(strong) < 1e-3 * d(free)


def test_initial_noise_is_second_difference_variance_minus_measurement_noise(data):
    task, km, ro = data
    acc = em.initial_map(km, ro.s, 0.1, 1e-4)
    qd = km.z_of(ro.s)[..., km.nq:]
    v = np.diff(qd, axis=1).reshape(-1, km.nq).var(axis=0) / km.dt ** 2 - 0.2 / km.dt ** 2
    np.testing.assert_allclose(np.diagonal(acc.S[0]), np.maximum(v, 1e-4))
    assert not acc.B.any() and not acc.D.any() and not acc.c.any()



def _same(r1, r2):
    for f in ("B", "D", "c", "S"):
        np.testing.assert_array_equal(getattr(r1.accel, f), getattr(r2.accel, f))
    for a, b in zip(r1.smoothed[:5], r2.smoothed[:5]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(r1.loglik, r2.loglik)


@pytest.mark.skipif(not can_fork(), reason="needs fork and two CPUs")
def test_parallel_starts_equal_the_starts_run_in_turn(data):
    task, km, ro = data
    cfg = KinematicConfig()
    warm = em.fit(km, ro.s[:3], ro.a[:3], 0.1, cfg).accel        # another start, as the sampler's map would be
    inits = [warm, None]
    par = em.fit_starts(km, ro.s, ro.a, 0.1, cfg, inits, parallel=True)
    seq = em.fit_starts(km, ro.s, ro.a, 0.1, cfg, inits, parallel=False)
    assert len(par) == len(seq) == 2
    for p, q in zip(par, seq):
        _same(p, q)
    _same(seq[1], em.fit(km, ro.s, ro.a, 0.1, cfg, None))
    assert not np.array_equal(par[0].loglik, par[1].loglik)     # the two starts differ


@pytest.mark.skipif(not can_fork(), reason="needs fork and two CPUs")
def test_an_error_in_the_forked_start_is_raised_in_the_caller(data, monkeypatch):
    task, km, ro = data
    real = em.fit

    def failing(km, s, a, rho2, cfg, init=None):
        if init is None:
            raise np.linalg.LinAlgError("start from the data failed")
        return real(km, s, a, rho2, cfg, init)

    monkeypatch.setattr(em, "fit", failing)                       # the child is forked with it
    warm = real(km, ro.s[:3], ro.a[:3], 0.1, KinematicConfig()).accel
    with pytest.raises(np.linalg.LinAlgError, match="start from the data failed"):
        em.fit_starts(km, ro.s, ro.a, 0.1, KinematicConfig(), [warm, None], parallel=True)


def test_with_a_start_range_the_smoothed_start_is_not_pulled_to_the_nominal_start():
    """``[process_noise] start`` (docs/math.md §8.1): the smoother's ``z_0`` prior is ``p0 I`` plus the range's
    ``r^2 / 3`` on the state joints' angles, so the smoothed ``q_0`` follows the true one.  Oracle: the
    regression slope of the error ``E[q_0 | s, a] - q_0`` on the true offset is the shrinkage a Gaussian
    prior of that variance implies, ``-Var(q_0 | s, a) / (r^2 / 3)`` (about -0.05 here), within 4 standard
    errors; with the prior of a known start (``p0 I`` alone) the estimate stays at the nominal start
    (slope -1).  At ``rho^2 = 0`` the smoother still reads ``z`` off the measurements."""
    r = 0.2
    task = load_task("peg", overrides={"T": 20, "rho2": 0.01, "process_noise": {"start": r}})
    km = KinematicModel(task)
    nj = len(task.config.state.joints)
    np.testing.assert_allclose(km.start_cov, np.diag(np.r_[np.full(nj, r * r / 3), np.zeros(km.nz - nj)]), rtol=1e-15)
    ro = task.rollouts(task.initial_policy(0.1), 40, np.random.default_rng(3))
    delta = ro.x[:, 0, :nj] - task.x0[:nj]
    slopes = {}
    for prior in ("range", "known"):
        if prior == "known":
            km.start_cov = None
        res = em.fit(km, ro.s, ro.a, task.rho2, KinematicConfig(em_iters=2))
        e = res.smoothed.mean[:, 0, :nj] - ro.x[:, 0, :nj]
        slope = float((e * delta).sum() / (delta ** 2).sum())
        slopes[prior] = slope
        if prior == "range":
            var = res.smoothed.cov[:, 0, np.arange(nj), np.arange(nj)]
            expected = -float(var.mean()) / (r * r / 3)
            resid = e - slope * delta
            se = float(np.sqrt((resid ** 2).sum() / (e.size - 1) / (delta ** 2).sum()))
            assert abs(slope - expected) < 4 * se, (slope, expected, se)
    assert slopes["known"] < -0.9, slopes
    exact = load_task("peg", overrides={"T": 20, "rho2": 0.0, "process_noise": {"start": r}})
    ro0 = exact.rollouts(exact.initial_policy(0.1), 3, np.random.default_rng(3))
    km0 = KinematicModel(exact)
    res0 = em.fit(km0, ro0.s, ro0.a, 0.0, KinematicConfig(em_iters=1))
    np.testing.assert_array_equal(res0.smoothed.mean, km0.z_of(ro0.s))
