"""Tests for soc_opt/noise/kinematic/model.py: h reproduces the task's state, its Jacobian matches
finite differences, and the kinematic rows match MuJoCo's semi-implicit Euler (docs/math.md §11.1)."""

import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from soc_opt.config import ConfigError
from soc_opt.models import ShapeError
from soc_opt.noise.kinematic.model import AccelMap, KinematicModel, transition
from soc_opt.tasks import load_task


@pytest.fixture(scope="module", params=["peg", "door"])
def task_km(request):
    task = load_task(request.param)
    return task, KinematicModel(task)


@pytest.fixture(scope="module")
def rollouts_of(task_km):
    task, km = task_km
    return task.rollouts(task.initial_policy(1.0), 3, np.random.default_rng(0))


def test_h_reproduces_the_task_state(task_km, rollouts_of):
    task, km = task_km
    x = rollouts_of.x
    np.testing.assert_allclose(km.measure(km.z_of(x), jacobian=False), x, rtol=0, atol=1e-12)
    hx, _ = km.measure(km.z_of(x))
    np.testing.assert_allclose(hx, x, rtol=0, atol=1e-12)


def test_jacobian_matches_central_differences(task_km, rollouts_of):
    task, km = task_km
    eps = 1e-6
    for z in km.z_of(rollouts_of.x[0, ::25]):
        _, H = km.measure(z)
        E = eps * np.eye(km.nz)
        fd = np.stack([(km.measure(z + e, False) - km.measure(z - e, False)) / (2 * eps) for e in E], axis=-1)
        np.testing.assert_allclose(H, fd, rtol=0, atol=1e-7 * max(1.0, np.abs(H).max()))


def test_joint_rows_of_the_jacobian_are_selections(task_km, rollouts_of):
    task, km = task_km
    _, H = km.measure(km.z_of(rollouts_of.x[0, 10]))
    np.testing.assert_array_equal(H[km.zidx], np.eye(km.nz))


def test_batched_measure_keeps_leading_axes(task_km, rollouts_of):
    task, km = task_km
    z = km.z_of(rollouts_of.x)
    hx, H = km.measure(z)
    assert hx.shape == rollouts_of.x.shape and H.shape == rollouts_of.x.shape + (km.nz,)


def test_bad_latent_shape_names_the_shape(task_km):
    _, km = task_km
    with pytest.raises(ShapeError, match=r"\(\.\.\., 14\)"):
        km.measure(np.zeros((3, 5)))
    with pytest.raises(ShapeError, match="task states"):
        km.z_of(np.zeros(3))


def test_non_mujoco_task_is_rejected_by_name():
    with pytest.raises(ConfigError, match="task 'linear2d' is of kind 'linear'"):
        KinematicModel(load_task("linear2d"))


SLIDER = Path(__file__).parent / "data" / "slider" / "slider.toml"


def test_gym_mujoco_task_is_modelled_and_h_reproduces_its_state():
    """A gym: task is a MuJoCo task (its model and data are MuJoCo's): the model accepts it, and h of
    the joint coordinates read off a rollout rebuilds the rollout's states."""
    task = load_task("gym:Reacher-v5", overrides={"T": 10})
    km = KinematicModel(task)
    ro = task.rollouts(task.initial_policy(1.0), 2, np.random.default_rng(0))
    np.testing.assert_allclose(km.measure(km.z_of(ro.x), jacobian=False), ro.x, atol=1e-12)


def test_a_joint_moving_a_point_outside_the_state_is_refused_naming_both():
    """Without its slide joints in the state the puck's point would be rebuilt at its initial place."""
    task = load_task(SLIDER, overrides={"state": {"joints": ["shoulder", "elbow"], "sites": ["tip", "puck_c"]},
                                        "q0": [0.3, 0.6]})
    with pytest.raises(ConfigError, match=r"""joint 'puck_x' moves the site 'puck_c'.*extra_joints = \["puck_x", "puck_y"\]"""):
        KinematicModel(task)


def test_joints_that_move_no_point_of_the_state_may_stay_out_of_it():
    task = load_task(SLIDER, overrides={"state": {"joints": ["shoulder", "elbow"], "sites": ["tip"]}, "q0": [0.3, 0.6],
                                        "cost": [{"type": "torque", "wu": 1e-3}]})
    km = KinematicModel(task)
    ro = task.rollouts(task.initial_policy(1.0), 2, np.random.default_rng(0))
    np.testing.assert_allclose(km.measure(km.z_of(ro.x), jacobian=False), ro.x, atol=1e-12)


def test_model_pickles_and_measures_the_same(task_km, rollouts_of):
    _, km = task_km
    km2 = pickle.loads(pickle.dumps(km))
    z = km.z_of(rollouts_of.x[1])
    np.testing.assert_array_equal(km2.measure(z, False), km.measure(z, False))


@settings(max_examples=30, deadline=None)
@given(N=st.integers(1, 8), seed=st.integers(0, 2 ** 31 - 1))
def test_kinematic_rows_match_semi_implicit_euler_substeps(N, seed):
    """q, qd after N semi-implicit Euler substeps of constant acceleration u equal the transition."""
    rng = np.random.default_rng(seed)
    nq, m, h = 3, 2, 0.01
    z, u = rng.standard_normal(2 * nq), rng.standard_normal(nq)
    q, qd = z[:nq].copy(), z[nq:].copy()
    for _ in range(N):
        qd = qd + h * u
        q = q + h * qd
    acc = AccelMap(np.zeros((1, nq, m)), np.zeros((1, nq, 2 * nq)), u[None], np.broadcast_to(np.eye(nq), (1, nq, nq)))
    A, Bz, cz, Q = transition(acc, N * h, (N + 1) / (2 * N), 0.0)
    np.testing.assert_allclose(A[0] @ z + cz[0], np.r_[q, qd], rtol=1e-12, atol=1e-12)


def test_transition_noise_is_the_acceleration_noise_through_the_kinematics():
    rng = np.random.default_rng(1)
    nq, m, dt, c2, qv = 2, 1, 0.05, 0.6, 1e-4
    L = rng.standard_normal((nq, nq))
    S = L @ L.T + np.eye(nq)
    D = rng.standard_normal((1, nq, 2 * nq))
    B = rng.standard_normal((1, nq, m))
    acc = AccelMap(B, D, np.zeros((1, nq)), S[None])
    A, Bz, cz, Q = transition(acc, dt, c2, qv)
    Gm = np.r_[c2 * dt ** 2 * np.eye(nq), dt * np.eye(nq)]
    F = np.eye(2 * nq)
    F[:nq, nq:] = dt * np.eye(nq)
    np.testing.assert_allclose(A[0], F + Gm @ D[0], atol=1e-15)
    np.testing.assert_allclose(Bz[0], Gm @ B[0], atol=1e-15)
    np.testing.assert_allclose(Q[0], Gm @ S @ Gm.T + np.diag(np.r_[np.full(nq, qv), np.zeros(nq)]), atol=1e-15)


def _h_point_by_point(task, km, z):
    """Oracle: ``h(z)`` and ``H`` of one latent state by MuJoCo's calls made point by point, the velocity
    ``J_p(q) qd`` as ``jp[:, dof] @ qd`` (numpy's product of one row's matrix and vector)."""
    import mujoco as mj

    m, d = task.model, mj.MjData(task.model)
    nq, dof = km.nq, km.dof_adr
    d.qpos[:] = task._qinit
    d.qpos[km.qpos_adr], d.qvel[dof] = z[:nq], z[nq:]
    mj.mj_kinematics(m, d)
    mj.mj_comPos(m, d)
    mj.mj_comVel(m, d)
    hx, H = np.zeros(km.n), np.zeros((km.n, km.nz))
    hx[km.zidx] = z
    H[km.zidx, np.arange(km.nz)] = 1.0
    o_p, o_v = km.pos_sl.start, km.vel_sl.start
    jp, jr, jdp, jdr = (np.zeros((3, m.nv)) for _ in range(4))
    for j, (kind, pid) in enumerate(km.points):
        ps, vs = slice(o_p + 3 * j, o_p + 3 * j + 3), slice(o_v + 3 * j, o_v + 3 * j + 3)
        pos, body = (d.site_xpos[pid], m.site_bodyid[pid]) if kind == "site" else (d.xpos[pid], pid)
        (mj.mj_jacSite if kind == "site" else mj.mj_jacBody)(m, d, jp, jr, pid)
        mj.mj_jacDot(m, d, jdp, jdr, pos, int(body))
        Jq = jp[:, dof]
        hx[ps], hx[vs] = pos, Jq @ z[nq:]
        H[ps, :nq], H[vs, :nq], H[vs, nq:] = Jq, jdp[:, dof], Jq
    return hx, H


def test_h_of_a_batch_equals_mujoco_point_by_point_for_each_row(task_km, rollouts_of):
    """``measure`` runs MuJoCo per row and the products for all rows at once: every row equals, bit for
    bit, the point-by-point oracle of that row alone (so a rollout's ``h`` does not depend on the
    batch it is measured in; peg's joints are a contiguous range, the door's are not)."""
    task, km = task_km
    z = km.z_of(rollouts_of.x[:, ::9])                      # (3, 12, nz)
    z = z + 0.2 * np.random.default_rng(1).standard_normal(z.shape)
    hx, H = km.measure(z)
    h_only = km.measure(z, False)
    for i in np.ndindex(z.shape[:-1]):
        want = _h_point_by_point(task, km, z[i])
        np.testing.assert_array_equal(hx[i], want[0])
        np.testing.assert_array_equal(H[i], want[1])
        np.testing.assert_array_equal(h_only[i], want[0])
        np.testing.assert_array_equal(km.measure(z[i])[0], want[0])
