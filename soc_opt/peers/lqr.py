"""LQR kernels: the KL step's backward pass against mpc.pytorch's LQR step (docs/math.md §6).

The peer is ``mpc`` (mpc.pytorch, the differentiable box-constrained iLQR solver): its problem,
``min sum_{t<T} 1/2 tau_t^T C_t tau_t + c_t^T tau_t`` with ``tau_t = (x_t, u_t)`` and
``x_{t+1} = F_t tau_t + f_t``, no terminal cost, is soc_opt's :class:`~soc_opt.models.QuadraticCost`
and the mean of :class:`~soc_opt.models.LinearGaussianDynamics` (certainty equivalence: the
process noise changes no gain).  One LQR step from ``u = 0`` (``lqr_iter=1``, no bounds, the
line search accepts the full step on a convex problem) returns the optimal trajectory
``(x, u)`` from ``x_0``; mpc.pytorch does not return its gains, so the comparison is on that
trajectory: ``u_t = K_t x_t + k_t`` for soc_opt's gains.

Two solves per instance:

* **plain LQR**: :func:`soc_opt.lqg.lqr` (the backward pass with ``eta = 0``) against the peer on
  the same cost;
* **the KL step**: :func:`soc_opt.lqg.kl_step` with a total budget (closed form: dual solve, a
  handful of backward passes).  At its multiplier ``eta`` the new policy's mean is the LQR
  solution of the cost ``l - eta log phat`` (docs/math.md §6), i.e. ``C + eta [[Kh^T R Kh,
  -Kh^T R], [-R Kh, R]]``, ``c + eta [Kh^T R kh; -R kh]`` with ``R = Sh^-1``; the peer solves that
  LQR once (it has no KL constraint, so it is handed the multiplier soc_opt found).

Public functions:
    kl_cost(cost, reference, eta)                     -> QuadraticCost
    mean_trajectory(dynamics, policy, x0)             -> (x (T, n), u (T, m))
    run_mpc(dynamics, cost, x0)                       -> (x, u, seconds)
    compare(rng, n, m, T, nu, repeats)                -> dict (one row of the table)
"""

from __future__ import annotations

import time

import numpy as np

from ..lqg import kl_step, lqr
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost, symmetrize
from ..testing import make_kl_instance as make_instance
from . import require

__all__ = ["kl_cost", "mean_trajectory", "run_mpc", "compare"]


def kl_cost(cost: QuadraticCost, reference: LinearGaussianPolicy, eta: float | np.ndarray) -> QuadraticCost:
    """The cost ``l - eta log phat`` (constants dropped) whose LQR gains are the KL step's at ``eta``."""
    T, m, n = reference.K.shape
    eta = np.broadcast_to(np.asarray(eta, dtype=float), (T,))
    R = np.linalg.inv(reference.cov)
    G = np.concatenate([-reference.K, np.eye(m)[None].repeat(T, 0)], axis=2)  # a - Kh s = G z
    C = cost.C + eta[:, None, None] * np.einsum("tai,tab,tbj->tij", G, R, G)
    c = cost.c - eta[:, None] * np.einsum("tai,tab,tb->ti", G, R, reference.k)
    return QuadraticCost(symmetrize(C), c, n)


def mean_trajectory(dynamics: LinearGaussianDynamics, policy: LinearGaussianPolicy, x0) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free rollout of the policy mean from ``x0``: ``x (T, n)``, ``u (T, m)``."""
    T, m, n = policy.K.shape
    x = np.empty((T, n))
    u = np.empty((T, m))
    s = np.asarray(x0, dtype=float)
    for t in range(T):
        x[t] = s
        u[t] = policy.K[t] @ s + policy.k[t]
        s = dynamics.A[t] @ s + dynamics.B[t] @ u[t] + dynamics.c[t]
    return x, u


def run_mpc(dynamics: LinearGaussianDynamics, cost: QuadraticCost, x0) -> tuple[np.ndarray, np.ndarray, float]:
    """mpc.pytorch's LQR step (float64, one batch element): ``x (T, n)``, ``u (T, m)``, seconds."""
    torch = require("torch")
    try:
        mpc_mod = require("mpc.mpc")
    except ImportError as e:
        raise ImportError("mpc (mpc.pytorch) is not installed and is not in the [peers] extra: its sdist's "
                          "metadata is invalid for current setuptools; docs/results/peers/README.md shows how "
                          "to build its wheel") from e
    T, n, m = dynamics.B.shape
    F = torch.as_tensor(np.concatenate([dynamics.A, dynamics.B], axis=2)[:-1, None])  # (T-1, 1, n, n+m)
    f = torch.as_tensor(dynamics.c[:-1, None])
    C = torch.as_tensor(cost.C[:, None])
    c = torch.as_tensor(cost.c[:, None])
    solver = mpc_mod.MPC(n, m, T, lqr_iter=1, exit_unconverged=False, backprop=False, verbose=-1,
                         n_batch=1, u_init=torch.zeros(T, 1, m, dtype=torch.float64))
    t0 = time.perf_counter()
    x, u, _ = solver(torch.as_tensor(np.asarray(x0, dtype=float)[None]), mpc_mod.QuadCost(C, c),
                     mpc_mod.LinDx(F, f))
    dt = time.perf_counter() - t0
    return x[:, 0].numpy(), u[:, 0].numpy(), dt


def _timed(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def compare(rng: np.random.Generator, n: int, m: int, T: int, nu: float = 1.0, repeats: int = 5) -> dict:
    """One row: times (median of ``repeats``) and max trajectory differences for both solves."""
    dyn, cost, ref, mu0, P0 = make_instance(n, m, T, rng)
    row = {"n": n, "m": m, "T": T}
    pol, so_s = _timed(lambda: lqr(dyn, cost, mu0, P0), repeats)
    xs, us = mean_trajectory(dyn, pol, mu0)
    (xp, up, _), mpc_s = _timed(lambda: run_mpc(dyn, cost, mu0), repeats)
    row.update(lqr_soc_opt_ms=1e3 * so_s, lqr_mpc_ms=1e3 * mpc_s, lqr_ratio=mpc_s / so_s,
               lqr_max_du=float(np.abs(us - up).max()), lqr_max_dx=float(np.abs(xs - xp).max()),
               u_scale=float(np.abs(us).max()))
    res, kl_s = _timed(lambda: kl_step(dyn, cost, ref, nu, mu0, P0), repeats)
    eta = float(res.eta[0])
    xk, uk = mean_trajectory(dyn, res.policy, mu0)
    (xq, uq, _), mpc_kl_s = _timed(lambda: run_mpc(dyn, kl_cost(cost, ref, eta), mu0), repeats)
    row.update(kl_nu=nu, kl_eta=eta, kl_backward_passes=res.n_backward, kl_soc_opt_ms=1e3 * kl_s,
               kl_mpc_one_lqr_ms=1e3 * mpc_kl_s, kl_ratio=mpc_kl_s / kl_s,
               kl_max_du=float(np.abs(uk - uq).max()), kl_max_dx=float(np.abs(xk - xq).max()))
    return row
