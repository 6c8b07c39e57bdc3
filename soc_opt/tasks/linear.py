"""The linear-Gaussian task (``kind = "linear"``, e.g. ``linear2d``; docs/math.md §8)."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg

from ..config import ConfigError
from ..models import LinearGaussianDynamics, Rollouts
from .base import TaskBase, as_rng
from .config import TaskConfig

__all__ = ["LinearTask", "LinearSimulator"]


class LinearTask(TaskBase):
    """A discrete-time linear-Gaussian system (``kind = "linear"``; e.g. ``linear2d``, docs/math.md §8)."""

    kind = "linear"

    def __init__(self, config: TaskConfig, *, condition: int = 0):
        self.config = config
        lc = config.linear
        self.dt = (config.timestep or 0.1) * config.substeps
        if lc.system == "point_mass_2d":
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
        """``M`` rollouts (vectorised; ``workers`` is ignored).  Draw order: ``eps``, ``w``, process noise
        ``xi``, then ``[process_noise]``'s start offsets and actuation noise when on (:meth:`draw_noise`).

        A :class:`~soc_opt.noise.estimator.FilteredPolicy` acts on ``xhat_k``, its filter run online
        (causal: ``xhat_k`` from ``s_0..s_k`` and ``a_0..a_{k-1}``, docs/math.md §10.2); the draws are the
        same as for a plain policy.  ``[process_noise]``: ``x_0 + U(-r, r)`` per component (also with
        ``x0``), and ``x_{k+1} = A x_k + B (a_k + nu_k) + c + xi_k`` (docs/math.md §8.1); ``noise=False``
        draws none of them.
        """
        policy, filtered = self._check_policy(policy)
        rng = as_rng(rng)
        T, n, m = self.T, self.n, self.m
        start = nu = None
        if noise:
            draws = self.draw_noise(M, rng)
            eps, w, xi, start, nu = draws.eps, draws.w, draws.xi, draws.start, draws.actuation
        else:
            eps = np.zeros((M, T + 1, n))
            w = np.zeros((M, T, m))
            xi = np.zeros((M, T, n))
        L = policy.chol
        x = np.empty((M, T + 1, n))
        a = np.empty((M, T, m))
        x[:, 0] = self.x0 if x0 is None else np.asarray(x0, dtype=float)
        if start is not None:
            x[:, 0, self.process_noise.start_idx] += start
        s = x.copy()
        xhat = None
        for k in range(T):
            s[:, k] = x[:, k] + eps[:, k]
            if filtered is None:
                a[:, k] = s[:, k] @ policy.K[k].T + policy.k[k] + w[:, k] @ L[k].T
            else:
                xhat = filtered.estimate(k, s[:, k]) if k == 0 else filtered.estimate(k, s[:, k], xhat, a[:, k - 1])
                a[:, k] = xhat @ policy.K[k].T + policy.k[k] + w[:, k] @ L[k].T
            x[:, k + 1] = self.step(x[:, k], a[:, k] if nu is None else a[:, k] + nu[:, k]) + xi[:, k]
        s[:, T] = x[:, T] + eps[:, T]
        return self._finish(x, s, a)

    def _draw_transition_noise(self, M: int, rng: np.random.Generator) -> np.ndarray:
        """The process noise ``xi (M, T, n)`` of ``linear.process_var``, drawn after ``eps`` and ``w``."""
        return rng.standard_normal((M, self.T, self.n)) * math.sqrt(self.config.linear.process_var)

    def _start_coordinates(self):
        return list(self.state_labels), np.arange(self.n), "state component"

    def _start_jacobian(self) -> np.ndarray:
        return np.eye(self.n)

    def step(self, x, u) -> np.ndarray:
        """Noise-free transition ``A x + B u + c`` of ``x (..., n)``, ``u (..., m)`` (batched)."""
        return np.asarray(x, dtype=float) @ self.A.T + np.asarray(u, dtype=float) @ self.B.T + self.c

    def simulator(self) -> "LinearSimulator":
        """A step-by-step simulator of this task (what :class:`soc_opt.envs.SocOptEnv` steps)."""
        return LinearSimulator(self)

    def linearize(self, x=None, u=None, cov=None) -> LinearGaussianDynamics:
        """The exact model, repeated over the horizon T (process noise W unless ``cov`` is given)."""
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


class LinearSimulator:
    """One trajectory of a :class:`LinearTask`, one control step at a time.

    ``reset(x0)`` then ``step(u, xi)`` computes exactly what :meth:`LinearTask.rollouts`
    computes for one sample (same expression on ``(1, n)`` rows), so an episode replayed
    with the rollout's noise matches it bit for bit.  ``x``: the current true state ``(n,)``.
    """

    def __init__(self, task: LinearTask):
        self.task = task
        self.x = task.x0.copy()

    def reset(self, x0=None, start=None) -> np.ndarray:
        """Back to ``x0`` (default the task's ``x_0``) plus the start offsets ``start`` (one per component,
        a row of :attr:`RolloutNoise.start`); returns a copy of the state."""
        self.x = self.task.x0.copy() if x0 is None else np.array(x0, dtype=float)
        if start is not None:
            self.x[self.task.process_noise.start_idx] += start
        return self.x.copy()

    def step(self, u, xi=None, actuation=None) -> np.ndarray:
        """``x <- A x + B (u + actuation) + c (+ xi)``; returns a copy of the new state."""
        u = np.asarray(u, dtype=float)
        if actuation is not None:
            u = u + actuation
        nxt = self.task.step(self.x[None], u[None])[0]
        self.x = nxt if xi is None else nxt + xi
        return self.x.copy()
