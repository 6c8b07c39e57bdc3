"""Tests for soc_opt/tasks/process_noise.py and its use by the rollouts (docs/math.md §8.1; docs/tasks.md,
"Process noise"): a start range on the state joints and actuation noise, declared in ``[process_noise]``.

Oracles: the code before the table existed (arrays recorded at c977c31, ``tests/data/process_noise_off.npz``),
the Generator read by hand in the documented order, MuJoCo stepped by hand with the same draws, the
finite-difference linearisation (``task.linearize``) for the effect of the actuation noise, the uniform
distribution's moments and Kolmogorov-Smirnov test, and Monte Carlo covariances with tolerances from
their standard errors.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import scipy.stats

from soc_opt.config import ConfigError
from soc_opt.models import LinearGaussianDynamics, LinearGaussianPolicy
from soc_opt.noise.aware import noise_model
from soc_opt.noise.estimator import FilteredPolicy, kalman_filter
from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import build_task, load_task
from soc_opt.tasks.config import ProcessNoiseConfig

GOLDEN = Path(__file__).parent / "data" / "process_noise_off.npz"
PEG_JOINTS = 7


def _policy(task, seed):
    """The random feedback policy the golden arrays were recorded with."""
    rng = np.random.default_rng(seed)
    T, m, n = task.T, task.m, task.n
    return LinearGaussianPolicy(0.01 * rng.standard_normal((T, m, n)), rng.standard_normal((T, m)),
                                np.broadcast_to(0.3 * np.eye(m), (T, m, m)).copy())


def _filtered(task, pol):
    """The policy acting on a Kalman filter of a trivial model (MuJoCo: the lockstep path of the rollouts)."""
    T, n, m = task.T, task.n, task.m
    dyn = LinearGaussianDynamics(np.broadcast_to(np.eye(n), (T, n, n)).copy(), np.zeros((T, n, m)), np.zeros((T, n)),
                                 np.broadcast_to(0.01 * np.eye(n), (T, n, n)).copy())
    R = task.rho2 * np.eye(n)
    return FilteredPolicy(pol, kalman_filter(dyn, R, task.mu0, task.P0 - R))


# ----------------------------------------------------------------- off: nothing changes


@pytest.mark.parametrize("name", ["peg", "door", "linear2d"])
@pytest.mark.parametrize("table", [None, "zeros"])
def test_without_process_noise_rollouts_are_those_of_the_code_before_it(name, table):
    """No ``[process_noise]`` (or one of zeros): the rollouts of a plain and of a filtered policy (the lockstep
    path) are the arrays the code of c977c31 produced, and the Generator is left where that code left it.
    Recorded there (``T = 20``, 2 rollouts, policy seed 1, rollout seeds 5 and 6); bit for bit on the
    machine that recorded them, to rounding elsewhere."""
    over = {"T": 20}
    if table == "zeros":
        task = load_task(name, overrides=over)
        over["process_noise"] = {"start": [0.0] * len(task.process_noise.start), "actuation": 0.0}
    task = load_task(name, overrides=over)
    gold = np.load(GOLDEN)
    pol = _policy(task, 1)
    rng = np.random.default_rng(5)
    ro = task.rollouts(pol, 2, rng)
    for f in ("x", "a", "cost"):
        np.testing.assert_allclose(getattr(ro, f), gold[f"{name}_{f}"], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(rng.random(4), gold[f"{name}_next"])
    ro = task.rollouts(_filtered(task, pol), 2, np.random.default_rng(6))
    for f in ("x", "a"):
        np.testing.assert_allclose(getattr(ro, f), gold[f"{name}_filtered_{f}"], rtol=1e-12, atol=1e-12)
    draws = task.draw_noise(2, np.random.default_rng(0))
    assert draws.start is None and draws.actuation is None
    np.testing.assert_array_equal(task.P0, (task.rho2 + 1e-6) * np.eye(task.n))
    np.testing.assert_array_equal(task.start_cov, np.zeros((task.n, task.n)))
    if name != "linear2d":
        cfg = KinematicConfig()
        km = KinematicModel(task)
        acc = em.initial_map(km, ro.s, task.rho2, cfg.s_floor)
        np.testing.assert_array_equal(em.z_model(km, acc, cfg).P0, cfg.p0 * np.eye(km.nz))


# ----------------------------------------------------------------- the draws


def _peg(T=20, **table):
    return load_task("peg", overrides={"T": T, "process_noise": table})


@pytest.mark.parametrize("table", [{"start": 0.1}, {"actuation": 0.5}, {"start": [0.1, 0.0, 0.2, 0.0, 0.0, 0.05, 0.3],
                                                                         "actuation": [1.0, 0.5, 0.0, 0.2, 0.1, 0.1, 0.1]}])
def test_peg_draws_eps_then_w_then_start_offsets_then_actuation_noise_each_only_when_on(table):
    task = _peg(**table)
    M, T, n, m = 3, task.T, task.n, task.m
    got = task.draw_noise(M, np.random.default_rng(4))
    g = np.random.default_rng(4)
    np.testing.assert_array_equal(got.eps, g.standard_normal((M, T + 1, n)) * math.sqrt(task.rho2))
    np.testing.assert_array_equal(got.w, g.standard_normal((M, T, m)))
    assert got.xi is None
    r = np.broadcast_to(np.asarray(table.get("start", 0.0), dtype=float), (PEG_JOINTS,))
    sigma = np.broadcast_to(np.asarray(table.get("actuation", 0.0), dtype=float), (m,))
    if "start" in table:
        np.testing.assert_array_equal(got.start, g.uniform(-1.0, 1.0, (M, PEG_JOINTS)) * r)
    else:
        assert got.start is None
    if "actuation" in table:
        np.testing.assert_array_equal(got.actuation, g.standard_normal((M, T, m)) * sigma)
    else:
        assert got.actuation is None
    nxt = g.random(3)
    rng = np.random.default_rng(4)
    task.rollouts(task.initial_policy(), M, rng)  # the rollouts draw through draw_noise: same stream
    np.testing.assert_array_equal(rng.random(3), nxt)


def test_linear_task_draws_its_transition_noise_before_the_process_noise_table():
    task = load_task("linear2d", overrides={"T": 10, "process_noise": {"start": 0.5, "actuation": [0.1, 0.2]}})
    M, T, n, m = 2, task.T, task.n, task.m
    got = task.draw_noise(M, np.random.default_rng(1))
    g = np.random.default_rng(1)
    np.testing.assert_array_equal(got.eps, g.standard_normal((M, T + 1, n)) * math.sqrt(task.rho2))
    np.testing.assert_array_equal(got.w, g.standard_normal((M, T, m)))
    np.testing.assert_array_equal(got.xi, g.standard_normal((M, T, n)) * math.sqrt(task.config.linear.process_var))
    np.testing.assert_array_equal(got.start, g.uniform(-1.0, 1.0, (M, n)) * 0.5)
    np.testing.assert_array_equal(got.actuation, g.standard_normal((M, T, m)) * np.array([0.1, 0.2]))


def test_noise_false_draws_nothing_and_runs_the_policy_mean_from_the_nominal_start():
    task = _peg(start=0.2, actuation=1.0)
    pol = _policy(task, 2)
    rng = np.random.default_rng(9)
    ro = task.rollouts(pol, 2, rng, noise=False)
    np.testing.assert_array_equal(rng.random(2), np.random.default_rng(9).random(2))
    plain = load_task("peg", overrides={"T": 20}).rollouts(pol, 2, np.random.default_rng(0), noise=False)
    for f in ("x", "s", "a"):
        np.testing.assert_array_equal(getattr(ro, f), getattr(plain, f))


# ----------------------------------------------------------------- the start range


def test_start_offsets_are_uniform_in_the_stated_range_with_its_mean_and_variance():
    r = np.array([0.1, 0.0, 0.2, 0.05, 0.3, 0.15, 0.02])
    task = _peg(T=1, start=r.tolist())
    M = 4000
    d = task.draw_noise(M, np.random.default_rng(11)).start
    assert d.shape == (M, PEG_JOINTS)
    assert np.all(np.abs(d) <= r)
    assert not d[:, 1].any()
    on = r > 0
    u = d[:, on] / r[on]  # should be U(-1, 1)
    se_mean = math.sqrt(1 / 3 / M)
    se_var = math.sqrt((1 / 5 - 1 / 9) / M)  # of the mean of u^2: Var(u^2) = E u^4 - (E u^2)^2
    assert np.all(np.abs(u.mean(0)) < 5 * se_mean)
    assert np.all(np.abs((u ** 2).mean(0) - 1 / 3) < 5 * se_var)
    for j in range(u.shape[1]):
        assert scipy.stats.kstest(u[:, j], scipy.stats.uniform(-1, 2).cdf).pvalue > 1e-3


def test_rollouts_start_at_the_offset_joint_angles_at_rest_with_the_points_of_their_kinematics():
    task = _peg(T=3, start=0.2)
    ro = task.rollouts(task.initial_policy(), 4, np.random.default_rng(2))
    d = task.draw_noise(4, np.random.default_rng(2)).start
    nj = PEG_JOINTS
    np.testing.assert_array_equal(ro.x[:, 0, :nj], task.x0[:nj] + d)
    assert not ro.x[:, 0, task.layout["qvel"]].any() and not ro.x[:, 0, task.layout["site_vel"]].any()
    for i in range(4):  # the oracle: mj_forward on the offset configuration
        np.testing.assert_allclose(ro.x[i, 0], task.state_from_qpos(task.qpos_from_state(ro.x[i, 0])), atol=1e-12)
    assert np.abs(ro.x[:, 0, task.layout["site_pos"]] - task.x0[task.layout["site_pos"]]).max() > 0.01
    x0 = task.x0.copy()
    x0[:nj] += 0.05  # an x0 override: the offsets are added to it
    ro2 = task.rollouts(task.initial_policy(), 4, np.random.default_rng(2), x0=x0)
    np.testing.assert_array_equal(ro2.x[:, 0, :nj], x0[:nj] + d)


def test_start_cov_is_the_covariance_of_the_sampled_starts_and_enters_P0():
    """``task.start_cov`` against the empirical covariance of 4000 sampled true starts (entrywise within 5
    standard errors, ``sqrt((S_ii S_jj + S_ij^2) / M)`` for a covariance estimate), on the joint rows
    exactly ``diag(r^2 / 3)``; ``P0`` adds the measurement's ``(rho2 + 1e-6) I``, and the estimators' true
    start ``P0 - R`` is ``start_cov + 1e-6 I``."""
    r = np.array([0.02, 0.01, 0.03, 0.02, 0.02, 0.01, 0.02])
    task = _peg(T=1, start=r.tolist())
    C = task.start_cov
    nj = PEG_JOINTS
    np.testing.assert_allclose(C[:nj, :nj], np.diag(r ** 2 / 3), rtol=1e-14, atol=0)
    np.testing.assert_array_equal(C, C.T)
    M = 4000
    ro = task.rollouts(task.initial_policy(), M, np.random.default_rng(8))
    emp = np.cov(ro.x[:, 0], rowvar=False)
    se = np.sqrt((np.outer(np.diag(C), np.diag(C)) + C ** 2) / M)
    assert np.all(np.abs(emp - C) <= 5 * se + 1e-15)
    pts = task.layout["site_pos"]
    assert np.diag(C)[pts].min() > 1e-6  # the points move with the joints
    np.testing.assert_allclose(task.P0, C + (task.rho2 + 1e-6) * np.eye(task.n), rtol=1e-15, atol=1e-18)
    nm = noise_model(task)
    np.testing.assert_allclose(nm.P0, C + 1e-6 * np.eye(task.n), rtol=1e-12, atol=1e-15)


def test_linear_start_offsets_every_component_and_its_covariance_is_diagonal():
    task = load_task("linear2d", overrides={"T": 5, "process_noise": {"start": [1, 2, 0, 0, 0.5, 0]}})
    r = np.array([1, 2, 0, 0, 0.5, 0.0])
    np.testing.assert_allclose(task.start_cov, np.diag(r ** 2 / 3), rtol=1e-15)
    ro = task.rollouts(task.initial_policy(), 3, np.random.default_rng(1))
    np.testing.assert_array_equal(ro.x[:, 0], task.x0 + task.draw_noise(3, np.random.default_rng(1)).start)


# ----------------------------------------------------------------- actuation noise


def test_peg_actuation_noise_is_added_to_the_plant_control_as_mujoco_stepped_by_hand_with_the_same_draws():
    """Oracle: ``mj_step`` from the offset start with ``ctrl = a_k + nu_k`` held for the substeps; the
    recorded action is the policy's ``a_k`` (``K_k s_k`` plus its offset), not the plant's control."""
    task = _peg(T=15, start=0.1, actuation=[1.0, 0.5, 0.3, 0.3, 0.1, 0.1, 0.1])
    pol = _policy(task, 3)
    M = 3
    ro = task.rollouts(pol, M, np.random.default_rng(5))
    dr = task.draw_noise(M, np.random.default_rng(5))
    m_, T = task.model, task.T
    offs = pol.k[None] + np.einsum("tij,mtj->mti", pol.chol, dr.w)
    for i in range(M):
        d = mujoco.MjData(m_)
        d.qpos[:] = task._qinit
        d.qpos[task.qpos_adr[:PEG_JOINTS]] += dr.start[i]
        mujoco.mj_forward(m_, d)
        for k in range(T):
            np.testing.assert_array_equal(ro.x[i, k, :PEG_JOINTS], d.qpos[task.qpos_adr[:PEG_JOINTS]])
            np.testing.assert_array_equal(ro.x[i, k, PEG_JOINTS:2 * PEG_JOINTS], d.qvel[task.dof_adr[:PEG_JOINTS]])
            s_k = ro.x[i, k] + dr.eps[i, k]
            np.testing.assert_allclose(ro.a[i, k], pol.K[k] @ s_k + offs[i, k], rtol=1e-12, atol=1e-12)
            d.ctrl[task.actuator_ids] = ro.a[i, k] + dr.actuation[i, k]
            mujoco.mj_step(m_, d, task.substeps)
        np.testing.assert_array_equal(ro.x[i, T, :PEG_JOINTS], d.qpos[task.qpos_adr[:PEG_JOINTS]])


def test_peg_actuation_noise_spreads_the_velocities_of_one_step_as_the_linearised_torque_map_implies():
    """With the policy's mean at zero torque, after one control step ``Cov(x_1) = B_0 diag(sigma^2) B_0^T``
    (``B_0`` by finite differences of MuJoCo, ``task.linearize``), on the joint velocities within 5
    standard errors of the Monte Carlo covariance of 3000 rollouts."""
    sigma = np.array([1.0, 0.5, 0.3, 0.3, 0.1, 0.1, 0.1])
    task = _peg(T=1, actuation=sigma.tolist())
    T, m, n = task.T, task.m, task.n
    pol = LinearGaussianPolicy(np.zeros((T, m, n)), np.zeros((T, m)), np.zeros((T, m, m)), allow_singular=True)
    M = 3000
    ro = task.rollouts(pol, M, np.random.default_rng(12))
    assert not ro.a.any()  # the recorded actions stay the policy's
    B = task.linearize(np.stack([task.x0, task.x0]), np.zeros((1, m))).B[0]
    C = (B * sigma ** 2) @ B.T
    v = task.layout["qvel"]
    emp = np.cov(ro.x[:, 1, v], rowvar=False)
    Cv = C[v, v]
    se = np.sqrt((np.outer(np.diag(Cv), np.diag(Cv)) + Cv ** 2) / M)
    assert np.all(np.abs(emp - Cv) <= 5 * se)
    assert np.diag(Cv).min() > 1e-8


def test_linear_actuation_noise_enters_before_B():
    task = load_task("linear2d", overrides={"T": 6, "process_noise": {"actuation": [0.3, 0.7]}})
    pol = _policy(task, 4)
    ro = task.rollouts(pol, 3, np.random.default_rng(2))
    dr = task.draw_noise(3, np.random.default_rng(2))
    want = ro.x[:, :-1] @ task.A.T + (ro.a + dr.actuation) @ task.B.T + task.c + dr.xi
    np.testing.assert_allclose(ro.x[:, 1:], want, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------- paths that must agree


def _one_at_a_time(task, pol, M, seed):
    """Each rollout on its own :class:`~soc_opt.tasks.mujoco.MujocoSimulator`, the filter stepped on its own
    vectors: what the lockstep simulation of a filtered policy must reproduce."""
    dr = task.draw_noise(M, np.random.default_rng(seed))
    offs = pol.policy.k[None] + np.einsum("tij,mtj->mti", pol.policy.chol, dr.w)
    T = task.T
    x, s, a = np.empty((M, T + 1, task.n)), np.empty((M, T + 1, task.n)), np.empty((M, T, task.m))
    for i in range(M):
        sim = task.simulator()
        x[i, 0] = sim.reset(None, None if dr.start is None else dr.start[i])
        xhat = None
        for k in range(T + 1):
            s[i, k] = x[i, k] + dr.eps[i, k]
            if k == T:
                break
            xhat = pol.estimate(k, s[i, k]) if k == 0 else pol.estimate(k, s[i, k], xhat, a[i, k - 1])
            a[i, k] = np.dot(pol.policy.K[k], xhat) + offs[i, k]
            x[i, k + 1] = sim.step(a[i, k], None, None if dr.actuation is None else dr.actuation[i, k])
    return x, s, a


@pytest.mark.parametrize("name", ["peg", "door"])
def test_lockstep_rollouts_with_process_noise_equal_the_rollouts_simulated_one_at_a_time(name):
    task = load_task(name, overrides={"T": 15, "process_noise": {"start": 0.05, "actuation": 0.5}})
    pol = _filtered(task, _policy(task, 5))
    got = task.rollouts(pol, 4, np.random.default_rng(6))
    for f, want in zip(("x", "s", "a"), _one_at_a_time(task, pol, 4, 6)):
        np.testing.assert_array_equal(getattr(got, f), want)
    for workers in (2, 3):
        many = task.rollouts(pol, 4, np.random.default_rng(6), workers=workers)
        for f in ("x", "s", "a", "cost"):
            np.testing.assert_array_equal(getattr(many, f), getattr(got, f))


def test_plain_rollouts_with_process_noise_are_independent_of_workers():
    task = _peg(start=0.1, actuation=0.5)
    pol = _policy(task, 6)
    one = task.rollouts(pol, 5, np.random.default_rng(1))
    for workers in (2, 3):
        many = task.rollouts(pol, 5, np.random.default_rng(1), workers=workers)
        for f in ("x", "s", "a", "cost"):
            np.testing.assert_array_equal(getattr(many, f), getattr(one, f))


# ----------------------------------------------------------------- configuration


@pytest.mark.parametrize("table, says", [
    ({"start": -0.1}, "process_noise.start: must be >= 0"),
    ({"actuation": [0.1, -1.0]}, "process_noise.actuation[1]: must be >= 0"),
    ({"start": float("nan")}, "process_noise.start"),
    ({"actuation": float("inf")}, "process_noise.actuation"),
    ({"start": []}, "process_noise.start: an empty list"),
    ({"start": [0.1, 0.2]}, "process_noise.start: expected 7 numbers (one per joint of state.joints: shoulder_pan"),
    ({"actuation": [0.1] * 6}, "process_noise.actuation: expected 7 numbers (one per actuator: shoulder_pan"),
    ({"start": "wide"}, "process_noise.start"),
    ({"stat": 0.1}, "unknown config key 'stat' in [process_noise]"),
])
def test_config_errors_name_the_key(table, says):
    with pytest.raises(ConfigError) as e:
        load_task("peg", overrides={"process_noise": table})
    assert says in str(e.value)


def test_a_start_range_without_state_joints_is_refused_naming_the_key():
    xml = """<mujoco><worldbody><body><joint name="j" type="hinge"/><geom size="0.1"/><site name="tip"/></body>
    </worldbody><actuator><motor joint="j"/></actuator></mujoco>"""
    cfg = {"name": "sites_only", "T": 5, "state": {"sites": ["tip"]}, "process_noise": {"start": 0.1}}
    with pytest.raises(ConfigError, match=r"process_noise.start: the task has no joint of state.joints"):
        build_task(cfg, xml=xml)
    cfg["process_noise"] = {"actuation": 0.1}
    assert build_task(cfg, xml=xml).process_noise.actuation_on


def test_the_table_round_trips_and_defaults_to_off():
    assert ProcessNoiseConfig().to_dict() == {"start": 0.0, "actuation": 0.0}
    task = _peg(start=[0.1] * 7, actuation=0.2)
    assert task.config.to_dict()["process_noise"] == {"start": [0.1] * 7, "actuation": 0.2}
    assert task.process_noise.start_on and task.process_noise.actuation_on
    assert not load_task("door").process_noise.start_on
