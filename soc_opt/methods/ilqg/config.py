"""iLQG's own settings, the ``[ilqg]`` table of a run configuration (docs/math.md §7)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ...config import Config, Interval, config_error
from ..limits import MAX_ITERATIONS

__all__ = ["ILQGConfig"]


@dataclass(frozen=True)
class ILQGConfig(Config):
    """Model-based iLQG on a known model (docs/math.md §7); the ``[ilqg]`` table of a run configuration.

    iterations:  maximum outer iterations (``soc-opt run --method ilqg --iterations N`` overrides it).
    mu_init:     initial Levenberg–Marquardt regulariser added to the action Hessian.
    mu_factor:   multiply/divide ``mu`` by this on rejection/acceptance.
    mu_max:      give up past this regulariser.
    mu_restart:  after a failed backward pass ``mu`` becomes at least this (so that ``mu_init = 0``
                 still grows).
    alphas:      backtracking line-search step sizes, tried in order.
    tol:         stop when the relative cost decrease is below ``tol``.
    policy_var:  covariance of the returned (initialiser) policy.
    fd_eps:      finite-difference step of the MuJoCo linearisation (``task.linearize(..., eps=fd_eps)``; a
                 task whose linearisation is exact, e.g. a linear task, ignores it).  Default 1e-2: through
                 the door's hook-handle contact a step of 1e-6 gives Jacobians of norm up to 7e13 (spectral
                 radius 2e11) and iLQG from zero actions stops at min hinge -0.50 (cost 62, no descent
                 step); 1e-3: -0.88 (43.6); 3e-3: -0.997 (1.76); 1e-2: -1.002 (2.21, converged); 3e-2: -0.98
                 (4.8).  Peg: cost 16.8 at 1e-6, 13.9 at 1e-2 (docs/results/acceptance.md §5).
    filter_q:    process-noise standard deviation per control step, ``W = filter_q^2 I``, of the Kalman filter the
                 final policy acts on under sensor noise (:func:`filtered_policy`; 1e-3: the door and peg have no
                 process noise, ``W`` stands for the linearisation's error).  Door at rho^2 = 0.1, mean action:
                 1e-3 min hinge -1.010 (cost 4.6), 1e-2 -0.874 (98.5).
    filter_p0:   prior variance of the start state in that filter (``P0 = filter_p0 I`` around the task's
                 ``x_0``, 1e-6, plus the task's ``start_cov`` with ``[process_noise] start``): iLQG plans from
                 the task's nominal start.  With the measurement's own variance
                 (``rho^2 + 1e-6``) the door's mean action reaches only -0.16.
    init_policy: path of a policy ``.npz`` (e.g. a learned run's ``final_policy.npz``) whose mean action,
                 run once without noise from the task's start, gives the initial actions (default: zero
                 actions).  A warm start: iLQG then refines that trajectory on the known model.  The file
                 is read when the run starts (its actions are in the checkpoint from then on).
    """

    iterations: int = 20
    mu_init: float = 1e-6
    mu_factor: float = 10.0
    mu_max: float = 1e10
    mu_restart: float = 1e-6
    alphas: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.03, 0.01)
    tol: float = 1e-4
    policy_var: float = 1.0
    fd_eps: float = 1e-2
    filter_q: float = 1e-3
    filter_p0: float = 1e-6
    init_policy: str | None = None

    _constraints = {
        "iterations": [Interval(1, MAX_ITERATIONS)],
        "mu_init": [Interval(0)],
        "mu_factor": [Interval(1, None, "neither")],
        "mu_max": [Interval(0, None, "neither")],
        "mu_restart": [Interval(0, None, "neither")],
        "tol": [Interval(0)],
        "policy_var": [Interval(0, None, "neither")],
        "fd_eps": [Interval(0, None, "neither")],
        "filter_q": [Interval(0, None, "neither")],
        "filter_p0": [Interval(0, None, "neither")],
    }

    def __post_init__(self):
        if self.mu_max < self.mu_init:
            raise config_error("mu_max", f"must be >= mu_init, got {self.mu_max!r}")
        if not self.alphas or not all(a > 0 for a in self.alphas):
            raise config_error("alphas", f"must be non-empty and positive, got {self.alphas!r}")
        if self.init_policy is not None:
            if not isinstance(self.init_policy, str) or not self.init_policy:
                raise config_error("init_policy", f"expected the path of a policy .npz file, got {self.init_policy!r}")
            if not Path(self.init_policy).is_file():
                raise config_error("init_policy", f"no such file: {self.init_policy!r}")
