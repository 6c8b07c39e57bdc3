"""Task configuration: the TOML schema of a task (docs/math.md §0, §8; ``docs/tasks.md``).

:class:`TaskConfig` is the top level; ``cost`` entries are parsed into the term
configs by their ``type`` key (:data:`TERM_TYPES`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from ..config import Config, ConfigError, config_error

__all__ = [
    "Ramp",
    "FloatOrList",
    "StateConfig",
    "PointTermConfig",
    "TorqueTermConfig",
    "StateTermConfig",
    "QuadraticTermConfig",
    "TERM_TYPES",
    "MetricConfig",
    "LinearConfig",
    "GymConfig",
    "ProcessNoiseConfig",
    "GYM_PREFIX",
    "PKG_PREFIX",
    "MAX_HORIZON",
    "MAX_SUBSTEPS",
    "TaskConfig",
]

#: Prefix of a task name or ``model`` naming a Gymnasium environment (``gym:<EnvId>``; docs/gym.md).
GYM_PREFIX = "gym:"
#: Prefix of a ``model`` naming an MJCF file shipped inside an installed Python package
#: (``pkg:<package>/<path inside the package>``, e.g. ``pkg:gymnasium/envs/mujoco/assets/reacher.xml``).
PKG_PREFIX = "pkg:"
#: Longest horizon ``T`` and most simulator steps per time step a task may ask for (docs/security.md): the
#: paper's tasks use 100 steps; these keep a task file from asking for a run that never ends.
MAX_HORIZON = 10_000
MAX_SUBSTEPS = 10_000

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
    target is a fixed ``target`` (3 per site) or ``target_sites`` (moving points), optionally shifted
    by ``target_offset`` (3 per site, world frame: ``d`` measured to ``target_site + offset``).
    """

    type: Literal["point"] = "point"
    sites: tuple[str, ...] = ()
    indices: tuple[int, ...] = ()
    target: tuple[float, ...] | None = None
    target_sites: tuple[str, ...] = ()
    target_offset: tuple[float, ...] | None = None
    wp: FloatOrList = 1.0
    l1: float = 0.0
    l2: float = 1.0
    alpha: float = 1e-5
    ramp: Ramp = "constant"
    final_multiplier: float = 1.0
    weight: float = 1.0
    window: tuple[float, ...] | None = None


@dataclass(frozen=True)
class TorqueTermConfig(Config):
    """``type = "torque"``: ``1/2 a^T diag(wu) a``."""

    type: Literal["torque"] = "torque"
    wu: FloatOrList = 1.0
    ramp: Ramp = "constant"
    final_multiplier: float = 1.0
    weight: float = 1.0
    window: tuple[float, ...] | None = None


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
    window: tuple[float, ...] | None = None


@dataclass(frozen=True)
class QuadraticTermConfig(Config):
    """``type = "quadratic"``: docs/math.md §0 ``(s-s*)^T Qs (s-s*) + (a-a*)^T Qa (a-a*)``.

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
    window: tuple[float, ...] | None = None


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

    def __post_init__(self):
        for key in ("mass", "tau", "process_var"):
            value = getattr(self, key)
            if not (value > 0 if key != "process_var" else value >= 0):
                err = ConfigError(f"{key}: must be {'positive' if key != 'process_var' else '>= 0'}, got {value!r}")
                err.key = key  # TaskConfig.from_dict prefixes the table: "linear.mass: ..."
                raise err


@dataclass(frozen=True)
class GymConfig(Config):
    """``[gym]``: options of a task whose ``model`` is ``"gym:<EnvId>"`` (docs/gym.md).

    reset_seed: the initial state ``x_0`` is the environment's state after
                ``env.reset(seed=reset_seed + condition)`` (its own initial distribution,
                e.g. Reacher's random goal), fixed for the whole run.
    kwargs:     keyword arguments of ``gymnasium.make`` (e.g. ``{ctrl_cost_weight = 0.2}``).
    fd_step:    relative step ``h_i = fd_step * max(1, |z_i|)`` of the finite-difference
                expansion of ``-reward`` (when no ``cost`` terms override it).
    """

    reset_seed: int = 0
    kwargs: dict[str, Any] = field(default_factory=dict)
    fd_step: float = 1e-4

    def __post_init__(self):
        if not self.fd_step > 0:
            raise ConfigError(f"gym.fd_step: must be positive, got {self.fd_step!r}")
        if self.reset_seed < 0:
            raise ConfigError(f"gym.reset_seed: must be >= 0 (a Gymnasium seed), got {self.reset_seed!r}")
        if "render_mode" in self.kwargs:
            raise ConfigError("gym.kwargs: 'render_mode' is not allowed (soc_opt renders with render_filmstrip)")


@dataclass(frozen=True)
class ProcessNoiseConfig(Config):
    """``[process_noise]``: randomness of the plant itself, beside the sensor noise ``rho2``
    (docs/math.md §8.1; ``docs/tasks.md``, "Process noise").  Both default to 0: nothing is drawn.

    start:     half-width ``r`` of a uniform range around the start: the true ``x_0`` of each rollout
               has the joint angles ``q0 + U(-r, r)`` (rad, or m for slide joints) for the joints of
               ``state.joints`` (velocities as without it, zero for MJCF tasks; points by forward
               kinematics); a number for every joint or one per joint.  Linear tasks: one per state
               component (``x_0 + U(-r, r)``).
    actuation: standard deviation of Gaussian noise added to the control the plant receives, drawn
               per control step and actuator and held over the step's substeps (the units of the
               action); a number for every actuator or one per actuator.  The recorded action ``a``
               stays the policy's, so a learner sees it as process noise.  Linear tasks: added to
               ``a`` before ``B``.
    """

    start: FloatOrList = 0.0
    actuation: FloatOrList = 0.0

    def __post_init__(self):
        for key in ("start", "actuation"):
            value = getattr(self, key)
            values = value if isinstance(value, (tuple, list)) else (value,)
            if not values:
                raise config_error(key, "an empty list; give a number or one per entry")
            for i, v in enumerate(values):
                if not v >= 0:
                    raise config_error(f"{key}[{i}]" if isinstance(value, (tuple, list)) else key, f"must be >= 0, got {v!r}")


@dataclass(frozen=True)
class TaskConfig(Config):
    """A task: model, horizon, state definition, cost terms, noise, metric (see ``docs/tasks.md``).

    ``model``: an MJCF file relative to the config, ``"pkg:<package>/<path>"`` for an MJCF file
    inside an installed Python package (e.g. Gymnasium's raw ``reacher.xml``), or ``"gym:<EnvId>"``
    for a Gymnasium MuJoCo environment (options in ``[gym]``; ``docs/gym.md``).

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
    gym: GymConfig = field(default_factory=GymConfig)
    camera: str | None = None
    process_noise: ProcessNoiseConfig = field(default_factory=ProcessNoiseConfig)

    #: Run directories recorded before ``[process_noise]`` existed ran without it (docs/tasks.md).
    _implied_when_absent = {"process_noise": ({"start": 0.0, "actuation": 0.0}, {})}

    def __post_init__(self):
        checks = [
            ("T", 1 <= self.T <= MAX_HORIZON, f"must be in [1, {MAX_HORIZON}]"),
            ("substeps", 1 <= self.substeps <= MAX_SUBSTEPS, f"must be in [1, {MAX_SUBSTEPS}]"),
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
