"""The KL-step row of the claims table (docs/math.md §6, §9), checked through the library's code path like
the rows of :mod:`soc_opt.verification.checks`.

``kl_step`` — the closed-form KL-constrained LQG step (``lqg.kl_step``: the dual over the multipliers, one
backward pass per trial multiplier) returns a KKT point of ``min sum_k E[l_k] s.t. KL_k <= nu_k`` (per-step
budgets) or ``sum_k KL_k <= nu`` (one total budget), and so, the problem being convex in the policy's
moments, its solution.  Checked per instance, each quantity from a second code path of the library
(``lqg.expected_cost`` and ``lqg.kl_divergence``: the closed-form forward pass and KL of :mod:`soc_opt.lqg.moments`,
not the dual's own eigenvalue form of the KL):

1. *feasibility and complementary slackness*: ``KL_k <= nu_k`` for every step, with equality where
   ``eta_k > 10 eta_min`` (relative ``KL_TOL``; for a total budget on the sum);
2. *stationarity*: the returned policy minimises the Lagrangian ``sum_k E[l_k] + sum_k eta_k KL_k`` for
   its multipliers: the central-difference gradient in ``(K_k, k_k, L_k)`` (``Sigma_k = L_k L_k^T``) is at
   most ``GRAD_TOL`` of the gradients of its two parts (free of units);
3. *strong and weak duality*: the returned ``dual_value`` equals the expected cost, and the dual function
   (``lqg.dual.dual_function``: the backward pass, the forward pass and ``lqg.dual.dual_objective``) at
   multipliers ``e^{+-1/2} eta`` and at random ones stays below the optimal cost (plus ``eta`` times the
   budgets' own tolerance), as for any feasible policy.

A sign error in the dual's KL (its covariance term) breaks 1, a backward pass that reads the wrong step
breaks 2, a sign flip in ``dual_objective`` breaks 3 (tests/test_verification_claims.py, the mutants).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import lqg
from ..errors import SolverError
from ..lqg import dual as lqg_dual
from ..lqg.problem import KLProblem, KLStepConfig
from ..models import LinearGaussianPolicy, NotPositiveDefiniteError
from ..testing import make_kl_instance
from .checks import Outcome

__all__ = ["KL_TOL", "GRAD_TOL", "DUAL_TOL", "KlCase", "kl_case", "kl_step_kkt"]

#: relative tolerance of KL_k against nu_k (the dual solver stops at 1e-10 relative; the second code path
#: agrees to about 1e-13)
KL_TOL = 1e-7
#: stationarity: |grad Lagrangian| <= GRAD_TOL (|grad cost| + |grad eta KL|) (central differences, step 1e-5)
GRAD_TOL = 1e-5
#: duality: |dual_value - cost| and the weak-duality slack, relative to 1 + |cost|
DUAL_TOL = 1e-8


@dataclass(frozen=True)
class KlCase:
    """One instance's measurements: the worst relative violation of each KKT condition (<= 0 or small: held)."""

    kind: str
    feasibility: float  # max_k (KL_k - nu_k) / nu_k on the second code path
    slackness: float  # max over active steps |KL_k - nu_k| / nu_k
    stationarity: float  # |grad L| / (|grad cost| + |grad eta KL|)
    strong: float  # |dual_value - cost| / (1 + |cost|)
    weak: float  # max over trial multipliers (g(eta') - cost - eta' tol) / (1 + |cost|)

    @property
    def ok(self) -> bool:
        return (self.feasibility <= KL_TOL and self.slackness <= KL_TOL and self.stationarity <= GRAD_TOL
                and self.strong <= DUAL_TOL and self.weak <= DUAL_TOL)

    @property
    def margin(self) -> float:
        return max(self.feasibility / KL_TOL, self.slackness / KL_TOL, self.stationarity / GRAD_TOL,
                   self.strong / DUAL_TOL, self.weak / DUAL_TOL)


def _params(policy: LinearGaussianPolicy) -> tuple[np.ndarray, np.ndarray]:
    """``theta`` = every ``K_k``, ``k_k`` and lower-triangular ``L_k`` entry, and the lower-triangle mask."""
    L = np.linalg.cholesky(policy.cov)
    low = np.tril(np.ones(policy.cov.shape[1:], dtype=bool))
    return np.concatenate([policy.K.ravel(), policy.k.ravel(), L[:, low].ravel()]), low


def _policy(theta: np.ndarray, T: int, m: int, n: int, low: np.ndarray) -> LinearGaussianPolicy:
    K = theta[:T * m * n].reshape(T, m, n)
    k = theta[T * m * n:T * m * (n + 1)].reshape(T, m)
    L = np.zeros((T, m, m))
    L[:, low] = theta[T * m * (n + 1):].reshape(T, -1)
    return LinearGaussianPolicy(K, k, L @ np.swapaxes(L, 1, 2))


def _stationarity(prob, policy, eta, scalar: bool) -> float:
    """Relative norm of the Lagrangian's central-difference gradient at ``policy`` (module docstring, 2)."""
    dyn, cost, ref, mu0, P0 = prob
    T, m, n = policy.K.shape
    theta, low = _params(policy)
    w = np.full(T, eta[0]) if scalar else np.where(np.isfinite(eta), eta, 0.0)

    def parts(th):
        p = _policy(th, T, m, n, low)
        return float(lqg.expected_cost(dyn, cost, p, mu0, P0).sum()), float(w @ lqg.kl_divergence(dyn, p, ref, mu0, P0))

    g_cost, g_kl = np.zeros_like(theta), np.zeros_like(theta)
    for i in range(theta.size):
        h = 1e-5 * max(1.0, abs(theta[i]))
        up, dn = theta.copy(), theta.copy()
        up[i] += h
        dn[i] -= h
        (cu, ku), (cd, kd) = parts(up), parts(dn)
        g_cost[i], g_kl[i] = (cu - cd) / (2 * h), (ku - kd) / (2 * h)
    scale = np.linalg.norm(g_cost) + np.linalg.norm(g_kl)
    return float(np.linalg.norm(g_cost + g_kl) / scale) if scale > 0 else 0.0


def kl_case(rng: np.random.Generator, n: int, m: int, T: int, kind: str) -> KlCase:
    """Draw one instance (``testing.make_kl_instance``, budgets in ``[0.05, 0.5]`` per step) and check it."""
    prob = make_kl_instance(n, m, T, rng)
    dyn, cost, ref, mu0, P0 = prob
    per_step = rng.uniform(0.05, 0.5, T)
    scalar = kind == "total"
    nu = float(per_step.sum()) if scalar else per_step
    cfg = KLStepConfig()
    res = lqg.kl_step(dyn, cost, ref, nu, mu0, P0)
    kl = lqg.kl_divergence(dyn, res.policy, ref, mu0, P0)
    c_star = float(lqg.expected_cost(dyn, cost, res.policy, mu0, P0).sum())
    eta = np.asarray(res.eta, dtype=float)
    if scalar:
        feas = float((kl.sum() - nu) / nu)
        slack = abs(feas) if eta[0] > 10 * cfg.eta_min else 0.0
        nu_k = np.full(T, nu / T)
    else:
        feas = float(np.max((kl - per_step) / per_step))
        active = eta > 10 * cfg.eta_min
        slack = float(np.max(np.abs(kl - per_step)[active] / per_step[active])) if active.any() else 0.0
        nu_k = per_step
    strong = abs(float(res.dual_value) - c_star) / (1.0 + abs(c_star))
    kp = KLProblem(dyn, cost, ref, mu0, P0)
    trials = [eta * np.exp(0.5), eta * np.exp(-0.5)]
    trials.append(eta * np.exp(rng.uniform(-1, 1, 1 if scalar else T)))
    weak = -np.inf
    excess = np.maximum(kl - nu_k, 0.0) if not scalar else np.full(T, max(kl.sum() - nu, 0.0) / T)
    for e in trials:
        g, _ = lqg_dual.dual_function(kp, np.broadcast_to(e, (T,)).copy(), nu_k)
        allowance = float(np.broadcast_to(e, (T,)) @ excess)
        weak = max(weak, (g - c_star - allowance) / (1.0 + abs(c_star)))
    return KlCase(kind, feas, slack, _stationarity(prob, res.policy, eta, scalar), strong, float(weak))


def kl_step_kkt(rng: np.random.Generator, instances: int, full: bool):
    """The ``kl_step`` row: sizes ``n`` in 1..3, ``m`` in 1..2, ``T`` in 1..4, total and per-step budgets in turn."""
    out = Outcome("worst KKT violation over the checks, in units of each check's tolerance (held if <= 1)")
    for i in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(1, 5))
        kind = ("total", "per_step")[i % 2]
        try:
            case = kl_case(rng, n, m, T, kind)
        except (SolverError, NotPositiveDefiniteError) as e:  # the step itself failed on a convex instance
            out.add(False, np.inf, {"n": n, "m": m, "T": T, "budget": kind, "error": f"{type(e).__name__}: {e}"})
            continue
        out.add(case.ok, case.margin, {"n": n, "m": m, "T": T, "budget": kind, "feasibility": case.feasibility,
                                       "slackness": case.slackness, "stationarity": case.stationarity,
                                       "strong_duality": case.strong, "weak_duality": case.weak})
    return out, None
