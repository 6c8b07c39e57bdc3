"""soc_opt tasks as Gymnasium environments (docs/math.md §0, §8; ``docs/gym.md``).

Importing this module registers, in Gymnasium's registry:

============================  =====================================================
``soc_opt/Linear2d-v0``       the built-in ``linear2d`` task
``soc_opt/Peg-v0``            the built-in ``peg`` task
``soc_opt/Door-v0``           the built-in ``door`` task
``soc_opt/Task-v0``           any task: ``gymnasium.make("soc_opt/Task-v0", task="my.toml")``
============================  =====================================================

Gymnasium 1.x has no plugin mechanism (the ``gymnasium.envs`` entry-point group of
gym/gymnasium 0.x was removed), so import this module first, or let ``gymnasium.make``
import it: ``gymnasium.make("soc_opt.envs:soc_opt/Peg-v0")``.

One episode of :class:`SocOptEnv` is one sample of :meth:`Task.rollouts` driven by the
agent's actions instead of a linear-Gaussian policy:

* ``reset(seed=s)`` draws the episode's noise from ``self.np_random`` with
  :meth:`Task.draw_noise` (``M = 1``: ``eps``, then ``w`` -- unused, the agent acts --, then
  the process noise of linear tasks, then the start offset and the actuation noise of the task's
  ``[process_noise]`` when on), exactly as ``task.rollouts(policy, 1, np.random.default_rng(s))``
  does; the episode starts at the offset start and each step's control gets its actuation noise
  (docs/math.md §8.1), the agent's action being recorded as it gave it;
* the observation is the *measured* state ``s_k = x_k + eps_k`` (docs/math.md §0; ``rho2`` as
  configured by the task), ``float64 (n,)``;
* ``step(a_k)`` advances the task's own simulator (:meth:`LinearTask.simulator`,
  :meth:`MujocoTask.simulator`) by one control step; the reward is ``-Y_k``, the task's
  stage cost of ``(s_k, a_k)`` alone (:meth:`Task.stage_cost`: O(1) per step, bit for bit the
  ``k``-th entry of :meth:`Task.cost` on the whole episode);
* ``terminated`` is always false; ``truncated`` is true after ``T`` steps (stepping further
  raises);
* ``info``: ``true_state`` (``x_k``), ``step`` (``k``) and, from ``step``, ``stage_cost``;
  at truncation also ``metrics`` (:meth:`Task.metrics` of the episode, e.g. ``min_distance``)
  and ``episode`` (the episode's ``x``, ``s``, ``a``, ``cost`` arrays).

Rendering (``render_mode="rgb_array"``): MuJoCo tasks are rendered in-process with
``mujoco.Renderer`` (set ``MUJOCO_GL=egl`` or ``osmesa`` without a display, before
Python starts); if no OpenGL context can be made, and for linear tasks, the frame is a
matplotlib plot of the task's points (``Task.ee_points``) so far.
"""

from __future__ import annotations

import os
import sys

import gymnasium
import numpy as np
from gymnasium import spaces

from .config import ConfigError
from .models import Rollouts
from .tasks import LinearTask, MujocoTask, load_task

__all__ = ["ENV_IDS", "SocOptEnv", "register_envs", "make"]

#: Registered environment ids and the built-in task each one loads (``None``: pass ``task=``).
ENV_IDS: dict[str, str | None] = {
    "soc_opt/Linear2d-v0": "linear2d",
    "soc_opt/Peg-v0": "peg",
    "soc_opt/Door-v0": "door",
    "soc_opt/Task-v0": None,
}


#: Why in-process MuJoCo rendering failed in this process (``None``: not failed yet).  After a
#: failed OpenGL context creation MuJoCo aborts the process on the next attempt, so a failure
#: is remembered process-wide and every later frame is a matplotlib plot.
_GL_FAILURE: str | None = None


def _gl_configured() -> bool:
    """Whether an OpenGL context can plausibly be made: ``MUJOCO_GL`` = egl/osmesa, or a display."""
    gl = os.environ.get("MUJOCO_GL", "").strip().lower()
    if gl in ("egl", "osmesa"):
        return True
    if gl in ("", "glfw", "glx", "enable", "enabled", "on", "true", "1"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("darwin", "win32")
    return False


def _action_space(task) -> spaces.Box:
    """``Box (m,)``: the actuators' ``ctrlrange`` where ``ctrllimited``, unbounded otherwise."""
    low = np.full(task.m, -np.inf)
    high = np.full(task.m, np.inf)
    if isinstance(task, MujocoTask):
        model = task.model
        for j, i in enumerate(task.actuator_ids):
            if bool(model.actuator_ctrllimited[i]):
                low[j], high[j] = model.actuator_ctrlrange[i]
    return spaces.Box(low, high, (task.m,), np.float64)


class SocOptEnv(gymnasium.Env):
    """A soc_opt task as a ``gymnasium.Env`` (semantics in the module docstring).

    task:        a built-in task name, a task TOML path, or a task object (``LinearTask``
                 or ``MujocoTask``).
    render_mode: ``None`` or ``"rgb_array"``.
    condition:   initial-state condition of the task (``offsets`` in its TOML).
    overrides:   top-level task keys replacing the file's values (e.g. ``{"T": 20}``).
    width, height: frame size of ``render()``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task=None, render_mode: str | None = None, *, condition: int = 0,
                 overrides: dict | None = None, width: int = 320, height: int = 240):
        if task is None:
            raise ConfigError(
                "soc_opt env: no task given; use gymnasium.make('soc_opt/Task-v0', task=<built-in name or TOML path>)"
            )
        if isinstance(task, (str, bytes)) or hasattr(task, "__fspath__"):
            task = load_task(task, condition=condition, overrides=overrides)
        elif overrides:
            raise ConfigError("soc_opt env: 'overrides' needs a task name or path, not a task object")
        if not isinstance(task, (LinearTask, MujocoTask)) or not hasattr(task, "simulator"):
            raise ConfigError(f"soc_opt env: unsupported task object {type(task).__name__}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ConfigError(f"soc_opt env: render_mode {render_mode!r} is not one of {self.metadata['render_modes']}")
        self.task = task
        self.render_mode = render_mode
        self.width, self.height = int(width), int(height)
        self.metadata = {**type(self).metadata, "render_fps": max(1, int(round(1.0 / task.dt)))}
        self.observation_space = spaces.Box(-np.inf, np.inf, (task.n,), np.float64)
        self.action_space = _action_space(task)
        self._sim = task.simulator()
        self._renderer = None
        self.render_backend: str | None = None  # "mujoco" or "matplotlib" once render() ran
        self._k = None  # None: reset() not called yet

    # -- episode
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode at the task's ``x_0`` with fresh noise from ``self.np_random``.

        ``options``: ``{"x0": array (n,)}`` starts from another true state (plus the start offset of
        ``[process_noise] start``, as ``Task.rollouts(..., x0=)``).
        """
        super().reset(seed=seed)
        task = self.task
        T, n, m = task.T, task.n, task.m
        noise = task.draw_noise(1, self.np_random)
        self._eps = noise.eps[0]
        self._xi = None if noise.xi is None else noise.xi[0]
        self._nu = None if noise.actuation is None else noise.actuation[0]
        x0 = None
        if options:
            unknown = sorted(set(options) - {"x0"})
            if unknown:
                raise ConfigError(f"soc_opt env reset: unknown option(s) {unknown}; allowed: ['x0']")
            x0 = options.get("x0")
        self._x = np.zeros((1, T + 1, n))
        self._s = np.zeros((1, T + 1, n))
        self._a = np.zeros((1, T, m))
        self._x[0, 0] = self._sim.reset(x0, None if noise.start is None else noise.start[0])
        self._s[0, 0] = self._x[0, 0] + self._eps[0]
        self._k = 0
        return self._s[0, 0].copy(), {"true_state": self._x[0, 0].copy(), "step": 0}

    def step(self, action):
        k = self._k
        task = self.task
        if k is None:
            raise RuntimeError("soc_opt env: call reset() before step()")
        if k >= task.T:
            raise RuntimeError(f"soc_opt env: the episode ended after T = {task.T} steps; call reset()")
        a = np.asarray(action, dtype=float)
        if a.shape != (task.m,):
            raise ValueError(f"soc_opt env: action must have shape ({task.m},), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"soc_opt env: action {a} is not finite")
        self._a[0, k] = a
        xi = None if self._xi is None else self._xi[k]
        self._x[0, k + 1] = self._sim.step(a, xi, None if self._nu is None else self._nu[k])
        self._s[0, k + 1] = self._x[0, k + 1] + self._eps[k + 1]
        stage = task.stage_cost(self._s[0, k], self._a[0, k], k)  # O(1); = task.cost(s, a)[0, k] bit for bit
        self._k = k + 1
        truncated = self._k == task.T
        info = {"true_state": self._x[0, k + 1].copy(), "step": self._k, "stage_cost": stage}
        if truncated:
            ep = self.episode()
            info["metrics"] = task.metrics(ep)
            info["episode"] = {"x": ep.x[0].copy(), "s": ep.s[0].copy(), "a": ep.a[0].copy(), "cost": ep.cost[0].copy()}
        return self._s[0, k + 1].copy(), -stage, False, truncated, info

    def episode(self) -> Rollouts:
        """The finished episode as a one-sample :class:`Rollouts` (``x``, ``s``, ``a``, stage costs)."""
        if self._k != self.task.T:
            raise RuntimeError(f"soc_opt env: the episode is not finished ({self._k} of {self.task.T} steps)")
        return self.task._finish(self._x.copy(), self._s.copy(), self._a.copy())

    # -- rendering
    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn("soc_opt env: render() called without render_mode; make the env with render_mode='rgb_array'")
            return None
        if isinstance(self.task, MujocoTask):
            frame = self._render_mujoco()
            if frame is not None:
                return frame
        return self._render_points()

    def _render_mujoco(self):
        global _GL_FAILURE
        if _GL_FAILURE is None and not _gl_configured():
            _GL_FAILURE = "no MUJOCO_GL backend (egl/osmesa) set and no display"
        if _GL_FAILURE is not None:
            if self.render_backend is None:
                gymnasium.logger.warn(f"soc_opt env: MuJoCo rendering unavailable ({_GL_FAILURE}); rendering a "
                                      "matplotlib plot instead (start Python with MUJOCO_GL=egl or osmesa)")
            return None
        import mujoco

        model = self.task.model
        try:
            if self._renderer is None:
                w = min(self.width, int(model.vis.global_.offwidth))
                h = min(self.height, int(model.vis.global_.offheight))
                self._renderer = mujoco.Renderer(model, h, w)
            cam = self.task.config.camera
            self._renderer.update_scene(self._sim.data, camera=cam if cam is not None else -1)
            frame = np.array(self._renderer.render(), dtype=np.uint8)
        except Exception as e:  # no OpenGL context: never try again in this process (a retry aborts it)
            _GL_FAILURE = f"{type(e).__name__}: {e}"
            gymnasium.logger.warn(f"soc_opt env: MuJoCo rendering unavailable ({_GL_FAILURE}); rendering a "
                                  "matplotlib plot instead (start Python with MUJOCO_GL=egl or osmesa)")
            self._renderer = None
            return None
        self.render_backend = "mujoco"
        return frame

    def _render_points(self) -> np.ndarray:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.render_backend = "matplotlib"
        k = 0 if self._k is None else self._k
        pts = self.task.ee_points(self._x[0, : k + 1]) if self._k is not None else self.task.ee_points(self.task.x0[None])
        fig = Figure(figsize=(self.width / 100, self.height / 100), dpi=100)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        for p in range(pts.shape[1]):
            ax.plot(pts[:, p, 0], pts[:, p, 1], color=f"C{p}", lw=1)
            ax.scatter(pts[-1:, p, 0], pts[-1:, p, 1], color=f"C{p}", s=12)
        ax.set_title(f"{self.task.name}, step {k}", fontsize=8)
        ax.tick_params(labelsize=6)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def register_envs() -> None:
    """Register :data:`ENV_IDS` in Gymnasium's registry (idempotent; done on import)."""
    for env_id, task in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            kwargs = {} if task is None else {"task": task}
            gymnasium.register(id=env_id, entry_point="soc_opt.envs:SocOptEnv", kwargs=kwargs)


def make(env_id: str, **kwargs) -> gymnasium.Env:
    """``gymnasium.make`` for the soc_opt ids, with an error naming the id and the known ids."""
    if env_id not in ENV_IDS:
        raise ConfigError(f"unknown soc_opt environment {env_id!r}; known: {', '.join(ENV_IDS)}")
    return gymnasium.make(env_id, **kwargs)


register_envs()
