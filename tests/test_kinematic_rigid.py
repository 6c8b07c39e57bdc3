"""Tests for soc_opt/noise/kinematic/rigid.py (docs/math.md §11.2, the rigid-body start): the map
predicts MuJoCo's own contact-free step, its action block is the inverse mass matrix for direct-drive
motors, it leaves an unactuated, unmoving joint alone, and EM from it fits a batch at least as well."""

import mujoco
import numpy as np
import pytest

from soc_opt.config import ConfigError
from soc_opt.models import ShapeError
from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.noise.kinematic.rigid import rigid_body_map
from soc_opt.tasks import load_task


@pytest.fixture(scope="module", params=["peg", "door"])
def km(request):
    return KinematicModel(load_task(request.param))


def _step_free(km, z, a):
    """The oracle: one control step of a fresh model and data with constraints disabled."""
    task = km.task
    m = load_task(task.name).model
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    d = mujoco.MjData(m)
    d.qpos[:] = km.task._qinit
    d.qpos[km.qpos_adr] = z[:km.nq]
    d.qvel[km.dof_adr] = z[km.nq:]
    d.ctrl[task.actuator_ids] = a
    mujoco.mj_step(m, d, task.substeps)
    return (d.qvel[km.dof_adr] - z[km.nq:]) / km.dt


def test_the_map_is_the_first_order_expansion_of_mujocos_step(km):
    """The map's error against the simulated step is second order: 100x smaller for a 10x smaller
    perturbation of the state and the action (a linearisation error, not a wrong slope)."""
    z0 = km.z_of(km.task.x0)
    am = rigid_body_map(km, np.tile(z0, (km.T, 1)), np.broadcast_to(np.eye(km.nq), (km.T, km.nq, km.nq)))
    rng = np.random.default_rng(0)
    a1, dz1 = rng.normal(size=km.m), 0.05 * rng.normal(size=km.nz)
    errs = []
    for h in (1.0, 0.1):
        a, z = h * a1, z0 + h * dz1
        errs.append(np.linalg.norm(_step_free(km, z, a) - (am.B[0] @ a + am.D[0] @ z + am.c[0])))
    assert errs[1] < 0.03 * errs[0] or errs[1] < 1e-8, errs


def test_the_action_block_is_the_step_integrated_inverse_mass_matrix_for_motors(km):
    """With motors of gear 1 and small steps the action block is close to ``M(q)^{-1}`` restricted to
    the actuated dofs (the integrator's damping and armature make it a little smaller)."""
    m = km.model
    d = mujoco.MjData(m)
    z0 = km.z_of(km.task.x0)
    d.qpos[:] = km.task._qinit
    d.qpos[km.qpos_adr] = z0[:km.nq]
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    act_dof = [int(m.jnt_dofadr[m.actuator_trnid[i, 0]]) for i in km.task.actuator_ids]
    Minv = np.linalg.inv(M)[np.ix_(km.dof_adr, act_dof)] * m.actuator_gear[km.task.actuator_ids, 0]
    am = rigid_body_map(km, np.tile(z0, (km.T, 1)), np.broadcast_to(np.eye(km.nq), (km.T, km.nq, km.nq)))
    rel = np.linalg.norm(am.B[0] - Minv) / np.linalg.norm(Minv)
    assert rel < 0.35, rel
    assert np.allclose(np.sign(np.diag(am.B[0][:len(act_dof)])), 1.0)


def test_an_unactuated_joint_at_rest_gets_no_acceleration_from_the_actions():
    km = KinematicModel(load_task("door"))
    z0 = km.z_of(km.task.x0)
    am = rigid_body_map(km, np.tile(z0, (km.T, 1)), np.broadcast_to(np.eye(km.nq), (km.T, km.nq, km.nq)))
    hinge = km.nq - 1  # the door's hinge is the extra joint, last in z
    np.testing.assert_allclose(am.B[:, hinge], 0.0, atol=1e-12)
    np.testing.assert_allclose(am.c[:, hinge] + am.D[:, hinge] @ z0, 0.0, atol=1e-9)


def test_the_nominal_trajectory_must_have_the_horizons_shape(km):
    with pytest.raises(ShapeError, match="zbar"):
        rigid_body_map(km, np.zeros((km.T - 1, km.nz)), np.broadcast_to(np.eye(km.nq), (km.T, km.nq, km.nq)))


def test_start_map_is_checked_by_name():
    with pytest.raises(ConfigError, match="start_map"):
        KinematicConfig(start_map="inertia")


def test_em_from_the_rigid_body_start_explains_a_noisy_batch_better_than_from_zero():
    """Peg at rho^2 = 0.1 under the initial policy: the first E-step's likelihood of the measurements
    is higher from the rigid-body map than from B = D = c = 0, and EM keeps it higher."""
    task = load_task("peg")
    assert float(task.rho2) == 0.1  # the task's measurements carry the paper's sensor noise
    km = KinematicModel(task)
    ro = task.rollouts(task.initial_policy(1.0), 8, np.random.default_rng(3))
    s = ro.s
    zero = em.fit(km, s, ro.a, 0.1, KinematicConfig(em_iters=2))
    rigid = em.fit(km, s, ro.a, 0.1, KinematicConfig(em_iters=2, start_map="rigid_body"))
    assert rigid.loglik[0] > zero.loglik[0]
    assert rigid.loglik[-1] > zero.loglik[-1]
