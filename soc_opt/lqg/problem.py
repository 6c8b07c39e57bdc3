"""Shared types, input validation and the per-step problem arrays of the KL-constrained LQG
step (docs/math.md §6; the problem is stated in :mod:`soc_opt.lqg`).

The bottom of the package: imports nothing from its siblings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np
from scipy.linalg import lapack

from .. import errors
from ..config import Config, Interval, Options, config_error
from ..linalg import inv_from_chol, logdet_chol, tri_solve
from ..models import (
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    QuadraticCost,
    ShapeError,
    check_array,
    check_covariances,
    symmetrize,
)


class SolverError(errors.SolverError):
    """A numerical solver of the KL step (IPOPT, the dual solvers) failed; the message carries
    its status.  A :class:`soc_opt.errors.SolverError`: ``.status`` is IPOPT's return status
    (IPOPT failures), ``.step`` the step of an unreachable per-step budget (vector dual)."""


class BudgetUnreachable(SolverError):
    """The dual cannot make the step as small as the budget asks: ``KL(eta_max) > nu`` (scalar budget) or
    ``KL_k(eta_max) > nu_k`` at ``.step`` (per-step budgets).  The limit of a vanishing step is the
    reference itself (docs/math.md §12.2, the zero step of step acceptance)."""


class LocalModel(NamedTuple):
    """The KL step's model (docs/math.md §6): fitted dynamics, the quadratic cost expansion and the
    initial state distribution ``N(mu0, P0)``."""

    dynamics: LinearGaussianDynamics
    cost: QuadraticCost
    mu0: np.ndarray
    P0: np.ndarray


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
    """Options of the KL step's solvers, :func:`kl_step` (docs/math.md §6).

    Dual solver (closed form):
        kl_rtol, kl_atol: stop when ``|KL - nu| <= kl_rtol * nu + kl_atol`` for every active
                        budget (1e-10, 1e-13 per step: the roundoff floor of the KL formula).
        eta_init:       first multiplier when no warm start ``eta0`` is given (1.0).
        eta_min:        lower bound on a finite-budget multiplier; a budget with
                        ``KL(eta_min) < nu`` is reported slack with ``eta = eta_min`` (1e-12).
        eta_max:        upper bound; reaching it is an error (1e16).
        max_backward:   budget of backward passes for one dual solve (500).
        max_log_step:   cap on one step of either dual solver in ``log eta`` (``log 1e3``).
    Quu repair (see :mod:`soc_opt.lqg.backward`):
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
    fatrop (method ``"fatrop"``, :mod:`soc_opt.lqg.fatrop_nlp`):
        fatrop_tol:     fatrop ``tol`` (1e-8; policy and multipliers then agree with the closed
                        form to about 1e-10 on the tested instances).
        fatrop_max_iter: fatrop ``max_iter`` (1000).
        fatrop_expand:  expand the NLP's MX graph into SX before solving (True: faster
                        evaluations; False saves build time and memory on large problems).
        fatrop_options: extra fatrop options (override the above).

    The step-size rule that sets the budget is not a solver option: its settings are
    :class:`soc_opt.lqg.step_size.StepSizeConfig`.
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
    fatrop_tol: float = 1e-8
    fatrop_max_iter: int = 1000
    fatrop_expand: bool = True
    fatrop_options: dict[str, Any] = field(default_factory=dict)

    _constraints = {
        **{name: [Interval(0, None, "neither")]
           for name in ("kl_rtol", "kl_atol", "eta_init", "eta_min", "eta_max", "max_log_step", "ipopt_tol",
                        "ipopt_acceptable_tol", "chol_floor", "fatrop_tol")},
        "repair_factor": [Interval(1.0, None, "neither")],
        "repair_margin": [Interval(0.0)],
        **{name: [Interval(1)] for name in ("max_backward", "ipopt_max_iter", "fatrop_max_iter")},
        "casadi_nlp": [Options(("auto", "symbolic", "structured"))],
        "casadi_auto_max_vars": [Interval(0)],
    }

    def __post_init__(self):
        if self.eta_min >= self.eta_max:
            raise config_error("eta_min", f"must be below eta_max = {self.eta_max!r}, got {self.eta_min!r}")


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
        method:        ``"closed_form"``, ``"casadi"`` or ``"fatrop"``.
        n_iter:        dual iterations (closed form) or IPOPT / fatrop iterations.
        status:        solver status string.
        marginals:     :class:`Marginals` of the optimal policy.
        lam_g:         CasADi and fatrop only: multipliers of the KL constraints (one per
                       constrained step, or one for the total budget).
        solver_stats:  CasADi only: ``{"n_vars", "formulation", "build_s", "solve_s"}`` (NLP size,
                       ``"symbolic"`` or ``"structured"`` (``"none"`` if nothing was solved),
                       seconds to build the NLP (symbolic: with its exact Hessian), seconds in
                       IPOPT); fatrop: the same keys (formulation ``"multiple_shooting"``) and
                       ``"n_ocp_vars"`` (states and controls of the multiple-shooting NLP).
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


def check_dims(dynamics, *, cost=None, policy=None, reference=None) -> tuple[int, int, int]:
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


def check_init(mu0, P0, n: int) -> tuple[np.ndarray, np.ndarray]:
    mu0 = check_array("mu0", mu0, (n,))
    P0 = check_array("P0", P0, (n, n))
    P0 = check_covariances("P0", P0, psd_only=True)
    return mu0, P0


def reference_chol(reference: LinearGaussianPolicy) -> np.ndarray:
    """Lower Cholesky factors of the reference covariances (batched); clear error naming the
    first step that is not PD."""
    try:
        return np.linalg.cholesky(reference.cov)
    except np.linalg.LinAlgError:
        pass
    for t in range(reference.T):
        if lapack.dpotrf(reference.cov[t], lower=1, clean=1)[1] != 0:
            ev = float(np.linalg.eigvalsh(reference.cov[t])[0])
            raise NotPositiveDefiniteError(
                f"reference cov[{t}] is not positive definite (smallest eigenvalue {ev:.3e}); "
                "the KL step needs a reference policy with Sigma > 0"
            )
    raise NotPositiveDefiniteError("reference cov is not positive definite")  # pragma: no cover


def check_nu(nu, T: int) -> tuple[np.ndarray, bool]:
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


def ref_inverse(Lh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Sh^-1, log|Sh|)`` from the Cholesky factors (batched triangular solves), symmetrised."""
    return inv_from_chol(Lh), logdet_chol(Lh)


# --------------------------------------------------------------------------------------------
# per-step arrays (homogeneous coordinates x = (s, 1), z = (s, 1, a))
# --------------------------------------------------------------------------------------------


class KLProblem:
    """Per-step arrays of one problem, precomputed once (vectorised over T).

    In homogeneous coordinates ``z~ = (s, 1, a)`` the stage cost is ``1/2 z~^T Ct z~``, the mean
    dynamics ``(s', 1) = F z~`` and ``-log phat(a|s) = 1/2 z~^T H z~ + const``.  The backward
    pass (:mod:`.backward`) works in the deviation coordinates ``z' = (s, 1, delta)``,
    ``delta = a - Kh s - kh`` (``delta = a`` without a reference): ``z~ = E z'`` with
    ``E = [[I, 0], [Kth, I]]``, dynamics ``Fd = F E`` and stage cost ``Ctd = E^T Ct E``.

    Fields (``n1 = n + 1``, ``d = n1 + m``): ``F`` (T, n1, d), ``Ct`` (T, d, d), ``Fd`` (T, n1, d),
    ``Fdut = [Fdu, Fdx]^T`` (T, d, n1: ``Fd``'s columns in the order (u, x), transposed and
    C-contiguous, so that ``Fdut[t].T`` is that matrix in Fortran order, as BLAS takes it),
    ``Ctd`` (T, d, d), ``has_ref``; with a reference also
    ``Lh`` (T, m, m) (``Sh = Lh Lh^T``), ``Lhinv = Lh^-1``, ``Shinv`` (T, m, m), ``logdetSh`` (T,),
    ``Kth = [Kh, kh]`` (T, m, n1) and ``H`` (T, d, d) (computed on first use).
    """

    def __init__(self, dynamics: LinearGaussianDynamics, cost: QuadraticCost, reference, mu0, P0):
        T, n, m = dynamics.T, dynamics.n, dynamics.m
        self.T, self.n, self.m = T, n, m
        self.dynamics, self.cost = dynamics, cost
        self.mu0, self.P0 = mu0, P0
        n1 = n + 1
        d = n1 + m
        F = np.zeros((T, n1, d))
        F[:, :n, :n] = dynamics.A
        F[:, :n, n] = dynamics.c
        F[:, :n, n1:] = dynamics.B
        F[:, n, n] = 1.0
        self.F = F
        Ct = np.zeros((T, d, d))
        C, c = cost.C, cost.c
        Ct[:, :n, :n] = C[:, :n, :n]
        Ct[:, :n, n1:] = C[:, :n, n:]
        Ct[:, n1:, :n] = C[:, n:, :n]
        Ct[:, n1:, n1:] = C[:, n:, n:]
        Ct[:, :n, n] = c[:, :n]
        Ct[:, n, :n] = c[:, :n]
        Ct[:, n1:, n] = c[:, n:]
        Ct[:, n, n1:] = c[:, n:]
        Ct[:, n, n] = 2.0 * cost.c0
        self.Ct = Ct
        self.has_ref = reference is not None
        self._H = None
        self.workspace = None  # buffers of backward_pass, created there on first use
        self.fwd_workspace = None  # buffers of the forward pass (moments.ForwardWorkspace), likewise
        if not self.has_ref:
            self.Fd, self.Ctd = F, Ct
            self.Fdut = ux_transpose(F, n1)
            return
        self.reference = reference
        self.Lh = reference_chol(reference)
        self.Kh, self.kh, self.Sh = reference.K, reference.k, reference.cov
        self.Lhinv = tri_solve(self.Lh, np.broadcast_to(np.eye(m), (T, m, m)))  # (T, m, m)
        # = ref_inverse(Lh) (the same triangular solves), reusing Lh^-1
        self.Shinv = symmetrize(tri_solve(np.swapaxes(self.Lh, 1, 2), self.Lhinv))
        self.logdetSh = logdet_chol(self.Lh)
        self.Kth = Kth = np.concatenate([reference.K, reference.k[:, :, None]], axis=2)  # (T, m, n1)
        # Fd = F E = [Fx + Fu Kth, Fu];  Ctd = E^T Ct E by blocks (Ct_ux + Ct_uu Kth = Ctd_ux)
        # (the batched products on contiguous operands: numpy's batched matmul is much faster so)
        Fd = F.copy()
        Fd[:, :n, :n1] += dynamics.B @ Kth  # (the last row of Fu is 0)
        self.Fd = Fd
        self.Fdut = ux_transpose(Fd, n1)
        Ctd = np.empty((T, d, d))
        ux = Ct[:, n1:, :n1] + np.ascontiguousarray(Ct[:, n1:, n1:]) @ Kth
        xx = (Ct[:, :n1, :n1] + np.ascontiguousarray(Ct[:, :n1, n1:]) @ Kth
              + np.ascontiguousarray(np.swapaxes(Kth, 1, 2)) @ ux)
        Ctd[:, :n1, :n1] = symmetrize(xx)
        Ctd[:, n1:, :n1] = ux
        Ctd[:, :n1, n1:] = np.swapaxes(ux, 1, 2)
        Ctd[:, n1:, n1:] = Ct[:, n1:, n1:]
        self.Ctd = Ctd

    @property
    def H(self) -> np.ndarray | None:
        """(T, d, d) quadratic form of ``-log phat`` in ``z~`` (None without a reference)."""
        if self._H is None and self.has_ref:
            T, m = self.T, self.m
            ref = self.reference
            G = np.concatenate([-ref.K, -ref.k[:, :, None], np.broadcast_to(np.eye(m), (T, m, m))], axis=2)
            self._H = symmetrize(np.swapaxes(G, 1, 2) @ self.Shinv @ G)
        return self._H


def ux_transpose(F: np.ndarray, n1: int) -> np.ndarray:
    """(T, d, n1) ``[F[:, :, n1:], F[:, :, :n1]]^T`` of (T, n1, d) dynamics ``F`` (columns (x, u)),
    C-contiguous (the layout of ``KLProblem.Fdut``)."""
    return np.concatenate([np.swapaxes(F[:, :, n1:], 1, 2), np.swapaxes(F[:, :, :n1], 1, 2)], axis=1)


def policy_from(K, k, S, eta) -> LinearGaussianPolicy:
    return LinearGaussianPolicy(K, k, S, allow_singular=bool(np.any(eta == 0)))
