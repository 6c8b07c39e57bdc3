"""Finite-difference linearisation of a :class:`~soc_opt.tasks.MujocoTask` in task coordinates
(docs/math.md §7, model-based iLQG; ``docs/tasks.md``, "Linearisation").

Per control step the physics transition is differentiated at each of the ``substeps`` physics
steps along the nominal substep trajectory and chained; the result is mapped to task
coordinates with the output Jacobian of the state (joint rows are selections, point rows use the
site/body Jacobians).  The physics derivatives come from ``mujoco.mjd_transitionFD`` (centred),
except for the RK4 integrator, which ``mjd_transitionFD`` does not support: there
:func:`step_derivatives` takes central differences of the whole ``mj_step`` in
``(qpos, qvel, ctrl)`` instead.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..models import LinearGaussianDynamics, ShapeError, check_array

if TYPE_CHECKING:
    from .mujoco import MujocoTask

__all__ = ["step_derivatives", "output_jacobian", "linearize"]


def import_mujoco():
    import mujoco

    return mujoco


def step_derivatives(m, d, eps: float, A: np.ndarray, B: np.ndarray) -> None:
    """``A (2nv, 2nv)``, ``B (2nv, nu)``: central differences of one ``mj_step`` from the state in ``d``.

    For models whose joints are all hinges or slides (``qpos`` and the tangent space coincide),
    perturbing ``qpos``, ``qvel`` and ``ctrl`` one entry at a time by ``±eps``; the rest of ``d``
    (time, warm start) is copied from ``d`` for every evaluation.  ``d`` is not changed.  This is
    what ``mjd_transitionFD(m, d, eps, True, A, B, None, None)`` computes for the integrators it
    supports; here it serves the RK4 integrator.
    """
    mj = import_mujoco()
    nv, nu = m.nv, m.nu
    qadr = np.array([m.jnt_qposadr[m.dof_jntid[v]] for v in range(nv)], dtype=int)
    work = mj.MjData(m)

    def next_state(kind: str, i: int, delta: float) -> np.ndarray:
        mj.mj_copyData(work, m, d)
        if kind == "q":
            work.qpos[qadr[i]] += delta
        elif kind == "v":
            work.qvel[i] += delta
        else:
            work.ctrl[i] += delta
        mj.mj_step(m, work)
        return np.concatenate([work.qpos[qadr], work.qvel])

    for kind, size, out, col0 in (("q", nv, A, 0), ("v", nv, A, nv), ("u", nu, B, 0)):
        for i in range(size):
            out[:, col0 + i] = (next_state(kind, i, eps) - next_state(kind, i, -eps)) / (2 * eps)


def output_jacobian(task: MujocoTask, d) -> np.ndarray:
    """``H = d s / d (dq, dv)`` at the state in ``d`` (positions computed): ``(n, 2 nv)``.

    Joint rows are selections; point positions use ``mj_jacSite``/``mj_jacBody``; point
    velocities ``v = J(q) qdot`` use ``J`` for ``d v / d qdot`` and central differences of
    ``J(q) qdot`` in ``q`` (hinge/slide joints only).
    """
    mj = import_mujoco()
    m = task.model
    nv = m.nv
    H = np.zeros((task.n, 2 * nv))
    H[task.state_qpos_idx, task.dof_adr] = 1.0
    H[task.state_qvel_idx, nv + task.dof_adr] = 1.0
    points = task.point_refs
    if not points:
        return H
    jac = np.zeros((3, nv))

    def point_jac(dd, kind, pid):
        (mj.mj_jacSite if kind == "site" else mj.mj_jacBody)(m, dd, jac, None, pid)
        return jac

    o_p = task.layout["site_pos"].start
    o_v = task.layout["site_vel"].start
    qd = d.qvel.copy()
    for j, (kind, pid) in enumerate(points):
        J = point_jac(d, kind, pid)
        H[o_p + 3 * j : o_p + 3 * j + 3, :nv] = J
        H[o_v + 3 * j : o_v + 3 * j + 3, nv:] = J
    h = 1e-6
    q = d.qpos.copy()
    d2 = mj.MjData(m)
    for dof in range(nv):
        adr = m.jnt_qposadr[m.dof_jntid[dof]]
        vs = []
        for sign in (1.0, -1.0):
            d2.qpos[:] = q
            d2.qpos[adr] += sign * h
            mj.mj_kinematics(m, d2)
            mj.mj_comPos(m, d2)
            vs.append(np.concatenate([point_jac(d2, kind, pid) @ qd for kind, pid in points]))
        H[o_v : o_v + 3 * len(points), dof] = (vs[0] - vs[1]) / (2 * h)
    return H


def linearize(task: MujocoTask, x, u, cov=0.0, eps: float = 1e-6) -> LinearGaussianDynamics:
    """Local linear model ``s_{k+1} ~ A_k s_k + B_k a_k + c_k`` around ``(x_k, u_k)`` in task coordinates.

    Per control step: the physics derivatives (module docstring) at each of the ``substeps``
    physics steps along the nominal substep trajectory, chained (``A = A_S...A_1``,
    ``B = sum_j A_S...A_{j+1} B_j``, ctrl held), then mapped to task coordinates:
    ``A_k = H_{k+1} A G``, ``B_k = H_{k+1} B`` with ``G`` picking ``(q, qdot)`` from the task
    state (point components are functions of them, so their columns are zero) and ``H`` the
    output Jacobian.  ``c_k = step(x_k, u_k) - A_k x_k - B_k u_k``.  ``cov``: process noise
    (scalar times identity, or ``(n, n)``).  Needs every degree of freedom of the model in the
    state (:meth:`MujocoTask.check_linearizable`).
    """
    mj = import_mujoco()
    task.check_linearizable()
    T = task.T
    x = check_array("linearize x", x, (None, task.n))
    u = check_array("linearize u", u, (None, task.m))
    if x.shape[0] not in (T, T + 1) or u.shape[0] != T:
        raise ShapeError(f"linearize needs x ({T + 1}, {task.n}) and u ({T}, {task.m}), got {x.shape}, {u.shape}")
    m = task.model
    nv = m.nv
    rk4 = int(m.opt.integrator) == int(mj.mjtIntegrator.mjINT_RK4)
    d = mj.MjData(m)
    G = np.zeros((2 * nv, task.n))
    G[task.dof_adr, task.state_qpos_idx] = 1.0
    G[nv + task.dof_adr, task.state_qvel_idx] = 1.0
    Aj = np.zeros((2 * nv, 2 * nv))
    Bj = np.zeros((2 * nv, m.nu))
    A = np.zeros((T, task.n, task.n))
    B = np.zeros((T, task.n, task.m))
    c = np.zeros((T, task.n))
    nxt = np.empty(task.n)
    for k in range(T):
        task.reset_data(d, x[k])
        d.ctrl[task.actuator_ids] = u[k]
        Atot = np.eye(2 * nv)
        Btot = np.zeros((2 * nv, m.nu))
        for _ in range(task.substeps):
            if rk4:
                step_derivatives(m, d, eps, Aj, Bj)
            else:
                mj.mjd_transitionFD(m, d, eps, True, Aj, Bj, None, None)
            Atot = Aj @ Atot
            Btot = Aj @ Btot + Bj
            mj.mj_step(m, d)
        mj.mj_forward(m, d)
        task.read_state(d, nxt)
        H = output_jacobian(task, d)
        A[k] = H @ Atot @ G
        B[k] = H @ Btot[:, task.actuator_ids]
        c[k] = nxt - A[k] @ x[k] - B[k] @ u[k]
    W = np.asarray(cov, dtype=float)
    W = W * np.eye(task.n) if W.ndim == 0 else W
    return LinearGaussianDynamics(A, B, c, np.broadcast_to(W, (T, task.n, task.n)).copy())
