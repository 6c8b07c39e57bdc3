"""iLQG's saved state (docs/math.md §7): :class:`ILQGState` and its history rows :class:`ILQGRecord`
(cost, regulariser, step size; no ``kl``, ``nu``, ``mult`` columns)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np

from ...models import LinearGaussianPolicy, Rollouts
from ..state import BestPolicy

__all__ = ["ILQGRecord", "ILQGState"]


@dataclass(frozen=True)
class ILQGRecord:
    """One iLQG iteration (a row of ``metrics.csv``).

    cost:      (1,) total cost of the noise-free rollout of the iterate after this iteration
               (the previous iterate's when no step was accepted).
    mu:        the regulariser after the iteration; ``alpha`` the accepted step size (0 if none).
    accepted:  whether a descent step was found.
    rel_decrease: relative cost decrease of the iteration.
    metrics:   the task metric of that rollout; ``timings``: wall time per phase (seconds).
    """

    iteration: int
    cost: np.ndarray
    mu: float
    alpha: float
    accepted: bool
    rel_decrease: float
    metrics: dict[str, float]
    timings: dict[str, float]
    phase: Literal["ilqg"] = "ilqg"
    em: None = None

    nonfinite_floats: ClassVar[bool] = True  # a record: state files accept NaN/inf here

    def summary(self) -> dict:
        """The ``metrics.csv`` row; ``cost_mean`` is the cost of the single noise-free rollout."""
        return {
            "iteration": self.iteration,
            "phase": self.phase,
            "cost_mean": float(np.mean(self.cost)),
            "mu": self.mu,
            "alpha": self.alpha,
            "accepted": self.accepted,
            "rel_decrease": self.rel_decrease,
            **{f"metric_{k}": v for k, v in self.metrics.items()},
            **{f"time_{k}": v for k, v in self.timings.items()},
        }


@dataclass(frozen=True)
class ILQGState:
    """Everything needed to continue an iLQG run (checkpointed after each iteration).

    iteration:     finished outer iterations.
    x:             (T+1, n) nominal states of the current iterate.
    u:             (T, m) nominal actions.
    K:             (T, m, n) feedback gains of the last accepted step (zeros before).
    J:             total cost of the current iterate.
    mu:            current Levenberg–Marquardt regulariser.
    costs:         cost of every accepted iterate, the initial one first (strictly decreasing).
    policy:        the current iterate as a linear-Gaussian policy (covariance ``policy_var I``).
    status:        "running", "converged" (relative decrease below ``tol``) or "no_descent"
                   (``mu`` passed ``mu_max`` without a descent step).
    history:       the :class:`ILQGRecord` of every iteration.
    last_rollouts: the noise-free rollout of the current iterate.
    """

    iteration: int
    x: np.ndarray
    u: np.ndarray
    K: np.ndarray
    J: float
    mu: float
    costs: tuple[float, ...]
    policy: LinearGaussianPolicy
    status: Literal["running", "converged", "no_descent"] = "running"
    history: tuple[ILQGRecord, ...] = ()
    last_rollouts: Rollouts | None = None

    @property
    def best(self):
        """The lowest-cost iterate so far (:class:`~soc_opt.methods.state.BestPolicy`; iLQG only
        accepts descent steps, so it is the current one), or None before the first iteration."""
        if not self.history:
            return None
        costs = [float(np.mean(r.cost)) for r in self.history]
        return BestPolicy(self.J, self.policy, int(np.argmin(costs)))
