"""The structured model of a MuJoCo task: known kinematics, learned actuation (``docs/math.md §11.1``).

Latent joint state ``z = (q, qd)`` over the task's state joints then extra joints (``nq`` each,
``nz = 2 nq``).  The measurement map ``h(z)`` rebuilds the task's state vector (joint angles and
velocities as they are, point positions by forward kinematics of ``q``, point velocities
``J_p(q) qd``); its Jacobian comes from the same MuJoCo calls (``mj_kinematics``, ``mj_comPos``,
``mj_comVel``, ``mj_jacSite``/``mj_jacBody``, ``mj_jacDot``).  For a point ``p(q)``,
``d(J_p(q) qd)/dq = Jdot_p`` (the Hessian of ``p`` is symmetric), which is what ``mj_jacDot``
returns for hinge and slide joints.

Transition per control step (``dt = timestep * substeps``)::

    q_{k+1}  = q_k + dt qd_k + c2 dt^2 u_k + w^q_k,     qd_{k+1} = qd_k + dt u_k
    u_k      = B_k a_k + D_k z_k + c_k + w_k,           w_k ~ N(0, S_k),  w^q_k ~ N(0, q_var I)

``c2 = (N + 1) / (2 N)`` for MuJoCo's semi-implicit Euler with ``N`` substeps under a constant
acceleration (``1/2`` for the other integrators); ``w^q`` absorbs the residual of that
idealisation.  Only the acceleration map ``(B, D, c, S)`` is learned (:mod:`soc_opt.noise.kinematic.em`).
The model uses the robot's kinematics (not its masses, inertia or damping).
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass

import numpy as np

from ...config import ConfigError
from ...linalg import as_index
from ...models import ShapeError, check_array

__all__ = ["KinematicModel", "AccelMap", "transition", "check_task"]

#: What the model reads off a MuJoCo task (:class:`soc_opt.tasks.mujoco.MujocoTask`, gym: tasks included).
_MUJOCO_TASK_ATTRS = ("qpos_adr", "dof_adr", "state_qpos_idx", "state_qvel_idx", "point_refs", "layout", "substeps",
                      "_qinit", "x0")


def _task_name(task) -> str:
    return str(getattr(task, "name", None) or type(task).__name__)


def check_task(task) -> None:
    """Raise :class:`~soc_opt.config.ConfigError` unless the kinematic estimator can model ``task``
    (``docs/noise.md`` §11, "What the estimator needs of a task").

    * The task is a MuJoCo task: an MJCF model or a ``gym:`` MuJoCo environment (its model and data
      are MuJoCo's).  A linear task has no kinematics to use.
    * Every joint that moves a point of the state (``state.sites``: a site or a body origin) is in
      the state (``state.joints`` or ``state.extra_joints``).  The model rebuilds the points from
      the state's joints alone, so a joint left out would be frozen at its initial value and the
      point placed wrongly; the message names the joint, the point and where to add the joint.
      Joints that move no point of the state (e.g. a goal marker's slides) may stay out.
    """
    import mujoco

    model = getattr(task, "model", None)
    missing = [a for a in _MUJOCO_TASK_ATTRS if not hasattr(task, a)]
    if not isinstance(model, mujoco.MjModel) or missing:
        kind = getattr(task, "kind", type(task).__name__)
        raise ConfigError(f"estimator = 'kinematic' needs a MuJoCo task (an MJCF model or a gym: MuJoCo environment) "
                          f"to take its kinematics from; task {_task_name(task)!r} is of kind {kind!r}, which has none "
                          "(use estimator = 'none' or 'kalman' for it)")
    in_state = {int(a) for a in task.qpos_adr}
    bad = []
    for kind, pid in task.point_refs:
        body = int(model.site_bodyid[pid]) if kind == "site" else int(pid)
        point = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE if kind == "site" else mujoco.mjtObj.mjOBJ_BODY, pid)
        while body > 0:
            for j in range(int(model.body_jntadr[body]), int(model.body_jntadr[body]) + int(model.body_jntnum[body])):
                if int(model.jnt_qposadr[j]) not in in_state:
                    bad.append((mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"<joint {j}>", kind, point,
                                int(model.jnt_type[j])))
            body = int(model.body_parentid[body])
    if bad:
        joint, kind, point, jtype = bad[0]
        names = list(dict.fromkeys(b[0] for b in bad))
        free = jtype not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        fix = ("it is a free/ball joint, which the state cannot hold: declare a point that it does not move"
               if free else "add " + ("it" if len(names) == 1 else "them") + " to state.extra_joints in the task TOML, "
               "e.g. extra_joints = [" + ", ".join(f'"{n}"' for n in names) + "]")
        raise ConfigError(f"task {_task_name(task)!r}: joint {joint!r} moves the {kind} {point!r} of state.sites but is "
                          "not in the state (state.joints or state.extra_joints); the kinematic estimator rebuilds the "
                          f"points from the state's joints alone and would hold it at its initial value; {fix}")


@dataclass(frozen=True)
class AccelMap:
    """The learned acceleration map ``u_k = B_k a_k + D_k z_k + c_k + w_k``, ``w_k ~ N(0, S_k)``.

    Fields: ``B (T, nq, m)``, ``D (T, nq, nz)``, ``c (T, nq)``, ``S (T, nq, nq)`` (positive definite).
    """

    B: np.ndarray
    D: np.ndarray
    c: np.ndarray
    S: np.ndarray

    def __post_init__(self):
        T, nq, m = np.shape(self.B)
        for name, shape in (("B", (T, nq, m)), ("D", (T, nq, 2 * nq)), ("c", (T, nq)), ("S", (T, nq, nq))):
            a = check_array(f"acceleration map {name}", getattr(self, name), shape).copy()
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def T(self) -> int:
        return self.B.shape[0]

    @staticmethod
    def zero(T: int, nq: int, m: int, S) -> "AccelMap":
        """``B = D = c = 0`` and noise ``S (T, nq, nq)`` (the first EM round, ``docs/math.md §11.2``)."""
        return AccelMap(np.zeros((T, nq, m)), np.zeros((T, nq, 2 * nq)), np.zeros((T, nq)), S)


def transition(accel: AccelMap, dt: float, c2: float, q_var: float):
    """``(A (T, nz, nz), Bz (T, nz, m), cz (T, nz), Q (T, nz, nz))`` of ``z_{k+1} = A z + Bz a + cz + noise``."""
    T, nq, _ = accel.B.shape
    nz = 2 * nq
    F = np.eye(nz)
    F[:nq, nq:] = dt * np.eye(nq)
    Gm = np.concatenate([c2 * dt * dt * np.eye(nq), dt * np.eye(nq)], axis=0)  # (nz, nq)
    A = F[None] + Gm[None] @ accel.D
    Bz = Gm[None] @ accel.B
    cz = accel.c @ Gm.T
    Q = Gm[None] @ accel.S @ Gm.T[None]
    Q[:, np.arange(nq), np.arange(nq)] += q_var
    return A, Bz, cz, 0.5 * (Q + np.swapaxes(Q, 1, 2))


class KinematicModel:
    """``h``, its Jacobian and the kinematic constants of a :class:`~soc_opt.tasks.mujoco.MujocoTask`
    (``gym:`` tasks included; :func:`check_task` says what it refuses).

    Attributes: ``n`` (task state), ``nq``, ``nz = 2 nq``, ``m``, ``T``, ``dt``, ``c2``,
    ``zidx (nz,)`` (positions of ``(q, qd)`` in the task state, so ``z = x[..., zidx]``),
    ``start_cov (nz, nz)``: the covariance of the true ``z_0`` of a task with ``[process_noise] start``
    (the rows and columns of ``z`` of ``task.start_cov``: ``r^2 / 3`` on the angles of ``state.joints``),
    ``None`` for a known start (docs/math.md §8.1).
    """

    def __init__(self, task):
        import mujoco

        check_task(task)
        self.mj = mujoco
        self.task = task
        self.model = task.model
        self.n, self.m, self.T, self.dt = int(task.n), int(task.m), int(task.T), float(task.dt)
        self.nq = len(task.qpos_adr)
        self.nz = 2 * self.nq
        self.zidx = np.r_[task.state_qpos_idx, task.state_qvel_idx].astype(int)
        self.qpos_adr = np.asarray(task.qpos_adr, dtype=int)
        self.dof_adr = np.asarray(task.dof_adr, dtype=int)
        N = int(task.substeps)
        euler = int(self.model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_EULER)
        self.c2 = (N + 1) / (2 * N) if euler else 0.5
        self.points = list(task.point_refs)
        self.pos_sl, self.vel_sl = task.layout["site_pos"], task.layout["site_vel"]
        self._qinit = np.array(task._qinit)
        pn = getattr(task, "process_noise", None)
        self.start_cov = np.asarray(task.start_cov)[np.ix_(self.zidx, self.zidx)] if pn is not None and pn.start_on else None
        self._local = threading.local()

    def __getstate__(self):
        return {"task": self.task}

    def __setstate__(self, state):
        self.__init__(state["task"])

    @property
    def _data(self):
        """One ``MjData`` per thread (rollouts may run the filter in worker threads)."""
        d = getattr(self._local, "data", None)
        if d is None:
            d = self._local.data = self.mj.MjData(self.model)
        return d

    def free_accel(self, z, a) -> np.ndarray:
        """``u (nq,)``: the mean acceleration ``(qd_{k+1} - qd_k) / dt`` of the latent joints over one
        control step from ``z (nz,)`` under actions ``a (m,)``, simulated by MuJoCo with every
        constraint (contacts, joint limits) disabled: the robot's own rigid-body dynamics (masses,
        inertia, damping, gravity, the integrator), not its contacts.  Joints outside ``z`` start
        at their initial angle with zero velocity (``docs/math.md §11.2``, the rigid-body start)."""
        mj = self.mj
        loc = self._local
        if getattr(loc, "free", None) is None:
            fm = copy.deepcopy(self.model)
            fm.opt.disableflags |= int(mj.mjtDisableBit.mjDSBL_CONSTRAINT)
            loc.free = (fm, mj.MjData(fm))
        fm, d = loc.free
        mj.mj_resetData(fm, d)
        d.qpos[:] = self._qinit
        d.qpos[self.qpos_adr] = z[:self.nq]
        d.qvel[self.dof_adr] = z[self.nq:]
        d.ctrl[np.asarray(self.task.actuator_ids, dtype=int)] = a
        mj.mj_step(fm, d, int(self.task.substeps))
        return (d.qvel[self.dof_adr] - z[self.nq:]) / self.dt

    def z_of(self, x) -> np.ndarray:
        """``z = (q, qd)`` read off task states ``x (..., n)``."""
        x = np.asarray(x, dtype=float)
        if x.shape[-1] != self.n:
            raise ShapeError(f"task states must have shape (..., {self.n}), got {x.shape}")
        return x[..., self.zidx]

    def measure(self, z, jacobian: bool = True):
        """``h(z) (..., n)`` and, with ``jacobian``, ``H = dh/dz (..., n, nz)`` (``docs/math.md §11.1``)."""
        z = np.asarray(z, dtype=float)
        if z.shape[-1] != self.nz:
            raise ShapeError(f"latent states z must have shape (..., {self.nz}), got {z.shape}")
        lead = z.shape[:-1]
        zf = z.reshape(-1, self.nz)
        N, nq, n = zf.shape[0], self.nq, self.n
        hx = np.zeros((N, n))
        H = np.zeros((N, n, self.nz)) if jacobian else None
        qi, vi = self.zidx[:nq], self.zidx[nq:]
        hx[:, qi] = zf[:, :nq]
        hx[:, vi] = zf[:, nq:]
        if jacobian:
            H[:, qi, np.arange(nq)] = 1.0
            H[:, vi, nq + np.arange(nq)] = 1.0
        if self.points:
            self._points(zf, hx, H, self._data)
        return (hx.reshape(lead + (n,)), H.reshape(lead + (n, self.nz))) if jacobian else hx.reshape(lead + (n,))

    def _points(self, zf, hx, H, d):
        """The point rows of ``hx (N, n)`` and, with ``H``, of ``H (N, n, nz)`` at ``zf (N, nz)``.

        MuJoCo's kinematics run once per row (on ``d``), writing each point's position and Jacobians
        (``mj_jacSite``/``mj_jacBody``, ``mj_jacDot``; translation only) into stacks; the products and
        copies into ``hx`` and ``H`` then run once for all rows.  The velocity ``J_p(q) qd`` is a stack of
        the matrix-vector products one row computes alone, so every row is independent of the others
        to the last bit (and of how many rows there are)."""
        mj, m = self.mj, self.model
        nq, nv = self.nq, m.nv
        N, P = zf.shape[0], len(self.points)
        dof, qadr = self.dof_adr, self.qpos_adr
        dof_i, qadr_i = as_index(dof), as_index(qadr)
        o_p, o_v = self.pos_sl.start, self.vel_sl.start
        jac = H is not None
        pos_all = np.empty((N, P, 3))
        jp_all = np.empty((N, P, 3, nv))
        jdp_all = np.empty((N, P, 3, nv)) if jac else None
        # joints outside z keep their initial angle and zero velocity (written once: the
        # kinematics calls read qpos/qvel and never write them); check_task refuses a task where
        # such a joint moves a point, so they move none of the points read here
        d.qpos[:] = self._qinit
        d.qvel[:] = 0.0
        plan = []
        for j, (kind, pid) in enumerate(self.points):
            if kind == "site":
                plan.append((j, d.site_xpos[pid], int(m.site_bodyid[pid]), mj.mj_jacSite, pid))
            else:
                plan.append((j, d.xpos[pid], pid, mj.mj_jacBody, pid))
        qpos, qvel = d.qpos, d.qvel
        kin, compos, comvel, jacdot = mj.mj_kinematics, mj.mj_comPos, mj.mj_comVel, mj.mj_jacDot
        for i in range(N):
            qpos[qadr_i] = zf[i, :nq]
            qvel[dof_i] = zf[i, nq:]
            kin(m, d)
            compos(m, d)
            if jac:
                comvel(m, d)
            for j, pos, body, jacf, pid in plan:
                jacf(m, d, jp_all[i, j], None, pid)
                pos_all[i, j] = pos
                if jac:
                    jacdot(m, d, jdp_all[i, j], None, pos, body)
        # (N, P, 3, nq), each (3, nq) matrix stored column by column, as numpy stores one row's ``jp[:, dof]``
        # (the indexed axis outermost): the memory order of a matrix decides which BLAS kernel, and so which
        # rounding, the product J_p qd takes
        Jq = np.ascontiguousarray(np.swapaxes(jp_all[..., dof], -1, -2)).swapaxes(-1, -2)
        vel = (Jq @ zf[:, None, nq:, None])[..., 0]  # (N, P, 3): J_p(q) qd, one matrix-vector product per row
        hx[:, o_p:o_p + 3 * P] = pos_all.reshape(N, 3 * P)
        hx[:, o_v:o_v + 3 * P] = vel.reshape(N, 3 * P)
        if jac:
            H[:, o_p:o_p + 3 * P, :nq] = Jq.reshape(N, 3 * P, nq)
            H[:, o_v:o_v + 3 * P, :nq] = jdp_all[..., dof].reshape(N, 3 * P, nq)
            H[:, o_v:o_v + 3 * P, nq:] = Jq.reshape(N, 3 * P, nq)
