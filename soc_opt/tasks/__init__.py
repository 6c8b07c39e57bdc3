"""Tasks: ``linear2d``, MuJoCo tasks built from an MJCF file plus a TOML config, and Gymnasium
MuJoCo environments (``gym:<EnvId>``) (docs/math.md §0, §8).

A task owns the simulator, the state definition, the cost and the metrics.  Every
built-in task is a TOML file under ``problems/`` loaded through the same
:class:`TaskConfig` mechanism as a user's own model (``docs/tasks.md``).

Modules:

* :mod:`.config`: :class:`TaskConfig` and the state, cost-term, metric and linear-system configs (TOML schema).
* :mod:`.base`: the :class:`Task` protocol, the shared base class, :class:`RolloutNoise` and :class:`SimulationError`.
* :mod:`.linear`: :class:`LinearTask` (``kind = "linear"``) and its step-by-step :class:`LinearSimulator`.
* :mod:`.mujoco`: :class:`MujocoTask` (state layout, rollouts, finite-difference linearisation)
  and its step-by-step :class:`MujocoSimulator`.
* :mod:`.gym`: :class:`GymMujocoTask`, a Gymnasium MuJoCo environment as a task (``gym:<EnvId>``).
* :mod:`.loading`: :data:`BUILTIN_TASKS`, :func:`build_task`, :func:`load_task`.
* :mod:`.render`: :func:`render_filmstrip` (offscreen frames in :mod:`.render_worker`, matplotlib fallback).
"""

from __future__ import annotations

from .base import RolloutNoise, SimulationError, Task
from .config import (
    GYM_PREFIX,
    PKG_PREFIX,
    TERM_TYPES,  # noqa: F401 (public: the cost term kinds)
    FloatOrList,  # noqa: F401
    GymConfig,
    LinearConfig,
    MetricConfig,
    PointTermConfig,
    QuadraticTermConfig,
    Ramp,  # noqa: F401
    StateConfig,
    StateTermConfig,
    TaskConfig,
    TorqueTermConfig,
)
from .gym import GymMujocoTask
from .linear import LinearSimulator, LinearTask
from .loading import BUILTIN_TASKS, build_task, load_task
from .mujoco import MujocoSimulator, MujocoTask
from .render import RenderResult, render_filmstrip

__all__ = [
    "SimulationError",
    "RolloutNoise",
    "TaskConfig",
    "StateConfig",
    "MetricConfig",
    "LinearConfig",
    "GymConfig",
    "GYM_PREFIX",
    "PKG_PREFIX",
    "PointTermConfig",
    "TorqueTermConfig",
    "StateTermConfig",
    "QuadraticTermConfig",
    "Task",
    "LinearTask",
    "LinearSimulator",
    "MujocoTask",
    "MujocoSimulator",
    "GymMujocoTask",
    "BUILTIN_TASKS",
    "load_task",
    "build_task",
    "RenderResult",
    "render_filmstrip",
]
