"""The task interface (:class:`Task`), the shared base class of the built-in tasks and
:class:`SimulationError` (docs/math.md §0, §8; docs/architecture.md, "tasks").

:class:`TaskBase` holds what every task shares: cost terms built from the config,
metrics, the initial distribution of ``s_0`` and the initial policy.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import Config, ConfigError
from ..costs import (
    CostSum,
    PointCost,
    QuadraticStateActionCost,
    StateCost,
    TorqueCost,
)
from ..models import (
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    QuadraticCost,
    Rollouts,
    ShapeError,
    symmetrize,
)
from ..noise.estimator import FilteredPolicy
from . import process_noise
from .config import (
    MetricConfig,
    PointTermConfig,
    QuadraticTermConfig,
    StateTermConfig,
    TaskConfig,
    TorqueTermConfig,
)

__all__ = ["SimulationError", "RolloutNoise", "Task", "TaskBase"]


class SimulationError(RuntimeError):
    """The simulation diverged (NaN/inf or a MuJoCo instability warning); names the sample and step."""


@dataclass(frozen=True)
class RolloutNoise:
    """The random draws of ``M`` rollouts, in the order :meth:`TaskBase.draw_noise` takes them.

    eps:   (M, T+1, n) measurement noise ``s_k - x_k`` (already scaled by ``sqrt(rho2)``).
    w:     (M, T, m)   standard normal policy noise (``a_k = K_k s_k + k_k + L_k w_k``; ``xhat_k``
                       in place of ``s_k`` for a filtered policy, docs/math.md §10.2).
    xi:    (M, T, n)   process noise added to the transition (scaled), or ``None`` when the
                       task has none (MuJoCo tasks).
    start: (M, k)      offsets of the start coordinates of ``x_0`` (``task.process_noise.start_idx``:
                       the angles of ``state.joints``, every component of a linear task), uniform in
                       ``[-r, r]``; ``None`` without ``[process_noise] start`` (docs/math.md §8.1).
    actuation: (M, T, m) actuation noise added to the control the plant receives (scaled); ``None``
                       without ``[process_noise] actuation``.
    """

    eps: np.ndarray
    w: np.ndarray
    xi: np.ndarray | None = None
    start: np.ndarray | None = None
    actuation: np.ndarray | None = None


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


class TaskBase(abc.ABC):
    """Shared behaviour: cost evaluation, metrics, initial distribution and policy.  A task kind derives
    from it and defines the two start hooks (:meth:`_start_coordinates`, :meth:`_start_jacobian`)."""

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
        names, idx, what = self._start_coordinates()
        self.process_noise = process_noise.resolve(c.process_noise, names, idx, self._action_names(), what)
        self._start_cov = None

    @abc.abstractmethod
    def _start_coordinates(self) -> tuple[list[str], np.ndarray, str]:
        """``(names, state indices, what they are)`` of the coordinates ``[process_noise] start`` offsets."""

    def _action_names(self) -> list[str]:
        """One name per action (for the errors of ``[process_noise] actuation``)."""
        return [f"a{i}" for i in range(self.m)]

    @abc.abstractmethod
    def _start_jacobian(self) -> np.ndarray:
        """``(n, k)``: ``d x_0 / d`` (start coordinates) at the nominal start."""

    # -- cost
    def _site_indices(self, sites, key) -> list[int]:
        raise ConfigError(f"{key}: this task has no sites")

    def _joint_index(self, joint, key) -> int:
        raise ConfigError(f"{key}: this task has no joints")

    def _build_term(self, i: int, t: Config):
        key = f"cost[{i}]"
        common = dict(ramp=t.ramp, final_multiplier=t.final_multiplier, weight=t.weight, window=t.window)
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
                    if t.target_offset is not None and len(t.target_offset) != len(idx):
                        raise ConfigError(f"{key}.target_offset: expected {len(idx)} numbers (3 per site), "
                                          f"got {len(t.target_offset)}")
                    return PointCost(self.n, self.m, idx, target_idx=tidx, target_offset=t.target_offset, wp=t.wp, l1=t.l1,
                                     l2=t.l2, alpha=t.alpha, **common)
                if t.target_offset is not None:
                    raise ConfigError(f"{key}.target_offset: only with 'target_sites' (a fixed 'target' needs no offset)")
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

    def stage_cost(self, s_k, a_k, k: int) -> float:
        """Stage cost ``Y_k`` of ``(s_k (n,), a_k (m,))`` at stage ``k`` alone, in O(1).

        Bit for bit ``self.cost(s, a)[..., k]`` of any trajectory through ``(s_k, a_k)`` at
        stage ``k`` (:meth:`soc_opt.costs.CostSum.stage`); the reward of one step of
        :class:`soc_opt.envs.SocOptEnv` (docs/gym.md, "Reward").
        """
        return self._cost.stage(s_k, a_k, k, self.T)

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
        """Mean of the measured initial state ``s_0``: the nominal initial state ``x_0`` (with
        ``[process_noise] start``, the mean of the true start to first order: docs/math.md §8.1)."""
        return self.x0.copy()

    @property
    def start_cov(self) -> np.ndarray:
        """``(n, n)`` covariance of the true initial state: zero for a known start, else the start range's
        ``J diag(r^2 / 3) J^T`` (:meth:`soc_opt.tasks.process_noise.ProcessNoise.start_cov`; exact on the
        joint rows, first order on the point rows; docs/math.md §8.1)."""
        if not self.process_noise.start_on:
            return np.zeros((self.n, self.n))
        if self._start_cov is None:
            self._start_cov = self.process_noise.start_cov(self._start_jacobian())
            self._start_cov.setflags(write=False)
        return self._start_cov.copy()

    @property
    def P0(self) -> np.ndarray:
        """Covariance of ``s_0 = x_0 + eps_0``: ``(rho2 + 1e-6) I`` (jitter keeps it PD for ``rho2 = 0``),
        plus :attr:`start_cov` with ``[process_noise] start``."""
        P0 = (self.rho2 + 1e-6) * np.eye(self.n)
        if self.process_noise.start_on:
            P0 = symmetrize(P0 + self.start_cov)
        return P0

    def initial_policy(self, var: float | None = None) -> LinearGaussianPolicy:
        """Zero gains and offsets (zero torque: with gravity off the arm holds still), cov ``var I``."""
        var = self.config.init_var if var is None else float(var)
        return LinearGaussianPolicy.zeros(self.T, self.n, self.m, var)

    def draw_noise(self, M: int, rng: np.random.Generator) -> RolloutNoise:
        """The noise of ``M`` rollouts drawn from ``rng`` in this order (docs/math.md §0, §8.1):
        ``eps``, ``w``, the transition noise ``xi`` of linear tasks, then the start offsets and the
        actuation noise of ``[process_noise]``, each of the last two only when it is on.

        :meth:`rollouts` draws through this method, so a caller replaying a rollout step by
        step (e.g. :class:`soc_opt.envs.SocOptEnv`) gets the same numbers from the same
        Generator state.
        """
        T, n, m = self.T, self.n, self.m
        eps = rng.standard_normal((M, T + 1, n)) * math.sqrt(self.rho2)
        w = rng.standard_normal((M, T, m))
        xi = self._draw_transition_noise(M, rng)
        start, act = self.process_noise.draw(M, T, rng)
        return RolloutNoise(eps, w, xi, start, act)

    def _draw_transition_noise(self, M: int, rng: np.random.Generator) -> np.ndarray | None:
        """The transition noise ``xi (M, T, n)`` of the task's own model (linear tasks), else ``None``."""
        return None

    def simulate(self, policy: LinearGaussianPolicy, x0=None) -> Rollouts:
        """One noise-free rollout of the policy mean (``eps = 0``, ``w = 0``) from ``x0`` (default ``x_0``)."""
        return self.rollouts(policy, 1, np.random.default_rng(0), noise=False, x0=x0)

    def _check_policy(self, policy) -> tuple[LinearGaussianPolicy, FilteredPolicy | None]:
        """``(gains, filtered)`` of a rollout policy, checked against the task's ``(T, m, n)``.

        A :class:`~soc_opt.noise.estimator.FilteredPolicy` (docs/math.md §10.2) acts on the filter's estimate
        ``xhat_k``, run online inside the rollout; ``gains`` is its linear-Gaussian part.  A plain
        :class:`LinearGaussianPolicy` acts on the measured ``s_k`` (``filtered`` is ``None``).
        """
        filtered = policy.for_task(self) if isinstance(policy, FilteredPolicy) else None
        gains = policy.policy if filtered is not None else policy
        if not isinstance(gains, LinearGaussianPolicy):
            raise TypeError(f"policy must be a LinearGaussianPolicy or a FilteredPolicy, got {type(policy).__name__}")
        if (gains.T, gains.m, gains.n) != (self.T, self.m, self.n):
            raise ShapeError(
                f"policy has (T, m, n) = {(gains.T, gains.m, gains.n)}, task {self.name!r} needs {(self.T, self.m, self.n)}"
            )
        return gains, filtered


def as_rng(rng) -> np.random.Generator:
    """``rng`` itself if it is a Generator, else ``default_rng(rng)`` (a seed, ``None`` or a SeedSequence).

    Not :func:`soc_opt.linalg.as_generator`, which rejects seeds: ``Task.rollouts`` accepts them.
    """
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
