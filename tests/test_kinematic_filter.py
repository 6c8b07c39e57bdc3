"""Tests for soc_opt/noise/kinematic/filter.py and loop.py (docs/math.md §11.3): the online filter in
rollouts equals the offline one, it is exact at rho^2 = 0, it is saved as plain arrays."""

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from soc_opt.models import LinearGaussianPolicy, ShapeError
from soc_opt.noise.kinematic import loop
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import KinematicFilter, KinematicFilteredPolicy
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import load_task


@pytest.fixture(scope="module")
def peg():
    task = load_task("peg")
    ro = task.rollouts(task.initial_policy(0.3), 8, np.random.default_rng(2))
    smoothed, filt, diag = loop.learn(task, ro, task.initial_policy(0.3), KinematicConfig())
    return task, ro, smoothed, filt, diag


def _policy(task, rng):
    K = 0.05 * rng.standard_normal((task.T, task.m, task.n))
    return LinearGaussianPolicy(K, np.zeros((task.T, task.m)), np.broadcast_to(0.3 * np.eye(task.m), (task.T, task.m, task.m)).copy())


def test_online_filter_in_rollouts_equals_offline_filter(peg):
    task, ro, _, filt, _ = peg
    pol = KinematicFilteredPolicy(_policy(task, np.random.default_rng(0)), filt)
    r = task.rollouts(pol, 3, np.random.default_rng(1))
    xhat = filt.states(r.s, r.a)
    w_free = r.a - np.einsum("tij,mtj->mti", pol.policy.K, xhat[:, :-1])
    # the actions are K xhat + k + L w: recompute the same draws
    rng = np.random.default_rng(1)
    draws = task.draw_noise(3, rng)
    expect = pol.policy.k[None] + np.einsum("tij,mtj->mti", pol.policy.chol, draws.w)
    np.testing.assert_allclose(w_free, expect, atol=1e-10)


def test_filter_beats_raw_measurement_and_smoother_beats_filter(peg):
    task, ro, smoothed, filt, _ = peg
    p = task.layout["site_pos"]
    err = lambda e: np.sqrt(np.mean(e[..., p] ** 2))  # noqa: E731
    raw, fil, smo = err(ro.s - ro.x), err(filt.states(ro.s, ro.a) - ro.x), err(smoothed.s - ro.x)
    assert smo < fil < 0.5 * raw


def test_smoothed_rollouts_carry_costs_of_the_smoothed_states(peg):
    task, ro, smoothed, _, diag = peg
    np.testing.assert_allclose(smoothed.cost, task.cost(smoothed.s, ro.a))
    np.testing.assert_array_equal(smoothed.x, ro.x)
    assert diag["kin_loglik_last"] >= diag["kin_loglik_first"]


def test_rho2_zero_filter_returns_the_measurement():
    task = load_task("peg", overrides={"rho2": 0.0})
    ro = task.rollouts(task.initial_policy(0.3), 3, np.random.default_rng(0))
    smoothed, filt, _ = loop.learn(task, ro, task.initial_policy(0.3), KinematicConfig())
    np.testing.assert_allclose(smoothed.s, ro.s, atol=1e-12)
    np.testing.assert_array_equal(filt.states(ro.s, ro.a), ro.s)


def test_saved_as_plain_arrays_and_restored(peg, tmp_path):
    task, ro, _, filt, _ = peg
    pol = KinematicFilteredPolicy(_policy(task, np.random.default_rng(3)), filt)
    path = tmp_path / "policy.npz"
    np.savez(path, **pol.to_dict())
    with np.load(path, allow_pickle=False) as d:
        attached = KinematicFilteredPolicy.from_dict(d, task)
        linear = KinematicFilteredPolicy.from_dict(d)
    np.testing.assert_array_equal(attached.filter.states(ro.s, ro.a), filt.states(ro.s, ro.a))
    np.testing.assert_array_equal(attached.filter.G, filt.G)
    # without the task, h is the linearisation along the nominal: exact on the nominal itself
    zbar = filt.zbar
    np.testing.assert_allclose(linear.filter.h0, KinematicModel(task).measure(zbar, False), atol=1e-12)
    pk = pickle.loads(pickle.dumps(pol))
    np.testing.assert_array_equal(pk.filter.states(ro.s, ro.a), filt.states(ro.s, ro.a))


def test_policy_shape_mismatch_is_named(peg):
    task, _, _, filt, _ = peg
    bad = LinearGaussianPolicy(np.zeros((task.T, task.m, 3)), np.zeros((task.T, task.m)),
                               np.broadcast_to(np.eye(task.m), (task.T, task.m, task.m)).copy())
    with pytest.raises(ShapeError, match="kinematic filter"):
        KinematicFilteredPolicy(bad, filt)


def test_learn_on_filtered_gives_the_new_filters_estimates_and_their_costs(peg):
    """``learn_on = "filtered"``: the learner's rollouts carry the batch re-filtered by the batch's own new
    filter (what the next policy acts on), with costs of those estimates; the filter is unchanged."""
    task, ro, smoothed, filt, _ = peg
    filtered, filt2, _ = loop.learn(task, ro, task.initial_policy(0.3), KinematicConfig(learn_on="filtered"))
    for f in ("A", "G", "zbar", "accel_D"):
        np.testing.assert_array_equal(getattr(filt2, f), getattr(filt, f))
    np.testing.assert_allclose(filtered.s, filt.states(ro.s, ro.a), rtol=0, atol=1e-12)
    np.testing.assert_allclose(filtered.cost, task.cost(filtered.s, ro.a), rtol=1e-12)
    np.testing.assert_array_equal(filtered.x, ro.x)
    np.testing.assert_array_equal(filtered.a, ro.a)
    assert not np.allclose(filtered.s, smoothed.s)


@pytest.fixture(scope="module")
def peg_online(peg):
    task, ro, _, _, _ = peg
    _, filt, _ = loop.learn(task, ro, task.initial_policy(0.3), KinematicConfig(gains="online"))
    return task, ro, filt


def test_online_update_is_the_extended_kalman_update_with_the_nominal_prior(peg_online):
    """Oracle: the gain form ``z + P H^T (H P H^T + R)^{-1} (s - h(z))`` with ``H = dh/dz`` at the
    rollout's own prediction and the nominal predicted covariance ``P``, one step at a time."""
    task, ro, filt = peg_online
    km = KinematicModel(task)
    assert filt.online
    xhat = filt.states(ro.s, ro.a)
    for i in (0, 5):
        for k in (0, 1, 40, task.T):
            if k == 0:
                pred, Pm = filt.z0, filt.P0
            else:
                pred = xhat[i, k - 1, filt.zidx] @ filt.A[k - 1].T + ro.a[i, k - 1] @ filt.Bz[k - 1].T + filt.cz[k - 1]
                Pm = filt.A[k - 1] @ filt.P[k - 1] @ filt.A[k - 1].T + filt.Q[k - 1]
            hx, H = km.measure(pred)
            gain = Pm @ H.T @ np.linalg.inv(H @ Pm @ H.T + filt.R)
            expect = km.measure(pred + gain @ (ro.s[i, k] - hx), False)
            np.testing.assert_allclose(xhat[i, k], expect, rtol=1e-9, atol=1e-9)


def test_online_filter_in_rollouts_equals_offline_and_is_saved(peg_online, tmp_path):
    task, _, filt = peg_online
    pol = KinematicFilteredPolicy(_policy(task, np.random.default_rng(0)), filt)
    r = task.rollouts(pol, 2, np.random.default_rng(1))
    xhat = filt.states(r.s, r.a)
    draws = task.draw_noise(2, np.random.default_rng(1))
    expect = pol.policy.k[None] + np.einsum("tij,mtj->mti", pol.policy.chol, draws.w)
    np.testing.assert_allclose(r.a - np.einsum("tij,mtj->mti", pol.policy.K, xhat[:, :-1]), expect, atol=1e-10)
    path = tmp_path / "policy.npz"
    np.savez(path, **pol.to_dict())
    with np.load(path, allow_pickle=False) as d:
        back = KinematicFilteredPolicy.from_dict(d, task)
        legacy = KinematicFilteredPolicy.from_dict({k: d[k] for k in d.files if k != "kfilter_online"}, task)
    assert back.filter.online and not legacy.filter.online
    np.testing.assert_array_equal(back.filter.states(r.s, r.a), xhat)
    with pytest.raises(ValueError, match="R = rho"):
        KinematicFilter(**{**{k: getattr(filt, k) for k in ("A", "Bz", "cz", "Q", "z0", "P0", "zbar", "h0", "H", "zidx",
                                                            "accel_B", "accel_D", "accel_c", "accel_S")},
                           "R": np.diag(np.linspace(0.1, 0.2, task.n)), "online": True})


def test_rollouts_of_a_filtered_policy_in_threads_equal_those_in_one_thread(peg_online):
    """``workers > 1`` runs blocks of a filtered policy's rollouts in threads, each block in lockstep:
    the same states, measurements and actions, bit for bit, as one block in one thread."""
    task, _, filt = peg_online
    pol = KinematicFilteredPolicy(_policy(task, np.random.default_rng(0)), filt)
    one = task.rollouts(pol, 5, np.random.default_rng(4))
    for workers in (2, 3):
        many = task.rollouts(pol, 5, np.random.default_rng(4), workers=workers)
        for name in ("x", "s", "a", "cost", "y"):
            np.testing.assert_array_equal(getattr(many, name), getattr(one, name))


def _one_at_a_time(task, pol, M, seed):
    """Oracle: the rollouts of ``pol`` simulated one after the other, each on its own
    :class:`~soc_opt.tasks.mujoco.MujocoSimulator` (the rollouts' physics calls, tested in test_envs), its
    filter stepped on that rollout's vectors alone and the action ``K_k xhat_k`` as one ``numpy.dot``:
    the per-rollout arithmetic the lockstep simulation must reproduce."""
    draws = task.draw_noise(M, np.random.default_rng(seed))
    offs = pol.policy.k[None] + np.einsum("tij,mtj->mti", pol.policy.chol, draws.w)
    T = task.T
    x, s, a = np.empty((M, T + 1, task.n)), np.empty((M, T + 1, task.n)), np.empty((M, T, task.m))
    for i in range(M):
        sim = task.simulator()
        x[i, 0] = sim.reset()
        xhat = None
        for k in range(T + 1):
            s[i, k] = x[i, k] + draws.eps[i, k]
            if k == T:
                break
            xhat = pol.estimate(k, s[i, k]) if k == 0 else pol.estimate(k, s[i, k], xhat, a[i, k - 1])
            a[i, k] = np.dot(pol.policy.K[k], xhat) + offs[i, k]
            x[i, k + 1] = sim.step(a[i, k])
    return x, s, a


@pytest.fixture(scope="module")
def peg_nominal(peg):
    task, ro, _, _, _ = peg
    _, filt, _ = loop.learn(task, ro, task.initial_policy(0.3), KinematicConfig(gains="nominal"))
    return task, ro, filt


@pytest.mark.parametrize("gains", ["nominal", "online"])
def test_lockstep_rollouts_equal_the_rollouts_simulated_one_at_a_time(peg_nominal, peg_online, gains):
    """The samples of a filtered policy are stepped together, the filter updating all of them in one
    call per step: every state, measurement and action equals, bit for bit, that rollout simulated
    alone with its filter stepped on its own vectors (nominal gains with ``h`` attached, and the
    online extended update)."""
    task, _, filt = peg_online if gains == "online" else peg_nominal
    assert filt.online == (gains == "online")
    pol = KinematicFilteredPolicy(_policy(task, np.random.default_rng(0)), filt)
    got = task.rollouts(pol, 4, np.random.default_rng(6))
    for name, want in zip(("x", "s", "a"), _one_at_a_time(task, pol, 4, 6)):
        np.testing.assert_array_equal(getattr(got, name), want)


@settings(max_examples=15, deadline=None)
@given(rows=st.lists(st.integers(0, 7), min_size=1, max_size=6), k=st.sampled_from([0, 1, 37, 100]))
def test_a_filter_steps_rows_of_a_batch_as_it_steps_each_alone(peg_nominal, peg_online, rows, k):
    """Property: ``KinematicFilter.step`` on any batch of rows (repeats allowed, any order) returns for
    each row exactly what it returns for that row alone, so a rollout's estimates do not depend on
    the batch it is stepped in (nominal and online gains with ``h`` attached, and the linearised ``h``
    of a filter read back without its task)."""
    ro, nominal = peg_nominal[1], peg_nominal[2]
    linearised = KinematicFilter.from_dict(nominal.to_dict())
    for filt in (nominal, peg_online[2], linearised):
        xhat = filt.states(ro.s, ro.a)
        args = (ro.s[:, k],) if k == 0 else (ro.s[:, k], xhat[:, k - 1], ro.a[:, k - 1])
        batch = filt.step(k, *(v[rows] for v in args))
        for j, i in enumerate(rows):
            np.testing.assert_array_equal(batch[j], filt.step(k, *(v[i] for v in args)))
