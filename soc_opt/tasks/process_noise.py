"""Process noise a task declares in its TOML (``[process_noise]``; docs/math.md §8.1, ``docs/tasks.md``,
"Process noise").

Two kinds, both off by default (then nothing is drawn and every rollout is that of a task without the
table, bit for bit):

* **start**: the true ``x_0`` of each rollout has its start coordinates offset by ``U(-r, r)``
  (independent per rollout and coordinate).  The start coordinates are the angles of ``state.joints``
  for a MuJoCo task (velocities unchanged, the points recomputed by forward kinematics), every state
  component for a linear task.
* **actuation**: ``nu_k ~ N(0, diag(sigma^2))`` per control step is added to the control the plant
  receives (held over the step's substeps); the recorded action stays the policy's ``a_k``.

:class:`ProcessNoise` is the table resolved for one task (lengths checked against its joints and
actuators, errors naming the key); :meth:`ProcessNoise.draw` takes its draws from the rollouts'
Generator after the sensor and policy noise (:meth:`soc_opt.tasks.base.TaskBase.draw_noise`).
What the learners are told: the task's start covariance (:meth:`ProcessNoise.start_cov`, the
uniform's ``r^2 / 3`` carried to the state by the start Jacobian) enters ``task.P0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import ConfigError
from ..models import symmetrize
from .config import ProcessNoiseConfig

__all__ = ["ProcessNoise", "resolve"]


@dataclass(frozen=True)
class ProcessNoise:
    """``[process_noise]`` of one task, as arrays.

    Fields:
        start:     (k,) half-widths ``r`` of the uniform start offsets, one per start coordinate
        start_idx: (k,) positions of the start coordinates in the task state
        actuation: (m,) standard deviations ``sigma`` of the actuation noise, one per action
    """

    start: np.ndarray
    start_idx: np.ndarray
    actuation: np.ndarray

    def __post_init__(self):
        for name in ("start", "start_idx", "actuation"):
            a = np.array(getattr(self, name), dtype=int if name == "start_idx" else float)
            if a.ndim != 1:
                raise ValueError(f"process noise {name}: expected a vector, got shape {a.shape}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if self.start.shape != self.start_idx.shape:
            raise ValueError(f"process noise: start {self.start.shape} and start_idx {self.start_idx.shape} differ")

    @property
    def start_on(self) -> bool:
        """Whether start offsets are drawn (some ``r > 0``)."""
        return bool(np.any(self.start > 0.0))

    @property
    def actuation_on(self) -> bool:
        """Whether actuation noise is drawn (some ``sigma > 0``)."""
        return bool(np.any(self.actuation > 0.0))

    def draw(self, M: int, T: int, rng: np.random.Generator) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(start (M, k), actuation (M, T, m))`` drawn from ``rng`` in this order, each only when on
        (``None`` otherwise, and nothing taken from ``rng``): ``r * U(-1, 1)`` and ``sigma * N(0, 1)``."""
        start = rng.uniform(-1.0, 1.0, (M, self.start.size)) * self.start if self.start_on else None
        act = rng.standard_normal((M, T, self.actuation.size)) * self.actuation if self.actuation_on else None
        return start, act

    @property
    def start_var(self) -> np.ndarray:
        """``(k,)`` variances ``r^2 / 3`` of the start offsets (of the uniform on ``[-r, r]``)."""
        return self.start * self.start / 3.0

    def start_cov(self, J: np.ndarray) -> np.ndarray:
        """``(n, n)`` covariance of the true ``x_0``: ``J diag(r^2 / 3) J^T`` for the start Jacobian
        ``J = d x_0 / d (start coordinates)`` ``(n, k)`` (exact on the coordinates themselves, first
        order on the points; docs/math.md §8.1)."""
        J = np.asarray(J, dtype=float)
        return symmetrize((J * self.start_var) @ J.T)


def _per_entry(value, names: list[str], key: str, what: str) -> np.ndarray:
    """``value`` (a number or one per name) as a vector over ``names``; ``ConfigError`` naming ``key``."""
    if isinstance(value, (tuple, list)):
        if len(value) != len(names):
            raise ConfigError(f"process_noise.{key}: expected {len(names)} numbers (one per {what}: "
                              f"{', '.join(names)}) or one number, got {len(value)}")
        return np.array(value, dtype=float)
    return np.full(len(names), float(value))


def resolve(cfg: ProcessNoiseConfig, start_names: list[str], start_idx, actuators: list[str], what: str) -> ProcessNoise:
    """The :class:`ProcessNoise` of ``cfg`` for a task whose start coordinates are ``start_names`` (at
    ``start_idx`` in its state; ``what`` names them in errors, e.g. ``"joint of state.joints"``) and whose
    actions drive ``actuators``; lengths are checked here, with the key named."""
    start = _per_entry(cfg.start, list(start_names), "start", what)
    if not start_names and np.any(np.asarray(cfg.start, dtype=float) > 0):
        raise ConfigError(f"process_noise.start: the task has no {what} to start at random (state.joints is empty)")
    actuation = _per_entry(cfg.actuation, list(actuators), "actuation", "actuator")
    return ProcessNoise(start, np.asarray(start_idx, dtype=int), actuation)
