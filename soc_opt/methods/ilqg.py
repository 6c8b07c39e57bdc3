"""Model-based iLQG on a known model (docs/math.md §7), as a resumable step function.

One iLQG iteration linearises the task along the nominal trajectory (``task.linearize``: MuJoCo
finite differences, or the exact model of a linear task), expands the cost to second order,
and searches for a descent step: an LQR backward pass with the Levenberg–Marquardt term
``mu I`` on the action Hessian, then a backtracking line search on the feed-forward change.
An accepted step lowers ``mu``; a failed backward pass or line search raises it, up to
``mu_max``.

The loop is written like the sample-based methods (:mod:`soc_opt.methods`): an explicit
:class:`ILQGState` and a pure step :func:`ilqg_iteration`, so that ``soc-opt run --method ilqg``
checkpoints after every iteration and a resumed run ends with the same numbers as an
uninterrupted one (iLQG draws no random numbers).  :func:`ilqg` is the one-call form.
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, ClassVar, Literal

import numpy as np

from .. import files, lqg
from ..config import Config, ConfigError, Interval, config_error
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, Rollouts
from ..noise.estimator import FilteredPolicy, kalman_filter, measurement_noise
from .base import MethodBase
from .config import MAX_ITERATIONS
from .state import BestPolicy

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["ILQGConfig", "ILQGRecord", "ILQGState", "check_task", "initial_ilqg_state", "warm_start_actions",
           "ilqg_iteration", "linearize", "filtered_policy",
           "run_ilqg", "ilqg", "ILQG", "ILQG_METHOD"]


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
                 ``x_0``, 1e-6): iLQG plans from the task's known start.  With the measurement's own variance
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


def check_task(task: Task) -> None:
    """Raise :class:`ConfigError` (before any simulation) if iLQG cannot run on ``task``.

    iLQG needs ``task.linearize``; a MuJoCo task needs every degree of freedom of its model in
    the state (:meth:`soc_opt.tasks.MujocoTask.check_linearizable` names the missing joints).
    """
    if not callable(getattr(task, "linearize", None)):
        raise ConfigError(f"task {task.name!r} has no linearize(): iLQG needs a model it can linearise")
    check = getattr(task, "check_linearizable", None)
    if check is not None:
        check()


def _policy(K, x, u, cfg: ILQGConfig) -> LinearGaussianPolicy:
    T, m, _ = K.shape
    k = u - np.einsum("tij,tj->ti", K, x[:-1])
    return LinearGaussianPolicy(K, k, np.broadcast_to(cfg.policy_var * np.eye(m), (T, m, m)).copy())


def _simulate(task: Task, K, kff) -> tuple[np.ndarray, np.ndarray, float, Rollouts]:
    """The noise-free rollout of ``a = K s + kff``: states, actions, total cost, the rollout."""
    T, m = kff.shape
    pol = LinearGaussianPolicy(K, kff, np.zeros((T, m, m)), allow_singular=True)
    ro = task.rollouts(pol, 1, np.random.default_rng(0), noise=False)
    return ro.x[0], ro.a[0], float(task.true_cost(ro)[0].sum()), ro


def initial_ilqg_state(task: Task, cfg: ILQGConfig = ILQGConfig(), u_init: np.ndarray | None = None) -> ILQGState:
    """The state before the first iteration: the rollout of the open-loop actions ``u_init`` (default 0)."""
    T, n, m = task.T, task.n, task.m
    u = np.zeros((T, m)) if u_init is None else np.asarray(u_init, float).copy()
    K = np.zeros((T, m, n))
    x, u, J, ro = _simulate(task, K, u)
    return ILQGState(iteration=0, x=x, u=u, K=K, J=J, mu=cfg.mu_init, costs=(J,),
                     policy=_policy(K, x, u, cfg), last_rollouts=ro)


def warm_start_actions(task: Task, path: str | None) -> np.ndarray | None:
    """``(T, m)`` initial actions from the policy file ``path`` (:attr:`ILQGConfig.init_policy`): its mean
    action ``K s + k`` run once without noise from the task's start; ``None`` without a file."""
    if path is None:
        return None
    try:
        pol = LinearGaussianPolicy.load(path, allow_singular=True)
    except (OSError, ValueError) as e:
        raise ConfigError(f"init_policy: {path!r} is not a readable policy file ({e})") from None
    if (pol.T, pol.m, pol.n) != (task.T, task.m, task.n):
        raise ConfigError(f"init_policy: {path!r} has (T, m, n) = {(pol.T, pol.m, pol.n)}, the task "
                          f"{task.name!r} needs {(task.T, task.m, task.n)}")
    ro = task.rollouts(pol.mean_policy(), 1, np.random.default_rng(0), noise=False)
    return np.asarray(ro.a[0])


def _line_search(task, cfg, x, u, J, Knew, d):
    """The first step size in ``cfg.alphas`` whose rollout lowers the cost, or None."""
    from ..tasks import SimulationError

    for alpha in cfg.alphas:
        kff = u + alpha * d - np.einsum("tij,tj->ti", Knew, x[:-1])
        try:
            x_new, u_new, J_new, ro = _simulate(task, Knew, kff)
        except (SimulationError, ValueError, FloatingPointError):
            continue  # a diverging trial step is a rejected step
        if J_new < J:
            return alpha, x_new, u_new, J_new, ro
    return None


def linearize(task: Task, x, u, eps: float):
    """``task.linearize(x, u, eps=eps)``, or ``task.linearize(x, u)`` for a task whose linearisation takes no
    finite-difference step (an exact model)."""
    if "eps" in inspect.signature(task.linearize).parameters:
        return task.linearize(x, u, eps=eps)
    return task.linearize(x, u)


def ilqg_iteration(task: Task, cfg: ILQGConfig, state: ILQGState) -> ILQGState:
    """One outer iLQG iteration (module docstring).  Pure: returns a new state."""
    n, m = task.n, task.m
    x, u, J = state.x, state.u, state.J
    t0 = time.perf_counter()
    dyn = linearize(task, x, u, cfg.fd_eps)
    cost = task.cost_expansion(x, u)
    t_lin = time.perf_counter() - t0
    t0 = time.perf_counter()
    mu = state.mu
    found = None
    while mu <= cfg.mu_max and found is None:
        C = np.array(cost.C)
        C[:, n:, n:] += mu * np.eye(m)
        reg = type(cost)(C, cost.c, cost.n, cost.c0)
        try:
            pol = lqg.lqr(dyn, reg, x[0], np.eye(n) * 1e-9)  # (mu0, P0) do not enter the gains
        except ValueError:
            mu = max(mu * cfg.mu_factor, cfg.mu_restart)
            continue
        Knew = np.asarray(pol.K)
        d = np.einsum("tij,tj->ti", Knew, x[:-1]) + pol.k - u  # change of the mean action at x_bar
        found = _line_search(task, cfg, x, u, J, Knew, d)
        if found is None:
            mu *= cfg.mu_factor
    timings = {"linearize": t_lin, "search": time.perf_counter() - t0}
    if found is None:
        rec = ILQGRecord(state.iteration, np.array([J]), float(mu), 0.0, False, 0.0,
                         _metrics(task, state.last_rollouts), timings)
        return dataclasses.replace(state, iteration=state.iteration + 1, mu=mu, status="no_descent",
                                   history=state.history + (rec,))
    alpha, x_new, u_new, J_new, ro = found
    rel = (J - J_new) / max(abs(J), 1e-12)
    mu = max(mu / cfg.mu_factor, cfg.mu_init)
    rec = ILQGRecord(state.iteration, np.array([J_new]), float(mu), float(alpha), True, float(rel),
                     _metrics(task, ro), timings)
    return ILQGState(
        iteration=state.iteration + 1, x=x_new, u=u_new, K=Knew, J=J_new, mu=mu,
        costs=state.costs + (J_new,), policy=_policy(Knew, x_new, u_new, cfg),
        status="converged" if rel < cfg.tol else "running",
        history=state.history + (rec,), last_rollouts=ro,
    )


def filtered_policy(task: Task, state: ILQGState, cfg: ILQGConfig = ILQGConfig()) -> FilteredPolicy:
    """The iterate acting on a Kalman filter of its own model: what iLQG runs under sensor noise (docs/math.md §7).

    iLQG knows the model, so its estimator may too: the time-varying Kalman filter (docs/math.md §10.2)
    of the linearisation along the nominal trajectory (``x_{k+1} = A_k x_k + B_k a_k + c_k``, the
    ``task.linearize`` the iterations plan with, step ``fd_eps``), process noise ``W = filter_q^2 I``
    for the linearisation's error, measurement noise ``R = (rho^2 + 1e-6) I`` (the task's), prior
    ``N(x_0, filter_p0 I)`` at the task's start.  The policy ``a_k = K_k xhat_k + k_k`` (covariance
    ``policy_var I``) is the iterate's, read on the estimate instead of the raw measurement.
    """
    lin = linearize(task, state.x, state.u, cfg.fd_eps)
    T, n = lin.T, lin.n
    W = np.broadcast_to((cfg.filter_q ** 2) * np.eye(n), (T, n, n)).copy()
    R = measurement_noise(float(getattr(task, "rho2", 0.0)) + 1e-6, n)
    kf = kalman_filter(LinearGaussianDynamics(lin.A, lin.B, lin.c, W), R, np.asarray(state.x[0], float),
                       cfg.filter_p0 * np.eye(n))
    return FilteredPolicy(state.policy, kf)


def _metrics(task, ro) -> dict[str, float]:
    return {k: float(v) for k, v in task.metrics(ro).items()} if ro is not None else {}


def run_ilqg(task: Task, cfg: ILQGConfig = ILQGConfig(), state: ILQGState | None = None,
             on_iteration: Callable[[ILQGState], None] | None = None) -> ILQGState:
    """Iterate from ``state`` (or a fresh start) until ``cfg.iterations`` iterations, convergence
    or no descent; ``on_iteration`` gets the new state after every iteration (checkpointing)."""
    check_task(task)
    if state is None:
        state = initial_ilqg_state(task, cfg)
    while state.iteration < cfg.iterations and state.status == "running":
        state = ilqg_iteration(task, cfg, state)
        if on_iteration is not None:
            on_iteration(state)
    return state


def ilqg(task: Task, x0: np.ndarray | None = None, u_init: np.ndarray | None = None, cfg: ILQGConfig = ILQGConfig(),
         on_iteration: Callable[[int, float, float], None] | None = None):
    """Model-based iLQG on a known model (docs/math.md §7), in one call.

    Derivatives from ``task.linearize`` (MuJoCo: ``mujoco.mjd_transitionFD``, or central
    differences of the whole step for the RK4 integrator), Levenberg–Marquardt regularisation
    ``mu I`` on the action Hessian, backtracking line search on the feed-forward term.  Returns
    ``(policy, costs)`` where ``costs`` lists the cost of every accepted iterate (strictly
    decreasing) and ``policy`` is a linear-Gaussian initialiser ``a = u_bar + K (s - s_bar)``
    with covariance ``policy_var * I``.  ``on_iteration(it, J, mu)`` is called after every
    accepted step (``it``: 0-based outer iteration).  ``x0`` is unused (the task's initial
    state is used).
    """
    def report(st: ILQGState):
        if on_iteration is not None and st.history[-1].accepted:
            on_iteration(st.iteration - 1, st.J, st.mu)

    check_task(task)
    st = run_ilqg(task, cfg, initial_ilqg_state(task, cfg, u_init), on_iteration=report)
    return st.policy, list(st.costs)


class ILQG(MethodBase):
    """iLQG as a :class:`~soc_opt.methods.base.Method`: reads the ``[ilqg]`` table; deterministic
    (the seed is not part of a run's identity); stops early on convergence or without descent."""

    name = "ilqg"
    sections: tuple[str, ...] = ("ilqg",)
    seeded = False
    sample_based = False
    cost_phase = "ilqg"
    settings = ILQGConfig  # the [ilqg] table
    state_types = (ILQGState, ILQGRecord)

    def check_task(self, task: Task, cfg=None) -> None:
        check_task(task)

    def check_file(self, data: dict, path) -> None:
        misplaced = sorted(set(data) & set(ILQGConfig.__dataclass_fields__))
        if misplaced:
            raise ConfigError(f"{path}: iLQG settings {', '.join(map(repr, misplaced))} belong in an [ilqg] "
                              "table of the run configuration (docs/configuration.md)")

    def apply_overrides(self, cfg, values: dict, paper: bool):
        unused = sorted(k for k in values if k != "iterations") + (["paper"] if paper else [])
        if unused:
            raise ConfigError(f"--{unused[0].replace('_', '-')} does not apply to --method ilqg "
                              "(it sets the sample-based methods); iLQG reads the [ilqg] table and --iterations")
        if "iterations" in values:
            cfg = cfg.replace(ilqg=cfg.ilqg.replace(iterations=values["iterations"]))
        return cfg

    def total_iterations(self, cfg) -> int:
        return cfg.ilqg.iterations

    def initial_state(self, task: Task, cfg, seed: int) -> ILQGState:
        return initial_ilqg_state(task, cfg.ilqg, warm_start_actions(task, cfg.ilqg.init_policy))

    def iterate(self, task: Task, cfg, state: ILQGState) -> ILQGState:
        return ilqg_iteration(task, cfg.ilqg, state)

    def finished(self, cfg, state: ILQGState) -> bool:
        return state.iteration >= cfg.ilqg.iterations or state.status != "running"

    def progress_fields(self, record: ILQGRecord) -> dict[str, float]:
        return {"mu": float(record.mu)}

    def progress_line(self, seed: int, where: str, state: ILQGState, metrics: str, times: str) -> str:
        rec = state.history[-1]
        step = f"step {rec.alpha:g}" if rec.accepted else "no descent step"
        return f"[ilqg] {where} cost {np.mean(rec.cost):.6g}  {step}  mu {rec.mu:.1e}  {metrics}  {times}"

    def finish(self, state: ILQGState, out) -> str:
        buf = io.BytesIO()
        np.savez_compressed(buf, **state.policy.to_dict())
        files.write_bytes(out / "policy.npz", buf.getvalue())  # renamed into place: no link followed
        why = {"converged": "converged (relative decrease below tol)", "no_descent": "no descent step found",
               "running": "iteration limit"}[state.status]
        return (f"iLQG: cost {state.costs[0]:.6g} -> {state.costs[-1]:.6g} in {len(state.costs) - 1} accepted "
                f"iterations ({why}); final policy {out / 'policy.npz'}; run directory {out}")


ILQG_METHOD = ILQG()
