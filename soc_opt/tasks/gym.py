"""Gymnasium MuJoCo environments as tasks: ``gym:<EnvId>`` (docs/math.md §8 "any MuJoCo model"; docs/gym.md).

A :class:`GymMujocoTask` is a :class:`MujocoTask` built on the environment's own
``env.unwrapped.model``: rollouts and the finite-difference linearisation are the MuJoCo
task's, with the environment's ``frame_skip`` as ``substeps``.

* State: ``(qpos, qvel)`` of every joint (hinge and slide joints only, so ``nq = nv``), plus
  the positions and velocities of any ``state.sites`` the task TOML adds.
* Actions: every actuator, in the model's order (the environment's action vector).
* Initial state ``x_0``: the environment's state after ``env.reset(seed=gym.reset_seed +
  condition)``, positions *and* velocities; fixed for the run (measurement noise ``rho2``
  is the only initial randomness, docs/math.md §0, unless ``[process_noise] start`` offsets the
  joint angles, §8.1).
* Cost: ``l(s_k, a_k) = -r(s_k, a_k)``, the environment's reward for taking ``a_k`` in state
  ``s_k`` (:class:`EnvReward`: reset the data, ``set_state``, ``env.unwrapped.step``), so it
  needs no reimplementation of any reward.  Its quadratic expansion (:class:`RewardCost`)
  is by central finite differences, ``1 + N + N^2`` reward evaluations per time step for
  ``N = n + m``.  ``cost`` terms in the task TOML replace the reward (the reward is then only
  reported, as the ``return`` metric).
* Termination of the environment is ignored: the horizon is ``T`` (default: the environment's
  ``max_episode_steps``, at most 100).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ..config import ConfigError, shorten, show
from ..costs import CostSum, Derivatives
from ..models import LinearGaussianDynamics, Rollouts, ShapeError, check_array
from .base import SimulationError
from .config import GYM_PREFIX, StateConfig, TaskConfig
from .mjcf import check_model
from .mujoco import MujocoTask, import_mujoco

__all__ = ["GYM_PREFIX", "DEFAULT_T", "DEFAULT_RHO2", "GymMujocoTask", "EnvReward", "RewardCost", "make_gym_env", "load_gym_task",
           "check_gym_import"]

#: Horizon of a ``gym:<EnvId>`` task without ``T``: the environment's ``max_episode_steps``, capped here.
DEFAULT_T = 100
#: Measurement noise of a ``gym:`` task without ``rho2``: Gymnasium observes exact states, so
#: the default is small (the paper's ``rho2 = 0.1`` is for its own tasks; set it to study noise).
DEFAULT_RHO2 = 1e-3


def make_gym_env(env_id: str, kwargs: dict | None = None, *, modules: tuple[str, ...] = ()):
    """``gymnasium.make(env_id, **kwargs)``, checked to be a MuJoCo environment.

    ``env_id`` of the form ``<module>:<EnvId>`` makes Gymnasium import ``<module>`` first, which runs its
    code: allowed only when ``<module>`` is in ``modules`` (what the caller asked for itself: a task named on
    the command line, or ``--gym-module``; an id from a task or sweep file must be registered, docs/gym.md).
    A ``gym.kwargs.xml_file`` is resolved as Gymnasium does and checked, with every file it references,
    before Gymnasium opens it (:func:`soc_opt.tasks.mjcf.check_model`).

    Raises :class:`ConfigError` naming ``env_id`` if Gymnasium (or its MuJoCo extra) is not
    installed, the id is unknown, or the environment has no MuJoCo ``model``/``data``.
    """
    name = GYM_PREFIX + env_id
    try:
        import gymnasium
    except ImportError as e:  # pragma: no cover - gymnasium is a dependency
        raise ConfigError(f"{name}: gymnasium is not installed (pip install 'gymnasium[mujoco]')") from e
    if not env_id:
        raise ConfigError(f"{name!r}: no environment id after {GYM_PREFIX!r} (e.g. gym:InvertedPendulum-v5)")
    check_gym_import(name, modules)
    kwargs = dict(kwargs or {})
    if "render_mode" in kwargs:  # checked before the environment exists: a window must never open
        raise ConfigError("gym.kwargs: 'render_mode' is not allowed (soc_opt renders with render_filmstrip)")
    if isinstance(kwargs.get("xml_file"), str):  # Gymnasium opens it (and MuJoCo its includes) unchecked
        _check_xml_file(kwargs["xml_file"])
    try:
        env = gymnasium.make(env_id, **kwargs)
    except gymnasium.error.DependencyNotInstalled as e:
        raise ConfigError(f"{name}: {e} (install the extra: pip install 'gymnasium[mujoco]')") from e
    except gymnasium.error.Error as e:
        raise ConfigError(f"{name}: unknown Gymnasium environment id {env_id!r} ({e})") from e
    except (TypeError, ValueError, ModuleNotFoundError) as e:
        raise ConfigError(f"{name}: gymnasium.make with gym.kwargs = {show(kwargs)} failed: {type(e).__name__}: "
                          f"{shorten(str(e))}") from e
    mj = import_mujoco()
    u = env.unwrapped
    if not (isinstance(getattr(u, "model", None), mj.MjModel) and isinstance(getattr(u, "data", None), mj.MjData)
            and hasattr(u, "set_state") and hasattr(u, "frame_skip")):
        env.close()
        raise ConfigError(
            f"{name}: {type(u).__name__} is not a Gymnasium MuJoCo environment (no MjModel/MjData at "
            f"env.unwrapped.model/data); gym: tasks need one, e.g. gym:InvertedDoublePendulum-v5"
        )
    if kwargs:
        try:
            _probe(env)
        except Exception as e:  # noqa: BLE001 - any failure of a step is the kwargs' fault here
            env.close()
            raise ConfigError(f"{name}: {_bad_kwarg(env_id, kwargs)} is rejected by the environment "
                              f"(reset and one step): {type(e).__name__}: {e}") from e
    return env


def check_gym_import(model: str, modules: tuple[str, ...] = ()) -> None:
    """:class:`ConfigError` when ``model = "gym:<module>:<EnvId>"`` names a module outside ``modules``: Gymnasium
    would import it, running its code, and only the command line may ask for that (docs/gym.md)."""
    env_id = model[len(GYM_PREFIX):] if model.startswith(GYM_PREFIX) else model
    module = env_id.partition(":")[0] if ":" in env_id else None
    if module is not None and module not in modules:
        raise ConfigError(f"{shorten(model)}: would import the Python module {shorten(module)!r}, which runs its code; "
                          "a task or sweep file may name only registered environment ids. To import it, name it on "
                          f"the command line: --gym-module {shorten(module)} (docs/gym.md)")


def _check_xml_file(xml_file: str) -> None:
    """The model file ``gym.kwargs.xml_file`` names, found as Gymnasium finds it (a path starting with ``/``,
    ``.`` or ``~``, else a file of its MuJoCo assets), checked with what it references."""
    from gymnasium.envs.mujoco import mujoco_env

    if xml_file.startswith(("/", ".", "~")):
        path = os.path.expanduser(xml_file)
    else:
        path = os.path.join(os.path.dirname(mujoco_env.__file__), "assets", xml_file)
    if not os.path.lexists(path):
        raise ConfigError(f"gym.kwargs.xml_file: {str(path)!r} does not exist")
    try:
        check_model(path)
    except ConfigError as e:
        raise ConfigError(f"gym.kwargs.xml_file: {e}") from None


def _probe(env) -> None:
    """Reset ``env`` and take one zero-action step (a run reseeds it; nothing carries over)."""
    env.reset(seed=0)
    env.step(np.zeros(env.action_space.shape, dtype=env.action_space.dtype))


def _bad_kwarg(env_id: str, kwargs: dict) -> str:
    """``gym.kwargs.<key> = <value>`` of the first keyword argument that fails alone, else all of them."""
    import gymnasium

    for key, value in kwargs.items():
        try:
            env = gymnasium.make(env_id, **{key: value})
        except Exception:  # noqa: BLE001
            return f"gym.kwargs.{key} = {value!r}"
        try:
            _probe(env)
        except Exception:  # noqa: BLE001
            return f"gym.kwargs.{key} = {value!r}"
        finally:
            env.close()
    return f"gym.kwargs = {kwargs!r}"


class EnvReward:
    """The environment's reward ``r(x, a)`` for action ``a (m,)`` in task state ``x (n,)``.

    Resets the environment's ``MjData`` (so no solver warm start carries over between
    evaluations), sets ``(qpos, qvel)`` from ``x`` and calls ``env.unwrapped.step(a)``.
    """

    def __init__(self, env, task: "GymMujocoTask"):
        self.u = env.unwrapped
        self.qadr, self.sq = task.qpos_adr, task.state_qpos_idx
        self.dadr, self.sqd = task.dof_adr, task.state_qvel_idx
        self.nq, self.nv = task.model.nq, task.model.nv
        self.name = task.name
        self.evaluations = 0

    def __call__(self, x, a) -> float:
        mj = import_mujoco()
        u = self.u
        qpos = np.empty(self.nq)
        qvel = np.empty(self.nv)
        qpos[self.qadr] = x[self.sq]
        qvel[self.dadr] = x[self.sqd]
        mj.mj_resetData(u.model, u.data)
        u.set_state(qpos, qvel)
        r = u.step(np.array(a, dtype=float))[1]
        self.evaluations += 1
        r = float(r)
        if not np.isfinite(r):
            raise SimulationError(f"{self.name}: non-finite reward {r} at state {x} and action {a}")
        return r


class RewardCost(CostSum):
    """Stage cost ``l(s, a) = -r(s, a)`` of a Gymnasium environment, a :class:`CostSum` without terms.

    ``__call__`` evaluates the reward at every ``(s_k, a_k)``; :meth:`derivatives` expands it
    by central differences with steps ``h_i = fd_step * max(1, |z_i|)`` on ``z = (s_k, a_k)``:
    ``g_i = (f(+i) - f(-i)) / 2h_i``, ``H_ii = (f(+i) - 2 f + f(-i)) / h_i^2`` and
    ``H_ij = (f(+i+j) + f(-i-j) - f(+i) - f(-i) - f(+j) - f(-j) + 2 f) / (2 h_i h_j)`` (all
    second-order accurate).  :meth:`CostSum.expand` turns them into the absolute quadratic
    form (docs/math.md §6).
    """

    name = "reward"

    def __init__(self, reward: EnvReward, n: int, m: int, fd_step: float):
        super().__init__([], n, m)
        self.reward = reward
        self.fd_step = float(fd_step)
        self._last = None  # (s, a, value) of the last call on read-only arrays (Rollouts)

    def __call__(self, s, a) -> np.ndarray:
        """``-r`` at every stage: ``s (..., T+1 or T, n)``, ``a (..., T, m)`` -> ``(..., T)``."""
        last = self._last
        if last is not None and last[0] is s and last[1] is a:
            return last[2].copy()
        S = np.asarray(s, dtype=float)
        A = np.asarray(a, dtype=float)
        T = A.shape[-2] if A.ndim >= 2 else -1
        if A.ndim < 2 or A.shape[-1] != self.m or S.shape[-1] != self.n or S.shape[-2] not in (T, T + 1) \
                or S.shape[:-2] != A.shape[:-2]:
            raise ShapeError(f"reward cost: need s (..., T+1, {self.n}) and a (..., T, {self.m}), got {S.shape}, {A.shape}")
        Sf = S[..., :T, :].reshape(-1, self.n)
        Af = A.reshape(-1, self.m)
        out = np.array([-self.reward(x, u) for x, u in zip(Sf, Af)]).reshape(A.shape[:-1])
        if isinstance(s, np.ndarray) and isinstance(a, np.ndarray) and not s.flags.writeable and not a.flags.writeable:
            self._last = (s, a, out.copy())
        return out

    def stage(self, s_k, a_k, k: int, T: int) -> float:
        """``-r(s_k, a_k)``: one stage, one reward evaluation (equal to ``self(s, a)[..., k]``)."""
        s_k = np.asarray(s_k, dtype=float)
        a_k = np.asarray(a_k, dtype=float)
        if s_k.shape != (self.n,) or a_k.shape != (self.m,) or not 0 <= k < T:
            raise ShapeError(f"reward cost: one stage needs s_k ({self.n},), a_k ({self.m},) and 0 <= k < {T}, "
                             f"got {s_k.shape}, {a_k.shape}, k = {k}")
        return float(-self.reward(s_k, a_k))

    def derivatives(self, s, a) -> Derivatives:
        """``-r`` and its finite-difference derivatives along ``s (T+1 or T, n)``, ``a (T, m)``."""
        a = np.asarray(a, dtype=float)
        s = np.asarray(s, dtype=float)
        if a.ndim != 2 or a.shape[1] != self.m or s.ndim != 2 or s.shape[1] != self.n or s.shape[0] not in (len(a), len(a) + 1):
            raise ShapeError(f"reward cost: need s (T+1, {self.n}) and a (T, {self.m}), got {s.shape}, {a.shape}")
        T, n = len(a), self.n
        out = Derivatives(np.zeros(T), np.zeros((T, n)), np.zeros((T, self.m)), np.zeros((T, n, n)),
                          np.zeros((T, self.m, self.m)), np.zeros((T, self.m, n)))
        for k in range(T):
            f0, g, H = self._expand_one(np.concatenate([s[k], a[k]]))
            out.l[k] = f0
            out.lx[k], out.lu[k] = g[:n], g[n:]
            out.lxx[k], out.luu[k], out.lux[k] = H[:n, :n], H[n:, n:], H[n:, :n]
        return out

    def _expand_one(self, z):
        n, N = self.n, self.n + self.m
        h = self.fd_step * np.maximum(1.0, np.abs(z))

        def f(dz):
            zz = z + dz
            return -self.reward(zz[:n], zz[n:])

        E = np.diag(h)
        f0 = f(np.zeros(N))
        fp = np.array([f(E[i]) for i in range(N)])
        fm = np.array([f(-E[i]) for i in range(N)])
        g = (fp - fm) / (2 * h)
        H = np.diag((fp - 2 * f0 + fm) / h**2)
        for i in range(N):
            for j in range(i + 1, N):
                fpp = f(E[i] + E[j])
                fmm = f(-E[i] - E[j])
                H[i, j] = H[j, i] = (fpp + fmm - fp[i] - fm[i] - fp[j] - fm[j] + 2 * f0) / (2 * h[i] * h[j])
        return f0, g, H


class GymMujocoTask(MujocoTask):
    """A Gymnasium MuJoCo environment as a task (module docstring; ``kind = "gym"``).

    env:    the ``gymnasium.Env`` (from :func:`make_gym_env`); the task uses and keeps it.
    config: a :class:`TaskConfig` with ``model = "gym:<EnvId>"``.
    """

    kind = "gym"

    def __init__(self, config: TaskConfig, env, *, condition: int = 0):
        mj = import_mujoco()
        env_id = config.model[len(GYM_PREFIX):]
        name = config.model
        bad = [k for k, ok in (("q0", not config.q0), ("offsets", not config.offsets), ("actuated", not config.actuated),
                               ("timestep", config.timestep is None), ("substeps", config.substeps == 1),
                               ("state.joints", not config.state.joints), ("state.extra_joints", not config.state.extra_joints))
               if not ok]
        if bad:
            raise ConfigError(
                f"{name}: {bad[0]!r} cannot be set for a gym: task (every joint is in the state, every actuator "
                f"is actuated, the initial state comes from env.reset and substeps from the env's frame_skip)"
            )
        u = env.unwrapped
        model = u.model
        joints = []
        for j in range(model.njnt):
            jt = int(model.jnt_type[j])
            jname = model.joint(j).name
            if jt not in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)):
                kind = mj.mjtJoint(jt).name.removeprefix("mjJNT_").lower()
                raise ConfigError(f"{name}: joint {jname or j!r} is a {kind} joint; gym: tasks support hinge and slide joints only")
            if not jname:
                raise ConfigError(f"{name}: joint {j} has no name; gym: tasks need named joints")
            joints.append(jname)
        self.env = env
        self.env_id = env_id
        seed = config.gym.reset_seed + condition
        env.reset(seed=seed)
        qpos, qvel = u.data.qpos.copy(), u.data.qvel.copy()
        self._qvel_init = qvel
        config = dataclasses.replace(
            config,
            state=StateConfig(joints=tuple(joints), sites=config.state.sites),
            q0=tuple(float(qpos[model.jnt_qposadr[j]]) for j in range(model.njnt)),
            substeps=int(u.frame_skip),
        )
        super().__init__(config, model, condition=0, source=name)
        self.condition = condition
        self.reset_seed = seed
        parents = set(int(p) for p in model.body_parentid[1:])
        self._leaves = np.array([b for b in range(1, model.nbody) if b not in parents], dtype=int)
        self.ee_bodies = [model.body(int(b)).name for b in self._leaves]
        self._kin_data = mj.MjData(model)
        self.reward = EnvReward(env, self)
        self.reward_is_cost = not config.cost
        if self.reward_is_cost:
            self._cost = RewardCost(self.reward, self.n, self.m, config.gym.fd_step)

    def linearize(self, x, u, cov=0.0, eps: float = 1e-6) -> LinearGaussianDynamics:
        """:meth:`MujocoTask.linearize`; for RK4 models (which ``mjd_transitionFD`` does not
        support: most Gymnasium environments) central differences of whole control steps.

        RK4: ``A_k[:, i] = (f(x_k + eps e_i, u_k) - f(x_k - eps e_i, u_k)) / 2 eps`` over the joint
        coordinates of the state (site components are functions of them: zero columns), the same
        for ``B_k``, and ``c_k = f(x_k, u_k) - A_k x_k - B_k u_k``; ``f`` is :meth:`soc_opt.tasks.mujoco.MujocoTask.step`.
        """
        mj = import_mujoco()
        if int(self.model.opt.integrator) != int(mj.mjtIntegrator.mjINT_RK4):
            return super().linearize(x, u, cov=cov, eps=eps)
        T, n, m = self.T, self.n, self.m
        x = check_array("linearize x", x, (None, n))
        u = check_array("linearize u", u, (None, m))
        if x.shape[0] not in (T, T + 1) or u.shape[0] != T:
            raise ShapeError(f"linearize needs x ({T + 1}, {n}) and u ({T}, {m}), got {x.shape}, {u.shape}")
        sim = self.simulator()

        def f(xk, uk):
            sim.reset(xk)
            return sim.step(uk)

        cols = np.concatenate([self.state_qpos_idx, self.state_qvel_idx])
        A, B, c = np.zeros((T, n, n)), np.zeros((T, n, m)), np.zeros((T, n))
        for k in range(T):
            for i in cols:
                e = np.zeros(n)
                e[i] = eps
                A[k][:, i] = (f(x[k] + e, u[k]) - f(x[k] - e, u[k])) / (2 * eps)
            for j in range(m):
                e = np.zeros(m)
                e[j] = eps
                B[k][:, j] = (f(x[k], u[k] + e) - f(x[k], u[k] - e)) / (2 * eps)
            c[k] = f(x[k], u[k]) - A[k] @ x[k] - B[k] @ u[k]
        W = np.asarray(cov, dtype=float)
        W = W * np.eye(n) if W.ndim == 0 else W
        return LinearGaussianDynamics(A, B, c, np.broadcast_to(W, (T, n, n)).copy())

    def ee_points(self, x) -> np.ndarray:
        """``(..., P, 3)`` points for figures: the state sites, or else the positions of the leaf
        bodies of the kinematic tree (:attr:`ee_bodies`, e.g. a pendulum's pole, a cheetah's feet)."""
        if self.point_refs:  # the state points (sites or bodies)
            return super().ee_points(x)
        mj = import_mujoco()
        x = np.asarray(x, dtype=float)
        flat = x.reshape(-1, self.n)
        d = self._kin_data
        out = np.empty((len(flat), len(self._leaves), 3))
        for i, xi in enumerate(flat):
            d.qpos[self.qpos_adr] = xi[self.state_qpos_idx]
            mj.mj_kinematics(self.model, d)
            out[i] = d.xpos[self._leaves]
        return out.reshape(x.shape[:-1] + (len(self._leaves), 3))

    def reset_data(self, d, x0):
        super().reset_data(d, x0)
        if x0 is None:
            d.qvel[:] = self._qvel_init

    def per_sample_metrics(self, rollouts: Rollouts) -> dict[str, np.ndarray]:
        """The task metrics plus ``return``: the environment's summed reward on the true states."""
        out = super().per_sample_metrics(rollouts)
        if self.reward_is_cost:
            out["return"] = -out["cost"]
        else:
            x, a = rollouts.x, rollouts.a
            out["return"] = np.array([sum(self.reward(x[i, k], a[i, k]) for k in range(a.shape[1])) for i in range(len(a))])
        return out


def load_gym_task(data: dict, *, condition: int = 0, modules: tuple[str, ...] = ()) -> GymMujocoTask:
    """A :class:`GymMujocoTask` from a task table with ``model = "gym:<EnvId>"`` (``modules``: the Python
    modules a ``gym:<module>:<EnvId>`` may import, :func:`make_gym_env`).

    Missing ``name`` defaults to the model string, missing ``T`` to the environment's
    ``max_episode_steps`` capped at :data:`DEFAULT_T`, missing ``rho2`` to :data:`DEFAULT_RHO2`.
    """
    data = dict(data)
    model = data.get("model", "")
    env_id = model[len(GYM_PREFIX):]
    gym_table = data.get("gym", {})
    kwargs = gym_table.get("kwargs", {}) if isinstance(gym_table, dict) else {}
    if not isinstance(kwargs, dict):
        raise ConfigError(f"{model}: gym.kwargs must be a table")
    env = make_gym_env(env_id, kwargs, modules=modules)
    try:
        data.setdefault("name", model)
        data.setdefault("rho2", DEFAULT_RHO2)
        if "T" not in data:
            steps = env.spec.max_episode_steps if env.spec is not None else None
            data["T"] = min(DEFAULT_T, steps or DEFAULT_T)
        if data.get("kind", "mujoco") != "mujoco":
            raise ConfigError(f"{model}: kind must be 'mujoco' (the default) for a gym: model, got {data['kind']!r}")
        return GymMujocoTask(TaskConfig.from_dict(data), env, condition=condition)
    except Exception:
        env.close()
        raise
