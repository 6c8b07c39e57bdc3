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
import time
from typing import TYPE_CHECKING, Callable

import numpy as np

from ... import lqg
from ...config import ConfigError
from ...models import LinearGaussianDynamics, LinearGaussianPolicy, Rollouts, symmetrize
from ...noise.estimator import FilteredPolicy, kalman_filter, measurement_noise
from .config import ILQGConfig
from .state import ILQGRecord, ILQGState

if TYPE_CHECKING:
    from ...tasks import Task

__all__ = ["check_task", "initial_ilqg_state", "warm_start_actions", "ilqg_iteration", "linearize", "filtered_policy",
           "run_ilqg", "ilqg"]


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
    from ...tasks import SimulationError

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
    ``policy_var I``) is the iterate's, read on the estimate instead of the raw measurement.  With a start
    range (``[process_noise] start``) the prior covariance adds the task's ``start_cov``.
    """
    lin = linearize(task, state.x, state.u, cfg.fd_eps)
    T, n = lin.T, lin.n
    W = np.broadcast_to((cfg.filter_q ** 2) * np.eye(n), (T, n, n)).copy()
    R = measurement_noise(float(getattr(task, "rho2", 0.0)) + 1e-6, n)
    P0 = cfg.filter_p0 * np.eye(n)
    pn = getattr(task, "process_noise", None)
    if pn is not None and pn.start_on:  # a start range (docs/math.md §8.1): the prior covers it
        P0 = symmetrize(P0 + task.start_cov)
    kf = kalman_filter(LinearGaussianDynamics(lin.A, lin.B, lin.c, W), R, np.asarray(state.x[0], float), P0)
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
