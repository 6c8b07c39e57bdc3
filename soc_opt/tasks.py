"""Tasks: ``linear2d`` and MuJoCo tasks built from an MJCF file plus a TOML config (SPEC §0, §8).

A task owns the simulator, the state definition, the cost and the metrics.  Every
built-in task is a TOML file under ``problems/`` loaded through the same
:class:`TaskConfig` mechanism as a user's own model (``docs/tasks.md``).

State of a MuJoCo task (``x`` true, ``s = x + eps`` measured, SPEC §0)::

    [ qpos(state.joints), qvel(state.joints),
      site positions (3 per state.sites), site velocities (3 per site, world frame),
      qpos(state.extra_joints), qvel(state.extra_joints) ]

Rollouts: from ``x_0`` (``q0`` + condition offset, zero velocity) the action
``a_k = K_k s_k + k_k + L_k w_k`` is computed from the *measured* state and held
as ``ctrl`` for ``substeps`` calls of ``mj_step`` (``dt = timestep * substeps``).
All noise (``eps`` then ``w``) is drawn from the Generator before simulating,
so results do not depend on ``workers``.  The stage cost ``Y_k`` is evaluated on
the measured ``s_k`` (SPEC §0) and ``y_k = exp(-y_scale * Y_k)``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
import scipy.linalg

from .config import Config, ConfigError, read_toml
from .costs import (
    CostSum,
    PointCost,
    QuadraticStateActionCost,
    StateCost,
    TorqueCost,
)
from .models import (
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    QuadraticCost,
    Rollouts,
    ShapeError,
    check_array,
)

__all__ = [
    "SimulationError",
    "TaskConfig",
    "StateConfig",
    "MetricConfig",
    "LinearConfig",
    "PointTermConfig",
    "TorqueTermConfig",
    "StateTermConfig",
    "QuadraticTermConfig",
    "Task",
    "LinearTask",
    "MujocoTask",
    "BUILTIN_TASKS",
    "load_task",
    "build_task",
    "RenderResult",
    "render_filmstrip",
]


class SimulationError(RuntimeError):
    """The simulation diverged (NaN/inf or a MuJoCo instability warning); names the sample and step."""


# --------------------------------------------------------------------------- config

Ramp = Literal["constant", "linear", "quadratic", "final_only"]
FloatOrList = float | tuple[float, ...]


@dataclass(frozen=True)
class StateConfig(Config):
    """Which simulator quantities make up the state vector (layout in the module docstring)."""

    joints: tuple[str, ...] = ()
    sites: tuple[str, ...] = ()
    extra_joints: tuple[str, ...] = ()


@dataclass(frozen=True)
class PointTermConfig(Config):
    """``type = "point"``: ``1/2 l2 d^2 + l1 sqrt(alpha + d^2)`` of stacked site positions.

    ``sites`` (MuJoCo) or ``indices`` (any task) pick the point coordinates; the
    target is a fixed ``target`` (3 per site) or ``target_sites`` (moving points).
    """

    type: Literal["point"] = "point"
    sites: tuple[str, ...] = ()
    indices: tuple[int, ...] = ()
    target: tuple[float, ...] | None = None
    target_sites: tuple[str, ...] = ()
    wp: FloatOrList = 1.0
    l1: float = 0.0
    l2: float = 1.0
    alpha: float = 1e-5
    ramp: Ramp = "constant"
    final_multiplier: float = 1.0
    weight: float = 1.0


@dataclass(frozen=True)
class TorqueTermConfig(Config):
    """``type = "torque"``: ``1/2 a^T diag(wu) a``."""

    type: Literal["torque"] = "torque"
    wu: FloatOrList = 1.0
    ramp: Ramp = "constant"
    final_multiplier: float = 1.0
    weight: float = 1.0


@dataclass(frozen=True)
class StateTermConfig(Config):
    """``type = "state"``: ``1/2 sum w_i (s_i - s*_i)^2`` over ``joints`` (their angles),
    ``labels`` (state labels), ``indices``, or the whole state if none is given."""

    type: Literal["state"] = "state"
    joints: tuple[str, ...] = ()
    labels: tuple[str, ...] = ()
    indices: tuple[int, ...] = ()
    target: FloatOrList = 0.0
    weights: FloatOrList = 1.0
    ramp: Ramp = "constant"
    final_multiplier: float = 1.0
    weight: float = 1.0


@dataclass(frozen=True)
class QuadraticTermConfig(Config):
    """``type = "quadratic"``: SPEC §0 ``(s-s*)^T Qs (s-s*) + (a-a*)^T Qa (a-a*)``.

    ``Qs``/``Qa``: scalar (times identity), diagonal list or full matrix.
    """

    type: Literal["quadratic"] = "quadratic"
    Qs: float | tuple[float, ...] | tuple[tuple[float, ...], ...] = 1.0
    Qa: float | tuple[float, ...] | tuple[tuple[float, ...], ...] = 0.0
    target: FloatOrList = 0.0
    action_target: FloatOrList = 0.0
    ramp: Ramp = "constant"
    final_multiplier: float = 1.0
    weight: float = 1.0


TERM_TYPES: dict[str, type[Config]] = {
    "point": PointTermConfig,
    "torque": TorqueTermConfig,
    "state": StateTermConfig,
    "quadratic": QuadraticTermConfig,
}


@dataclass(frozen=True)
class MetricConfig(Config):
    """Task metric, evaluated on the true states of a rollout batch.

    * ``min_distance``: per sample ``min_k ||p_k - target||`` of a ``site`` (or state
      ``indices``); success/failure rates use the ``success``/``failure`` thresholds.
    * ``min_joint``: per sample ``min_k q_k`` of ``joint`` (lower is better).
    """

    type: Literal["none", "min_distance", "min_joint"] = "none"
    site: str | None = None
    indices: tuple[int, ...] = ()
    target: tuple[float, ...] = ()
    joint: str | None = None
    success: float | None = None
    failure: float | None = None


@dataclass(frozen=True)
class LinearConfig(Config):
    """``kind = "linear"``: ``x_{k+1} = A x_k + B a_k + c + xi_k``, ``xi_k ~ N(0, process_var I)``.

    ``system = "point_mass_2d"`` builds ``A, B`` by exact zero-order-hold
    discretisation (``dt`` = timestep * substeps) of a 2-D point mass with a
    first-order force actuator per axis: ``p' = v, v' = f / mass, f' = (u - f) / tau``,
    state ``(px, py, vx, vy, fx, fy)``.  ``system = "matrices"`` takes ``A``, ``B``
    (and optionally ``c``) as given.
    """

    system: Literal["point_mass_2d", "matrices"] = "point_mass_2d"
    mass: float = 1.0
    tau: float = 0.2
    A: tuple[tuple[float, ...], ...] = ()
    B: tuple[tuple[float, ...], ...] = ()
    c: tuple[float, ...] = ()
    process_var: float = 1e-4
    x0: tuple[float, ...] = ()
    labels: tuple[str, ...] = ()
    point: tuple[int, ...] = (0, 1)


@dataclass(frozen=True)
class TaskConfig(Config):
    """A task: model, horizon, state definition, cost terms, noise, metric (see ``docs/tasks.md``).

    ``cost`` is a list of tables, each with a ``type`` key selecting
    :class:`PointTermConfig`, :class:`TorqueTermConfig`, :class:`StateTermConfig`
    or :class:`QuadraticTermConfig`; they are parsed strictly on construction.
    """

    name: str
    T: int
    kind: Literal["mujoco", "linear"] = "mujoco"
    description: str = ""
    model: str | None = None
    timestep: float | None = None
    substeps: int = 1
    q0: tuple[float, ...] = ()
    offsets: tuple[tuple[float, ...], ...] = ()
    state: StateConfig = field(default_factory=StateConfig)
    actuated: tuple[str, ...] = ()
    cost: tuple[dict[str, Any], ...] = ()
    rho2: float = 0.1
    init_var: float = 1.0
    y_scale: float = 1.0
    metric: MetricConfig = field(default_factory=MetricConfig)
    linear: LinearConfig = field(default_factory=LinearConfig)
    camera: str | None = None

    def __post_init__(self):
        checks = [
            ("T", self.T >= 1, "must be >= 1"),
            ("substeps", self.substeps >= 1, "must be >= 1"),
            ("timestep", self.timestep is None or self.timestep > 0, "must be positive"),
            ("rho2", self.rho2 >= 0, "must be >= 0"),
            ("init_var", self.init_var > 0, "must be positive"),
            ("y_scale", self.y_scale > 0, "must be positive"),
        ]
        for key, ok, msg in checks:
            if not ok:
                raise ConfigError(f"{key}: {msg}, got {getattr(self, key)!r}")
        for i, off in enumerate(self.offsets):
            if self.q0 and len(off) != len(self.q0):
                raise ConfigError(f"offsets[{i}]: expected {len(self.q0)} entries (like q0), got {len(off)}")
        terms = []
        for i, term in enumerate(self.cost):
            if isinstance(term, Config):
                terms.append(term)
                continue
            typ = term.get("type")
            if typ not in TERM_TYPES:
                raise ConfigError(f"cost[{i}].type: {typ!r} is not one of {list(TERM_TYPES)}")
            terms.append(TERM_TYPES[typ].from_dict(dict(term), _path=f"cost[{i}]"))
        object.__setattr__(self, "cost", tuple(terms))

    def to_dict(self) -> dict:
        out = super().to_dict()
        out["cost"] = [t.to_dict() for t in self.cost]
        return out


# --------------------------------------------------------------------------- task protocol


@runtime_checkable
class Task(Protocol):
    """What algorithms use (docs/architecture.md, "tasks")."""

    name: str
    n: int
    m: int
    T: int
    dt: float
    rho2: float
    state_labels: list[str]

    @property
    def mu0(self) -> np.ndarray: ...

    @property
    def P0(self) -> np.ndarray: ...

    def rollouts(self, policy, M, rng, noise=True, workers=1) -> Rollouts: ...

    def cost(self, s, a) -> np.ndarray: ...

    def true_cost(self, rollouts: Rollouts) -> np.ndarray: ...

    def cost_expansion(self, s, a) -> QuadraticCost: ...

    def metrics(self, rollouts: Rollouts) -> dict[str, float]: ...

    def initial_policy(self, var=None) -> LinearGaussianPolicy: ...

    def linearize(self, x, u) -> LinearGaussianDynamics: ...

    def ee_points(self, x) -> np.ndarray: ...


class _TaskBase:
    """Shared behaviour: cost evaluation, metrics, initial distribution and policy."""

    config: TaskConfig
    n: int
    m: int
    T: int
    x0: np.ndarray
    state_labels: list[str]

    def _setup_common(self):
        c = self.config
        self.name = c.name
        self.T = c.T
        self.rho2 = c.rho2
        self.y_scale = c.y_scale
        self._label_index = {lab: i for i, lab in enumerate(self.state_labels)}
        self._cost = CostSum([self._build_term(i, t) for i, t in enumerate(c.cost)], self.n, self.m)
        self._metric = self._build_metric(c.metric)

    # -- cost
    def _site_indices(self, sites, key) -> list[int]:
        raise ConfigError(f"{key}: this task has no sites")

    def _joint_index(self, joint, key) -> int:
        raise ConfigError(f"{key}: this task has no joints")

    def _build_term(self, i: int, t: Config):
        key = f"cost[{i}]"
        common = dict(ramp=t.ramp, final_multiplier=t.final_multiplier, weight=t.weight)
        try:
            if isinstance(t, PointTermConfig):
                if bool(t.sites) == bool(t.indices):
                    raise ConfigError(f"{key}: give exactly one of 'sites' or 'indices'")
                idx = self._site_indices(t.sites, f"{key}.sites") if t.sites else list(t.indices)
                self._check_indices(idx, f"{key}.indices")
                if t.target_sites:
                    if len(t.target_sites) * 3 != len(idx):
                        raise ConfigError(f"{key}.target_sites: need one target site per site ({len(idx) // 3})")
                    tidx = self._site_indices(t.target_sites, f"{key}.target_sites")
                    if t.target is not None:
                        raise ConfigError(f"{key}: give either 'target' or 'target_sites', not both")
                    return PointCost(self.n, self.m, idx, target_idx=tidx, wp=t.wp, l1=t.l1, l2=t.l2, alpha=t.alpha, **common)
                if t.target is None:
                    raise ConfigError(f"{key}: missing 'target' (or 'target_sites')")
                if len(t.target) != len(idx):
                    raise ConfigError(f"{key}.target: expected {len(idx)} numbers, got {len(t.target)}")
                return PointCost(self.n, self.m, idx, target=t.target, wp=t.wp, l1=t.l1, l2=t.l2, alpha=t.alpha, **common)
            if isinstance(t, TorqueTermConfig):
                return TorqueCost(self.n, self.m, wu=t.wu, **common)
            if isinstance(t, StateTermConfig):
                if sum(map(bool, (t.joints, t.labels, t.indices))) > 1:
                    raise ConfigError(f"{key}: give at most one of 'joints', 'labels', 'indices'")
                if t.joints:
                    idx = [self._joint_index(j, f"{key}.joints") for j in t.joints]
                elif t.labels:
                    missing = [lab for lab in t.labels if lab not in self._label_index]
                    if missing:
                        raise ConfigError(f"{key}.labels: unknown state label {missing[0]!r}; labels: {self.state_labels}")
                    idx = [self._label_index[lab] for lab in t.labels]
                elif t.indices:
                    idx = list(t.indices)
                    self._check_indices(idx, f"{key}.indices")
                else:
                    idx = None
                return StateCost(self.n, self.m, idx=idx, target=t.target, weights=t.weights, **common)
            if isinstance(t, QuadraticTermConfig):
                return QuadraticStateActionCost(
                    self.n, self.m, Qs=t.Qs, Qa=t.Qa, target=t.target, action_target=t.action_target, **common
                )
        except ConfigError:
            raise
        except (ValueError, ShapeError) as e:
            raise ConfigError(f"{key}: {e}") from e
        raise ConfigError(f"{key}: unsupported cost term {type(t).__name__}")

    def _check_indices(self, idx, key):
        bad = [i for i in idx if not 0 <= i < self.n]
        if bad:
            raise ConfigError(f"{key}: state index {bad[0]} out of range for n={self.n}")

    @property
    def cost_terms(self) -> CostSum:
        return self._cost

    def cost(self, s, a) -> np.ndarray:
        """Stage costs ``(..., T)`` of states ``s (..., T+1, n)`` and actions ``a (..., T, m)``."""
        return self._cost(s, a)

    def true_cost(self, rollouts: Rollouts) -> np.ndarray:
        """``(M, T)`` stage costs on the true states ``x`` (for reporting)."""
        return self._cost(rollouts.x, rollouts.a)

    def cost_expansion(self, s, a) -> QuadraticCost:
        """Second-order Taylor expansion of the cost around ``(s (T+1,n), a (T,m))``."""
        return self._cost.expand(s, a)

    def _finish(self, x, s, a) -> Rollouts:
        Y = self._cost(s, a)
        return Rollouts(x, s, a, Y, np.exp(-self.y_scale * Y))

    # -- metrics
    def _build_metric(self, mc: MetricConfig):
        if mc.type == "none":
            return None
        if mc.type == "min_distance":
            if bool(mc.site) == bool(mc.indices):
                raise ConfigError("metric: give exactly one of 'site' or 'indices'")
            idx = self._site_indices([mc.site], "metric.site") if mc.site else list(mc.indices)
            self._check_indices(idx, "metric.indices")
            if len(mc.target) != len(idx):
                raise ConfigError(f"metric.target: expected {len(idx)} numbers, got {len(mc.target)}")
            return ("min_distance", np.array(idx), np.array(mc.target, dtype=float), mc.success, mc.failure)
        if not mc.joint:
            raise ConfigError("metric: type 'min_joint' needs 'joint'")
        return ("min_joint", self._joint_index(mc.joint, "metric.joint"), mc.joint)

    def per_sample_metrics(self, rollouts: Rollouts) -> dict[str, np.ndarray]:
        """Per-sample metric values ``(M,)`` on the true states."""
        x = rollouts.x
        out = {"cost": self.true_cost(rollouts).sum(axis=1)}
        if self._metric is None:
            return out
        if self._metric[0] == "min_distance":
            _, idx, target, _, _ = self._metric
            dist = np.linalg.norm(x[..., idx] - target, axis=-1)
            out["min_distance"] = dist.min(axis=1)
            out["final_distance"] = dist[:, -1]
        else:
            _, i, joint = self._metric
            out[f"min_{joint}"] = x[:, :, i].min(axis=1)
            out[f"final_{joint}"] = x[:, -1, i]
        return out

    def metrics(self, rollouts: Rollouts) -> dict[str, float]:
        """Averages over samples of :meth:`per_sample_metrics`, best values, success/failure rates.

        ``min_distance``: ``min_distance`` (mean over samples of the per-sample minimum),
        ``min_distance_best``, ``final_distance``, ``success_rate`` (fraction below
        ``success``) and ``failure_rate`` (fraction above ``failure``).
        ``min_joint``: ``min_<joint>`` (mean), ``min_<joint>_best``, ``final_<joint>``.
        ``cost``: mean total true cost.
        """
        ps = self.per_sample_metrics(rollouts)
        out = {k: float(np.mean(v)) for k, v in ps.items()}
        if self._metric is not None:
            if self._metric[0] == "min_distance":
                _, _, _, succ, fail = self._metric
                out["min_distance_best"] = float(ps["min_distance"].min())
                if succ is not None:
                    out["success_rate"] = float(np.mean(ps["min_distance"] < succ))
                if fail is not None:
                    out["failure_rate"] = float(np.mean(ps["min_distance"] > fail))
            else:
                joint = self._metric[2]
                out[f"min_{joint}_best"] = float(ps[f"min_{joint}"].min())
        return out

    # -- initial distribution and policy
    @property
    def mu0(self) -> np.ndarray:
        """Mean of the measured initial state ``s_0``: the true initial state ``x_0``."""
        return self.x0.copy()

    @property
    def P0(self) -> np.ndarray:
        """Covariance of ``s_0 = x_0 + eps_0``: ``(rho2 + 1e-6) I`` (jitter keeps it PD for ``rho2 = 0``)."""
        return (self.rho2 + 1e-6) * np.eye(self.n)

    def initial_policy(self, var: float | None = None) -> LinearGaussianPolicy:
        """Zero gains and offsets (zero torque: with gravity off the arm holds still), cov ``var I``."""
        var = self.config.init_var if var is None else float(var)
        return LinearGaussianPolicy.zeros(self.T, self.n, self.m, var)

    def simulate(self, policy: LinearGaussianPolicy, x0=None) -> Rollouts:
        """One noise-free rollout of the policy mean (``eps = 0``, ``w = 0``) from ``x0`` (default ``x_0``)."""
        return self.rollouts(policy, 1, np.random.default_rng(0), noise=False, x0=x0)

    def _check_policy(self, policy: LinearGaussianPolicy):
        if (policy.T, policy.m, policy.n) != (self.T, self.m, self.n):
            raise ShapeError(
                f"policy has (T, m, n) = {(policy.T, policy.m, policy.n)}, task {self.name!r} needs {(self.T, self.m, self.n)}"
            )


def _rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


# --------------------------------------------------------------------------- linear task


class LinearTask(_TaskBase):
    """A discrete-time linear-Gaussian system (``kind = "linear"``; e.g. ``linear2d``, SPEC §8)."""

    kind = "linear"

    def __init__(self, config: TaskConfig, *, condition: int = 0):
        self.config = config
        lc = config.linear
        self.dt = (config.timestep or 0.1) * config.substeps
        if lc.system == "point_mass_2d":
            if lc.mass <= 0 or lc.tau <= 0:
                raise ConfigError("linear: mass and tau must be positive")
            Ac = np.zeros((6, 6))
            Bc = np.zeros((6, 2))
            for ax in range(2):
                Ac[ax, 2 + ax] = 1.0
                Ac[2 + ax, 4 + ax] = 1.0 / lc.mass
                Ac[4 + ax, 4 + ax] = -1.0 / lc.tau
                Bc[4 + ax, ax] = 1.0 / lc.tau
            E = scipy.linalg.expm(np.block([[Ac, Bc], [np.zeros((2, 8))]]) * self.dt)
            A, B = E[:6, :6], E[:6, 6:]
            labels = ["px", "py", "vx", "vy", "fx", "fy"]
        else:
            if not lc.A or not lc.B:
                raise ConfigError("linear: system 'matrices' needs A and B")
            A = np.array(lc.A, dtype=float)
            B = np.array(lc.B, dtype=float)
            if A.ndim != 2 or A.shape[0] != A.shape[1] or B.ndim != 2 or B.shape[0] != A.shape[0]:
                raise ConfigError(f"linear: A must be (n, n) and B (n, m), got {A.shape} and {B.shape}")
            labels = [f"s{i}" for i in range(A.shape[0])]
        self.A, self.B = A, B
        self.n, self.m = B.shape
        self.c = np.zeros(self.n) if not lc.c else np.asarray(lc.c, dtype=float)
        if self.c.shape != (self.n,):
            raise ConfigError(f"linear.c: expected {self.n} numbers, got {self.c.size}")
        if lc.process_var < 0:
            raise ConfigError("linear.process_var: must be >= 0")
        self.W = lc.process_var * np.eye(self.n)
        if lc.labels:
            if len(lc.labels) != self.n:
                raise ConfigError(f"linear.labels: expected {self.n} labels, got {len(lc.labels)}")
            labels = list(lc.labels)
        self.state_labels = labels
        x0 = np.zeros(self.n) if not lc.x0 else np.asarray(lc.x0, dtype=float)
        if x0.shape != (self.n,):
            raise ConfigError(f"linear.x0: expected {self.n} numbers, got {x0.size}")
        if config.offsets:
            off = np.asarray(config.offsets[condition], dtype=float)
            if off.shape != (self.n,):
                raise ConfigError(f"offsets[{condition}]: expected {self.n} numbers")
            x0 = x0 + off
        self.x0 = x0
        pt = list(lc.point)
        if not 1 <= len(pt) <= 3 or any(not 0 <= i < self.n for i in pt):
            raise ConfigError(f"linear.point: 1 to 3 state indices below n={self.n}, got {pt}")
        self._point = pt
        self._setup_common()

    def rollouts(self, policy, M, rng, noise=True, workers=1, x0=None) -> Rollouts:
        """``M`` rollouts (vectorised; ``workers`` is ignored).  Draw order: ``eps``, ``w``, process noise."""
        self._check_policy(policy)
        rng = _rng(rng)
        T, n, m = self.T, self.n, self.m
        if noise:
            eps = rng.standard_normal((M, T + 1, n)) * math.sqrt(self.rho2)
            w = rng.standard_normal((M, T, m))
            xi = rng.standard_normal((M, T, n)) * math.sqrt(self.config.linear.process_var)
        else:
            eps = np.zeros((M, T + 1, n))
            w = np.zeros((M, T, m))
            xi = np.zeros((M, T, n))
        L = policy.chol
        x = np.empty((M, T + 1, n))
        a = np.empty((M, T, m))
        x[:, 0] = self.x0 if x0 is None else np.asarray(x0, dtype=float)
        s = x.copy()
        for k in range(T):
            s[:, k] = x[:, k] + eps[:, k]
            a[:, k] = s[:, k] @ policy.K[k].T + policy.k[k] + w[:, k] @ L[k].T
            x[:, k + 1] = x[:, k] @ self.A.T + a[:, k] @ self.B.T + self.c + xi[:, k]
        s[:, T] = x[:, T] + eps[:, T]
        return self._finish(x, s, a)

    def step(self, x, u) -> np.ndarray:
        """Noise-free transition ``A x + B u + c``."""
        return self.A @ np.asarray(x, dtype=float) + self.B @ np.asarray(u, dtype=float) + self.c

    def linearize(self, x=None, u=None, cov=None) -> LinearGaussianDynamics:
        """The exact model, repeated over ``T`` (process noise ``W`` unless ``cov`` is given)."""
        T = self.T
        if cov is None:
            W = self.W
        else:
            W = np.asarray(cov, dtype=float)
            W = W * np.eye(self.n) if W.ndim == 0 else W

        def tile(X):
            return np.broadcast_to(X, (T,) + X.shape).copy()

        return LinearGaussianDynamics(tile(self.A), tile(self.B), tile(self.c), tile(W))

    def ee_points(self, x) -> np.ndarray:
        """``(..., 1, 3)``: the state components named by ``linear.point`` (zero-padded to 3-D)."""
        x = np.asarray(x, dtype=float)
        p = np.zeros(x.shape[:-1] + (1, 3))
        p[..., 0, : len(self._point)] = x[..., self._point]
        return p


# --------------------------------------------------------------------------- MuJoCo task


def _mujoco():
    import mujoco

    return mujoco


def _as_index(idx) -> slice | np.ndarray:
    """A slice when ``idx`` is a contiguous ascending range (cheaper to copy), else the array."""
    idx = np.asarray(idx, dtype=int)
    if idx.size and np.all(np.diff(idx) == 1):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


_BAD_WARNINGS = ("mjWARN_CONTACTFULL", "mjWARN_CNSTRFULL", "mjWARN_BADQPOS", "mjWARN_BADQVEL", "mjWARN_BADQACC", "mjWARN_BADCTRL")


class MujocoTask(_TaskBase):
    """A task from an MJCF model plus a :class:`TaskConfig` (SPEC §8 "any MuJoCo model")."""

    kind = "mujoco"

    def __init__(self, config: TaskConfig, model, *, condition: int = 0, source: str = "<model>"):
        mj = _mujoco()
        self.config = config
        self.model = model
        self.source = source
        if config.timestep is not None:
            model.opt.timestep = config.timestep
        self.substeps = config.substeps
        self.dt = float(model.opt.timestep) * self.substeps
        if model.na:
            raise ConfigError(f"model {source}: actuators with activation states (na={model.na}) are not supported")
        sc = config.state
        self._joint_ids = [self._find(mj.mjtObj.mjOBJ_JOINT, j, "state.joints") for j in sc.joints]
        self._extra_ids = [self._find(mj.mjtObj.mjOBJ_JOINT, j, "state.extra_joints") for j in sc.extra_joints]
        self._site_ids = [self._find(mj.mjtObj.mjOBJ_SITE, s, "state.sites") for s in sc.sites]
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
        self._qadr = np.array([model.jnt_qposadr[j] for j in jids], dtype=int)
        self._dadr = np.array([model.jnt_dofadr[j] for j in jids], dtype=int)
        self._sq = np.r_[np.arange(nj), o_e + np.arange(ne)].astype(int)
        self._sqd = np.r_[nj + np.arange(nj), o_e + ne + np.arange(ne)].astype(int)
        labels = [""] * self.n
        for nm, i in zip(alljoints, self._sq):
            labels[i] = f"q:{nm}"
        for nm, i in zip(alljoints, self._sqd):
            labels[i] = f"qd:{nm}"
        for j, nm in enumerate(sc.sites):
            for c, ax in enumerate("xyz"):
                labels[o_p + 3 * j + c] = f"{nm}.{ax}"
                labels[o_v + 3 * j + c] = f"{nm}.v{ax}"
        self.state_labels = labels
        self._joint_state_index = {nm: int(i) for nm, i in zip(alljoints, self._sq)}
        self._site_state_index = {nm: o_p + 3 * j for j, nm in enumerate(sc.sites)}
        self._all_dofs_in_state = sorted(self._dadr.tolist()) == list(range(model.nv))

        # actuators
        if config.actuated:
            self._act = np.array([self._actuator_for(a) for a in config.actuated], dtype=int)
            self.actuated = list(config.actuated)
        else:
            self._act = np.arange(model.nu)
            self.actuated = [model.actuator(i).name for i in range(model.nu)]
        if len(set(self._act.tolist())) != len(self._act):
            raise ConfigError("actuated: an actuator is listed twice")
        self.m = len(self._act)
        if self.m == 0:
            raise ConfigError(f"actuated: model {source} has no actuators")

        # initial configuration
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
            qinit[self._qadr] = q0
        self.condition = condition
        self.n_conditions = max(1, len(config.offsets))
        self._qinit = qinit

        # fast state reader: copy plans for qpos, qvel, sites
        self._q_src, self._q_dst = self._split_plan(self._qadr, self._sq)
        self._qd_src, self._qd_dst = self._split_plan(self._dadr, self._sqd)
        self._site_arr = np.array(self._site_ids, dtype=int)
        self._site_pos_sl = self.layout["site_pos"]
        self._site_vel_slices = [slice(o_v + 3 * j, o_v + 3 * j + 3) for j in range(ns)]
        self._split_step = int(model.opt.integrator) != int(mj.mjtIntegrator.mjINT_RK4)
        self._bad_warn = np.array([int(getattr(mj.mjtWarning, w)) for w in _BAD_WARNINGS])
        self._obj_site = mj.mjtObj.mjOBJ_SITE

        data = mj.MjData(model)
        self._reset(data, None)
        mj.mj_forward(model, data)
        x0 = np.empty(self.n)
        self._read(data, x0, np.empty(6))
        self.x0 = x0
        self._setup_common()

    # -- lookups
    def _find(self, objtype, name, key) -> int:
        mj = _mujoco()
        i = mj.mj_name2id(self.model, objtype, name)
        if i < 0:
            kind = {mj.mjtObj.mjOBJ_JOINT: "joint", mj.mjtObj.mjOBJ_SITE: "site"}.get(objtype, "object")
            count = self.model.njnt if kind == "joint" else self.model.nsite
            names = [mj.mj_id2name(self.model, objtype, k) for k in range(count)]
            raise ConfigError(f"{key}: {kind} {name!r} not found in model {self.source}; {kind}s: {names}")
        return i

    def _actuator_for(self, name) -> int:
        mj = _mujoco()
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
    def _reset(self, d, x0):
        mj = _mujoco()
        mj.mj_resetData(self.model, d)
        d.qpos[:] = self._qinit
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            d.qpos[self._qadr] = x0[self._sq]
            d.qvel[self._dadr] = x0[self._sqd]

    def _reader(self, d):
        """A function ``read(out)`` writing the task state of ``d`` into ``out (n,)``.

        Needs positions and velocities computed (after ``mj_step1`` or ``mj_forward``).  The
        array views of ``d`` and the copy plan are bound once: this runs every control step.
        """
        ov = _mujoco().mj_objectVelocity
        m, obj = self.model, self._obj_site
        qpos, qvel, site_xpos = d.qpos, d.qvel, d.site_xpos
        qplan = list(zip(self._q_src, self._q_dst))
        qdplan = list(zip(self._qd_src, self._qd_dst))
        sites = self._site_arr
        pos_sl = self._site_pos_sl
        vplan = list(zip(self._site_ids, self._site_vel_slices))
        res = np.empty(6)
        lin = res[3:]

        def read(out):
            for src, dst in qplan:
                out[dst] = qpos[src]
            for src, dst in qdplan:
                out[dst] = qvel[src]
            if vplan:
                out[pos_sl] = site_xpos[sites].ravel()
                for sid, sl in vplan:
                    ov(m, d, obj, sid, res, 0)
                    out[sl] = lin

        return read

    def _read(self, d, out, res=None):
        self._reader(d)(out)

    def state_from_qpos(self, qpos, qvel=None) -> np.ndarray:
        """Task state for a full ``qpos (nq,)`` (and ``qvel``, default zero), via ``mj_forward``."""
        mj = _mujoco()
        d = mj.MjData(self.model)
        d.qpos[:] = qpos
        if qvel is not None:
            d.qvel[:] = qvel
        mj.mj_forward(self.model, d)
        out = np.empty(self.n)
        self._read(d, out, np.empty(6))
        return out

    def qpos_from_state(self, x) -> np.ndarray:
        """``(..., nq)`` full configurations: state joints from ``x``, other joints at their initial values."""
        x = np.asarray(x, dtype=float)
        q = np.broadcast_to(self._qinit, x.shape[:-1] + (self.model.nq,)).copy()
        q[..., self._qadr] = x[..., self._sq]
        return q

    # -- rollouts (hot path)
    def _run_samples(self, samples, K, offs, eps, x, s, a, x0):
        mj = _mujoco()
        m = self.model
        d = mj.MjData(m)
        step1, step2, step, forward = mj.mj_step1, mj.mj_step2, mj.mj_step, mj.mj_forward
        nsub = self.substeps
        split = self._split_step
        ctrl = d.ctrl
        act = _as_index(self._act)
        warn = d.warning.number
        bad = self._bad_warn
        read = self._reader(d)
        dot = np.dot
        T = self.T
        for i in samples:
            self._reset(d, x0)
            xi, si, ai, ei, oi = x[i], s[i], a[i], eps[i], offs[i]
            for k in range(T):
                if split:
                    step1(m, d)
                else:
                    forward(m, d)
                xk, sk, ak = xi[k], si[k], ai[k]
                read(xk)
                np.add(xk, ei[k], out=sk)
                dot(K[k], sk, out=ak)
                ak += oi[k]
                ctrl[act] = ak
                if split:
                    step2(m, d)
                    if nsub > 1:
                        step(m, d, nsub - 1)
                else:
                    step(m, d, nsub)
                if warn.any():
                    self._diverged(i, k, d, warn, bad)
            forward(m, d)
            read(xi[T])
            np.add(xi[T], ei[T], out=si[T])
            if not (np.isfinite(xi).all() and np.isfinite(ai).all()):
                bad_k = np.flatnonzero(~np.isfinite(xi[:T]).all(axis=1) | ~np.isfinite(ai).all(axis=1))
                kk = int(bad_k[0]) if bad_k.size else T
                raise SimulationError(f"sample {i} diverged at control step {kk}: non-finite state or action")

    def _diverged(self, i, k, d, warn, bad):
        mj = _mujoco()
        names = [mj.mjtWarning(w).name for w in np.flatnonzero(warn) if w in bad]
        if not names:  # harmless warning (e.g. inertia): clear it and continue
            warn[:] = 0
            return
        raise SimulationError(
            f"sample {i} diverged at control step {k} (t = {k * self.dt:.3f} s): MuJoCo warning "
            f"{', '.join(names)} (NaN/inf or huge qpos/qvel/qacc/ctrl, or a full contact/constraint buffer)"
        )

    def rollouts(self, policy: LinearGaussianPolicy, M: int, rng, noise: bool = True, workers: int = 1, x0=None) -> Rollouts:
        """``M`` sampled trajectories (SPEC §0).

        Noise ``eps (M,T+1,n) ~ N(0, rho2 I)`` then ``w (M,T,m) ~ N(0, I)`` is drawn from
        ``rng`` up front (``noise=False``: both zero, the policy mean on the true state).
        ``workers > 1`` simulates contiguous blocks of samples in threads, one ``MjData``
        each (MuJoCo releases the GIL while stepping); results are identical for any
        ``workers``.  ``x0``: another initial state in task coordinates (its joint
        components are used; default ``self.x0``).  ``a`` records the policy's action
        before MuJoCo clamps it to ``ctrlrange``.  Raises :class:`SimulationError`
        naming the sample and step on divergence.
        """
        self._check_policy(policy)
        rng = _rng(rng)
        M = int(M)
        T, n, m = self.T, self.n, self.m
        if noise:
            eps = rng.standard_normal((M, T + 1, n)) * math.sqrt(self.rho2)
            w = rng.standard_normal((M, T, m))
            offs = policy.k[None] + np.einsum("tij,mtj->mti", policy.chol, w)
        else:
            eps = np.zeros((M, T + 1, n))
            offs = np.broadcast_to(policy.k, (M, T, m))
        K = np.ascontiguousarray(policy.K)
        x = np.empty((M, T + 1, n))
        s = np.empty((M, T + 1, n))
        a = np.empty((M, T, m))
        workers = max(1, min(int(workers), M))
        if workers == 1:
            self._run_samples(range(M), K, offs, eps, x, s, a, x0)
        else:
            blocks = [b for b in np.array_split(np.arange(M), workers) if b.size]
            with ThreadPoolExecutor(max_workers=workers) as ex:
                futs = [ex.submit(self._run_samples, b.tolist(), K, offs, eps, x, s, a, x0) for b in blocks]
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
        mj = _mujoco()
        d = mj.MjData(self.model)
        self._reset(d, x)
        d.ctrl[self._act] = u
        mj.mj_step(self.model, d, self.substeps)
        mj.mj_forward(self.model, d)
        out = np.empty(self.n)
        self._read(d, out, np.empty(6))
        return out

    def _output_jacobian(self, d) -> np.ndarray:
        """``H = d s / d (dq, dv)`` at the state in ``d`` (positions computed): ``(n, 2 nv)``.

        Joint rows are selections; site positions use ``mj_jacSite``; site
        velocities ``v = J(q) qdot`` use ``J`` for ``d v / d qdot`` and central
        differences of ``J(q) qdot`` in ``q`` (hinge/slide joints only).
        """
        mj = _mujoco()
        m = self.model
        nv = m.nv
        H = np.zeros((self.n, 2 * nv))
        H[self._sq, self._dadr] = 1.0
        H[self._sqd, nv + self._dadr] = 1.0
        if not self._site_ids:
            return H
        jac = np.zeros((3, nv))
        o_p = self.layout["site_pos"].start
        o_v = self.layout["site_vel"].start
        qd = d.qvel.copy()
        for j, sid in enumerate(self._site_ids):
            mj.mj_jacSite(m, d, jac, None, sid)
            H[o_p + 3 * j : o_p + 3 * j + 3, :nv] = jac
            H[o_v + 3 * j : o_v + 3 * j + 3, nv:] = jac
        h = 1e-6
        q = d.qpos.copy()
        d2 = mj.MjData(m)
        for dof in range(nv):
            jnt = m.dof_jntid[dof]
            adr = m.jnt_qposadr[jnt]
            vs = []
            for sign in (1.0, -1.0):
                d2.qpos[:] = q
                d2.qpos[adr] += sign * h
                mj.mj_kinematics(m, d2)
                mj.mj_comPos(m, d2)
                v = []
                for sid in self._site_ids:
                    mj.mj_jacSite(m, d2, jac, None, sid)
                    v.append(jac @ qd)
                vs.append(np.concatenate(v))
            H[o_v : o_v + 3 * len(self._site_ids), dof] = (vs[0] - vs[1]) / (2 * h)
        return H

    def linearize(self, x, u, cov=0.0, eps: float = 1e-6) -> LinearGaussianDynamics:
        """Local linear model ``s_{k+1} ~ A_k s_k + B_k a_k + c_k`` around ``(x_k, u_k)`` in task coordinates.

        Per control step: ``mjd_transitionFD`` (centred, ``eps``) at each of the
        ``substeps`` physics steps along the nominal substep trajectory, chained
        (``A = A_S...A_1``, ``B = sum_j A_S...A_{j+1} B_j``, ctrl held), then mapped
        to task coordinates: ``A_k = H_{k+1} A G``, ``B_k = H_{k+1} B`` with ``G``
        picking ``(q, qdot)`` from the task state (site components are functions of
        them, so their columns are zero) and ``H`` the output Jacobian (site
        Jacobians).  ``c_k = step(x_k, u_k) - A_k x_k - B_k u_k``.  ``cov``: process
        noise (scalar times identity, or ``(n, n)``).  Needs every degree of freedom
        of the model in the state.
        """
        mj = _mujoco()
        if not self._all_dofs_in_state:
            raise ValueError(
                f"linearize: task {self.name!r} does not have every degree of freedom of the model in its state"
            )
        T = self.T
        x = check_array("linearize x", x, (None, self.n))
        u = check_array("linearize u", u, (None, self.m))
        if x.shape[0] not in (T, T + 1) or u.shape[0] != T:
            raise ShapeError(f"linearize needs x ({T + 1}, {self.n}) and u ({T}, {self.m}), got {x.shape}, {u.shape}")
        m = self.model
        nv = m.nv
        d = mj.MjData(m)
        G = np.zeros((2 * nv, self.n))
        G[self._dadr, self._sq] = 1.0
        G[nv + self._dadr, self._sqd] = 1.0
        Aj = np.zeros((2 * nv, 2 * nv))
        Bj = np.zeros((2 * nv, m.nu))
        A = np.zeros((T, self.n, self.n))
        B = np.zeros((T, self.n, self.m))
        c = np.zeros((T, self.n))
        nxt = np.empty(self.n)
        res = np.empty(6)
        for k in range(T):
            self._reset(d, x[k])
            d.ctrl[self._act] = u[k]
            Atot = np.eye(2 * nv)
            Btot = np.zeros((2 * nv, m.nu))
            for _ in range(self.substeps):
                mj.mjd_transitionFD(m, d, eps, True, Aj, Bj, None, None)
                Atot = Aj @ Atot
                Btot = Aj @ Btot + Bj
                mj.mj_step(m, d)
            mj.mj_forward(m, d)
            self._read(d, nxt, res)
            H = self._output_jacobian(d)
            A[k] = H @ Atot @ G
            B[k] = H @ Btot[:, self._act]
            c[k] = nxt - A[k] @ x[k] - B[k] @ u[k]
        W = np.asarray(cov, dtype=float)
        W = W * np.eye(self.n) if W.ndim == 0 else W
        return LinearGaussianDynamics(A, B, c, np.broadcast_to(W, (T, self.n, self.n)).copy())

    def ee_points(self, x) -> np.ndarray:
        """``(..., P, 3)`` positions of the state sites (for figures)."""
        x = np.asarray(x, dtype=float)
        return x[..., self.layout["site_pos"]].reshape(x.shape[:-1] + (len(self._site_ids), 3))


# --------------------------------------------------------------------------- loading


def _problems_dir() -> Path:
    try:
        import problems

        return Path(problems.__file__).resolve().parent
    except ImportError:  # pragma: no cover - source checkout without install
        return Path(__file__).resolve().parent.parent / "problems"


BUILTIN_TASKS = {"linear2d": "linear2d/linear2d.toml", "peg": "peg/peg.toml", "door": "door/door.toml"}


def build_task(config: TaskConfig | dict, base_dir: str | Path | None = None, *, xml: str | None = None,
               condition: int = 0):
    """A task from a config (object or dict); ``model`` paths are relative to ``base_dir``.

    ``xml``: an MJCF string to use instead of the ``model`` file.  The model
    file's existence is checked (error naming the file) before anything is built.
    """
    if isinstance(config, dict):
        config = TaskConfig.from_dict(config)
    if config.kind == "linear":
        return LinearTask(config, condition=condition)
    mj = _mujoco()
    if xml is not None:
        source = "<xml string>"
        try:
            model = mj.MjModel.from_xml_string(xml)
        except ValueError as e:
            raise ConfigError(f"MJCF string does not compile: {e}") from e
    else:
        if not config.model:
            raise ConfigError("model: a MuJoCo task needs 'model' (an MJCF file path relative to the config)")
        path = Path(config.model)
        if not path.is_absolute():
            path = Path(base_dir or ".") / path
        if not path.is_file():
            raise ConfigError(f"model: MJCF file {str(path)!r} does not exist")
        source = str(path)
        try:
            model = mj.MjModel.from_xml_path(str(path))
        except ValueError as e:
            raise ConfigError(f"model: MJCF file {str(path)!r} does not compile: {e}") from e
    return MujocoTask(config, model, condition=condition, source=source)


def load_task(name_or_path: str | Path, *, condition: int = 0, overrides: dict | None = None):
    """Load a built-in task (``linear2d``, ``peg``, ``door``) or a task TOML file.

    ``overrides``: top-level keys replacing the file's values (e.g. ``{"T": 20, "rho2": 0.01}``).
    """
    name = str(name_or_path)
    path = _problems_dir() / BUILTIN_TASKS[name] if name in BUILTIN_TASKS else Path(name)
    if not path.is_file():
        raise ConfigError(f"task {name!r}: not a built-in task ({', '.join(BUILTIN_TASKS)}) and no file {str(path)!r}")
    data = read_toml(path)
    data.update(overrides or {})
    try:
        config = TaskConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    return build_task(config, path.parent, condition=condition)


# --------------------------------------------------------------------------- rendering


@dataclass(frozen=True)
class RenderResult:
    """Where the picture went and how: ``backend`` is ``"egl"``, ``"osmesa"``, ... or ``"matplotlib"``."""

    path: str
    backend: str
    message: str


_RENDER_SCRIPT = r"""
import json, sys
import numpy as np
import mujoco
work = sys.argv[1]
spec = json.load(open(work + "/spec.json"))
m = mujoco.MjModel.from_binary_path(work + "/model.mjb")
d = mujoco.MjData(m)
Q = np.load(work + "/qpos.npy")
r = mujoco.Renderer(m, spec["height"], spec["width"])
cam = spec["camera"]
if cam is None:
    cam = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(m, cam)
    cam.lookat[:] = spec["lookat"]
    cam.distance = spec["distance"]
    cam.azimuth = spec["azimuth"]
    cam.elevation = spec["elevation"]
frames = []
for q in Q:
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    r.update_scene(d, camera=cam)
    frames.append(r.render().copy())
strip = np.concatenate(frames, axis=1)
from PIL import Image
Image.fromarray(strip).save(spec["path"])
print("ok", strip.shape)
"""


def _trajectory(traj) -> np.ndarray:
    if isinstance(traj, Rollouts):
        return np.asarray(traj.x)
    x = np.asarray(traj, dtype=float)
    return x[None] if x.ndim == 2 else x


def render_filmstrip(task, traj, path, frames: int = 8, width: int = 320, height: int = 240,
                     backends: tuple[str, ...] | None = None, timeout: float = 120.0) -> RenderResult:
    """A PNG filmstrip of a trajectory (``Rollouts``: sample 0's true states; or ``x (T+1, n)``).

    MuJoCo tasks are rendered offscreen with ``mujoco.Renderer`` in a subprocess
    (so a broken GL driver cannot take the caller down), trying ``MUJOCO_GL`` =
    ``egl`` then ``osmesa`` (a user-set ``MUJOCO_GL`` first).  If no backend works,
    or the task has no MuJoCo model, a matplotlib 3-D plot of the end-effector
    points of all samples is written instead and ``message`` says why.
    """
    path = str(path)
    X = _trajectory(traj)
    reasons = []
    if isinstance(task, MujocoTask):
        if backends is None:
            env_gl = os.environ.get("MUJOCO_GL", "").lower()
            backends = tuple(dict.fromkeys([b for b in (env_gl, "egl", "osmesa") if b in ("egl", "osmesa", "glfw")]))
        x = X[0]
        idx = np.unique(np.linspace(0, x.shape[0] - 1, max(1, frames)).round().astype(int))
        Q = task.qpos_from_state(x[idx])
        mj = _mujoco()
        m = task.model
        width = min(width, int(m.vis.global_.offwidth))
        height = min(height, int(m.vis.global_.offheight))
        pts = task.ee_points(x)
        center = pts.reshape(-1, 3).mean(axis=0) if pts.size else np.asarray(m.stat.center)
        spec = {
            "path": os.path.abspath(path), "width": width, "height": height, "camera": task.config.camera,
            "lookat": [float(v) for v in center], "distance": float(1.5 * max(m.stat.extent, 0.3)),
            "azimuth": 135.0, "elevation": -25.0,
        }
        with tempfile.TemporaryDirectory() as work:
            mj.mj_saveModel(m, os.path.join(work, "model.mjb"), None)
            np.save(os.path.join(work, "qpos.npy"), Q)
            with open(os.path.join(work, "spec.json"), "w") as f:
                json.dump(spec, f)
            for b in backends:
                env = dict(os.environ, MUJOCO_GL=b)
                if b in ("egl", "osmesa"):
                    env["PYOPENGL_PLATFORM"] = b
                try:
                    p = subprocess.run([sys.executable, "-c", _RENDER_SCRIPT, work], env=env, capture_output=True,
                                       text=True, timeout=timeout)
                except subprocess.TimeoutExpired:
                    reasons.append(f"{b}: timed out")
                    continue
                if p.returncode == 0 and os.path.isfile(path):
                    return RenderResult(path, b, f"rendered {len(idx)} frames with MUJOCO_GL={b}")
                err = (p.stderr.strip().splitlines() or [f"exit code {p.returncode}"])[-1]
                reasons.append(f"{b}: {err}")
        message = "MuJoCo offscreen rendering unavailable (" + "; ".join(reasons) + "); wrote a matplotlib plot instead"
    else:
        message = f"task {task.name!r} has no MuJoCo model; wrote a matplotlib plot of its points"
    _plot_points(task, X, path, message)
    return RenderResult(path, "matplotlib", message)


def _plot_points(task, X, path, title):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pts = task.ee_points(X)  # (M, T+1, P, 3)
    fig = Figure(figsize=(6, 5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    for p in range(pts.shape[2]):
        color = f"C{p}"
        for i in range(pts.shape[0]):
            ax.plot(pts[i, :, p, 0], pts[i, :, p, 1], pts[i, :, p, 2], color=color, alpha=0.6, lw=1,
                    label=f"point {p}" if i == 0 else None)
        ax.scatter(*pts[:, 0, p].T, color=color, marker="o", s=12)
        ax.scatter(*pts[:, -1, p].T, color=color, marker="x", s=16)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(loc="upper left", fontsize=7)
    fig.suptitle(f"{task.name}: end-effector points (o start, x end)", fontsize=9)
    fig.text(0.01, 0.01, title[:200], fontsize=6)
    fig.savefig(path, dpi=100)
