"""LQR and the KL-constrained LQG step (SPEC §6).

Problem.  Dynamics ``s_{k+1} ~ N(A_k s_k + B_k a_k + c_k, W_k)`` (``k = 0..T-1``), stage
costs ``l_k(z) = 1/2 z^T C_k z + z^T c_k + c0_k`` on ``z = (s_k, a_k)`` (no terminal cost:
``s_T`` is not charged), ``s_0 ~ N(mu0, P0)``, a reference policy
``phat(a|s) = N(Kh_k s + kh_k, Sh_k)`` with ``Sh_k > 0`` and KL budgets ``nu``::

    min_p  sum_k E_p[l_k]   s.t.   KL_k = E_{p(s_k)} KL(p(.|s_k) || phat(.|s_k)) <= nu_k

``nu`` is either a ``(T,)`` array (per-step budgets, multipliers ``eta_k``) or a scalar (one
total budget ``sum_k KL_k <= nu`` with one multiplier ``eta``, the GPS form).

Lagrangian and sign convention.  ``L(p, eta) = sum_k E[l_k] + sum_k eta_k (KL_k - nu_k)`` with
``eta_k >= 0``; the dual ``g(eta) = min_p L(p, eta)`` is concave with gradient
``dg/deta_k = KL_k - nu_k`` (envelope theorem).  CasADi/IPOPT use the Lagrangian
``f + lam_g^T g``; for ``g_k = KL_k <= ubg_k = nu_k`` an active upper bound has
``lam_g_k >= 0`` and ``lam_g_k = eta_k`` (no sign flip; checked by the tests).

Closed form for fixed ``eta`` (``eta_k > 0``).  ``E_p[l] + eta (KL - nu)`` equals
``E_p[l - eta log phat] - eta H(p) - eta nu``; a backward pass with the quadratic
Q-function ``Q_k`` of ``l_k - eta_k log phat + V_{k+1}`` gives
``p(a|s) = N(-Quu^{-1}(Qus s + qu), eta_k Quu^{-1})``, and the value function keeps only its
quadratic and linear parts ``V = Qss - Qsu Quu^{-1} Qus``, ``v = qs - Qsu Quu^{-1} qu``: the
entropy, log-normaliser and noise constants do not affect any policy, and the dual value is
evaluated exactly from the forward pass instead (``g = sum E[l] + sum eta (KL - nu)``).
``eta_k = 0`` (only for ``nu_k = inf``) removes the KL term: the step is the deterministic
LQR step.  ``eta_k = inf`` (only for ``nu_k = 0``) pins the step to the reference.

Every finite budget is active in a non-degenerate problem: as ``eta_k -> 0`` the policy
covariance ``eta_k Quu^{-1}`` collapses and ``KL_k -> inf``.  A budget is slack only when
``nu_k = inf`` (``eta_k = 0`` exactly), or when it is so large that ``KL_k(eta_min) < nu_k``
(then ``eta_k = eta_min``, "numerically zero"; this happens for ``nu_k`` above about
``m/2 log(1/eta_min)``), or in degenerate steps where the action changes no cost.

Dual solvers (method ``"closed_form"``), each counting its backward passes (one backward
pass = one policy; each is followed by one forward pass for the moments and ``KL_k``):

* scalar ``eta`` (total budget): ``KL(eta) = sum_k KL_k`` is continuous and strictly decreasing,
  so we solve ``log KL(e^x) = log nu`` for ``x = log eta`` by a safeguarded Newton/secant
  iteration with bisection fallback (:func:`_solve_scalar`).  Typically 5-9 backward passes.
* vector ``eta`` (per-step budgets): the concave dual is maximised over ``eta_k >= eta_min`` by a
  projected, diagonally preconditioned L-BFGS method in ``x = log eta`` with the analytic
  gradient ``eta_k (KL_k - nu_k)`` (:func:`_solve_vector`).  Typically 10-20 backward passes,
  independent of ``T``.

Quu repair rule (GPS-style).  If a backward pass meets a ``Quu_k`` that is not positive
definite (Cholesky fails), the smallest multiplier making it PD with the later steps fixed is
``eta_crit = -lambda_min(Lh^T Q0uu Lh)`` (``Sh = Lh Lh^T``, ``Q0uu`` = ``Quu`` without the KL term);
the multiplier is raised to ``max(repair_factor * eta, (1 + repair_margin) * eta_crit)`` and the pass
restarted (scalar ``eta``) or continued (per step).  Past ``config.eta_max`` a
:class:`~soc_opt.models.NotPositiveDefiniteError` names the step.

CasADi form (method ``"casadi"``): the same problem as an NLP over ``(K_k, k_k, L_k)`` with
single-shooting moments, solved by IPOPT (:func:`_kl_step_casadi`), in one of two formulations
(``KLStepConfig.casadi_nlp``, by default chosen by size):

* ``"symbolic"`` (:func:`_casadi_symbolic`, up to ``casadi_auto_max_vars = 600`` NLP variables):
  SX expressions and CasADi's symbolic exact Hessian, dense in all variables; a reference solver
  for small problems (documented and tested for ``n <= 6, T <= 20``).
* ``"structured"`` (:class:`_StructuredNLP`, above): the policy variables rescaled by the
  reference policy (KL Hessian close to the identity), objective and constraints as chained
  per-step CasADi functions, the gradient and the constraint Jacobian from the adjoint
  (value-function) recursion of the moment dynamics, and a per-step block-diagonal Hessian of
  the Lagrangian.  The Lagrangian is linear in the state second moments, and at a KKT point the
  backward-pass optimality ``(Q_ux + Q_uu G_k) X_k = 0`` makes every cross-step block of the
  exact Hessian vanish: IPOPT sees the exact Hessian at the solution and converges
  superlinearly, in 12-16 iterations from the reference on the random instances up to
  ``n=26, m=7, T=100`` (21 700 variables; about 10 s), about 40 when some budget is slack and
  ``Sigma_k`` collapses onto the ``chol_floor`` bound.

Both agree with the closed form to about 1e-10 in policy and multipliers on the tested
instances.

Speed (closed form, one core of the development machine, ``n=26, m=7, T=100``): scalar budget
about 40 ms / 8 backward passes, per-step budgets about 80 ms / 16 passes
(``python -m soc_opt.bench.lqg``).

Step-size adaptation (GPS, SPEC §6 last bullet): :func:`laplace_improvements` and
:func:`adapt_step`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np
from scipy.linalg import lapack

from .config import Config
from .models import (
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    QuadraticCost,
    ShapeError,
    check_array,
    check_covariances,
    symmetrize,
)

__all__ = [
    "SolverError",
    "Marginals",
    "KLStepConfig",
    "KLStepResult",
    "LocalModel",
    "forward",
    "expected_cost",
    "kl_divergence",
    "lqr",
    "kl_step",
    "adapt_step",
    "laplace_improvements",
]


class SolverError(RuntimeError):
    """A numerical solver (IPOPT, the dual solver) failed; the message carries its status."""


class Marginals(NamedTuple):
    """State-action marginals of a linear-Gaussian closed loop.

    Fields:
        mean:    (T+1, n)    ``E[s_k]``
        cov:     (T+1, n, n) ``Cov(s_k)``
        a_mean:  (T, m)      ``E[a_k]``
        a_cov:   (T, m, m)   ``Cov(a_k)``
        sa_cov:  (T, n, m)   ``Cov(s_k, a_k)``
    """

    mean: np.ndarray
    cov: np.ndarray
    a_mean: np.ndarray
    a_cov: np.ndarray
    sa_cov: np.ndarray


@dataclass(frozen=True)
class KLStepConfig(Config):
    """Hyperparameters of :func:`kl_step` and :func:`adapt_step` (SPEC §6).

    Dual solver (closed form):
        kl_rtol, kl_atol: stop when ``|KL - nu| <= kl_rtol * nu + kl_atol`` for every active
                        budget (1e-10, 1e-13 per step: the roundoff floor of the KL formula).
        eta_init:       first multiplier when no warm start ``eta0`` is given (1.0).
        eta_min:        lower bound on a finite-budget multiplier; a budget with
                        ``KL(eta_min) < nu`` is reported slack with ``eta = eta_min`` (1e-12).
        eta_max:        upper bound; reaching it is an error (1e16).
        max_backward:   budget of backward passes for one dual solve (500).
        max_log_step:   cap on one step of either dual solver in ``log eta`` (``log 1e3``).
    Quu repair (see module docstring):
        repair_factor:  multiplicative raise of ``eta`` (10.0).
        repair_margin:  relative margin above the exact PD threshold (0.1).
    CasADi / IPOPT:
        ipopt_tol:      IPOPT ``tol`` (1e-12); ``ipopt_acceptable_tol`` (1e-9).
        ipopt_max_iter: IPOPT ``max_iter`` (3000).
        chol_floor:     lower bound on the diagonal of the NLP's Cholesky factors ``L_k`` (1e-9;
                        structured formulation: on the diagonal of ``Gam_k = Lh_k^-1 L_k``).
        ipopt_options:  extra options passed as ``ipopt.<key>`` (override the above).
        casadi_nlp:     NLP formulation: ``"symbolic"`` (single shooting in ``(K, k, L)``, dense
                        exact Hessian built symbolically by CasADi: the reference solver for small
                        problems, tested up to ``n=6, m=3, T=20``), ``"structured"`` (single
                        shooting in rescaled ``(K, k, L)``, analytic adjoint gradient and
                        Jacobian, per-step block-diagonal Hessian that is exact at the solution:
                        seconds at ``n=26, m=7, T=100``, tested up to there) or ``"auto"``
                        (default): ``"symbolic"`` up to ``casadi_auto_max_vars`` NLP variables,
                        ``"structured"`` above.  Both agree with the closed form to about 1e-10.
        casadi_auto_max_vars: the ``"auto"`` threshold (600: just above the largest tested
                        symbolic size, 540 variables at ``n=6, m=3, T=20``, where the symbolic
                        Hessian already takes tens of seconds to build; its cost grows about
                        cubically with the size).
    Step-size adaptation (:func:`adapt_step`, GPS rule):
        min_mult, max_mult: clip of the budget multiplier ``predicted / (2 (predicted - actual))``
                        (0.1, 5.0).
        min_gap:        floor of the denominator ``predicted - actual`` (1e-4, cost units).
        nu_min, nu_max: clip of the new budget (1e-4, 1e4).
    """

    kl_rtol: float = 1e-10
    kl_atol: float = 1e-13
    eta_init: float = 1.0
    eta_min: float = 1e-12
    eta_max: float = 1e16
    max_backward: int = 500
    max_log_step: float = math.log(1e3)
    repair_factor: float = 10.0
    repair_margin: float = 0.1
    ipopt_tol: float = 1e-12
    ipopt_acceptable_tol: float = 1e-9
    ipopt_max_iter: int = 3000
    chol_floor: float = 1e-9
    ipopt_options: dict[str, Any] = field(default_factory=dict)
    casadi_nlp: Literal["auto", "symbolic", "structured"] = "auto"
    casadi_auto_max_vars: int = 600
    min_mult: float = 0.1
    max_mult: float = 5.0
    min_gap: float = 1e-4
    nu_min: float = 1e-4
    nu_max: float = 1e4

    def __post_init__(self):
        pos = ("kl_rtol", "kl_atol", "eta_init", "eta_min", "eta_max", "max_log_step", "ipopt_tol",
               "ipopt_acceptable_tol", "chol_floor", "min_mult", "max_mult", "min_gap", "nu_min", "nu_max")
        for name in pos:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"KLStepConfig.{name} must be a positive finite number, got {v!r}")
        if self.eta_min >= self.eta_max:
            raise ValueError("KLStepConfig.eta_min must be below eta_max")
        if self.repair_factor <= 1.0 or self.repair_margin < 0.0:
            raise ValueError("KLStepConfig.repair_factor must be > 1 and repair_margin >= 0")
        if self.min_mult > self.max_mult or self.nu_min > self.nu_max:
            raise ValueError("KLStepConfig: min_mult <= max_mult and nu_min <= nu_max required")
        if self.max_backward < 1 or self.ipopt_max_iter < 1:
            raise ValueError("KLStepConfig.max_backward and ipopt_max_iter must be >= 1")
        if self.casadi_nlp not in ("auto", "symbolic", "structured"):
            raise ValueError("KLStepConfig.casadi_nlp must be 'auto', 'symbolic' or 'structured', "
                             f"got {self.casadi_nlp!r}")
        mv = self.casadi_auto_max_vars
        if isinstance(mv, bool) or not isinstance(mv, int) or mv < 0:
            raise ValueError(f"KLStepConfig.casadi_auto_max_vars must be an integer >= 0, got {mv!r}")


class KLStepResult(NamedTuple):
    """Result of :func:`kl_step`.

    Fields:
        policy:        the optimal :class:`LinearGaussianPolicy` (``allow_singular`` where
                       ``eta_k = 0``).
        eta:           (T,) multipliers; for a scalar budget all entries are the one ``eta``.
        kl:            (T,) ``KL_k`` of ``policy`` against the reference.
        expected_cost: ``sum_k E[l_k]`` of ``policy`` (float).
        n_backward:    backward passes used (closed form; CasADi: 0).
        scalar_eta:    True when ``nu`` was a scalar (one total budget, one multiplier).
        nu:            the budget(s) as given: float or (T,).
        dual_value:    ``g(eta) = sum E[l] + sum eta (KL - nu)`` (closed form) or the NLP
                       objective (CasADi).
        method:        ``"closed_form"`` or ``"casadi"``.
        n_iter:        dual iterations (closed form) or IPOPT iterations.
        status:        solver status string.
        marginals:     :class:`Marginals` of the optimal policy.
        lam_g:         CasADi only: IPOPT multipliers of the KL constraints (one per constrained
                       step, or one for the total budget).
        solver_stats:  CasADi only: ``{"n_vars", "formulation", "build_s", "solve_s"}`` (NLP size,
                       ``"symbolic"`` or ``"structured"`` (``"none"`` if nothing was solved),
                       seconds to build the NLP (symbolic: with its exact Hessian), seconds in
                       IPOPT).
    """

    policy: LinearGaussianPolicy
    eta: np.ndarray
    kl: np.ndarray
    expected_cost: float
    n_backward: int
    scalar_eta: bool
    nu: Any
    dual_value: float
    method: str
    n_iter: int
    status: str
    marginals: Marginals
    lam_g: np.ndarray | None = None
    solver_stats: dict | None = None


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------


def _check_dims(dynamics, *, cost=None, policy=None, reference=None) -> tuple[int, int, int]:
    if not isinstance(dynamics, LinearGaussianDynamics):
        raise TypeError(f"dynamics must be a LinearGaussianDynamics, got {type(dynamics).__name__}")
    T, n, m = dynamics.T, dynamics.n, dynamics.m
    if cost is not None:
        if not isinstance(cost, QuadraticCost):
            raise TypeError(f"cost must be a QuadraticCost, got {type(cost).__name__}")
        if (cost.T, cost.n, cost.m) != (T, n, m):
            raise ShapeError(
                f"cost has (T, n, m) = {(cost.T, cost.n, cost.m)} but dynamics has {(T, n, m)}"
            )
    for name, pol in (("policy", policy), ("reference", reference)):
        if pol is None:
            continue
        if not isinstance(pol, LinearGaussianPolicy):
            raise TypeError(f"{name} must be a LinearGaussianPolicy, got {type(pol).__name__}")
        if (pol.T, pol.n, pol.m) != (T, n, m):
            raise ShapeError(f"{name} has (T, n, m) = {(pol.T, pol.n, pol.m)} but dynamics has {(T, n, m)}")
    return T, n, m


def _check_init(mu0, P0, n: int) -> tuple[np.ndarray, np.ndarray]:
    mu0 = check_array("mu0", mu0, (n,))
    P0 = check_array("P0", P0, (n, n))
    P0 = check_covariances("P0", P0, psd_only=True)
    return mu0, P0


def _reference_chol(reference: LinearGaussianPolicy) -> np.ndarray:
    """Lower Cholesky factors of the reference covariances; clear error if not PD."""
    out = np.empty_like(reference.cov)
    for t in range(reference.T):
        L, info = lapack.dpotrf(reference.cov[t], lower=1, clean=1)
        if info != 0:
            ev = float(np.linalg.eigvalsh(reference.cov[t])[0])
            raise NotPositiveDefiniteError(
                f"reference cov[{t}] is not positive definite (smallest eigenvalue {ev:.3e}); "
                "the KL step needs a reference policy with Sigma > 0"
            )
        out[t] = L
    return out


def _check_nu(nu, T: int) -> tuple[np.ndarray, bool]:
    """Return ``(nu as (T,) or (1,), scalar?)``; errors name the step."""
    a = np.asarray(nu, dtype=float)
    if a.ndim == 0:
        scalar = True
        a = a.reshape(1)
    elif a.shape == (T,):
        scalar = False
    else:
        raise ShapeError(f"nu must be a scalar (total budget) or have shape ({T},), got {a.shape}")
    if np.any(np.isnan(a)):
        raise ValueError(f"nu contains NaN (at step {int(np.argwhere(np.isnan(a))[0, 0])})")
    if np.any(a < 0):
        t = int(np.argwhere(a < 0)[0, 0])
        where = "the total budget" if scalar else f"step {t}"
        raise ValueError(f"infeasible budget: nu is negative ({a[t]!r}) for {where}; KL >= 0 always")
    return a, scalar


# --------------------------------------------------------------------------------------------
# moments: forward pass, expected cost, KL
# --------------------------------------------------------------------------------------------


def _forward_arrays(dynamics: LinearGaussianDynamics, K, k, S, mu0, P0) -> Marginals:
    T, n = dynamics.T, dynamics.n
    A, B = dynamics.A, dynamics.B
    Acl = A + B @ K  # (T, n, n) closed-loop state matrices
    AclT = np.swapaxes(Acl, 1, 2)
    bias = (B @ k[:, :, None])[:, :, 0] + dynamics.c
    N = (B @ S) @ np.swapaxes(B, 1, 2) + dynamics.cov  # B Sigma B^T + W
    mean = np.empty((T + 1, n))
    cov = np.empty((T + 1, n, n))
    mean[0] = mu0
    cov[0] = P0
    mu = mu0
    tmp = np.empty((n, n))
    for t in range(T):
        Ac = Acl[t]
        mu = Ac @ mu + bias[t]
        mean[t + 1] = mu
        np.matmul(Ac, cov[t], out=tmp)
        Pn = cov[t + 1]
        np.matmul(tmp, AclT[t], out=Pn)
        Pn += N[t]
        Pn += Pn.T
        Pn *= 0.5
    sa_cov = cov[:T] @ np.swapaxes(K, 1, 2)  # Cov(s, a) = P K^T, (T, n, m)
    a_mean = (K @ mean[:T, :, None])[:, :, 0] + k
    a_cov = symmetrize(K @ sa_cov + S)
    return Marginals(mean, cov, a_mean, a_cov, sa_cov)


def forward(dynamics: LinearGaussianDynamics, policy: LinearGaussianPolicy, mu0, P0) -> Marginals:
    """State-action marginals of ``policy`` on ``dynamics`` from ``s_0 ~ N(mu0, P0)``.

    ``E[s_{k+1}] = (A + B K) E[s_k] + B k + c``,
    ``Cov(s_{k+1}) = (A + B K) P_k (A + B K)^T + B Sigma B^T + W``; action moments
    ``E[a] = K E[s] + k``, ``Cov(a) = K P K^T + Sigma``, ``Cov(s, a) = P K^T``.
    """
    T, n, m = _check_dims(dynamics, policy=policy)
    mu0, P0 = _check_init(mu0, P0, n)
    return _forward_arrays(dynamics, policy.K, policy.k, policy.cov, mu0, P0)


def _expected_cost_marg(cost: QuadraticCost, marg: Marginals) -> np.ndarray:
    n, T = cost.n, cost.T
    zbar = np.concatenate([marg.mean[:T], marg.a_mean], axis=1)
    C = cost.C
    # tr(C Cov(z)) with Cov(z) = [[P, Psa], [Psa^T, Pa]] (C symmetric)
    tr = (
        np.einsum("tij,tij->t", C[:, :n, :n], marg.cov[:T])
        + 2.0 * np.einsum("tij,tij->t", C[:, :n, n:], marg.sa_cov)
        + np.einsum("tij,tij->t", C[:, n:, n:], marg.a_cov)
    )
    quad = np.einsum("ti,ti->t", (C @ zbar[:, :, None])[:, :, 0], zbar)
    return 0.5 * tr + 0.5 * quad + np.einsum("ti,ti->t", zbar, cost.c) + cost.c0


def expected_cost(dynamics, cost, policy, mu0, P0) -> np.ndarray:
    """(T,) closed-form ``E[l_k(s_k, a_k)] = 1/2 tr(C_k Cov(z_k)) + l_k(E[z_k])``."""
    _check_dims(dynamics, cost=cost, policy=policy)
    return _expected_cost_marg(cost, forward(dynamics, policy, mu0, P0))


def _logdet_pd(S: np.ndarray) -> np.ndarray:
    """(T,) log-determinants by Cholesky; ``-inf`` where a matrix is not PD (singular)."""
    out = np.empty(S.shape[0])
    for t in range(S.shape[0]):
        L, info = lapack.dpotrf(S[t], lower=1, clean=1)
        out[t] = 2.0 * np.log(np.diag(L)).sum() if info == 0 else -np.inf
    return out


def _kl_batched(K, k, S, logdetS, Kh, kh, Shinv, logdetSh, mean, cov) -> np.ndarray:
    """(T,) ``E_{s~N(mean, cov)} KL(N(K s + k, S) || N(Kh s + kh, Sh))``.

    ``KL = 1/2 [tr(Sh^-1 S) - m + log|Sh| - log|S| + (dK mu + dk)^T Sh^-1 (dK mu + dk)
    + tr(dK^T Sh^-1 dK P)]`` with ``dK = K - Kh``, ``dk = k - kh``.
    """
    T, m, _ = K.shape
    dK = K - Kh
    dm = (dK @ mean[:T, :, None])[:, :, 0] + (k - kh)
    tr1 = np.einsum("tij,tij->t", Shinv, S)
    RdK = Shinv @ dK
    quad = np.einsum("tij,tij->t", RdK @ cov[:T], dK) + np.einsum("ti,ti->t", (Shinv @ dm[:, :, None])[:, :, 0], dm)
    return 0.5 * (tr1 - m + logdetSh - logdetS + quad)


def _ref_inverse(Lh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Sh^-1, log|Sh|)`` from the Cholesky factors (LAPACK ``potri``), symmetrised."""
    T = Lh.shape[0]
    Shinv = np.empty_like(Lh)
    for t in range(T):
        X = lapack.dpotri(Lh[t], lower=1)[0]
        Shinv[t] = np.tril(X) + np.tril(X, -1).T
    logdet = 2.0 * np.log(np.diagonal(Lh, axis1=1, axis2=2)).sum(axis=1)
    return Shinv, logdet


def kl_divergence(dynamics, policy, reference, mu0, P0) -> np.ndarray:
    """(T,) ``KL_k = E_{p(s_k)} KL(p(.|s_k) || phat(.|s_k))`` in closed form.

    ``p(s_k)`` is the state marginal of ``policy`` (it enters through the gain difference
    ``K - Kh``); ``inf`` where the policy covariance is singular.
    """
    _check_dims(dynamics, policy=policy, reference=reference)
    Lh = _reference_chol(reference)
    Shinv, logdetSh = _ref_inverse(Lh)
    marg = forward(dynamics, policy, mu0, P0)
    logdetS = _logdet_pd(policy.cov)
    return _kl_batched(policy.K, policy.k, policy.cov, logdetS, reference.K, reference.k, Shinv, logdetSh,
                       marg.mean, marg.cov)


# --------------------------------------------------------------------------------------------
# backward pass (homogeneous coordinates x = (s, 1), z = (s, 1, a))
# --------------------------------------------------------------------------------------------


class _Problem:
    """Per-step arrays of one problem, precomputed once (vectorised over T).

    In homogeneous coordinates ``z~ = (s, 1, a)`` the stage cost is ``1/2 z~^T Ct z~``, the mean
    dynamics ``(s', 1) = F z~`` and ``-log phat(a|s) = 1/2 z~^T H z~ + const``.
    """

    def __init__(self, dynamics: LinearGaussianDynamics, cost: QuadraticCost, reference, mu0, P0):
        T, n, m = dynamics.T, dynamics.n, dynamics.m
        self.T, self.n, self.m = T, n, m
        self.dynamics, self.cost = dynamics, cost
        self.mu0, self.P0 = mu0, P0
        d = n + 1 + m
        F = np.zeros((T, n + 1, d))
        F[:, :n, :n] = dynamics.A
        F[:, :n, n] = dynamics.c
        F[:, :n, n + 1 :] = dynamics.B
        F[:, n, n] = 1.0
        self.F = F
        self.Ft = np.ascontiguousarray(np.swapaxes(F, 1, 2))
        Ct = np.zeros((T, d, d))
        C, c = cost.C, cost.c
        Ct[:, :n, :n] = C[:, :n, :n]
        Ct[:, :n, n + 1 :] = C[:, :n, n:]
        Ct[:, n + 1 :, :n] = C[:, n:, :n]
        Ct[:, n + 1 :, n + 1 :] = C[:, n:, n:]
        Ct[:, :n, n] = c[:, :n]
        Ct[:, n, :n] = c[:, :n]
        Ct[:, n + 1 :, n] = c[:, n:]
        Ct[:, n, n + 1 :] = c[:, n:]
        Ct[:, n, n] = 2.0 * cost.c0
        self.Ct = Ct
        self.H = None
        if reference is not None:
            self.reference = reference
            self.Lh = _reference_chol(reference)
            self.Kh, self.kh, self.Sh = reference.K, reference.k, reference.cov
            self.Shinv, self.logdetSh = _ref_inverse(self.Lh)
            G = np.concatenate(
                [-reference.K, -reference.k[:, :, None], np.broadcast_to(np.eye(m), (T, m, m))], axis=2
            )
            self.H = symmetrize(np.swapaxes(G, 1, 2) @ self.Shinv @ G)
            self.Kth = np.concatenate([reference.K, reference.k[:, :, None]], axis=2)  # (T, m, n+1)
            self.KthR = np.swapaxes(self.Kth, 1, 2) @ self.Shinv  # (T, n+1, m)


class _NotPD(Exception):
    def __init__(self, t: int, eta: float, eta_crit: float):
        super().__init__(t, eta, eta_crit)
        self.t, self.eta, self.eta_crit = t, eta, eta_crit


class _Backward(NamedTuple):
    K: np.ndarray  # (T, m, n)
    k: np.ndarray  # (T, m)
    dK: np.ndarray  # (T, m, n)  K - Kh  (computed directly, without cancellation)
    dk: np.ndarray  # (T, m)     k - kh
    S: np.ndarray  # (T, m, m) policy covariances eta Quu^-1
    logdetS: np.ndarray  # (T,)
    Quu_inv: np.ndarray  # (T, m, m)  Quu (with the KL term) inverted
    Q0uu: np.ndarray  # (T, m, m)  Quu without the KL term
    eta: np.ndarray  # (T,) multipliers actually used (after repair)


def _eta_crit(prob: _Problem, t: int, Q0uu: np.ndarray) -> float:
    """Smallest ``eta`` making ``Quu(eta) = Q0uu + eta Sh^-1`` PD at step ``t`` (later steps fixed)."""
    Lh = prob.Lh[t]
    lam = float(np.linalg.eigvalsh(symmetrize(Lh.T @ Q0uu @ Lh))[0])
    return max(-lam, 0.0)


def _backward(prob: _Problem, eta: np.ndarray, *, repair: np.ndarray | None = None,
              config: KLStepConfig | None = None) -> _Backward:
    """Backward pass for fixed multipliers ``eta`` (T,).

    ``eta_k = 0``: deterministic LQR step; ``eta_k = inf``: step pinned to the reference.
    For ``eta_k > 0`` the deviation from the reference is computed directly,
    ``[dK, dk] = -Quu^-1 (Q0ux + Q0uu [Kh, kh])``, which stays accurate when ``eta`` is large
    and the policy is close to the reference.  Raises :class:`_NotPD` at the first (latest)
    step whose ``Quu`` is not PD, unless that step is marked in the boolean mask ``repair``:
    then ``eta_k`` is raised in place by the repair rule (module docstring) and the pass continues.
    """
    T, n, m = prob.T, prob.n, prob.m
    n1 = n + 1
    eta = np.array(eta, dtype=float)
    Kt = np.empty((T, m, n1))
    dKt = np.zeros((T, m, n1))
    S = np.empty((T, m, m))
    Qi_all = np.zeros((T, m, m))  # lower triangles of Quu^-1 (LAPACK potri), symmetrised below
    Q0_all = np.empty((T, m, m))
    logdetS = np.empty(T)
    Ldiag = np.ones((T, m))
    V = np.zeros((n1, n1))
    Ct, Ft, F, H = prob.Ct, prob.Ft, prob.F, prob.H
    has_ref = H is not None
    if has_ref:
        Kth, KthR, Shinv = prob.Kth, prob.KthR, prob.Shinv
    for t in range(T - 1, -1, -1):
        Q = Ct[t] + Ft[t] @ V @ F[t]
        Q0uu = Q[n1:, n1:]
        Q0_all[t] = Q0uu
        e = eta[t]
        if e == math.inf:  # pinned to the reference: cost-to-go under phat (KL_t = 0)
            Kh_t = Kth[t]
            Kt[t] = Kh_t
            S[t] = prob.Sh[t]
            logdetS[t] = 2.0 * np.log(prob.Lh[t].diagonal()).sum()
            QxuK = Q[:n1, n1:] @ Kh_t
            V = Q[:n1, :n1] + QxuK + QxuK.T + Kh_t.T @ Q0uu @ Kh_t
            V = 0.5 * (V + V.T)
            continue
        Quu = Q0uu + e * Shinv[t] if e > 0 else Q0uu
        L, info = lapack.dpotrf(Quu, lower=1, clean=1)
        while info != 0:
            crit = _eta_crit(prob, t, Q0uu) if has_ref else math.inf
            if repair is None or not repair[t]:
                raise _NotPD(t, e, crit)
            e = max(config.repair_factor * e, (1.0 + config.repair_margin) * crit)
            if e > config.eta_max:
                raise NotPositiveDefiniteError(
                    f"Quu[{t}] is not positive definite for any multiplier up to eta_max={config.eta_max:g} "
                    f"(needs eta > {crit:.3e})"
                )
            eta[t] = e
            Quu = Q0uu + e * Shinv[t]
            L, info = lapack.dpotrf(Quu, lower=1, clean=1)
        Qi_all[t] = lapack.dpotri(L, lower=1)[0]
        Ldiag[t] = L.diagonal()
        if e > 0:
            D = -(lapack.dpotrs(L, Q[n1:, :n1] + Q0uu @ Kth[t], lower=1)[0])  # [dK, dk]
            dKt[t] = D
            Kt_t = Kth[t] + D
            # V = min_a Q_eta = Q0xx + Q0xu [K,k] + eta (Hxx + Hxu [K,k]),  Hxx + Hxu [K,k] = -Kth^T R [dK,dk]
            V = Q[:n1, :n1] + Q[:n1, n1:] @ Kt_t - e * (KthR[t] @ D)
        else:
            Kt_t = -lapack.dpotrs(L, Q[n1:, :n1], lower=1)[0]
            if has_ref:
                dKt[t] = Kt_t - Kth[t]
            V = Q[:n1, :n1] + Q[:n1, n1:] @ Kt_t  # Qxx - Qxu Quu^-1 Qux
        Kt[t] = Kt_t
        V = 0.5 * (V + V.T)
    Qi_all = np.tril(Qi_all) + np.swapaxes(np.tril(Qi_all, -1), 1, 2)
    pos = np.isfinite(eta) & (eta > 0)
    S[pos] = eta[pos, None, None] * Qi_all[pos]
    S[eta == 0] = 0.0
    logdetS[pos] = m * np.log(eta[pos]) - 2.0 * np.log(Ldiag[pos]).sum(axis=1)
    logdetS[eta == 0] = -np.inf
    return _Backward(Kt[:, :, :n].copy(), Kt[:, :, n].copy(), dKt[:, :, :n].copy(), dKt[:, :, n].copy(),
                     S, logdetS, Qi_all, Q0_all, eta)


class _Eval(NamedTuple):
    bw: _Backward
    marg: Marginals
    kl: np.ndarray
    cost: np.ndarray
    Md: np.ndarray  # (T, m, m) E[delta delta^T], delta = (K - Kh) s + (k - kh)
    mu_eig: np.ndarray  # (T, m) eigenvalues of Lh^T Q0uu Lh


def _evaluate(prob: _Problem, bw: _Backward) -> _Eval:
    """Forward pass, expected costs and ``KL_k`` of a backward-pass policy.

    The covariance part of ``KL_k`` is evaluated from the eigenvalues ``mu_i`` of
    ``Lh^T Q0uu Lh`` (the eigenvalues of ``Sh^-1 Sigma`` are ``eta/(mu_i + eta)``):
    ``tr(Sh^-1 S) - m - log|Sh^-1 S| = sum_i log1p(mu_i/eta) - mu_i/(mu_i + eta)``, accurate
    even when ``KL`` is many orders below 1 (large ``eta``).
    """
    T = prob.T
    marg = _forward_arrays(prob.dynamics, bw.K, bw.k, bw.S, prob.mu0, prob.P0)
    dm = (bw.dK @ marg.mean[:T, :, None])[:, :, 0] + bw.dk
    Md = bw.dK @ marg.cov[:T] @ np.swapaxes(bw.dK, 1, 2) + dm[:, :, None] * dm[:, None, :]
    quad = np.einsum("tij,tij->t", prob.Shinv, Md)
    LhT = np.swapaxes(prob.Lh, 1, 2)
    mu_eig = np.linalg.eigvalsh(symmetrize(LhT @ bw.Q0uu @ prob.Lh))
    eta = bw.eta
    pos = np.isfinite(eta) & (eta > 0)
    cov_part = np.zeros(T)
    e = eta[pos][:, None]
    mu = mu_eig[pos]
    cov_part[pos] = (np.log1p(mu / e) - mu / (mu + e)).sum(axis=1)
    cov_part[eta == 0] = np.inf
    kl = 0.5 * (cov_part + quad)
    kl[np.isinf(eta)] = 0.0
    cost = _expected_cost_marg(prob.cost, marg)
    return _Eval(bw, marg, kl, cost, Md, mu_eig)


def _direct_dkl(prob: _Problem, ev: _Eval) -> np.ndarray:
    """(T,) ``dKL_k/deta_k`` through step ``k``'s own policy only (later steps and ``p(s_k)`` fixed).

    With ``R = Sh^-1``, ``Quu = Q0 + eta R``, ``delta(s) = (K - Kh) s + k - kh``:
    ``dKL/deta = -tr((Q0 Quu^-1)^2)/(2 eta) - tr(R Quu^-1 R E[delta delta^T])`` (< 0), where
    ``tr((Q0 Quu^-1)^2) = sum_i (mu_i/(mu_i + eta))^2``.  Used by the vector dual solver.
    """
    bw = ev.bw
    eta = np.where(np.isfinite(bw.eta) & (bw.eta > 0), bw.eta, 1.0)
    mu = ev.mu_eig
    t1 = ((mu / (mu + eta[:, None])) ** 2).sum(axis=1)
    R = prob.Shinv
    t2 = np.einsum("tij,tji->t", R @ bw.Quu_inv @ R, ev.Md)
    return -0.5 * t1 / eta - t2


def lqr(dynamics: LinearGaussianDynamics, cost: QuadraticCost, mu0, P0) -> LinearGaussianPolicy:
    """Unconstrained optimum of ``sum_k E[l_k]``: the deterministic LQR policy (``cov = 0``).

    The optimal feedback does not depend on ``(mu0, P0)`` (certainty equivalence); they are
    validated for interface symmetry.  Raises :class:`NotPositiveDefiniteError` naming the step
    if ``Quu_k`` is not positive definite (cost-to-go not strictly convex in ``a_k``).
    """
    T, n, m = _check_dims(dynamics, cost=cost)
    _check_init(mu0, P0, n)
    prob = _Problem(dynamics, cost, None, None, None)
    try:
        bw = _backward(prob, np.zeros(T))
    except _NotPD as e:
        raise NotPositiveDefiniteError(
            f"Quu[{e.t}] is not positive definite: the cost-to-go is not strictly convex in a_{e.t}, "
            "so the unconstrained LQR problem has no unique minimiser"
        ) from None
    return LinearGaussianPolicy(bw.K, bw.k, np.zeros((T, m, m)), allow_singular=True)


# --------------------------------------------------------------------------------------------
# dual solvers
# --------------------------------------------------------------------------------------------


class _Counter:
    def __init__(self, prob: _Problem, config: KLStepConfig):
        self.prob, self.config, self.n = prob, config, 0

    def __call__(self, eta: np.ndarray, repair=None) -> _Eval | _NotPD:
        if self.n >= self.config.max_backward:
            raise SolverError(
                f"dual solver exceeded max_backward={self.config.max_backward} backward passes"
            )
        self.n += 1
        try:
            bw = _backward(self.prob, eta, repair=repair, config=self.config)
        except _NotPD as e:
            return e
        return _evaluate(self.prob, bw)


def _solve_scalar(prob: _Problem, nu: float, config: KLStepConfig, eta0) -> tuple[_Eval, int, int, str]:
    """Root of ``f(x) = log sum_k KL_k(e^x) - log nu`` (continuous, strictly decreasing) in ``x = log eta``.

    Safeguarded Newton iteration in log-log coordinates (``rtsafe``-style): the slope is the
    secant through the last two points when they are within 1 of each other in ``log eta``,
    else the analytic slope ``eta sum_k dKL_k/deta / sum_k KL_k`` through each step's own
    policy (:func:`_direct_dkl`); slopes clipped to ``[-10, -1e-3]``, steps capped at
    ``max_log_step``; a step leaving the current bracket, or two steps in a row that do not
    halve ``|f|``, is replaced by bisection.  Non-PD points raise ``eta`` by the repair rule and
    become a lower end of the bracket.  Stops when ``|KL - nu| <= kl_rtol nu + T kl_atol``;
    ``KL(eta_min) < nu`` returns ``eta_min`` (slack budget).  Typically 5-9 backward passes.
    Returns ``(eval, n_backward, n_iter, status)``.
    """
    T = prob.T
    call = _Counter(prob, config)
    ftol = math.log1p(config.kl_rtol + T * config.kl_atol / nu)
    xmin, xmax = math.log(config.eta_min), math.log(config.eta_max)
    cap = config.max_log_step
    e0 = np.asarray(config.eta_init if eta0 is None else eta0, dtype=float).ravel()
    e0 = e0[np.isfinite(e0) & (e0 > 0)]
    e0 = float(np.max(e0)) if e0.size else config.eta_init
    x = min(max(math.log(max(e0, config.eta_min)), xmin), xmax)
    lo, hi = -math.inf, math.inf  # f(lo) > 0 (or lo outside the domain), f(hi) < 0
    prev = None
    slow = 0
    it = 0
    while True:
        it += 1
        r = call(np.full(T, config.eta_min if x <= xmin else math.exp(x)))
        if isinstance(r, _NotPD):  # repair rule: raise eta
            lo = max(lo, x)
            e = max(config.repair_factor * math.exp(x), (1.0 + config.repair_margin) * r.eta_crit)
            if e > config.eta_max:
                raise NotPositiveDefiniteError(
                    f"Quu[{r.t}] is not positive definite for any multiplier up to eta_max={config.eta_max:g} "
                    f"(needs eta > {r.eta_crit:.3e})"
                )
            x = math.log(e)
            if x >= hi:
                x = 0.5 * (lo + hi)
            continue
        ksum = float(r.kl.sum())
        f = math.log(max(ksum, 1e-300)) - math.log(nu)
        if abs(f) <= ftol:
            return r, call.n, it, "converged"
        if f > 0:
            lo = max(lo, x)
            if x >= xmax:
                raise SolverError(f"KL budget nu={nu:g} not reachable: KL(eta_max={config.eta_max:g}) = {ksum:.3e}")
        else:
            hi = min(hi, x)
            if x <= xmin:
                return r, call.n, it, "slack (eta = eta_min)"
        if hi - lo < 1e-13:
            if abs(f) > 1e3 * ftol:
                raise SolverError(f"scalar dual did not converge: KL/nu - 1 = {math.expm1(f):.3e}")
            return r, call.n, it, "converged (bracket width)"
        slope = None
        if prev is not None and abs(x - prev[0]) < 1.0 and prev[1] != f:
            slope = (f - prev[1]) / (x - prev[0])
        if slope is None or not -10.0 < slope < -1e-3:
            sd = math.exp(x) * float(_direct_dkl(prob, r).sum()) / max(ksum, 1e-300)
            slope = min(max(sd, -10.0), -1e-3) if math.isfinite(sd) else -1.0
        slow = slow + 1 if prev is not None and abs(f) > 0.5 * abs(prev[1]) else 0
        xn = x + min(max(-f / slope, -cap), cap)
        if not lo < xn < hi or (slow >= 2 and math.isfinite(lo) and math.isfinite(hi)):
            if math.isfinite(lo) and math.isfinite(hi):
                xn = 0.5 * (lo + hi)
                slow = 0
            else:
                xn = x + (cap if f > 0 else -cap)
        prev = (x, f)
        x = min(max(xn, xmin), xmax)


def _solve_vector(prob: _Problem, nu: np.ndarray, config: KLStepConfig, eta0) -> tuple[_Eval, int, int, str]:
    """Maximise the concave dual over ``eta_k >= eta_min`` (steps with finite ``nu_k > 0``).

    Minimises ``phi(x) = -g(e^x)`` over ``x = log eta >= log eta_min`` (gradient
    ``eta_k (nu_k - KL_k)``):

    * diagonal model: per step the Newton step of ``log KL_k(x_k) = log nu_k`` in log-log
      coordinates, with the slope ``dlog KL_k/dx_k`` through step ``k``'s own policy
      (:func:`_direct_dkl`).  This is exact for the power law ``KL ~ eta^-2`` of large ``eta`` and
      moves a slack budget to ``eta_min`` in a few steps.  As a curvature it tends to the diagonal
      ``eta_k^2 |dKL_k/deta_k|`` of the dual Hessian at the solution, and the preconditioned
      Hessian is well conditioned (eigenvalues in about [0.6, 1.3] on random instances);
    * L-BFGS (memory 10) with that diagonal as the initial inverse Hessian, used only once every
      free budget is within 10 % (``|log KL_k/nu_k| < 0.1``) or after 25 iterations: far from
      the solution the coupling between steps (through the value function and the state
      marginals) is nonlinear and curvature pairs hurt (notably while slack budgets travel to
      ``eta_min``), but when the coupling dominates (non-convex costs with budgets that put the
      solution close to the PD boundary of some ``Quu``) only the memory makes progress; the
      memory is reset when the active set changes;
    * each component of the step capped at ``max_log_step``; Armijo backtracking on
      ``phi`` (non-PD trial points are rejected, roundoff-level increases of ``phi`` tolerated);
      the bound ``eta_min`` by projection with the usual active set (at the bound and pushed
      outwards).

    ``nu_k = inf`` steps keep ``eta_k = 0`` and ``nu_k = 0`` steps ``eta_k = inf``.  The first
    point is repaired (non-PD ``Quu_k`` raise ``eta_k`` by the repair rule).  Stops when
    ``|KL_k - nu_k| <= kl_rtol nu_k + kl_atol`` for every free step off the bound and
    ``KL_k <= nu_k (1 + kl_rtol) + kl_atol`` at the bound.
    """
    T = prob.T
    call = _Counter(prob, config)
    free = np.isfinite(nu) & (nu > 0)
    eta = np.where(np.isinf(nu), 0.0, np.where(nu == 0, np.inf, 0.0))
    if not free.any():
        r = call(eta)
        if isinstance(r, _NotPD):
            _raise_unbounded(r)
        return r, call.n, 0, "no finite budget"
    xmin, xmax = math.log(config.eta_min), math.log(config.eta_max)
    e0 = np.full(T, config.eta_init) if eta0 is None else np.broadcast_to(np.asarray(eta0, float), (T,))
    e0 = np.where(np.isfinite(e0) & (e0 > 0), e0, config.eta_init)  # warm start may hold 0 / inf entries
    x = np.zeros(T)
    x[free] = np.clip(np.log(np.maximum(e0[free], config.eta_min)), xmin, xmax)
    nuf = nu[free]

    def full(xv):
        out = eta.copy()
        # exactly eta_min at the bound (within the active-set tolerance 1e-12 used below: a point
        # a few ulps above xmin must not report eta = 1.0000000000000044e-12 > eta_min)
        out[free] = np.where(xv[free] <= xmin + 1e-12, config.eta_min, np.exp(xv[free]))
        return out

    r = call(full(x), repair=free)  # first point: repair non-PD steps upwards
    if isinstance(r, _NotPD):
        _raise_unbounded(r)
    x[free] = np.log(r.bw.eta[free])

    def merit(rr: _Eval):
        ef = rr.bw.eta[free]
        grad = np.zeros(T)
        grad[free] = ef * (nuf - rr.kl[free])
        return -(rr.cost.sum() + ef @ (rr.kl[free] - nuf)), grad

    phi, g = merit(r)
    mem_s: list[np.ndarray] = []
    mem_y: list[np.ndarray] = []
    prev_active = None
    cap = config.max_log_step
    it = 0
    while True:
        kl = r.kl[free]
        at_lo = x[free] <= xmin + 1e-12
        tol = config.kl_rtol * nuf + config.kl_atol
        ok = np.where(at_lo, kl <= nuf + tol, np.abs(kl - nuf) <= tol)
        if ok.all():
            return r, call.n, it, "converged"
        it += 1
        # diagonal model: per step the Newton step of log KL_k = log nu_k in v_k = log(eta_k - c_k),
        # c_k = max(0, -lambda_min(Lh^T Q0uu Lh)) the PD threshold of Quu_k (0 for convex costs),
        # with the slope through step k's own policy; as a curvature h_k = -g_k / d_k, which tends
        # to eta_k^2 |dKL_k/deta_k| (the diagonal of the dual Hessian) at the solution
        etaf = np.exp(x)
        eta_fr, kl_fr = etaf[free], np.maximum(r.kl[free], 1e-300)
        dkl = np.abs(_direct_dkl(prob, r))[free]
        c = np.minimum(np.maximum(-r.mu_eig[free].min(axis=1), 0.0), 0.999 * eta_fr)
        gap = eta_fr - c
        lr = np.log(kl_fr / nuf)
        sv = np.maximum(gap * dkl / kl_fr, 1e-12)  # |dlog KL / dv|
        dv = np.clip(lr / sv, -cap, cap)
        dx = np.log((c + gap * np.exp(dv)) / eta_fr)
        h = np.ones(T)
        h_lim = np.maximum(eta_fr ** 2 * dkl, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            h_dir = -g[free] / dx
        h[free] = np.where((np.abs(lr) > 1e-8) & (h_dir > 0) & np.isfinite(h_dir), h_dir, h_lim)
        active = ~free | ((x <= xmin + 1e-12) & (g > 0))
        near = it > _GATE_ITERS or np.all(np.abs(lr)[~active[free]] < _NEAR)
        if not near or (prev_active is not None and np.any(active != prev_active)):
            mem_s.clear()
            mem_y.clear()
        prev_active = active
        q = np.where(active, 0.0, g)
        alphas = []
        for s_, y_ in zip(reversed(mem_s), reversed(mem_y)):
            rho = 1.0 / (y_ @ s_)
            a_ = rho * (s_ @ q)
            q = q - a_ * y_
            alphas.append((rho, a_, s_, y_))
        d = np.where(active, 0.0, q / h)
        for rho, a_, s_, y_ in reversed(alphas):
            b_ = rho * (y_ @ d)
            d = d + s_ * (a_ - b_)
        d = np.clip(np.where(active, 0.0, -d), -cap, cap)
        if g @ d >= 0:  # not a descent direction: drop the memory, use the diagonal step
            mem_s.clear()
            mem_y.clear()
            d = np.clip(np.where(active, 0.0, -g / h), -cap, cap)
        step = 1.0
        slope = g @ d
        while True:
            xn = np.where(free, np.clip(x + step * d, xmin, xmax), x)
            rn = call(full(xn))
            if not isinstance(rn, _NotPD):
                phin, gn = merit(rn)
                if phin <= phi + 1e-4 * step * slope + 1e-12 * abs(phi):
                    break
            step *= 0.5
            if step < 1e-12:
                raise SolverError("vector dual line search failed (no decrease along the quasi-Newton direction)")
        s_ = np.where(active, 0.0, xn - x) if near else np.zeros(T)
        y_ = np.where(active, 0.0, gn - g)
        if s_ @ y_ > 1e-12 * np.linalg.norm(s_) * np.linalg.norm(y_):
            mem_s.append(s_)
            mem_y.append(y_)
            if len(mem_s) > _MEM:
                mem_s.pop(0)
                mem_y.pop(0)
        x, r, phi, g = xn, rn, phin, gn
        if np.any(x[free] >= xmax - 1e-12):
            t = int(np.flatnonzero(free & (x >= xmax - 1e-12))[0])
            raise SolverError(f"KL budget nu[{t}]={nu[t]:g} not reachable below eta_max={config.eta_max:g}")


_MEM = 10
_NEAR = 0.1  # L-BFGS memory is used only once every free |log(KL_k/nu_k)| < _NEAR ...
_GATE_ITERS = 25  # ... or after this many iterations (strongly coupled, e.g. non-convex, problems)


def _raise_unbounded(e: _NotPD):
    raise NotPositiveDefiniteError(
        f"Quu[{e.t}] is not positive definite at eta={e.eta:g} on a step without a finite KL budget: "
        "the cost-to-go is not strictly convex in the action there"
    )


def _dual_value(ev: _Eval, eta: np.ndarray, nu: np.ndarray) -> float:
    use = np.isfinite(eta) & (eta > 0)
    return float(ev.cost.sum() + eta[use] @ (ev.kl[use] - nu[use]))


# --------------------------------------------------------------------------------------------
# KL step
# --------------------------------------------------------------------------------------------


def kl_step(dynamics: LinearGaussianDynamics, cost: QuadraticCost, reference: LinearGaussianPolicy, nu, mu0, P0,
            method: Literal["closed_form", "casadi"] = "closed_form", config: KLStepConfig | None = None,
            *, eta0=None) -> KLStepResult:
    """KL-constrained LQG step (SPEC §6): ``min sum_k E[l_k]  s.t.  KL_k <= nu_k`` (or ``sum KL <= nu``).

    Args:
        dynamics, cost: the local linear-Gaussian model and quadratic cost expansion.
        reference: ``phat`` (covariances must be positive definite).
        nu: scalar (one total budget, one multiplier: the GPS form) or ``(T,)`` per-step
            budgets; ``inf`` entries are unconstrained (``eta = 0``, deterministic step),
            ``0`` entries pin the step to the reference (``eta = inf``).
        mu0, P0: initial state distribution.
        method: ``"closed_form"`` (backward passes + dual solve) or ``"casadi"`` (IPOPT NLP).
        config: :class:`KLStepConfig`.
        eta0: optional warm start of the multiplier(s) (closed form only).
    Returns a :class:`KLStepResult`.
    """
    config = KLStepConfig() if config is None else config
    if not isinstance(config, KLStepConfig):
        raise TypeError(f"config must be a KLStepConfig, got {type(config).__name__}")
    T, n, m = _check_dims(dynamics, cost=cost, reference=reference)
    mu0, P0 = _check_init(mu0, P0, n)
    nu_arr, scalar = _check_nu(nu, T)
    prob = _Problem(dynamics, cost, reference, mu0, P0)
    nu_out = float(nu_arr[0]) if scalar else nu_arr.copy()
    if method == "closed_form":
        return _kl_step_closed(prob, nu_arr, scalar, nu_out, config, eta0)
    if method == "casadi":
        return _kl_step_casadi(prob, nu_arr, scalar, nu_out, config)
    raise ValueError(f"unknown method {method!r}; use 'closed_form' or 'casadi'")


def _policy_from(K, k, S, eta) -> LinearGaussianPolicy:
    return LinearGaussianPolicy(K, k, S, allow_singular=bool(np.any(eta == 0)))


def _kl_step_closed(prob: _Problem, nu: np.ndarray, scalar: bool, nu_out, config, eta0) -> KLStepResult:
    T = prob.T
    if scalar:
        v = float(nu[0])
        if math.isinf(v) or v == 0.0:
            eta_fixed = np.full(T, 0.0 if math.isinf(v) else math.inf)
            r, nb, it, status = _solve_vector(prob, np.full(T, v), config, None)
            status = "unconstrained (nu = inf): LQR" if math.isinf(v) else "nu = 0: reference policy"
            eta = eta_fixed
            dual = float(r.cost.sum())
        else:
            r, nb, it, status = _solve_scalar(prob, v, config, eta0)
            eta = r.bw.eta.copy()
            dual = float(r.cost.sum() + eta[0] * (r.kl.sum() - v))
    else:
        r, nb, it, status = _solve_vector(prob, nu, config, eta0)
        eta = r.bw.eta.copy()
        dual = _dual_value(r, eta, nu)
    bw = r.bw
    return KLStepResult(
        policy=_policy_from(bw.K, bw.k, bw.S, eta),
        eta=eta,
        kl=r.kl.copy(),
        expected_cost=float(r.cost.sum()),
        n_backward=nb,
        scalar_eta=scalar,
        nu=nu_out,
        dual_value=dual,
        method="closed_form",
        n_iter=it,
        status=status,
        marginals=r.marg,
    )


_IPOPT_OK = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def _casadi_kinds(nu: np.ndarray, scalar: bool, T: int) -> tuple[np.ndarray, np.ndarray]:
    """``(nu per step, kind per step)``: ``"free"`` (finite ``nu_k > 0``: ``K, k, L`` variables and a
    KL row), ``"det"`` (``nu_k = inf``: ``K, k`` only, ``Sigma_k = 0``), ``"pin"`` (``nu_k = 0``: the
    reference, no variables)."""
    nu_full = np.full(T, nu[0]) if scalar else nu
    return nu_full, np.where(np.isinf(nu_full), "det", np.where(nu_full == 0, "pin", "free"))


def _casadi_n_vars(kind: np.ndarray, n: int, m: int) -> int:
    """NLP size (both formulations): ``m n + m`` per unpinned step, ``m (m+1)/2`` more per free step."""
    return int(np.sum(kind != "pin") * (m * n + m) + np.sum(kind == "free") * (m * (m + 1) // 2))


def _kl_step_casadi(prob: _Problem, nu: np.ndarray, scalar: bool, nu_out, config: KLStepConfig) -> KLStepResult:
    """The same problem as a nonlinear program solved by IPOPT (CasADi ``nlpsol``).

    Decision variables per step: the gain ``K_k``, the offset ``k_k`` and the lower-triangular
    Cholesky factor ``L_k`` of ``Sigma_k = L_k L_k^T`` (directly, or affinely rescaled in the
    structured formulation).  Single shooting: the state moments are functions of the policy
    through the moment recursion, so every iterate is a valid policy with PSD moments.
    (A multiple-shooting variant with free ``P_k`` variables was tried and rejected: the
    bilinear ``K P`` terms make the Lagrangian Hessian strongly indefinite away from the
    solution and IPOPT failed on most ``T = 20`` instances; at ``n = 26`` its KKT systems would
    also have dense 350-variable covariance blocks per step.)  Objective ``sum_k E[l_k]`` and
    constraints ``KL_k <= nu_k`` (or ``sum_k KL_k <= nu``) in closed form.  Steps with
    ``nu_k = inf`` are deterministic (no ``L_k``, no constraint); steps with ``nu_k = 0`` are fixed
    to the reference.  Warm start: the reference policy.  The multipliers ``lam_g >= 0`` of the
    KL rows (CasADi Lagrangian ``f + lam_g^T g``, active upper bound) are the ``eta_k``.
    IPOPT's status is checked: anything but ``Solve_Succeeded``, ``Solved_To_Acceptable_Level``
    or ``Search_Direction_Becomes_Too_Small`` at an iterate whose primal and dual infeasibilities
    are below ``ipopt_acceptable_tol`` (``tol = 1e-12`` is below the roundoff floor of some
    problems with large multipliers) raises :class:`SolverError` (:func:`_ipopt_solve`).

    Two formulations (``config.casadi_nlp``; ``"auto"`` picks ``"symbolic"`` up to
    ``config.casadi_auto_max_vars`` NLP variables and ``"structured"`` above):
    :func:`_casadi_symbolic` (CasADi builds the dense exact Hessian symbolically: small problems)
    and :func:`_casadi_structured` (analytic adjoint derivatives and a per-step block-diagonal
    Hessian that is exact at the solution: scales to ``n=26, m=7, T=100``).
    """
    T, n, m = prob.T, prob.n, prob.m
    nu_full, kind = _casadi_kinds(nu, scalar, T)
    n_vars = _casadi_n_vars(kind, n, m)
    form = config.casadi_nlp
    if form == "auto":
        form = "symbolic" if n_vars <= config.casadi_auto_max_vars else "structured"
    free = np.flatnonzero(kind == "free")
    if scalar and free.size:
        ub = [float(nu[0])]
    else:
        ub = [float(nu_full[t]) for t in free]
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.tol": config.ipopt_tol,
        "ipopt.acceptable_tol": config.ipopt_acceptable_tol,
        "ipopt.max_iter": config.ipopt_max_iter,
        "ipopt.bound_relax_factor": 0.0,  # keep L_ii >= chol_floor > 0 exactly (log L_ii)
    }
    if n_vars == 0:  # every step pinned to the reference: nothing to optimise
        Kout, kout, Sout = prob.reference.K.copy(), prob.reference.k.copy(), prob.reference.cov.copy()
        lam, status, n_iter, fval = np.zeros(0), "nothing to solve (nu = 0)", 0, float("nan")
        timing = {"build_s": 0.0, "solve_s": 0.0}
    elif form == "structured":
        Kout, kout, Sout, lam, status, n_iter, fval, timing = _casadi_structured(prob, kind, scalar, ub, opts, config)
    else:
        Kout, kout, Sout, lam, status, n_iter, fval, timing = _casadi_symbolic(prob, kind, scalar, ub, opts, config)
    eta = np.where(kind == "pin", np.inf, 0.0)
    if scalar:
        if lam.size:
            eta[:] = lam[0]
    else:
        eta[free] = lam
    policy = _policy_from(Kout, kout, symmetrize(Sout), eta)
    marg = _forward_arrays(prob.dynamics, policy.K, policy.k, policy.cov, prob.mu0, prob.P0)
    ref = prob.reference
    logdetS = _logdet_pd(policy.cov)
    kl = _kl_batched(policy.K, policy.k, policy.cov, logdetS, ref.K, ref.k, prob.Shinv, prob.logdetSh,
                     marg.mean, marg.cov)
    costs = _expected_cost_marg(prob.cost, marg)
    return KLStepResult(
        policy=policy, eta=eta, kl=kl, expected_cost=float(costs.sum()), n_backward=0, scalar_eta=scalar,
        nu=nu_out, dual_value=fval, method="casadi", n_iter=n_iter, status=status, marginals=marg, lam_g=lam,
        solver_stats={"n_vars": n_vars, "formulation": form if n_vars else "none", **timing},
    )


def _ipopt_solve(solver_fn, x0, lbx, ub, n_kl, acceptable_tol: float):
    """Run an ``nlpsol`` and check IPOPT's status; returns ``(x, lam_g, status, n_iter, f, solve_s)``.

    Accepted: ``Solve_Succeeded``, ``Solved_To_Acceptable_Level``, and
    ``Search_Direction_Becomes_Too_Small`` when the last iterate's (scaled) primal and dual
    infeasibilities are at most ``acceptable_tol`` (IPOPT converged to the roundoff floor, above
    ``tol``, and stopped before its ``acceptable_iter`` count); anything else raises
    :class:`SolverError`.
    """
    t1 = time.perf_counter()
    sol = solver_fn(x0=x0, lbx=lbx, ubx=np.inf, lbg=-np.inf, ubg=ub)
    solve_s = time.perf_counter() - t1
    stats = solver_fn.stats()
    status = str(stats.get("return_status", "unknown"))
    ok = status in _IPOPT_OK
    if status == "Search_Direction_Becomes_Too_Small":
        its = stats.get("iterations", {})
        last = [its.get(k, [math.inf])[-1] if its.get(k) else math.inf for k in ("inf_pr", "inf_du")]
        ok = max(last) <= acceptable_tol
    if not ok:
        raise SolverError(f"IPOPT failed: return_status={status!r}")
    lam = np.asarray(sol["lam_g"]).ravel()[:n_kl]
    return (np.asarray(sol["x"]).ravel(), lam, status, int(stats.get("iter_count", -1)), float(sol["f"]),
            solve_s)


def _casadi_symbolic(prob: _Problem, kind: np.ndarray, scalar: bool, ub, opts: dict, config: KLStepConfig):
    """SX single shooting in ``(K_k, k_k, L_k)`` with CasADi's symbolic exact Hessian.

    ``L_k`` is the Cholesky factor of ``Sigma_k`` itself, its diagonal bounded below by
    ``chol_floor``.  The exact Hessian is dense in the ``T (m n + m + m(m+1)/2)`` variables and
    CasADi builds it symbolically, which dominates the run time (about 0.5 s at ``n=4, m=2,
    T=10``, 25 s at ``n=6, m=3, T=20``, out of reach at ``n=26, m=7, T=100``): the reference
    solver for small problems, agreeing with the closed form to about 1e-10.
    Returns ``(K, k, Sigma, lam_g, status, n_iter, f, timing)``.
    """
    import casadi as ca

    T, n, m = prob.T, prob.n, prob.m
    dyn, cst, ref = prob.dynamics, prob.cost, prob.reference
    tril = [(i, j) for i in range(m) for j in range(i + 1)]

    xs, x0, lbx = [], [], []

    def newvar(name, size, init, lb=-np.inf):
        v = ca.SX.sym(name, size)
        xs.append(v)
        x0.extend(np.ravel(init).tolist())
        lbx.extend(np.broadcast_to(lb, (size,)).tolist())
        return v

    obj = 0
    kl_terms: list[Any] = []
    mu, P = ca.DM(prob.mu0), ca.DM(prob.P0)
    for t in range(T):
        if kind[t] == "pin":
            K, kk, S = ca.DM(ref.K[t]), ca.DM(ref.k[t]), ca.DM(ref.cov[t])
        else:
            K = ca.reshape(newvar(f"K{t}", m * n, ref.K[t].T), m, n)  # column-major
            kk = newvar(f"k{t}", m, ref.k[t])
            if kind[t] == "det":
                S = ca.DM.zeros(m, m)
            else:
                Lh = np.linalg.cholesky(ref.cov[t])
                lv = newvar(f"L{t}", len(tril), [Lh[i, j] for i, j in tril],
                            lb=np.array([config.chol_floor if i == j else -np.inf for i, j in tril]))
                L = ca.SX.zeros(m, m)
                for idx, (i, j) in enumerate(tril):
                    L[i, j] = lv[idx]
                S = ca.mtimes(L, L.T)
        C = ca.DM(cst.C[t])
        a_mean = ca.mtimes(K, mu) + kk
        PKt = ca.mtimes(P, K.T)
        Pa = ca.mtimes(K, PKt) + S
        zbar = ca.vertcat(mu, a_mean)
        trace = (ca.sum1(ca.sum2(C[:n, :n] * P)) + 2 * ca.sum1(ca.sum2(C[:n, n:] * PKt))
                 + ca.sum1(ca.sum2(C[n:, n:] * Pa)))
        obj = obj + 0.5 * trace + 0.5 * ca.mtimes([zbar.T, C, zbar]) + ca.dot(ca.DM(cst.c[t]), zbar) + float(cst.c0[t])
        if kind[t] == "free":
            R = ca.DM(prob.Shinv[t])
            dK = K - ca.DM(ref.K[t])
            dm = ca.mtimes(dK, mu) + kk - ca.DM(ref.k[t])
            logdetS = 2 * sum(ca.log(L[i, i]) for i in range(m))
            kl = 0.5 * (ca.sum1(ca.sum2(R * S)) - m + float(prob.logdetSh[t]) - logdetS
                        + ca.mtimes([dm.T, R, dm]) + ca.sum1(ca.sum2(ca.mtimes([R, dK, P]) * dK)))
            kl_terms.append(kl)
        if t < T - 1:
            A, B = ca.DM(dyn.A[t]), ca.DM(dyn.B[t])
            Acl = A + ca.mtimes(B, K)
            mu = ca.mtimes(Acl, mu) + ca.mtimes(B, kk) + ca.DM(dyn.c[t])
            P = ca.mtimes([Acl, P, Acl.T]) + ca.mtimes([B, S, B.T]) + ca.DM(dyn.cov[t])
            P = 0.5 * (P + P.T)

    g_kl = ([sum(kl_terms)] if scalar else kl_terms) if kl_terms else []
    opts = dict(opts)
    opts.update({f"ipopt.{k}": v for k, v in config.ipopt_options.items()})
    x = ca.vertcat(*xs)
    g = ca.vertcat(*g_kl) if g_kl else ca.SX.zeros(0, 1)
    t0 = time.perf_counter()
    solver = ca.nlpsol("kl_step", "ipopt", {"x": x, "f": obj, "g": g}, opts)
    build_s = time.perf_counter() - t0
    sol_x, lam, status, n_iter, fval, solve_s = _ipopt_solve(solver, x0, lbx, ub, len(g_kl),
                                                             config.ipopt_acceptable_tol)

    Kout, kout, Sout = np.empty((T, m, n)), np.empty((T, m)), np.empty((T, m, m))
    pos = 0
    for t in range(T):  # same variable order as created
        if kind[t] == "pin":
            Kout[t], kout[t], Sout[t] = ref.K[t], ref.k[t], ref.cov[t]
            continue
        Kout[t] = sol_x[pos : pos + m * n].reshape(n, m).T
        pos += m * n
        kout[t] = sol_x[pos : pos + m]
        pos += m
        Sout[t] = 0.0
        if kind[t] == "free":
            Lt = np.zeros((m, m))
            for idx, (i, j) in enumerate(tril):
                Lt[i, j] = sol_x[pos + idx]
            pos += len(tril)
            Sout[t] = Lt @ Lt.T
    return Kout, kout, Sout, lam, status, n_iter, fval, {"build_s": build_s, "solve_s": solve_s}


class _StructuredNLP:
    """Scaled single-shooting NLP of the KL step with analytic first and second derivatives.

    Homogeneous state ``x = (s, 1)`` (``n1 = n + 1``), second moments ``X_k = E[x_k x_k^T]``,
    ``G_k = [K_k, k_k]``; ``X_{k+1} = Acl X_k Acl^T + Bt S_k Bt^T + Wt`` with
    ``Acl = [[A, c], [0, 1]] + Bt G``, ``Bt = [B; 0]``, ``Wt = blkdiag(W, 0)``;
    ``E[l_k] = 1/2 tr(Ct [I; G] X [I; G]^T) + 1/2 tr(Ct_uu S)`` (``Ct``: the cost in ``(s, 1, a)``).

    Variables (per unpinned step ``Z_k``, per free step also the lower-triangular ``Gam_k``)::

        G_k = Gh_k + Lh_k Z_k Mx_k,        L_k = Lh_k Gam_k   (Sigma_k = L_k L_k^T)

    where ``Sh = Lh Lh^T`` and ``Mx_k^T Mx_k = (X_k of the reference policy)^-1``, eigenvalues
    floored at 1e-6 of the largest (a singular ``X_k``, e.g. from ``P0 = 0``, leaves the NLP flat
    in some directions of ``K_k``; with a floor of 1e-8 the amplified roundoff there made IPOPT
    drift away after converging).  This affine change of variables is a preconditioner: the KL
    is ``1/2 (|Gam|_F^2 - m - 2 sum log Gam_ii + tr(Z Mx X Mx^T Z^T))``, with Hessian close to the
    identity; the reference is ``Z = 0, Gam = I``.  ``Gam_ii >= chol_floor``.

    Derivatives.  The Lagrangian ``sigma f + sum_k lam_k KL_k`` is linear in each ``X_k`` given
    the later policy: ``tr(Lam_k X_k) + const`` with the adjoint (value-function) recursion
    ``Q_k = sigma Ct_k + 2 F_k^T Lam_{k+1} F_k + lam_k H_k``, ``Lam_k = 1/2 [I; G]^T Q_k [I; G]``
    (``F_k = [[A, c, B], [0, 1, 0]]``, ``H_k`` the quadratic form of ``-log phat``).  Hence
    ``dL/dG_k = (Q_ux + Q_uu G) X_k`` and ``dL/dGam_k = tril(Lh^T Q_uu Lh Gam) - lam_k diag(1/Gam_ii)``.
    The per-step constraint Jacobian runs one such recursion per KL row, all rows at once
    (``O(T^2 n^3)`` flops in batched matrix products).  Hessian: the exact diagonal blocks
    ``(Mx X Mx^T) kron (Lh^T Q_uu Lh)`` (``Z``) and ``(Lh^T Q_uu Lh)_{ii'} delta_{jj'}
    + lam_k / Gam_ii^2`` (``Gam``; no ``Z``-``Gam`` coupling).  The off-diagonal blocks
    ``d2L/dtheta_j dtheta_k = (Q_ux + Q_uu G)_k dX_k/dtheta_j`` vanish at a KKT point (there
    ``(Q_ux + Q_uu G_k) X_k = 0`` with ``X_k`` positive definite: the backward-pass optimality), so
    IPOPT sees the exact Hessian at the solution and converges superlinearly, while the Hessian
    costs ``O(T (m n)^2)`` memory instead of the dense ``(T m n)^2``.

    Alternatives tried on the same rescaled single-shooting NLP: IPOPT's limited-memory BFGS
    Hessian with CasADi AD gradients needed 160 iterations at ``n=6, m=3, T=20`` and had not
    converged after 330 iterations (inf_pr ~ 5e2) at ``n=26, m=7, T=100`` (total budget); with
    per-step budgets, building the constraint Jacobian by CasADi AD through chained step
    functions took time quadratic in ``T`` (12 s at ``T=10``), because every KL row needs its own
    adjoint sweep.
    """

    def __init__(self, prob: _Problem, kind: np.ndarray, scalar: bool, chol_floor: float):
        T, n, m = prob.T, prob.n, prob.m
        n1 = n + 1
        self.prob, self.T, self.n, self.m, self.n1 = prob, T, n, m, n1
        self.kind, self.scalar = kind, scalar
        self.free = kind == "free"
        self.var = kind != "pin"
        self.cons = np.flatnonzero(self.free)
        self.ng = (1 if scalar else self.cons.size) if self.cons.size else 0
        self.tl = np.tril_indices(m)
        self.nt = self.tl[0].size
        self.nz = m * n1
        self.sizes = np.where(self.free, self.nz + self.nt, np.where(self.var, self.nz, 0))
        self.off = np.concatenate([[0], np.cumsum(self.sizes)]).astype(int)
        self.nx = int(self.off[-1])
        ref = prob.reference
        self.Fx = np.ascontiguousarray(prob.F[:, :, :n1])
        self.Fu = np.ascontiguousarray(prob.F[:, :, n1:])
        self.Wt = np.zeros((T, n1, n1))
        self.Wt[:, :n, :n] = prob.dynamics.cov
        x0h = np.append(prob.mu0, 1.0)
        self.X0 = np.outer(x0h, x0h)
        self.X0[:n, :n] += prob.P0
        mg = _forward_arrays(prob.dynamics, ref.K, ref.k, ref.cov, prob.mu0, prob.P0)
        xm = np.concatenate([mg.mean[:T], np.ones((T, 1))], axis=1)
        Xr = xm[:, :, None] * xm[:, None, :]
        Xr[:, :n, :n] += mg.cov[:T]
        w, V = np.linalg.eigh(symmetrize(Xr))
        w = np.maximum(w, 1e-6 * w[:, -1:])
        self.Mx = np.swapaxes(V / np.sqrt(w)[:, None, :], 1, 2)  # Mx Xr Mx^T ~ I
        self.Lh, self.Gh = prob.Lh, prob.Kth
        x0 = np.zeros(self.nx)
        lbx = np.full(self.nx, -np.inf)
        diag = self.tl[0] == self.tl[1]
        for t in self.cons:
            o = self.off[t] + self.nz
            x0[o : o + self.nt] = diag
            lbx[o : o + self.nt] = np.where(diag, chol_floor, -np.inf)
        self.x0, self.lbx = x0, lbx
        self._key, self._cache = None, None

    # -- moments --------------------------------------------------------------------------------

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T, m, n1 = self.T, self.m, self.n1
        Z = np.zeros((T, m, n1))
        Gam = np.zeros((T, m, m))
        for t in np.flatnonzero(self.var):
            o = self.off[t]
            Z[t] = x[o : o + self.nz].reshape(n1, m).T  # column-major, as CasADi's reshape
            if self.free[t]:
                Gam[t][self.tl] = x[o + self.nz : o + self.nz + self.nt]
        return Z, Gam

    def policy(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Z, Gam = self.unpack(x)
        G = self.Gh + self.Lh @ Z @ self.Mx
        LG = self.Lh @ Gam
        S = LG @ np.swapaxes(LG, 1, 2)
        pin = self.kind == "pin"
        S[pin] = self.prob.Sh[pin]
        return G, S, Gam

    def forward(self, x: np.ndarray) -> dict:
        key = x.tobytes()
        if key == self._key:
            return self._cache
        T, n1 = self.T, self.n1
        Z, _ = self.unpack(x)
        G, S, Gam = self.policy(x)
        Acl = self.Fx + self.Fu @ G
        N = self.Fu @ S @ np.swapaxes(self.Fu, 1, 2) + self.Wt
        X = np.empty((T, n1, n1))
        X[0] = self.X0
        for t in range(T - 1):
            Xn = Acl[t] @ X[t] @ Acl[t].T + N[t]
            X[t + 1] = 0.5 * (Xn + Xn.T)
        IG = np.concatenate([np.broadcast_to(np.eye(n1), (T, n1, n1)), G], axis=1)  # (T, n1 + m, n1)
        Y = self.Mx @ X @ np.swapaxes(self.Mx, 1, 2)
        c = {"Z": Z, "Gam": Gam, "G": G, "S": S, "Acl": Acl, "X": X, "IG": IG, "Y": Y}
        self._key, self._cache = key, c
        return c

    # -- derivatives ----------------------------------------------------------------------------

    def _adjoint(self, x: np.ndarray, sigma: float, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradient of ``sigma f + sum_k lam_k KL_k`` and the ``Q_uu`` of every step."""
        c = self.forward(x)
        T, m, n1, nz, nt = self.T, self.m, self.n1, self.nz, self.nt
        prob = self.prob
        grad = np.zeros(self.nx)
        Quu_all = np.empty((T, m, m))
        Lam = np.zeros((n1, n1))
        for t in range(T - 1, -1, -1):
            Ft = prob.F[t]
            Q = sigma * prob.Ct[t] + 2.0 * (Ft.T @ Lam @ Ft)
            if lam[t] != 0.0:
                Q = Q + lam[t] * prob.H[t]
            Quu = Q[n1:, n1:]
            Quu_all[t] = Quu
            if self.var[t]:
                o = self.off[t]
                gG = (Q[n1:, :n1] + Quu @ c["G"][t]) @ c["X"][t]
                grad[o : o + nz] = (self.Lh[t].T @ gG @ self.Mx[t].T).T.ravel()
                if self.free[t]:
                    Gm = c["Gam"][t]
                    gGam = self.Lh[t].T @ Quu @ self.Lh[t] @ Gm
                    gGam[np.diag_indices(m)] -= lam[t] / np.diag(Gm)
                    grad[o + nz : o + nz + nt] = gGam[self.tl]
            IG = c["IG"][t]
            Lam = 0.5 * (IG.T @ Q @ IG)
            Lam = 0.5 * (Lam + Lam.T)
        return grad, Quu_all

    def grad_f(self, x: np.ndarray) -> np.ndarray:
        return self._adjoint(x, 1.0, np.zeros(self.T))[0]

    def jac_g(self, x: np.ndarray) -> np.ndarray:
        """Dense ``(ng, nx)`` Jacobian of the KL rows (lower block triangular for per-step rows)."""
        if self.scalar:
            return self._adjoint(x, 0.0, self.free.astype(float))[0][None, :]
        c = self.forward(x)
        T, m, n1, nz, nt = self.T, self.m, self.n1, self.nz, self.nt
        J = np.zeros((self.ng, self.nx))
        stack = np.zeros((0, n1, n1))  # adjoints Lam^{(r)}_{t+1} of the rows r with cons[r] > t
        r_hi = self.ng  # those rows are r_hi..ng-1
        for t in range(T - 1, -1, -1):
            o = self.off[t]
            if self.var[t] and stack.shape[0]:
                Lh, Bt = self.Lh[t], self.Fu[t]
                W = np.swapaxes(stack @ (Bt @ Lh), 1, 2)  # Lh^T Bt^T Lam, (r, m, n1)
                gZ = W @ (2.0 * c["Acl"][t] @ c["X"][t] @ self.Mx[t].T)
                J[r_hi:, o : o + nz] = np.swapaxes(gZ, 1, 2).reshape(stack.shape[0], nz)
                if self.free[t]:
                    gGam = W @ (2.0 * Bt @ Lh @ c["Gam"][t])
                    J[r_hi:, o + nz : o + nz + nt] = gGam[:, self.tl[0], self.tl[1]]
            if self.free[t]:
                r = r_hi - 1
                Zt, Gm = c["Z"][t], c["Gam"][t]
                J[r, o : o + nz] = (Zt @ c["Y"][t]).T.ravel()
                gGam = Gm.copy()
                gGam[np.diag_indices(m)] -= 1.0 / np.diag(Gm)
                J[r, o + nz : o + nz + nt] = gGam[self.tl]
            if stack.shape[0]:
                Acl = c["Acl"][t]
                stack = np.swapaxes(stack @ Acl, 1, 2) @ Acl
                stack = 0.5 * (stack + np.swapaxes(stack, 1, 2))
            if self.free[t]:
                ZM = c["Z"][t] @ self.Mx[t]
                stack = np.concatenate([(0.5 * ZM.T @ ZM)[None], stack], axis=0)
                r_hi -= 1
        return J

    def hess_blocks(self, x: np.ndarray, sigma: float, lam_g: np.ndarray) -> list[np.ndarray]:
        """Diagonal blocks (one per unpinned step) of the Hessian of ``sigma f + lam_g^T g``."""
        lam = np.zeros(self.T)
        if self.ng:
            lam[self.cons] = lam_g[0] if self.scalar else lam_g
        c = self.forward(x)
        _, Quu = self._adjoint(x, sigma, lam)
        i, j = self.tl
        same_col = j[:, None] == j[None, :]
        dg = np.flatnonzero(i == j)
        blocks = []
        for t in np.flatnonzero(self.var):
            A = symmetrize(self.Lh[t].T @ Quu[t] @ self.Lh[t])
            hz = np.kron(c["Y"][t], A)
            if not self.free[t]:
                blocks.append(hz)
                continue
            hg = np.where(same_col, A[i[:, None], i[None, :]], 0.0)
            hg[dg, dg] += lam[t] / np.diag(c["Gam"][t]) ** 2
            B = np.zeros((self.sizes[t], self.sizes[t]))
            B[: self.nz, : self.nz] = hz
            B[self.nz :, self.nz :] = hg
            blocks.append(B)
        return blocks

    # -- CasADi ---------------------------------------------------------------------------------

    def oracle(self, ca):
        """``(x, f, g)`` as CasADi MX: one SX step function per step kind, chained over ``T``."""
        T, m, n1, nz, nt = self.T, self.m, self.n1, self.nz, self.nt
        d = n1 + m
        X = ca.SX.sym("X", n1, n1)
        zK, zL = ca.SX.sym("z", nz), ca.SX.sym("gam", nt)
        F, W, Ct = ca.SX.sym("F", n1, d), ca.SX.sym("W", n1, n1), ca.SX.sym("C", d, d)
        Gh, Lh, Mx = ca.SX.sym("Gh", m, n1), ca.SX.sym("Lh", m, m), ca.SX.sym("Mx", n1, n1)
        Zm = ca.reshape(zK, m, n1)
        ZM = ca.mtimes(Zm, Mx)
        IG = ca.vertcat(ca.SX.eye(n1), Gh + ca.mtimes(Lh, ZM))
        Acl = ca.mtimes(F, IG)
        Fu = F[:, n1:]
        XIG = ca.mtimes([IG, X, IG.T])

        def moments(S):
            Xn = ca.mtimes([Acl, X, Acl.T]) + ca.mtimes([Fu, S, Fu.T]) + W
            cost = 0.5 * (ca.sum1(ca.sum2(Ct * XIG)) + ca.sum1(ca.sum2(Ct[n1:, n1:] * S)))
            return Xn, cost

        Gam = ca.SX.zeros(m, m)
        for idx, (a, b) in enumerate(zip(*self.tl)):
            Gam[a, b] = zL[idx]
        LG = ca.mtimes(Lh, Gam)
        Xn, cost = moments(ca.mtimes(LG, LG.T))
        kl = 0.5 * (ca.sum1(ca.sum2(Gam * Gam)) - m - 2 * sum(ca.log(Gam[a, a]) for a in range(m))
                    + ca.sum1(ca.sum2(ca.mtimes(ZM, X) * ZM)))
        data = [F, W, Ct, Gh, Lh, Mx]
        f_free = ca.Function("kl_step_free", [X, zK, zL, *data], [Xn, cost, kl])
        f_det = ca.Function("kl_step_det", [X, zK, *data], list(moments(ca.SX.zeros(m, m))))
        x = ca.MX.sym("x", self.nx)
        Xc = ca.MX(self.X0)
        obj, kls = 0, []
        eye_tri = ca.DM(np.eye(m)[self.tl])
        zero = ca.DM.zeros(nz)
        prob = self.prob
        for t in range(T):
            dt = [prob.F[t], self.Wt[t], prob.Ct[t], self.Gh[t], self.Lh[t], self.Mx[t]]
            o = int(self.off[t])
            if self.kind[t] == "det":
                Xc, ct = f_det(Xc, x[o : o + nz], *dt)
            elif self.kind[t] == "free":
                Xc, ct, klt = f_free(Xc, x[o : o + nz], x[o + nz : o + nz + nt], *dt)
                kls.append(klt)
            else:  # pinned: Z = 0, Gam = I is the reference
                Xc, ct, _ = f_free(Xc, zero, eye_tri, *dt)
            obj = obj + ct
        g = ca.MX(0, 1) if not kls else (sum(kls) if self.scalar else ca.vertcat(*kls))
        return x, obj, g

    def derivative_functions(self, ca):
        """CasADi callbacks ``grad_f``, ``jac_g`` and ``hess_lag`` (``nlpsol`` signatures)."""
        nx, ng = self.nx, self.ng
        spx, spp, sp1, spg = (ca.Sparsity.dense(nx, 1), ca.Sparsity(0, 1), ca.Sparsity.dense(1, 1),
                              ca.Sparsity.dense(ng, 1))
        # Jacobian (compressed columns): the columns of step t hold the rows r with cons[r] >= t
        first = np.searchsorted(self.cons, np.arange(self.T)) if not self.scalar else np.zeros(self.T, int)
        colind = np.concatenate([[0], np.cumsum(np.repeat(ng - first, self.sizes))]).astype(int)
        rows = np.concatenate([np.tile(np.arange(first[t], ng), int(self.sizes[t])) for t in range(self.T)])
        jsp = ca.Sparsity(ng, nx, colind.tolist(), rows.astype(int).tolist())
        jseg = [(int(self.off[t]), int(self.sizes[t]), int(first[t]), int(colind[self.off[t]]))
                for t in range(self.T) if self.sizes[t]]
        # Hessian: upper triangle of the block diagonal, compressed columns
        tri = {nb: np.tril_indices(nb) for nb in set(self.sizes[self.var].tolist())}  # (col, row), by column
        steps = np.flatnonzero(self.var)
        hrow = np.concatenate([self.off[t] + tri[self.sizes[t]][1] for t in steps])
        per_col = np.concatenate([np.arange(1, self.sizes[t] + 1) for t in steps])  # column c of a block: c + 1
        hsp = ca.Sparsity(nx, nx, np.concatenate([[0], np.cumsum(per_col)]).astype(int).tolist(),
                          hrow.astype(int).tolist())
        hseg, pos = [], 0
        for t in np.flatnonzero(self.var):
            nb = int(self.sizes[t])
            hseg.append((pos, nb))
            pos += tri[nb][0].size

        def grad_f(arg, res):
            x = arg[0]
            if res[0] is not None and res[0].size:
                res[0][0] = self._cost(x)
            if res[1] is not None:
                res[1][:] = self.grad_f(x)

        def jac_g(arg, res):
            x = arg[0]
            if res[0] is not None and res[0].size:
                res[0][:] = self.constraints(x)
            out = res[1]
            if out is None:
                return
            J = self.jac_g(x)
            for o, nb, r0, pos in jseg:
                blk = J[r0:, o : o + nb].T.ravel()
                out[pos : pos + blk.size] = blk

        def hess(arg, res):
            blocks = self.hess_blocks(arg[0], float(arg[2][0]), arg[3])
            out = res[0]
            for (pos, nb), B in zip(hseg, blocks):
                c_, r_ = tri[nb]
                out[pos : pos + c_.size] = B[r_, c_]

        return (_buffer_callback(ca, "kl_step_grad_f", [spx, spp], [sp1, spx], grad_f),
                _buffer_callback(ca, "kl_step_jac_g", [spx, spp], [spg, jsp], jac_g),
                _buffer_callback(ca, "kl_step_hess_l", [spx, spp, sp1, spg], [hsp], hess))

    def _cost(self, x: np.ndarray) -> float:
        """``f = sum_k E[l_k]`` (the oracle's objective, in NumPy)."""
        c = self.forward(x)
        XIG = c["IG"] @ c["X"] @ np.swapaxes(c["IG"], 1, 2)
        Ct, n1 = self.prob.Ct, self.n1
        return float(0.5 * (np.einsum("tij,tij->", Ct, XIG) + np.einsum("tij,tij->", Ct[:, n1:, n1:], c["S"])))

    def constraints(self, x: np.ndarray) -> np.ndarray:
        """The KL rows ``g`` (the oracle's constraints, in NumPy)."""
        c = self.forward(x)
        fr = self.free
        Gam = c["Gam"][fr]
        kl = 0.5 * ((Gam**2).sum(axis=(1, 2)) - self.m - 2.0 * np.log(np.diagonal(Gam, axis1=1, axis2=2)).sum(axis=1)
                    + np.einsum("tij,tjk,tik->t", c["Z"][fr], c["Y"][fr], c["Z"][fr]))
        return np.array([kl.sum()]) if self.scalar else kl


def _buffer_callback(ca, name: str, sp_in: list, sp_out: list, fn):
    """A CasADi ``Callback`` evaluating ``fn(inputs, outputs)`` on NumPy views of its buffers."""

    class _Callback(ca.Callback):
        def __init__(self):
            ca.Callback.__init__(self)
            self.construct(name, {})

        def get_n_in(self):
            return len(sp_in)

        def get_n_out(self):
            return len(sp_out)

        def get_sparsity_in(self, i):
            return sp_in[i]

        def get_sparsity_out(self, i):
            return sp_out[i]

        def has_eval_buffer(self):
            return True

        def eval_buffer(self, arg, res):
            view = lambda b: None if b is None else np.frombuffer(b, dtype=float)  # noqa: E731
            fn([view(a) for a in arg], [view(r) for r in res])
            return 0

    return _Callback()


def _casadi_structured(prob: _Problem, kind: np.ndarray, scalar: bool, ub, opts: dict, config: KLStepConfig):
    """:class:`_StructuredNLP` solved by IPOPT: objective and constraints as CasADi MX graphs of
    per-step SX functions, first derivatives and the block-diagonal Hessian from NumPy callbacks.

    MUMPS uses the QAMD ordering (``mumps_pivot_order = 6``: the per-step KL rows of the Jacobian
    are dense; the default ordering makes the factorisation about 4 times slower at ``n=26, m=7,
    T=100``).  Returns ``(K, k, Sigma, lam_g, status, n_iter, f, timing)``.
    """
    import casadi as ca

    t0 = time.perf_counter()
    nlp = _StructuredNLP(prob, kind, scalar, config.chol_floor)
    x, f, g = nlp.oracle(ca)
    grad_f, jac_g, hess = nlp.derivative_functions(ca)
    opts = dict(opts, **{"ipopt.mumps_pivot_order": 6, "grad_f": grad_f, "jac_g": jac_g, "hess_lag": hess})
    opts.update({f"ipopt.{k}": v for k, v in config.ipopt_options.items()})
    solver = ca.nlpsol("kl_step", "ipopt", {"x": x, "f": f, "g": g}, opts)
    build_s = time.perf_counter() - t0
    sol_x, lam, status, n_iter, fval, solve_s = _ipopt_solve(solver, nlp.x0, nlp.lbx, ub, nlp.ng,
                                                             config.ipopt_acceptable_tol)
    G, S, _ = nlp.policy(sol_x)
    n = prob.n
    K, k = G[:, :, :n].copy(), G[:, :, n].copy()
    pin = kind == "pin"
    K[pin], k[pin] = prob.reference.K[pin], prob.reference.k[pin]  # exactly the reference
    S[kind == "det"] = 0.0
    return K, k, S, lam, status, n_iter, fval, {"build_s": build_s, "solve_s": solve_s}


# --------------------------------------------------------------------------------------------
# step-size adaptation (GPS) under the Laplace approximation
# --------------------------------------------------------------------------------------------


class LocalModel(NamedTuple):
    """A fitted local model: dynamics, quadratic cost expansion and initial state distribution."""

    dynamics: LinearGaussianDynamics
    cost: QuadraticCost
    mu0: np.ndarray
    P0: np.ndarray


def laplace_improvements(old_policy: LinearGaussianPolicy, new_policy: LinearGaussianPolicy,
                         previous: LocalModel, current: LocalModel) -> tuple[float, float]:
    """Predicted and actual improvement of the expected cost under the Laplace approximation.

    ``previous`` is the model (dynamics fit + cost expansion around the old trajectory) the
    KL step that produced ``new_policy`` was solved on; ``current`` is the model fitted to the
    samples of ``new_policy``.  With ``J_M(p) = sum_k E[l_k]`` in closed form under model ``M``:

        predicted = J_previous(old) - J_previous(new)     (what the step promised)
        actual    = J_previous(old) - J_current(new)      (what the new samples show)

    Returns ``(predicted, actual)`` as floats.
    """
    j_old = expected_cost(previous.dynamics, previous.cost, old_policy, previous.mu0, previous.P0).sum()
    j_pred = expected_cost(previous.dynamics, previous.cost, new_policy, previous.mu0, previous.P0).sum()
    j_act = expected_cost(current.dynamics, current.cost, new_policy, current.mu0, current.P0).sum()
    return float(j_old - j_pred), float(j_old - j_act)


def adapt_step(nu, predicted_improvement: float, actual_improvement: float,
               config: KLStepConfig | None = None):
    """GPS step-size rule: scale the KL budget by how well the model predicted the improvement.

    ``mult = predicted / (2 max(min_gap, predicted - actual))`` clipped to
    ``[min_mult, max_mult]`` (defaults 0.1, 5.0); ``new_nu = clip(mult * nu, nu_min, nu_max)``.
    The multiplier is the minimiser of the quadratic fitted to the two improvements: a perfect
    prediction (``actual = predicted``) gives ``max_mult``, ``actual = 0`` halves the budget,
    a cost increase (or a non-positive prediction) gives ``min_mult``.  ``nu`` may be a scalar
    or an array (every entry scaled by the same multiplier); returns the same kind.
    """
    config = KLStepConfig() if config is None else config
    pred, act = float(predicted_improvement), float(actual_improvement)
    if not (math.isfinite(pred) and math.isfinite(act)):
        raise ValueError(f"improvements must be finite, got predicted={pred!r}, actual={act!r}")
    nu_a = np.asarray(nu, dtype=float)
    if np.any(np.isnan(nu_a)) or np.any(nu_a < 0):
        raise ValueError(f"nu must be non-negative and not NaN, got {nu!r}")
    mult = pred / (2.0 * max(config.min_gap, pred - act))
    mult = min(max(mult, config.min_mult), config.max_mult)
    out = np.clip(mult * nu_a, config.nu_min, config.nu_max)
    return float(out) if nu_a.ndim == 0 else out
