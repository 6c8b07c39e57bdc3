"""Tests for soc_opt/tasks.py: task loading, state layout, rollouts, linearisation, config errors."""

import os

import mujoco
import numpy as np
import pytest
import scipy.integrate
from scipy.optimize import least_squares

from soc_opt.config import ConfigError
from soc_opt.models import LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost, Rollouts
from soc_opt.tasks import (
    LinearTask,
    MujocoTask,
    SimulationError,
    Task,
    TaskConfig,
    build_task,
    load_task,
    render_filmstrip,
)
from soc_opt.tasks.loading import problems_dir

START = np.array([0.1, 0.1, -1.54, -1.7, 1.54, -0.2, 0.0])


@pytest.fixture(scope="module")
def peg():
    return load_task("peg")


@pytest.fixture(scope="module")
def door():
    return load_task("door")


@pytest.fixture(scope="module")
def lin():
    return load_task("linear2d")


# ----------------------------------------------------------------- loading and dimensions


def test_builtin_tasks_load_with_spec_dimensions(peg, door, lin):
    assert isinstance(peg, MujocoTask) and isinstance(door, MujocoTask) and isinstance(lin, LinearTask)
    for t in (peg, door, lin):
        assert isinstance(t, Task)
        assert len(t.state_labels) == t.n and t.mu0.shape == (t.n,) and t.P0.shape == (t.n, t.n)
        assert np.all(np.linalg.eigvalsh(t.P0) > 0)
        pol = t.initial_policy(0.5)
        assert (pol.T, pol.m, pol.n) == (t.T, t.m, t.n) and np.allclose(pol.cov, 0.5 * np.eye(t.m))
    assert (peg.n, peg.m, peg.T) == (26, 7, 100) and peg.dt == pytest.approx(0.05)
    assert (door.n, door.m, door.T) == (26, 6, 100) and door.dt == pytest.approx(0.05)
    assert (lin.n, lin.m) == (6, 2)
    assert peg.model.opt.gravity.tolist() == [0.0, 0.0, 0.0] and peg.model.opt.timestep == 0.01
    np.testing.assert_allclose(peg.x0[:7], START)
    assert peg.state_labels[14:20] == ["peg_top.x", "peg_top.y", "peg_top.z", "peg_bottom.x", "peg_bottom.y", "peg_bottom.z"]
    assert door.state_labels[24:] == ["q:hinge", "qd:hinge"]
    assert peg.P0[0, 0] == pytest.approx(0.1 + 1e-6)


def test_peg_geometry_matches_spec(peg):
    m = peg.model
    g = m.geom("peg")
    assert g.size[0] == pytest.approx(0.028) and 2 * g.size[1] == pytest.approx(0.3)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert np.linalg.norm(d.site("peg_top").xpos - d.site("peg_bottom").xpos) == pytest.approx(0.3)
    # table top surface at z = -0.4 around a 0.066 x 0.066 hole centred at (0, 0.3); hole floor at z = -0.5
    left, right = d.geom("table_left"), d.geom("table_right")
    front, back = d.geom("table_front"), d.geom("table_back")
    assert left.xpos[2] + m.geom("table_left").size[2] == pytest.approx(-0.4)
    assert right.xpos[0] - m.geom("table_right").size[0] == pytest.approx(0.033)
    assert left.xpos[0] + m.geom("table_left").size[0] == pytest.approx(-0.033)
    assert back.xpos[1] - m.geom("table_back").size[1] == pytest.approx(0.333)
    assert front.xpos[1] + m.geom("table_front").size[1] == pytest.approx(0.267)
    fl = d.geom("hole_floor")
    assert fl.xpos[2] + m.geom("hole_floor").size[2] == pytest.approx(-0.5)


def _ik(task, targets, q_start):
    """Joint angles putting each site at its target (scipy least squares on MuJoCo kinematics)."""
    m = task.model
    d = mujoco.MjData(m)
    lo = np.where(m.jnt_limited, m.jnt_range[:, 0], -np.pi)
    hi = np.where(m.jnt_limited, m.jnt_range[:, 1], np.pi)

    def res(q):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        return np.concatenate([d.site(s).xpos - np.asarray(p) for s, p in targets.items()] + [1e-4 * (q - q_start)])

    q = least_squares(res, q_start, bounds=(lo, hi), xtol=1e-14, ftol=1e-14).x
    return q, np.abs(res(q)[:-len(q)]).max()


def test_peg_targets_are_reachable_within_joint_limits(peg):
    q, err = _ik(peg, {"peg_top": [0, 0.3, -0.2], "peg_bottom": [0, 0.3, -0.5]}, START)
    assert err < 1e-3
    d = mujoco.MjData(peg.model)
    d.qpos[:] = q
    mujoco.mj_forward(peg.model, d)
    assert d.ncon == 0  # inserted pose does not penetrate the table


# ----------------------------------------------------------------- physics sanity


def test_zero_torque_holds_still_from_rest(peg, door):
    for t in (peg, door):
        r = t.simulate(LinearGaussianPolicy(np.zeros((t.T, t.m, t.n)), np.zeros((t.T, t.m)), np.broadcast_to(np.eye(t.m), (t.T, t.m, t.m))))
        assert np.abs(r.x[0] - t.x0).max() < 1e-12


def _pd_policy(task, q_targets, steps_each, w=2 * np.pi, zeta=0.9):
    """PD on joint angles/velocities as a LinearGaussianPolicy: ``a = Kp (q* - q) - Kd qd``,
    i.e. ``K = [-Kp, -Kd, 0]``, ``k = Kp q*``; ``q*`` steps through ``q_targets`` (the last one is held)."""
    m = task.model
    d = mujoco.MjData(m)
    d.qpos[:] = q_targets[0]
    mujoco.mj_forward(m, d)
    Mf = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, Mf)
    Md = np.diag(Mf)  # gains scaled by the joint-space inertia: ~1 Hz, well damped
    Kp, Kd = w**2 * Md, 2 * zeta * w * Md
    T, n, mm = task.T, task.n, task.m
    K = np.zeros((T, mm, n))
    k = np.zeros((T, mm))
    j = np.arange(mm)
    K[:, j, j] = -Kp
    K[:, j, mm + j] = -Kd
    for t in range(T):
        k[t] = Kp * q_targets[min(t // steps_each, len(q_targets) - 1)]
    return LinearGaussianPolicy(K, k, np.broadcast_to(np.eye(mm), (T, mm, mm)))


def test_pd_policy_to_ik_poses_inserts_the_peg(peg):
    # hover 0.1 m above the table over the hole, then descend straight down through IK waypoints
    qs, q = [], START
    for dz in (0.2, 0.2, 0.15, 0.1, 0.05, 0.0):
        q, err = _ik(peg, {"peg_top": [0, 0.3, -0.2 + dz], "peg_bottom": [0, 0.3, -0.5 + dz]}, q)
        assert err < 1e-3
        qs.append(q)
    r = peg.simulate(_pd_policy(peg, qs, steps_each=15))
    pts = peg.ee_points(r.x[0])
    np.testing.assert_allclose(pts[29, 1], [0, 0.3, -0.3], atol=0.02)  # hovering over the hole
    met = peg.metrics(r)
    assert met["min_distance"] < 0.02 and met["success_rate"] == 1.0 and met["failure_rate"] == 0.0
    assert pts[-1, 1, 2] < -0.45  # the bottom is inside the hole, below the table surface


def test_door_can_be_hooked_and_pulled_open(door):
    """Feasibility of the door model: IK waypoints (hook tip down, into the gap behind the handle
    bar, then following the handle as the door turns) tracked by a joint PD policy open the door."""
    m, T = door.model, door.T
    qa, hq = door.qpos_adr[:6], door.qpos_adr[6]
    jid = [m.joint(nm).id for nm in door.config.state.joints]
    lo = np.where(m.jnt_limited[jid], m.jnt_range[jid, 0], -np.pi)
    hi = np.where(m.jnt_limited[jid], m.jnt_range[jid, 1], np.pi)
    hook, handle = m.site("hook").id, m.site("handle").id
    d = mujoco.MjData(m)

    def ik(offset, hinge, q0, local):
        def res(q):
            d.qpos[qa] = q
            d.qpos[hq] = hinge
            mujoco.mj_kinematics(m, d)
            R = d.site_xmat[handle].reshape(3, 3)
            target = d.site_xpos[handle] + (R @ offset if local else offset)
            return np.r_[d.site_xpos[hook] - target, 0.3 * (d.site_xmat[hook].reshape(3, 3)[:, 2] - [0, 0, 1]), 1e-3 * (q - q0)]

        return least_squares(res, q0, bounds=(lo, hi)).x

    qs, q = [], door.x0[:6]
    for off in ([-0.1, 0, 0.12], [0, 0, 0.12], [0, 0, 0]):  # above and in front, above the gap, into the gap
        q = ik(np.array(off), 0.0, q, local=False)
        qs.append(q)
    for h in np.linspace(-0.1, -1.2, 12):  # pull: follow the handle as the door opens
        q = ik(np.array([-0.02, 0, 0]), h, q, local=True)
        qs.append(q)
    sched = [0] * 12 + [1] * 12 + [2] * 12 + [3 + i for i in range(12) for _ in range(5)]
    d.qpos[:] = door.qpos_from_state(door.x0)
    mujoco.mj_forward(m, d)
    Mf = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, Mf)
    Md = np.diag(Mf)[door.dof_adr[:6]]
    Kp, Kd = 64.0 * Md, 2 * 0.8 * 8.0 * Md
    gear = m.actuator_gear[door.actuator_ids, 0]  # the PD torques in action units (torque = gear * action)
    K = np.zeros((T, 6, door.n))
    j = np.arange(6)
    K[:, j, j] = -Kp / gear
    K[:, j, 6 + j] = -Kd / gear
    k = np.array([Kp * qs[sched[min(t, len(sched) - 1)]] / gear for t in range(T)])
    r = door.simulate(LinearGaussianPolicy(K, k, np.broadcast_to(np.eye(6), (T, 6, 6))))
    assert door.metrics(r)["min_hinge"] < -0.8


# ----------------------------------------------------------------- state layout


def test_site_positions_in_state_equal_mj_kinematics(peg, door):
    for t in (peg, door):
        r = t.rollouts(t.initial_policy(), 2, np.random.default_rng(1))
        d = mujoco.MjData(t.model)
        sl = t.layout["site_pos"]
        for i, k in [(0, 0), (0, 37), (1, 100)]:
            d.qpos[:] = t.qpos_from_state(r.x[i, k])
            mujoco.mj_kinematics(t.model, d)
            expected = np.concatenate([d.site(s).xpos for s in t.config.state.sites])
            np.testing.assert_allclose(r.x[i, k, sl], expected, atol=1e-12)
            np.testing.assert_allclose(t.ee_points(r.x[i, k]).ravel(), expected, atol=1e-12)


def test_site_velocities_equal_finite_differences_of_positions(peg, door):
    for t in (peg, door):
        r = t.rollouts(t.initial_policy(), 1, np.random.default_rng(2))
        d = mujoco.MjData(t.model)
        sites = t.config.state.sites
        for k in (10, 60):
            x = r.x[0, k]
            q = t.qpos_from_state(x)
            qd = np.zeros(t.model.nv)
            qd[t.dof_adr] = x[t.state_qvel_idx]
            assert np.abs(qd).max() > 1e-2  # moving
            h = 1e-6
            pos = []
            for sign in (1, -1):
                d.qpos[:] = q + sign * h * qd  # hinge joints: qpos and qvel share coordinates
                mujoco.mj_kinematics(t.model, d)
                pos.append(np.concatenate([d.site(s).xpos for s in sites]))
            fd = (pos[0] - pos[1]) / (2 * h)
            np.testing.assert_allclose(x[t.layout["site_vel"]], fd, atol=1e-6 * max(1, np.abs(fd).max()))


# ----------------------------------------------------------------- rollouts


def test_rollouts_shapes_costs_on_measured_state(peg):
    r = peg.rollouts(peg.initial_policy(), 3, np.random.default_rng(0))
    assert isinstance(r, Rollouts) and r.x.shape == (3, 101, 26) and r.a.shape == (3, 100, 7)
    np.testing.assert_allclose(r.cost, peg.cost(r.s, r.a))
    np.testing.assert_allclose(r.y, np.exp(-peg.y_scale * r.cost))
    np.testing.assert_allclose(peg.true_cost(r), peg.cost(r.x, r.a))
    assert not np.allclose(peg.true_cost(r), r.cost)
    np.testing.assert_allclose(r.x[:, 0], np.broadcast_to(peg.x0, (3, 26)))


def test_rollouts_actions_follow_policy_on_measured_state(peg):
    rng = np.random.default_rng(5)
    T, m, n = peg.T, peg.m, peg.n
    pol = LinearGaussianPolicy(0.01 * rng.normal(size=(T, m, n)), rng.normal(size=(T, m)), np.broadcast_to(0.3 * np.eye(m), (T, m, m)))
    r = peg.rollouts(pol, 2, np.random.default_rng(6))
    # re-draw the same noise: eps first, then w
    g = np.random.default_rng(6)
    g.standard_normal((2, T + 1, n))
    w = g.standard_normal((2, T, m))
    expected = np.einsum("tij,mtj->mti", pol.K, r.s[:, :T]) + pol.k + np.einsum("tij,mtj->mti", pol.chol, w)
    np.testing.assert_allclose(r.a, expected, atol=1e-12)


def test_rollouts_are_reproducible_and_independent_of_workers(peg):
    pol = peg.initial_policy()
    r1 = peg.rollouts(pol, 5, np.random.default_rng(42))
    r2 = peg.rollouts(pol, 5, np.random.default_rng(42))
    r3 = peg.rollouts(pol, 5, np.random.default_rng(43))
    r4 = peg.rollouts(pol, 5, np.random.default_rng(42), workers=2)
    for f in ("x", "s", "a", "cost", "y"):
        np.testing.assert_array_equal(getattr(r1, f), getattr(r2, f))
        np.testing.assert_array_equal(getattr(r1, f), getattr(r4, f))
    assert np.abs(r1.x - r3.x).max() > 1e-3


def test_measurement_noise_has_variance_rho2(peg):
    r = peg.rollouts(peg.initial_policy(), 4, np.random.default_rng(7))
    eps = (r.s - r.x).ravel()
    N = eps.size
    se_var = peg.rho2 * np.sqrt(2.0 / (N - 1))
    assert abs(eps.var(ddof=1) - peg.rho2) < 5 * se_var
    assert abs(eps.mean()) < 5 * np.sqrt(peg.rho2 / N)
    r0 = peg.rollouts(peg.initial_policy(), 2, np.random.default_rng(7), noise=False)
    np.testing.assert_array_equal(r0.s, r0.x)


def test_metrics_door_and_peg(peg, door):
    r = door.rollouts(door.initial_policy(), 3, np.random.default_rng(0))
    met = door.metrics(r)
    ps = door.per_sample_metrics(r)
    np.testing.assert_allclose(ps["min_hinge"], r.x[:, :, 24].min(axis=1))
    assert met["min_hinge"] == pytest.approx(ps["min_hinge"].mean()) and met["min_hinge"] <= 0.0
    r = peg.rollouts(peg.initial_policy(), 3, np.random.default_rng(0))
    d = np.linalg.norm(r.x[:, :, 17:20] - [0, 0.3, -0.5], axis=-1).min(axis=1)
    met = peg.metrics(r)
    assert met["min_distance"] == pytest.approx(d.mean())
    assert met["success_rate"] == pytest.approx(np.mean(d < 0.10))
    assert met["failure_rate"] == pytest.approx(np.mean(d > 0.15))


def test_cost_expansion_matches_task_cost(peg):
    r = peg.rollouts(peg.initial_policy(), 1, np.random.default_rng(0))
    q = peg.cost_expansion(r.s[0], r.a[0])
    assert isinstance(q, QuadraticCost) and q.C.shape == (100, 33, 33)
    np.testing.assert_allclose(q(r.s[0], r.a[0]), peg.cost(r.s[0], r.a[0]), rtol=1e-9)


# ----------------------------------------------------------------- linear2d


def test_linear2d_matches_continuous_point_mass(lin):
    cfg = lin.config.linear
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=6), rng.normal(size=2)

    def f(t, z):
        v, F = z[2:4], z[4:]
        return np.r_[v, F / cfg.mass, (u - F) / cfg.tau]

    sol = scipy.integrate.solve_ivp(f, (0, lin.dt), x, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(lin.step(x, u), sol.y[:, -1], atol=1e-8)
    dyn = lin.linearize()
    assert isinstance(dyn, LinearGaussianDynamics) and dyn.T == lin.T
    np.testing.assert_allclose(dyn.A[3] @ x + dyn.B[3] @ u + dyn.c[3], lin.step(x, u))


def test_linear2d_spec_cost(lin):
    r = lin.rollouts(lin.initial_policy(), 2, np.random.default_rng(0), noise=False)
    np.testing.assert_allclose(r.x, 0.0)
    np.testing.assert_allclose(r.cost, 20.0**2 + 3.0**2)
    r = lin.rollouts(lin.initial_policy(), 2, np.random.default_rng(0))
    e = r.s[:, :-1] - [20, 3, 0, 0, 0, 0]
    np.testing.assert_allclose(r.cost, (e**2).sum(-1) + 1e-5 * (r.a**2).sum(-1))


# ----------------------------------------------------------------- custom model


TWO_LINK = """
<mujoco model="two_link_test">
  <option timestep="0.005" gravity="0 0 0"/>
  <worldbody>
    <body name="l1">
      <joint name="j1" type="hinge" axis="0 0 1" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.03" mass="1"/>
      <body name="l2" pos="0.5 0 0">
        <joint name="j2" type="hinge" axis="0 0 1" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="0.5"/>
        <site name="tip" pos="0.4 0 0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="m1" joint="j1"/>
    <motor name="m2" joint="j2"/>
  </actuator>
</mujoco>
"""


def _two_link_config(**over):
    cfg = {
        "name": "two_link",
        "T": 30,
        "substeps": 4,
        "q0": [0.3, 0.5],
        "state": {"joints": ["j1", "j2"], "sites": ["tip"]},
        "actuated": ["j1", "j2"],
        "rho2": 0.01,
        "init_var": 0.1,
        "cost": [
            {"type": "point", "sites": ["tip"], "target": [0.2, 0.6, 0.0], "l1": 0.1, "l2": 1.0, "ramp": "quadratic"},
            {"type": "torque", "wu": [1e-2, 1e-2]},
            {"type": "state", "labels": ["qd:j1", "qd:j2"], "weights": 0.1},
        ],
        "metric": {"type": "min_distance", "site": "tip", "target": [0.2, 0.6, 0.0], "success": 0.05},
    }
    cfg.update(over)
    return cfg


def test_custom_mjcf_string_task_end_to_end():
    t = build_task(_two_link_config(), xml=TWO_LINK)
    assert (t.n, t.m, t.T) == (2 + 2 + 3 + 3, 2, 30) and t.dt == pytest.approx(0.02)
    r = t.rollouts(t.initial_policy(), 6, np.random.default_rng(0), workers=2)
    met = t.metrics(r)
    assert set(met) >= {"min_distance", "success_rate", "cost"}
    q = t.cost_expansion(r.s[0], r.a[0])
    np.testing.assert_allclose(q(r.s[0], r.a[0]), t.cost(r.s[0], r.a[0]), rtol=1e-9)
    dyn = t.linearize(r.x[0], r.a[0])
    assert dyn.A.shape == (30, 10, 10)
    # the tip is 0.9 m from the origin at the start configuration (q0 = (0.3, 0.5))
    tip = t.ee_points(t.x0)[0]
    np.testing.assert_allclose(tip[:2], [0.5 * np.cos(0.3) + 0.4 * np.cos(0.8), 0.5 * np.sin(0.3) + 0.4 * np.sin(0.8)])


def test_task_toml_with_relative_model_path(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "arm.xml").write_text(TWO_LINK)
    lines = [
        'name = "two_link_file"', "T = 10", 'model = "models/arm.xml"', "q0 = [0.1, 0.2]",
        "[state]", 'joints = ["j1", "j2"]', 'sites = ["tip"]',
        "[[cost]]", 'type = "torque"', "wu = 0.1",
    ]
    (tmp_path / "task.toml").write_text("\n".join(lines))
    t = load_task(tmp_path / "task.toml")
    assert t.n == 10 and t.m == 2 and t.actuated == ["m1", "m2"]


def test_pkg_model_reads_an_mjcf_file_shipped_in_an_installed_package(tmp_path):
    """``model = "pkg:<package>/<path>"``: the MJCF file inside an installed package (here
    Gymnasium's raw reacher.xml, not its environment), hashed into the provenance like any file."""
    pytest.importorskip("gymnasium")
    t = load_task(problems_dir() / "reacher" / "reacher_mjcf.toml")
    assert (t.n, t.m, t.kind) == (10, 2, "mujoco")
    import hashlib

    import gymnasium

    shipped = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets", "reacher.xml")
    with open(shipped, "rb") as f:
        assert t.provenance["model_files"]["reacher.xml"] == hashlib.sha256(f.read()).hexdigest()


def test_pkg_model_outside_its_package_or_missing_is_refused_naming_it(tmp_path):
    pytest.importorskip("gymnasium")
    with pytest.raises(ConfigError, match="leaves the package directory"):
        build_task(_two_link_config(model="pkg:gymnasium/../numpy/__init__.py"))
    with pytest.raises(ConfigError, match="'no_such_package_xyz' is not an installed package"):
        build_task(_two_link_config(model="pkg:no_such_package_xyz/model.xml"))
    with pytest.raises(ConfigError, match="has no file 'envs/mujoco/assets/nothing.xml'"):
        build_task(_two_link_config(model="pkg:gymnasium/envs/mujoco/assets/nothing.xml"))
    with pytest.raises(ConfigError, match="expected pkg:<package>/<path"):
        build_task(_two_link_config(model="pkg:gymnasium"))


def test_cost_window_is_read_from_the_task_and_checked():
    t = build_task(_two_link_config(cost=[{"type": "torque", "wu": 1.0, "window": [0.5, 1.0]}]), xml=TWO_LINK)
    (term,) = t.cost_terms.terms
    assert term.window == (0.5, 1.0)
    with pytest.raises(ConfigError, match="window must be two fractions"):
        build_task(_two_link_config(cost=[{"type": "torque", "window": [0.7, 0.2]}]), xml=TWO_LINK)


# ----------------------------------------------------------------- config errors


def test_config_errors_name_the_problem(tmp_path):
    with pytest.raises(ConfigError, match="unknown config key 'horizon'"):
        build_task(_two_link_config(horizon=3), xml=TWO_LINK)
    bad_cost = _two_link_config(cost=[{"type": "torque", "wu": 1.0, "wp": 2.0}])
    with pytest.raises(ConfigError, match=r"'wp' in \[cost\[0\]\]"):
        build_task(bad_cost, xml=TWO_LINK)
    with pytest.raises(ConfigError, match="T: expected an integer"):
        build_task(_two_link_config(T="30"), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="state.joints: expected a list"):
        build_task(_two_link_config(state={"joints": "j1"}), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="cost\\[0\\].type: 'pointy'"):
        build_task(_two_link_config(cost=[{"type": "pointy"}]), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="ramp: 'cubic' is not one of"):
        build_task(_two_link_config(cost=[{"type": "torque", "ramp": "cubic"}]), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="no_such_model.xml"):
        build_task(_two_link_config(model="no_such_model.xml"), base_dir=tmp_path)
    with pytest.raises(ConfigError, match="site 'fingertip' not found"):
        build_task(_two_link_config(state={"joints": ["j1", "j2"], "sites": ["fingertip"]}), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="joint 'elbow' not found"):
        build_task(_two_link_config(state={"joints": ["j1", "elbow"], "sites": ["tip"]}), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="no joint or actuator named 'j3'"):
        build_task(_two_link_config(actuated=["j1", "j3"]), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="site 'elbow_site' is not in the state"):
        build_task(_two_link_config(cost=[{"type": "point", "sites": ["elbow_site"], "target": [0, 0, 0]}]), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="q0: expected 2 numbers"):
        build_task(_two_link_config(q0=[0.1]), xml=TWO_LINK)
    with pytest.raises(ConfigError, match="task 'bogus': not a built-in task"):
        load_task("bogus")


def test_missing_model_file_is_reported_before_simulation(tmp_path):
    (tmp_path / "t.toml").write_text('name = "x"\nT = 5\nmodel = "missing.xml"\n')
    with pytest.raises(ConfigError, match="missing.xml.*does not exist"):
        load_task(tmp_path / "t.toml")


def test_config_roundtrip_and_parsed_cost_terms():
    cfg = TaskConfig.from_dict(_two_link_config())
    assert [type(c).__name__ for c in cfg.cost] == ["PointTermConfig", "TorqueTermConfig", "StateTermConfig"]
    again = TaskConfig.from_dict(cfg.to_dict())
    assert again == cfg


# ----------------------------------------------------------------- divergence


def test_divergence_raises_simulation_error_naming_sample_and_step():
    t = build_task(_two_link_config(rho2=0.0), xml=TWO_LINK)
    T, m, n = t.T, t.m, t.n
    K = np.zeros((T, m, n))
    K[:, 0, 2] = K[:, 1, 3] = 1e6  # absurd positive velocity feedback
    pol = LinearGaussianPolicy(K, np.zeros((T, m)), np.broadcast_to(1e-2 * np.eye(m), (T, m, m)))
    for workers in (1, 2):
        with pytest.raises(SimulationError, match=r"sample 0 diverged at control step \d+"):
            t.rollouts(pol, 3, np.random.default_rng(0), workers=workers)


def test_a_filtered_policy_that_diverges_names_the_sample_and_step_of_one_at_a_time():
    """A filtered policy's samples run in lockstep; on a divergence they are simulated again one at a
    time, so the error is the one the first diverging sample in order raises (for any ``workers``)."""
    from soc_opt.noise.estimator import FilteredPolicy, kalman_filter

    t = build_task(_two_link_config(rho2=0.01), xml=TWO_LINK)
    T, m, n = t.T, t.m, t.n
    K = np.zeros((T, m, n))
    K[:, 0, 2] = K[:, 1, 3] = 1e6
    pol = LinearGaussianPolicy(K, np.zeros((T, m)), np.broadcast_to(1e-2 * np.eye(m), (T, m, m)))
    dyn = LinearGaussianDynamics(np.broadcast_to(np.eye(n), (T, n, n)), np.zeros((T, n, m)), np.zeros((T, n)),
                                 np.broadcast_to(0.1 * np.eye(n), (T, n, n)))
    fpol = FilteredPolicy(pol, kalman_filter(dyn, 0.01 * np.eye(n), t.x0, 0.01 * np.eye(n)))
    for workers in (1, 2):
        with pytest.raises(SimulationError, match=r"sample 0 diverged at control step \d+"):
            t.rollouts(fpol, 3, np.random.default_rng(0), workers=workers)


# ----------------------------------------------------------------- linearisation


def _fd_step(task, x, u, h=1e-6):
    A = np.zeros((task.n, task.n))
    B = np.zeros((task.n, task.m))
    joint_cols = np.r_[task.state_qpos_idx, task.state_qvel_idx]
    for i in joint_cols:
        e = np.zeros(task.n)
        e[i] = h
        A[:, i] = (task.step(x + e, u) - task.step(x - e, u)) / (2 * h)
    for j in range(task.m):
        e = np.zeros(task.m)
        e[j] = h
        B[:, j] = (task.step(x, u + e) - task.step(x, u - e)) / (2 * h)
    return A, B


@pytest.mark.parametrize("name", ["peg", "door"])
def test_linearize_matches_finite_differences_of_step(name):
    task = load_task(name, overrides={"T": 2})
    rng = np.random.default_rng(3)
    x = task.x0.copy()
    x[task.state_qpos_idx] += 0.05 * rng.normal(size=len(task.state_qpos_idx))
    x[task.state_qvel_idx] += 0.3 * rng.normal(size=len(task.state_qvel_idx))
    x = task.step(x, np.zeros(task.m))  # consistent site components
    u = rng.normal(size=task.m)
    X = np.stack([x, x, x])
    U = np.stack([u, u])
    dyn = task.linearize(X, U)
    A_fd, B_fd = _fd_step(task, x, u)
    np.testing.assert_allclose(dyn.A[0], A_fd, atol=1e-5 * np.abs(A_fd).max())
    np.testing.assert_allclose(dyn.B[0], B_fd, atol=1e-5 * np.abs(B_fd).max())
    np.testing.assert_allclose(dyn.A[0] @ x + dyn.B[0] @ u + dyn.c[0], task.step(x, u), atol=1e-10)
    # site components of the state carry no information of their own
    site_cols = np.setdiff1d(np.arange(task.n), np.r_[task.state_qpos_idx, task.state_qvel_idx])
    assert np.all(dyn.A[0][:, site_cols] == 0)


# ----------------------------------------------------------------- rendering


def test_render_fallback_writes_a_picture(tmp_path, peg, lin):
    r = peg.rollouts(peg.initial_policy(), 2, np.random.default_rng(0))
    res = render_filmstrip(peg, r, tmp_path / "peg.png", frames=3, backends=())
    assert res.backend == "matplotlib" and "unavailable" in res.message
    assert (tmp_path / "peg.png").read_bytes()[:4] == b"\x89PNG"
    res = render_filmstrip(lin, lin.simulate(lin.initial_policy()), tmp_path / "lin.png")
    assert res.backend == "matplotlib" and os.path.getsize(tmp_path / "lin.png") > 0


@pytest.mark.slow
def test_render_filmstrip_offscreen(tmp_path, peg):
    r = peg.simulate(peg.initial_policy())
    res = render_filmstrip(peg, r, tmp_path / "strip.png", frames=4, width=160, height=120)
    assert (tmp_path / "strip.png").read_bytes()[:4] == b"\x89PNG"
    if res.backend != "matplotlib":
        from PIL import Image

        assert Image.open(tmp_path / "strip.png").size == (4 * 160, 120)


# ----------------------------------------------------------------- bring-your-own MJCF (issue 13)


def _random_joint_state(task, seed=3):
    rng = np.random.default_rng(seed)
    x = task.x0.copy()
    x[task.state_qpos_idx] += 0.05 * rng.normal(size=len(task.state_qpos_idx))
    x[task.state_qvel_idx] += 0.3 * rng.normal(size=len(task.state_qvel_idx))
    return task.step(x, np.zeros(task.m)), rng.normal(size=task.m)


@pytest.mark.parametrize("substeps", [1, 3])
def test_rk4_model_linearises_by_finite_differences_of_the_whole_step(substeps):
    """mjd_transitionFD rejects RK4; the linearisation then differences whole steps instead."""
    xml = TWO_LINK.replace('gravity="0 0 0"', 'gravity="0 0 0" integrator="RK4"')
    task = build_task(_two_link_config(T=2, substeps=substeps), xml=xml)
    assert int(task.model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4)
    x, u = _random_joint_state(task)
    dyn = task.linearize(np.stack([x, x, x]), np.stack([u, u]))
    A_fd, B_fd = _fd_step(task, x, u)
    np.testing.assert_allclose(dyn.A[0], A_fd, atol=1e-5 * np.abs(A_fd).max())
    np.testing.assert_allclose(dyn.B[0], B_fd, atol=1e-5 * np.abs(B_fd).max())
    np.testing.assert_allclose(dyn.A[0] @ x + dyn.B[0] @ u + dyn.c[0], task.step(x, u), atol=1e-10)


def test_whole_step_differences_agree_with_mjd_transition_fd():
    """Where both apply (Euler), the RK4 fallback computes what MuJoCo's own derivative does."""
    from soc_opt.tasks.linearize import step_derivatives

    m = mujoco.MjModel.from_xml_string(TWO_LINK)
    d = mujoco.MjData(m)
    d.qpos[:] = [0.3, -0.4]
    d.qvel[:] = [0.5, 1.0]
    d.ctrl[:] = [0.2, -0.1]
    mujoco.mj_forward(m, d)
    A_ref, B_ref = np.zeros((4, 4)), np.zeros((4, 2))
    mujoco.mjd_transitionFD(m, d, 1e-6, True, A_ref, B_ref, None, None)
    A, B = np.zeros((4, 4)), np.zeros((4, 2))
    qpos = d.qpos.copy()
    step_derivatives(m, d, 1e-6, A, B)
    np.testing.assert_array_equal(d.qpos, qpos)  # d is left as it was
    np.testing.assert_allclose(A, A_ref, atol=1e-6)
    np.testing.assert_allclose(B, B_ref, atol=1e-6)


def test_ilqg_lowers_the_cost_on_an_rk4_model():
    from soc_opt.methods.ilqg import ILQGConfig, ilqg

    xml = TWO_LINK.replace('gravity="0 0 0"', 'gravity="0 0 0" integrator="RK4"')
    task = build_task(_two_link_config(T=15, substeps=2), xml=xml)
    _, costs = ilqg(task, cfg=ILQGConfig(iterations=2))
    assert len(costs) >= 2 and all(b < a for a, b in zip(costs, costs[1:]))


THREE_LINK = TWO_LINK.replace(
    '<site name="tip" pos="0.4 0 0"/>',
    '<body name="l3" pos="0.4 0 0"><joint name="wrist" type="hinge" axis="0 0 1" damping="0.1"/>'
    '<geom type="capsule" fromto="0 0 0 0.1 0 0" size="0.02" mass="0.1"/></body>'
    '<site name="tip" pos="0.4 0 0"/>',
)


def test_linearising_a_state_without_every_joint_names_them_and_the_fix():
    task = build_task(_two_link_config(T=3), xml=THREE_LINK)  # 'wrist' is not in the state
    x = np.stack([task.x0] * 4)
    with pytest.raises(ConfigError, match=r"joints not in it: 'wrist'.*state\.extra_joints"):
        task.linearize(x, np.zeros((3, task.m)))
    fixed = build_task(_two_link_config(T=3, q0=[0.3, 0.5, 0.0], state={"joints": ["j1", "j2"], "sites": ["tip"],
                                                                         "extra_joints": ["wrist"]}), xml=THREE_LINK)
    assert fixed.linearize(np.stack([fixed.x0] * 4), np.zeros((3, fixed.m))).A.shape == (3, fixed.n, fixed.n)


def test_a_free_joint_outside_the_state_is_named_as_unsupported():
    xml = TWO_LINK.replace("</worldbody>", '<body name="ball" pos="2 0 0"><freejoint name="float"/>'
                           '<geom type="sphere" size="0.05"/></body></worldbody>')
    task = build_task(_two_link_config(T=3), xml=xml)
    with pytest.raises(ConfigError, match=r"'float'.*free/ball joint"):
        task.check_linearizable()


BODY_POINT = TWO_LINK.replace('<site name="tip" pos="0.4 0 0"/>',
                              '<site name="tip" pos="0.4 0 0"/><site name="l2_origin" pos="0 0 0"/>')


def test_a_body_is_a_task_point_at_its_origin():
    """A body name in state.sites and the cost/metric reads the body frame's origin: the same
    numbers as a site placed at that origin."""
    def config(point):
        return _two_link_config(
            T=8, state={"joints": ["j1", "j2"], "sites": [point]},
            cost=[{"type": "point", "sites": [point], "target": [0.2, 0.6, 0.0]}, {"type": "torque", "wu": 0.01}],
            metric={"type": "min_distance", "site": point, "target": [0.2, 0.6, 0.0]})

    body = build_task(config("l2"), xml=BODY_POINT)
    site = build_task(config("l2_origin"), xml=BODY_POINT)
    pol = body.initial_policy()
    rb = body.rollouts(pol, 3, np.random.default_rng(1))
    rs = site.rollouts(pol, 3, np.random.default_rng(1))
    np.testing.assert_allclose(rb.x, rs.x, atol=1e-12)
    assert body.metrics(rb) == pytest.approx(site.metrics(rs), rel=1e-12)
    x, u = _random_joint_state(body)
    np.testing.assert_allclose(body.linearize(np.stack([x] * 9), np.stack([u] * 8)).A,
                               site.linearize(np.stack([x] * 9), np.stack([u] * 8)).A, atol=1e-9)


def _geom_spheres_in_view(model, Q, spec):
    """Whether every geom of a moving body, in every configuration, is inside the camera's view cone."""
    az, el = np.deg2rad(spec["azimuth"]), np.deg2rad(spec["elevation"])
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    cam = np.asarray(spec["lookat"]) - spec["distance"] * forward
    half = np.deg2rad(model.vis.global_.fovy) / 2
    d = mujoco.MjData(model)
    for q in Q:
        d.qpos[:] = q
        mujoco.mj_kinematics(model, d)
        for g in range(model.ngeom):
            if model.geom_bodyid[g] == 0:
                continue
            v = d.geom_xpos[g] - cam
            dist = np.linalg.norm(v)
            angle = np.arccos(np.clip(v @ forward / dist, -1, 1)) + np.arcsin(min(1.0, model.geom_rbound[g] / dist))
            if angle > half:
                return False
    return True


def test_filmstrip_without_a_named_camera_frames_the_whole_robot(tmp_path, monkeypatch):
    """A long arm whose point is at its tip: the free camera must still see every link."""
    import json
    import subprocess

    from soc_opt.tasks import render as render_mod

    xml = TWO_LINK.replace('fromto="0 0 0 0.5 0 0"', 'fromto="0 0 0 2.5 0 0"').replace('body name="l2" pos="0.5 0 0"',
                                                                                         'body name="l2" pos="2.5 0 0"')
    task = build_task(_two_link_config(T=6), xml=xml)
    seen = []

    def fake_run(argv, **kw):  # capture the camera the worker would use; report a failed backend
        seen.append(json.loads(open(os.path.join(argv[-1], "spec.json")).read()))
        seen.append(np.load(os.path.join(argv[-1], "qpos.npy")))
        return subprocess.CompletedProcess(argv, 1, "", "no GL here")

    monkeypatch.setattr(render_mod.subprocess, "run", fake_run)
    r = task.rollouts(task.initial_policy(), 1, np.random.default_rng(0))
    render_filmstrip(task, r, tmp_path / "strip.png", frames=4, backends=("egl",))
    spec, Q = seen
    assert spec["camera"] is None
    assert _geom_spheres_in_view(task.model, Q, spec)


def _peg_with_term(tmp_path, term: str):
    from soc_opt.tasks import load_task

    text = (problems_dir() / "peg" / "peg.toml").read_text().replace(
        'model = "arm7_peg.xml"', f'model = "{(problems_dir() / "peg" / "arm7_peg.xml").as_posix()}"')
    path = tmp_path / "peg_offset.toml"
    path.write_text(text + "\n[[cost]]\ntype = \"point\"\nsites = [\"peg_top\"]\n" + term + "\n")
    return load_task(path)


def test_a_point_cost_to_another_point_plus_an_offset_charges_the_distance_to_the_shifted_point(tmp_path):
    task = _peg_with_term(tmp_path, 'target_sites = ["peg_bottom"]\ntarget_offset = [0.0, 0.1, 0.3]\nl2 = 2.0\nl1 = 0.0')
    base = _peg_with_term(tmp_path, 'target_sites = ["peg_bottom"]\ntarget_offset = [0.0, 0.0, 0.0]\nl2 = 0.0\nl1 = 0.0')
    rng = np.random.default_rng(0)
    s = task.x0 + 0.05 * rng.normal(size=(task.T + 1, task.n))
    a = rng.normal(size=(task.T, task.m))
    top, bottom = (s[:task.T, task.layout["site_pos"]].reshape(task.T, 2, 3)[:, i] for i in (0, 1))
    expected = ((top - bottom - [0.0, 0.1, 0.3]) ** 2).sum(-1)  # 1/2 l2 d^2 with l2 = 2
    np.testing.assert_allclose(task.cost(s[None], a[None])[0] - base.cost(s[None], a[None])[0], expected, rtol=1e-10,
                               atol=1e-12)


@pytest.mark.parametrize("term, says", [
    ('target = [0.0, 0.3, -0.2]\ntarget_offset = [0.0, 0.0, 0.1]', "target_offset: only with 'target_sites'"),
    ('target_sites = ["peg_bottom"]\ntarget_offset = [0.0, 0.1]', "target_offset: expected 3 numbers"),
])
def test_a_misplaced_or_misshaped_target_offset_is_refused_naming_it(tmp_path, term, says):
    from soc_opt.config import ConfigError

    with pytest.raises(ConfigError, match=says):
        _peg_with_term(tmp_path, term)


def test_push_task_puck_rests_until_the_cage_touches_it_and_its_back_wall_pushes_it_forward():
    """problems/push: n = 36, m = 7; with zero torque the puck does not move (it slides on damped joints,
    not on the table); placed against the inside of the cage's back wall it is pushed out along the
    cage's opening (the tool's local +x), between the side walls."""
    task = load_task(problems_dir() / "push" / "push.toml")
    assert (task.n, task.m) == (36, 7)
    ro = task.rollouts(LinearGaussianPolicy(np.zeros((task.T, task.m, task.n)), np.zeros((task.T, task.m)),
                                            np.broadcast_to(1e-12 * np.eye(task.m), (task.T, task.m, task.m))),
                       1, np.random.default_rng(0))
    puck = [task.state_labels.index(f"puck_centre.{c}") for c in "xy"]
    np.testing.assert_allclose(ro.x[0, :, puck].T, np.broadcast_to(ro.x[0, 0, puck], (task.T + 1, 2)), atol=1e-9)

    m = mujoco.MjModel.from_xml_path(str(problems_dir() / "push" / "arm7_push.xml"))
    d = mujoco.MjData(m)
    d.qpos[:7] = task.config.q0[:7]
    mujoco.mj_forward(m, d)
    cage, rear = d.site("cage").xpos.copy(), d.site("cage_rear").xpos.copy()
    ahead = (cage - rear)[:2] / np.linalg.norm((cage - rear)[:2])       # the opening's direction
    start = rear[:2] + 0.025 * ahead                                    # 1 cm into the back wall
    d.qpos[7:9] = start - np.array([0.1, 0.25])                         # the puck body's slides
    m.body("puck").pos[2] = cage[2]                                     # at the cage's height
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
    arm = d.qpos[:7].copy()
    for _ in range(50):
        d.qpos[:7], d.qvel[:7] = arm, 0.0                               # the tool held still
        mujoco.mj_step(m, d)
    moved = d.site("puck_centre").xpos[:2] - start
    assert moved @ ahead > 0.008                                        # pushed out of the back wall
    assert abs(moved @ np.array([-ahead[1], ahead[0]])) < 0.5 * (moved @ ahead)


def test_push_task_cage_can_follow_the_straight_push_at_puck_height_with_its_heading():
    """Reachability of problems/push: within the joint limits, inverse kinematics puts the cage centre
    at puck height on every point of the straight line from the puck's start to the goal, with the
    tool's tail 0.25 m behind it on that line (the heading of the push)."""
    m = mujoco.MjModel.from_xml_path(str(problems_dir() / "push" / "arm7_push.xml"))
    d = mujoco.MjData(m)
    start, goal = np.array([0.10, 0.25]), np.array([0.05, 0.58])
    u = (goal - start) / np.linalg.norm(goal - start)
    lo, hi = m.jnt_range[:7, 0].copy(), m.jnt_range[:7, 1].copy()
    free = ~m.jnt_limited[:7].astype(bool)
    lo[free], hi[free] = -np.pi, np.pi
    q = np.clip(np.array([-0.13, -0.05, -1.55, -1.86, 1.70, -0.05, 0.16]), lo, hi)

    def residual(q, cage, tail):
        d.qpos[:7] = q
        mujoco.mj_kinematics(m, d)
        return np.r_[d.site("cage").xpos - cage, d.site("tool_tail").xpos - tail]

    for lam in np.linspace(0.0, 1.0, 6):
        p = start + lam * (goal - start)
        cage, tail = np.r_[p, -0.38], np.r_[p - 0.25 * u, -0.38]
        q = least_squares(residual, q, args=(cage, tail), bounds=(lo, hi), xtol=1e-12, ftol=1e-12).x
        assert np.abs(residual(q, cage, tail)).max() < 2e-3, lam


def test_a_pkg_model_of_a_dotted_package_is_found_without_importing_any_package(tmp_path, monkeypatch):
    """``pkg:a.b/<file>`` names the folder ``b`` of the package ``a``; neither ``a/__init__.py`` nor
    ``a/b/__init__.py`` runs (issue 48 item 4)."""
    import sys

    marker = tmp_path / "imported"
    pkg = tmp_path / "mods" / "plantedpkg48"
    (pkg / "sub").mkdir(parents=True)
    for init in (pkg / "__init__.py", pkg / "sub" / "__init__.py"):
        init.write_text(f"open({str(marker)!r}, 'a').write('code ran')\n")
    (pkg / "sub" / "arm.xml").write_text(TWO_LINK)
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    try:
        t = build_task(_two_link_config(model="pkg:plantedpkg48.sub/arm.xml"))
        assert t.n == 10 and not marker.exists() and "plantedpkg48" not in sys.modules
        with pytest.raises(ConfigError, match="has no folder 'nothing'"):
            build_task(_two_link_config(model="pkg:plantedpkg48.nothing/arm.xml"))
        with pytest.raises(ConfigError, match="is not a package name"):
            build_task(_two_link_config(model="pkg:plantedpkg48..sub/arm.xml"))
        assert not marker.exists()
    finally:
        sys.modules.pop("plantedpkg48", None)
        sys.modules.pop("plantedpkg48.sub", None)
