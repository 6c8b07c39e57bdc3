"""MuJoCo tasks: an MJCF model plus a :class:`TaskConfig` (docs/math.md §0, §8 "any MuJoCo model").

State of a MuJoCo task (``x`` true, ``s = x + eps`` measured, docs/math.md §0)::

    [ qpos(state.joints), qvel(state.joints),
      point positions (3 per state.sites), point velocities (3 per point, world frame),
      qpos(state.extra_joints), qvel(state.extra_joints) ]

A point named in ``state.sites`` (and in the cost terms' ``sites``/``target_sites`` and the
metric's ``site``) is a site of the model, or, if no site has that name, the origin of the body
of that name.

Rollouts: from ``x_0`` (``q0`` + condition offset, zero velocity) the action
``a_k = K_k s_k + k_k + L_k w_k`` is computed from the *measured* state and held
as ``ctrl`` for ``substeps`` calls of ``mj_step`` (``dt = timestep * substeps``).
All noise (``eps``, ``w``, then the start offsets and actuation noise of ``[process_noise]`` when
on: docs/math.md §8.1) is drawn from the Generator before simulating, so results do not depend on
``workers``.  The stage cost ``Y_k`` is evaluated on
the measured ``s_k`` (docs/math.md §0) and ``y_k = exp(-y_scale * Y_k)``.

The finite-difference linearisation in task coordinates (:meth:`MujocoTask.linearize`) is in
:mod:`soc_opt.tasks.linearize`.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .. import parallel
from ..config import ConfigError
from ..linalg import as_index
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, Rollouts
from . import linearize as _linearize
from .base import SimulationError, TaskBase, as_rng
from .config import StateConfig, TaskConfig

__all__ = ["MujocoTask", "MujocoSimulator"]


def import_mujoco():
    import mujoco

    return mujoco


#: Degrees of freedom per joint type (free, ball, slide, hinge).
_JOINT_DOFS = {0: 6, 1: 3, 2: 1, 3: 1}

_BAD_WARNINGS = ("mjWARN_CONTACTFULL", "mjWARN_CNSTRFULL", "mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC", "mjWARN_BADCTRL")


class MujocoTask(TaskBase):
    """A task from an MJCF model plus a :class:`TaskConfig` (docs/math.md §8 "any MuJoCo model")."""

    kind = "mujoco"

    def __init__(self, config: TaskConfig, model, *, condition: int = 0, source: str = "<model>"):
        mj = import_mujoco()
        self.config = config
        self.model = model
        self.source = source
        if config.timestep is not None:
            model.opt.timestep = config.timestep
        self.substeps = config.substeps
        self.dt = float(model.opt.timestep) * self.substeps
        if model.na:
            raise ConfigError(f"model {source}: actuators with activation states (na={model.na}) are not supported")
        self._setup_state(config.state)
        self._setup_actuators(config.actuated)
        self._setup_initial(condition)
        self._setup_reader()

        data = mj.MjData(model)
        self.reset_data(data, None)
        mj.mj_forward(model, data)
        x0 = np.empty(self.n)
        self.read_state(data, x0, np.empty(6))
        self.x0 = x0
        self._setup_common()

    # -- construction steps (in this order: each uses what the previous ones set)
    def _setup_state(self, sc: StateConfig):
        """Look up and check the state joints and sites; state layout, labels and index maps."""
        mj = import_mujoco()
        model = self.model
        self._joint_ids = [self._find(mj.mjtObj.mjOBJ_JOINT, j, "state.joints") for j in sc.joints]
        self._extra_ids = [self._find(mj.mjtObj.mjOBJ_JOINT, j, "state.extra_joints") for j in sc.extra_joints]
        self.point_refs = [self._find_point(s, "state.sites") for s in sc.sites]
        self._site_ids = [pid for kind, pid in self.point_refs if kind == "site"]
        alljoints = list(sc.joints) + list(sc.extra_joints)
        dup = {j for j in alljoints if alljoints.count(j) > 1} | {s for s in sc.sites if sc.sites.count(s) > 1}
        if dup:
            raise ConfigError(f"state: {sorted(dup)[0]!r} is listed twice")
        for key, names, ids in (("state.joints", sc.joints, self._joint_ids), ("state.extra_joints", sc.extra_joints, self._extra_ids)):
            for nm, j in zip(names, ids):
                if int(model.jnt_type[j]) not in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)):
                    raise ConfigError(f"{key}: joint {nm!r} is not a hinge or slide joint (free/ball joints are not supported)")
        if not alljoints and not sc.sites:
            raise ConfigError("state: empty; list joints and/or sites")

        # state layout
        nj, ns, ne = len(sc.joints), len(sc.sites), len(sc.extra_joints)
        self.n = 2 * nj + 6 * ns + 2 * ne
        o_p, o_v, o_e = 2 * nj, 2 * nj + 3 * ns, 2 * nj + 6 * ns
        self.layout = {
            "qpos": slice(0, nj),
            "qvel": slice(nj, 2 * nj),
            "site_pos": slice(o_p, o_v),
            "site_vel": slice(o_v, o_e),
            "extra_qpos": slice(o_e, o_e + ne),
            "extra_qvel": slice(o_e + ne, o_e + 2 * ne),
        }
        jids = self._joint_ids + self._extra_ids
        self.qpos_adr = np.array([model.jnt_qposadr[j] for j in jids], dtype=int)
        self._start_adr = as_index(self.qpos_adr[:nj])  # the joints [process_noise] start offsets
        self.dof_adr = np.array([model.jnt_dofadr[j] for j in jids], dtype=int)
        self.state_qpos_idx = np.r_[np.arange(nj), o_e + np.arange(ne)].astype(int)
        self.state_qvel_idx = np.r_[nj + np.arange(nj), o_e + ne + np.arange(ne)].astype(int)
        labels = [""] * self.n
        for nm, i in zip(alljoints, self.state_qpos_idx):
            labels[i] = f"q:{nm}"
        for nm, i in zip(alljoints, self.state_qvel_idx):
            labels[i] = f"qd:{nm}"
        for j, nm in enumerate(sc.sites):
            for c, ax in enumerate("xyz"):
                labels[o_p + 3 * j + c] = f"{nm}.{ax}"
                labels[o_v + 3 * j + c] = f"{nm}.v{ax}"
        self.state_labels = labels
        self._joint_state_index = {nm: int(i) for nm, i in zip(alljoints, self.state_qpos_idx)}
        self._site_state_index = {nm: o_p + 3 * j for j, nm in enumerate(sc.sites)}
        self._all_dofs_in_state = sorted(self.dof_adr.tolist()) == list(range(model.nv))

    def _setup_actuators(self, actuated):
        """The controlled actuators ``actuator_ids (m,)`` (all of the model's if ``actuated`` is empty)."""
        model = self.model
        if actuated:
            self.actuator_ids = np.array([self._actuator_for(a) for a in actuated], dtype=int)
            self.actuated = list(actuated)
        else:
            self.actuator_ids = np.arange(model.nu)
            self.actuated = [model.actuator(i).name for i in range(model.nu)]
        if len(set(self.actuator_ids.tolist())) != len(self.actuator_ids):
            raise ConfigError("actuated: an actuator is listed twice")
        self.m = len(self.actuator_ids)
        if self.m == 0:
            raise ConfigError(f"actuated: model {self.source} has no actuators")

    def _setup_initial(self, condition: int):
        """Initial full configuration ``_qinit (nq,)``: ``qpos0`` with the state joints at ``q0`` + offset."""
        model = self.model
        config = self.config
        jids = self._joint_ids + self._extra_ids
        qinit = model.qpos0.copy()
        if config.q0:
            if len(config.q0) != len(jids):
                raise ConfigError(
                    f"q0: expected {len(jids)} numbers (state.joints then state.extra_joints), got {len(config.q0)}"
                )
            q0 = np.array(config.q0, dtype=float)
            if config.offsets:
                if not 0 <= condition < len(config.offsets):
                    raise ConfigError(f"condition {condition} out of range: {len(config.offsets)} offsets given")
                q0 = q0 + np.array(config.offsets[condition], dtype=float)
            qinit[self.qpos_adr] = q0
        self.condition = condition
        self.n_conditions = max(1, len(config.offsets))
        self._qinit = qinit

    def _setup_reader(self):
        """Copy plans for the fast state reader, integrator split and divergence warnings."""
        mj = import_mujoco()
        model = self.model
        o_v = self.layout["site_vel"].start
        ns = len(self.point_refs)
        self._q_src, self._q_dst = self._split_plan(self.qpos_adr, self.state_qpos_idx)
        self._qd_src, self._qd_dst = self._split_plan(self.dof_adr, self.state_qvel_idx)
        self._site_arr = np.array(self._site_ids, dtype=int)
        self._site_pos_sl = self.layout["site_pos"]
        self._site_vel_slices = [slice(o_v + 3 * j, o_v + 3 * j + 3) for j in range(ns)]
        self._split_step = int(model.opt.integrator) != int(mj.mjtIntegrator.mjINT_RK4)
        self._bad_warn = np.array([int(getattr(mj.mjtWarning, w)) for w in _BAD_WARNINGS])
        self._obj_site = mj.mjtObj.mjOBJ_SITE
        self._obj_of = {"site": mj.mjtObj.mjOBJ_SITE, "body": mj.mjtObj.mjOBJ_XBODY}
        self._all_sites = all(kind == "site" for kind, _ in self.point_refs)

    # -- lookups
    def _find(self, objtype, name, key) -> int:
        mj = import_mujoco()
        i = mj.mj_name2id(self.model, objtype, name)
        if i < 0:
            kind = {mj.mjtObj.mjOBJ_JOINT: "joint", mj.mjtObj.mjOBJ_SITE: "site"}.get(objtype, "object")
            count = self.model.njnt if kind == "joint" else self.model.nsite
            names = [mj.mj_id2name(self.model, objtype, k) for k in range(count)]
            raise ConfigError(f"{key}: {kind} {name!r} not found in model {self.source}; {kind}s: {names}")
        return i

    def _find_point(self, name, key) -> tuple[str, int]:
        """``("site", id)`` for a site named ``name``, else ``("body", id)`` for a body (its origin)."""
        mj = import_mujoco()
        i = mj.mj_name2id(self.model, mj.mjtObj.mjOBJ_SITE, name)
        if i >= 0:
            return "site", i
        i = mj.mj_name2id(self.model, mj.mjtObj.mjOBJ_BODY, name)
        if i >= 0:
            return "body", i
        sites = [mj.mj_id2name(self.model, mj.mjtObj.mjOBJ_SITE, k) for k in range(self.model.nsite)]
        bodies = [mj.mj_id2name(self.model, mj.mjtObj.mjOBJ_BODY, k) for k in range(self.model.nbody)]
        raise ConfigError(f"{key}: site {name!r} not found in model {self.source}, nor a body of that name; "
                          f"sites: {sites}; bodies: {bodies}")

    def _actuator_for(self, name) -> int:
        mj = import_mujoco()
        m = self.model
        j = mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, name)
        if j >= 0:
            for i in range(m.nu):
                if int(m.actuator_trntype[i]) == int(mj.mjtTrn.mjTRN_JOINT) and int(m.actuator_trnid[i, 0]) == j:
                    return i
            raise ConfigError(f"actuated: joint {name!r} has no actuator in model {self.source}")
        i = mj.mj_name2id(m, mj.mjtObj.mjOBJ_ACTUATOR, name)
        if i >= 0:
            return i
        raise ConfigError(f"actuated: no joint or actuator named {name!r} in model {self.source}")

    def _site_indices(self, sites, key) -> list[int]:
        out = []
        for s in sites:
            if s not in self._site_state_index:
                raise ConfigError(f"{key}: site {s!r} is not in the state (state.sites = {list(self.config.state.sites)})")
            out += list(range(self._site_state_index[s], self._site_state_index[s] + 3))
        return out

    def _joint_index(self, joint, key) -> int:
        if joint not in self._joint_state_index:
            raise ConfigError(f"{key}: joint {joint!r} is not in the state (state.joints + state.extra_joints)")
        return self._joint_state_index[joint]

    @staticmethod
    def _split_plan(src, dst):
        """Group (src, dst) index pairs into runs that are contiguous in both (slice copies)."""
        plan_src, plan_dst = [], []
        start = 0
        for i in range(1, len(src) + 1):
            if i == len(src) or src[i] != src[i - 1] + 1 or dst[i] != dst[i - 1] + 1:
                plan_src.append(slice(int(src[start]), int(src[i - 1]) + 1))
                plan_dst.append(slice(int(dst[start]), int(dst[i - 1]) + 1))
                start = i
        return plan_src, plan_dst

    # -- simulator state <-> task state
    def reset_data(self, d, x0):
        mj = import_mujoco()
        mj.mj_resetData(self.model, d)
        d.qpos[:] = self._qinit
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            d.qpos[self.qpos_adr] = x0[self.state_qpos_idx]
            d.qvel[self.dof_adr] = x0[self.state_qvel_idx]

    def reset_start(self, d, x0, start=None):
        """:meth:`reset_data`, then the start offsets ``start (nj,)`` added to the angles of ``state.joints``
        (a row of :attr:`RolloutNoise.start <soc_opt.tasks.base.RolloutNoise>`; docs/math.md §8.1)."""
        self.reset_data(d, x0)
        if start is not None:
            d.qpos[self._start_adr] += start

    def _start_coordinates(self):
        nj = len(self.config.state.joints)
        return list(self.config.state.joints), self.state_qpos_idx[:nj], "joint of state.joints"

    def _action_names(self) -> list[str]:
        return list(self.actuated)

    def _start_jacobian(self) -> np.ndarray:
        """``d x_0 / d q`` over the joints of ``state.joints`` at the nominal start: the output Jacobian
        (:func:`soc_opt.tasks.linearize.output_jacobian`) at ``x_0``, its position columns of those joints."""
        mj = import_mujoco()
        d = mj.MjData(self.model)
        self.reset_data(d, None)
        mj.mj_forward(self.model, d)
        return _linearize.output_jacobian(self, d)[:, self.dof_adr[: len(self.config.state.joints)]]

    def _reader(self, d):
        """A function ``read(out)`` writing the task state of ``d`` into ``out (n,)``.

        Needs positions and velocities computed (after ``mj_step1`` or ``mj_forward``).  The
        array views of ``d`` and the copy plan are bound once: this runs every control step.
        """
        ov = import_mujoco().mj_objectVelocity
        m = self.model
        qpos, qvel, site_xpos = d.qpos, d.qvel, d.site_xpos
        qplan = list(zip(self._q_src, self._q_dst))
        qdplan = list(zip(self._qd_src, self._qd_dst))
        sites = self._site_arr
        pos_sl = self._site_pos_sl
        vplan = [(self._obj_of[kind], pid, sl) for (kind, pid), sl in zip(self.point_refs, self._site_vel_slices)]
        # positions: one fancy-index copy when every point is a site, else one copy per point
        o_p = pos_sl.start
        pplan = [((site_xpos if kind == "site" else d.xpos), pid, slice(o_p + 3 * j, o_p + 3 * j + 3))
                 for j, (kind, pid) in enumerate(self.point_refs)]
        all_sites = self._all_sites
        res = np.empty(6)
        lin = res[3:]

        def read(out):
            for src, dst in qplan:
                out[dst] = qpos[src]
            for src, dst in qdplan:
                out[dst] = qvel[src]
            if vplan:
                if all_sites:
                    out[pos_sl] = site_xpos[sites].ravel()
                else:
                    for arr, pid, sl in pplan:
                        out[sl] = arr[pid]
                for obj, pid, sl in vplan:
                    ov(m, d, obj, pid, res, 0)
                    out[sl] = lin

        return read

    def read_state(self, d, out, res=None):
        self._reader(d)(out)

    def state_from_qpos(self, qpos, qvel=None) -> np.ndarray:
        """Task state for a full ``qpos (nq,)`` (and ``qvel``, default zero), via ``mj_forward``."""
        mj = import_mujoco()
        d = mj.MjData(self.model)
        d.qpos[:] = qpos
        if qvel is not None:
            d.qvel[:] = qvel
        mj.mj_forward(self.model, d)
        out = np.empty(self.n)
        self.read_state(d, out, np.empty(6))
        return out

    def qpos_from_state(self, x) -> np.ndarray:
        """``(..., nq)`` full configurations: state joints from ``x``, other joints at their initial values."""
        x = np.asarray(x, dtype=float)
        q = np.broadcast_to(self._qinit, x.shape[:-1] + (self.model.nq,)).copy()
        q[..., self.qpos_adr] = x[..., self.state_qpos_idx]
        return q

    # -- rollouts (hot path)
    def _control_step(self):
        """``(begin, finish)`` of one control step on an ``MjData``: ``begin(d)`` computes positions and
        velocities (``mj_step1``, or ``mj_forward`` with RK4, which cannot be split), the state is read and
        the control set in between, ``finish(d)`` completes the step and its remaining substeps."""
        mj = import_mujoco()
        m, nsub = self.model, self.substeps
        step1, step2, step, forward = mj.mj_step1, mj.mj_step2, mj.mj_step, mj.mj_forward
        if not self._split_step:
            return (lambda d: forward(m, d)), (lambda d: step(m, d, nsub))

        def finish(d):
            step2(m, d)
            if nsub > 1:
                step(m, d, nsub - 1)

        return (lambda d: step1(m, d)), finish

    def _run_samples(self, samples, K, offs, eps, x, s, a, x0, filtered=None, proc=(None, None)):
        mj = import_mujoco()
        m = self.model
        d = mj.MjData(m)
        begin, finish = self._control_step()
        forward = mj.mj_forward
        ctrl = d.ctrl
        act = as_index(self.actuator_ids)
        warn = d.warning.number
        bad = self._bad_warn
        read = self._reader(d)
        dot = np.dot
        T = self.T
        start, nu = proc
        for i in samples:
            self.reset_start(d, x0, None if start is None else start[i])
            xi, si, ai, ei, oi = x[i], s[i], a[i], eps[i], offs[i]
            nui = None if nu is None else nu[i]
            xhat = None
            for k in range(T):
                begin(d)
                xk, sk, ak = xi[k], si[k], ai[k]
                read(xk)
                np.add(xk, ei[k], out=sk)
                if filtered is None:
                    dot(K[k], sk, out=ak)
                else:  # act on the online estimate xhat_k (docs/math.md §10.2)
                    xhat = filtered.estimate(k, sk) if k == 0 else filtered.estimate(k, sk, xhat, ai[k - 1])
                    dot(K[k], xhat, out=ak)
                ak += oi[k]
                ctrl[act] = ak if nui is None else ak + nui[k]  # the plant's control (docs/math.md §8.1)
                finish(d)
                if warn.any():
                    self._diverged(i, k, d, warn, bad)
            forward(m, d)
            read(xi[T])
            np.add(xi[T], ei[T], out=si[T])
            if not (np.isfinite(xi).all() and np.isfinite(ai).all()):
                bad_k = np.flatnonzero(~np.isfinite(xi[:T]).all(axis=1) | ~np.isfinite(ai).all(axis=1))
                kk = int(bad_k[0]) if bad_k.size else T
                raise SimulationError(f"sample {i} diverged at control step {kk}: non-finite state or action")

    def _run_lockstep(self, samples, K, offs, eps, x, s, a, x0, filtered, proc=(None, None)):
        """The rollouts ``samples`` of a filtered policy, all stepped together: one ``MjData`` per rollout,
        and per control step one call of the filter for all of them
        (:meth:`~soc_opt.noise.estimator.FilteredPolicy.estimate_rows`) instead of one per rollout.

        Each rollout's arithmetic is that of :meth:`_run_samples` (the same MuJoCo calls on its own data,
        the filter's rows bit for bit those of one rollout, the action ``K_k xhat_k`` as a stack of the
        same matrix-vector products), so the arrays are identical (tested).  On a divergence, or any error,
        the samples are simulated again one at a time, which raises what it raises there (the sample and
        step it names).
        """
        idx = np.asarray(samples, dtype=int)
        try:
            out = self._lockstep(idx, K, offs, eps, x0, filtered, proc)
        except Exception:  # noqa: BLE001 -- replayed one sample at a time below, which raises its own error
            out = None
        if out is None:
            return self._run_samples(samples, K, offs, eps, x, s, a, x0, filtered, proc)
        x[idx], s[idx], a[idx] = out

    def _lockstep(self, idx, K, offs, eps, x0, filtered, proc=(None, None)):
        """``(x, s, a)`` of the samples ``idx`` stepped together (:meth:`_run_lockstep`), or ``None`` on a
        divergence."""
        mj = import_mujoco()
        m = self.model
        B, T = idx.size, self.T
        datas = [mj.MjData(m) for _ in range(B)]
        reads = [self._reader(d) for d in datas]
        ctrls = [d.ctrl for d in datas]
        warns = [d.warning.number for d in datas]
        begin, finish = self._control_step()
        forward, bad = mj.mj_forward, self._bad_warn
        act = as_index(self.actuator_ids)
        xb, sb, ab = np.empty((B, T + 1, self.n)), np.empty((B, T + 1, self.n)), np.empty((B, T, self.m))
        eb, ob = eps[idx], offs[idx]
        Kc = K[:, None]  # (T, 1, m, n): K_k xhat_k for every row as a stack of matrix-vector products
        rows = list(zip(range(B), datas, reads, ctrls, warns))
        start, nu = proc
        for j, d in enumerate(datas):
            self.reset_start(d, x0, None if start is None else start[idx[j]])
        nub = None if nu is None else nu[idx]
        xhat = None
        for k in range(T):
            for j, d, read, _, _ in rows:
                begin(d)
                read(xb[j, k])
            sk = sb[:, k]
            np.add(xb[:, k], eb[:, k], out=sk)
            xhat = filtered.estimate_rows(k, sk) if k == 0 else filtered.estimate_rows(k, sk, xhat, ab[:, k - 1])
            ak = ab[:, k]
            np.add((Kc[k] @ xhat[:, :, None])[:, :, 0], ob[:, k], out=ak)
            for j, d, _, ctrl, warn in rows:
                ctrl[act] = ak[j] if nub is None else ak[j] + nub[j, k]
                finish(d)
                if warn.any():
                    try:
                        self._diverged(int(idx[j]), k, d, warn, bad)
                    except SimulationError:
                        return None
        for j, d, read, _, _ in rows:
            forward(m, d)
            read(xb[j, T])
        np.add(xb[:, T], eb[:, T], out=sb[:, T])
        if not (np.isfinite(xb).all() and np.isfinite(ab).all()):
            return None
        return xb, sb, ab

    def _diverged(self, i, k, d, warn, bad):
        mj = import_mujoco()
        names = [mj.mjtWarning(w).name for w in np.flatnonzero(warn) if w in bad]
        if not names:  # harmless warning (e.g. inertia): clear it and continue
            warn[:] = 0
            return
        raise SimulationError(
            f"sample {i} diverged at control step {k} (t = {k * self.dt:.3f} s): MuJoCo warning "
            f"{', '.join(names)} (NaN/inf or huge qpos/qvel/qacc/ctrl, or a full contact/constraint buffer)"
        )

    def rollouts(self, policy: LinearGaussianPolicy, M: int, rng, noise: bool = True, workers: int = 1, x0=None) -> Rollouts:
        """``M`` sampled trajectories (docs/math.md §0).

        Noise ``eps (M,T+1,n) ~ N(0, rho2 I)`` then ``w (M,T,m) ~ N(0, I)`` is drawn from
        ``rng`` up front, then ``[process_noise]``'s start offsets (added to the angles of
        ``state.joints`` at the start) and actuation noise (added to ``ctrl``, not to the recorded
        ``a``) when on (docs/math.md §8.1; ``noise=False``: none of them, the policy mean on the true
        state from the nominal start).
        ``workers > 1`` simulates contiguous blocks of samples in threads, one ``MjData``
        per sample (MuJoCo releases the GIL while stepping); results are identical for any ``workers``.
        A filtered policy's blocks run in one thread when no CPU is idle (:func:`soc_opt.parallel.spare_cpu`):
        its filter holds the GIL between the physics steps.  ``x0``: another initial state in task coordinates (its joint
        components are used, plus the start offsets; default ``self.x0``).  ``a`` records the policy's action
        before MuJoCo clamps it to ``ctrlrange``.  Raises :class:`SimulationError`
        naming the sample and step on divergence.  A :class:`~soc_opt.noise.estimator.FilteredPolicy`
        acts on ``xhat_k``, its filter run online on the measurements and the recorded actions
        (docs/math.md §10.2); the draws are the same as for a plain policy.  Its samples (of a block)
        are stepped in lockstep, the filter updating all of them in one call per control step
        (:meth:`_run_lockstep`); each sample's numbers are those of simulating it alone.
        """
        policy, filtered = self._check_policy(policy)
        rng = as_rng(rng)
        M = int(M)
        T, n, m = self.T, self.n, self.m
        proc = (None, None)
        if noise:
            draws = self.draw_noise(M, rng)
            eps, w = draws.eps, draws.w
            offs = policy.k[None] + np.einsum("tij,mtj->mti", policy.chol, w)
            proc = (draws.start, draws.actuation)
        else:
            eps = np.zeros((M, T + 1, n))
            offs = np.broadcast_to(policy.k, (M, T, m))
        K = np.ascontiguousarray(policy.K)
        x = np.empty((M, T + 1, n))
        s = np.empty((M, T + 1, n))
        a = np.empty((M, T, m))
        workers = max(1, min(int(workers), M))
        # a filtered policy's samples are stepped in lockstep (one call of its filter per step for all of them)
        run = self._run_samples if filtered is None else self._run_lockstep
        if filtered is not None and not parallel.spare_cpu():  # a second thread would only wait for the first's GIL
            workers = 1
        if workers == 1:
            run(range(M), K, offs, eps, x, s, a, x0, filtered, proc)
        else:
            blocks = [b for b in np.array_split(np.arange(M), workers) if b.size]
            with ThreadPoolExecutor(max_workers=workers) as ex:
                futs = [ex.submit(run, b.tolist(), K, offs, eps, x, s, a, x0, filtered, proc) for b in blocks]
                errors = []
                for f in futs:
                    try:
                        f.result()
                    except SimulationError as e:
                        errors.append(e)
                if errors:
                    raise errors[0]
        return self._finish(x, s, a)

    # -- deterministic step and linearisation
    def step(self, x, u) -> np.ndarray:
        """One noise-free control step from task state ``x (n,)`` with action ``u (m,)`` held for ``substeps``."""
        sim = self.simulator()
        sim.reset(x)
        return sim.step(u)

    def simulator(self) -> "MujocoSimulator":
        """A step-by-step simulator with its own ``MjData`` (what :class:`soc_opt.envs.SocOptEnv` steps)."""
        return MujocoSimulator(self)

    def check_linearizable(self) -> None:
        """Raise :class:`ConfigError` unless every degree of freedom of the model is in the state.

        Model-based iLQG (:meth:`linearize`) needs it; the message names the joints that are
        missing and where to add them (``state.extra_joints``), or says why they cannot be added.
        """
        if self._all_dofs_in_state:
            return
        mj = import_mujoco()
        m = self.model
        in_state = set(self.dof_adr.tolist())
        missing = [j for j in range(m.njnt) if any(
            dof not in in_state for dof in range(m.jnt_dofadr[j], m.jnt_dofadr[j] + _JOINT_DOFS[int(m.jnt_type[j])]))]
        names = [mj.mj_id2name(m, mj.mjtObj.mjOBJ_JOINT, j) or f"<joint {j}>" for j in missing]
        unsupported = [nm for nm, j in zip(names, missing)
                       if int(m.jnt_type[j]) not in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE))]
        msg = (f"task {self.name!r}: model-based iLQG needs every degree of freedom of model {self.source} "
               f"in the state; joints not in it: {', '.join(map(repr, names))}")
        if unsupported:
            raise ConfigError(msg + f"; {', '.join(map(repr, unsupported))} {'is a' if len(unsupported) == 1 else 'are'}"
                              " free/ball joint(s), which the state cannot hold, so iLQG cannot run on this model")
        raise ConfigError(msg + f"; add them to state.extra_joints in the task TOML, e.g. "
                          f"extra_joints = [{', '.join(repr(n) for n in names)}]".replace("'", '"'))

    def linearize(self, x, u, cov=0.0, eps: float = 1e-6) -> LinearGaussianDynamics:
        """Local linear model in task coordinates (:func:`soc_opt.tasks.linearize.linearize`)."""
        return _linearize.linearize(self, x, u, cov, eps)

    def _output_jacobian(self, d) -> np.ndarray:
        """``H = d s / d (dq, dv)`` (:func:`soc_opt.tasks.linearize.output_jacobian`)."""
        return _linearize.output_jacobian(self, d)

    def ee_points(self, x) -> np.ndarray:
        """``(..., P, 3)`` positions of the state points (for figures)."""
        x = np.asarray(x, dtype=float)
        return x[..., self.layout["site_pos"]].reshape(x.shape[:-1] + (len(self.point_refs), 3))


class MujocoSimulator:
    """One trajectory of a :class:`MujocoTask`, one control step at a time, in its own ``MjData``.

    The physics calls are those of :meth:`MujocoTask.rollouts` for one sample (positions and
    velocities computed, state read, ``ctrl`` held for ``substeps`` steps), so an episode
    with the same actions reproduces a rollout's true states.  ``data``: the ``MjData``
    (e.g. for rendering); ``x``: the current true state ``(n,)``; ``k``: control steps taken.
    """

    def __init__(self, task: MujocoTask):
        mj = import_mujoco()
        self.task = task
        self.data = mj.MjData(task.model)
        self.read_state = task._reader(self.data)
        self.actuator_ids = as_index(task.actuator_ids)
        self.x = np.empty(task.n)
        self.k = 0
        self.reset()

    def reset(self, x0=None, start=None) -> np.ndarray:
        """Back to ``x0`` (task coordinates; default the task's ``x_0``) with the start offsets ``start``
        (``(nj,)``, :meth:`MujocoTask.reset_start`); returns a copy of the state."""
        mj = import_mujoco()
        self.task.reset_start(self.data, x0, start)
        mj.mj_forward(self.task.model, self.data)
        self.read_state(self.x)
        self.k = 0
        return self.x.copy()

    def step(self, u, xi=None, actuation=None) -> np.ndarray:
        """Hold ``u (m,)`` (plus the actuation noise ``actuation (m,)``, docs/math.md §8.1) as ``ctrl`` for
        ``substeps`` physics steps; returns a copy of the new state.

        Raises :class:`SimulationError` on a divergence warning or a non-finite state.
        """
        if xi is not None:
            raise ValueError(f"task {self.task.name!r}: MuJoCo tasks have no transition noise xi (it must be None; "
                             "[process_noise] actuation is passed as actuation)")
        mj = import_mujoco()
        task, d = self.task, self.data
        d.ctrl[self.actuator_ids] = u if actuation is None else np.asarray(u, dtype=float) + actuation
        mj.mj_step(task.model, d, task.substeps)
        warn = d.warning.number
        if warn.any():
            task._diverged(0, self.k, d, warn, task._bad_warn)
        mj.mj_forward(task.model, d)
        self.read_state(self.x)
        self.k += 1
        if not np.isfinite(self.x).all():
            raise SimulationError(f"task {task.name!r} diverged at control step {self.k - 1}: non-finite state")
        return self.x.copy()
