"""M-step: the paper's surrogate ``Lbar_k``, the exact-EM objective, and their maximisers (SPEC §5).

Notation (time step ``k``; the index is dropped inside formulas)
-----------------------------------------------------------------
``zeta = (s_{k+1}, y_k)`` and ``stilde = (s_k, 1)`` both have ``n+1`` components.  The
smoothed second moments (:class:`soc_opt.estep.Moments`) are ``Szz = E[zeta zeta^T]``,
``Szs = E[zeta stilde^T]`` and ``Stilde = Sss = E[stilde stilde^T]``.  The policy is
``phi = (F, Sigma)`` with ``F = [K k]`` (``m x (n+1)``) so that the mean action is ``F stilde``.
From the augmented model: ``B = Bs_k = [B_k; By_k]`` (``(n+1) x m``), ``A_s = As_k``,
``So = So_k`` and ``Atil = [A_s co_k]`` so that ``A_s s + co = Atil stilde``.

Surrogate (the paper's ``Lbar_k``)
----------------------------------
With ``z = (s, F stilde + L w)``, ``w ~ N(0, I)`` independent of the smoothed state::

    Lbar = -1/2 E[(zeta - Ao z - co)^T So^{-1} (zeta - Ao z - co)] - 1/2 log|So|
         = -1/2 tr(So^{-1} E[e e^T]) - 1/2 tr(H Sigma) - 1/2 log|So|,
    e = zeta - (Atil + B F) stilde,   H = B^T So^{-1} B.

Expanding ``E[e e^T]`` gives ``Lbar = c0 - 1/2 tr(H F Stilde F^T) + tr(F^T R) - 1/2 tr(H Sigma)``
with ``R = B^T So^{-1} E[(zeta - Atil stilde) stilde^T] = B^T So^{-1} (Szs - Atil Stilde)``.
Its gradient in ``F`` is ``R - H F Stilde``; its Hessian in ``vec(F)`` (column-major) is
``-(Stilde kron H)``, negative definite iff ``H > 0`` (``B`` full column rank) and ``Stilde > 0``
(equivalently ``P_k > 0``: ``P_k`` is the Schur complement of the corner 1 in ``Stilde``).
Hence the closed form ``F = H^{-1} R Stilde^{-1}`` (Cholesky solves).  When it is not unique a
:class:`NonUniqueMaximizerError` names the step and the failed condition; ``min_norm=True``
returns ``H^+ R Stilde^+``, the minimum Frobenius-norm maximiser (``(S kron H)^+ = S^+ kron H^+``).

Covariance and constraint sets (:class:`MStepConstraints`)
---------------------------------------------------------
``Lbar`` is linear and non-increasing in ``Sigma``, so its unconstrained optimum is
``Sigma = 0`` — not a valid (positive definite) policy.  Supported sets:

* ``cov_floor``  ``Sigma >= Sigma_min``: optimum ``Sigma_min`` since ``tr(H (Sigma - Sigma_min)) >= 0``.
* ``entropy_floor``  ``log det Sigma >= c``: optimum ``alpha H^{-1}``, ``log alpha = (c + log det H)/m``.
  Derivation: by AM-GM on the eigenvalues of ``H^{1/2} Sigma H^{1/2}``,
  ``tr(H Sigma) >= m det(H Sigma)^{1/m} >= m (det H e^c)^{1/m} = m alpha`` with equality iff
  ``H^{1/2} Sigma H^{1/2} = alpha I`` and ``log det Sigma = c``.  Requires ``H > 0`` (otherwise the
  supremum is not attained).
* ``cov_ceiling``  ``Sigma <= Sigma_max``: on its own the optimum is still ``Sigma = 0``; it is
  only meaningful together with a floor or an entropy floor.  A ceiling alone (like no covariance
  constraint at all) is rejected unless ``allow_singular=True``, which returns ``Sigma = 0``.
* Floors, ceilings and entropy floors may be given per step (``T`` values), e.g. built from the
  previous policy's covariances.
* ``offset_bound`` ``|k|_inf <= b`` (elementwise) and ``trust_region``
  ``||[K k] - [K k]_prev||_F <= delta``: no closed form; CVXPY only.

Combined covariance constraints use the relaxation rule: the closed-form optimum of a single
constraint (``Sigma_min``, ``alpha H^{-1}``) that satisfies all the other constraints is optimal
for the whole set.  If no such candidate exists at some step (two constraints active at once)
``method="closed_form"`` raises :class:`ClosedFormUnavailableError` and ``method="cvxpy"`` is
needed.  Infeasible sets (floor not below ceiling, entropy floor above ``log det`` of the ceiling)
raise :class:`InfeasibleConstraintsError` naming them.

CVXPY form
----------
The same objective as a disciplined concave program over ``(F, Sigma)``:
``-1/2 ||Lh^T F Ls - C||_F^2 - 1/2 <H, Sigma>`` plus constants, with ``H = Lh Lh^T``,
``Stilde = Ls Ls^T`` and ``C = Lh^{-1} R Ls^{-T}`` (the completed square, so the unconstrained
optimum of the quadratic is exactly 0).  ``parameter @ variable @ parameter`` is *not* DPP in
CVXPY (a product of two parameter-dependent factors), so an auxiliary variable ``Z = F Ls`` is
introduced and the residual is ``Lh^T Z - C``.  The time-invariant quadratic
``sum_k Stilde_k kron H_k`` does not factor, so it is written ``-1/2 ||Lq^T vec(F) - c||^2``
with ``Lq Lq^T = sum_k Stilde_k kron H_k``.  These two forms are used when ``F`` is unconstrained
(only covariance constraints).  With an ``offset_bound`` and/or a ``trust_region`` the spectral
form below is used instead.  Problems are built once per ``(form, n, m, constraint structure)``,
cached, and re-solved per step by updating parameter values.  Solver statuses other than optimal
raise :class:`SolverError`.

Trust region in CVXPY.  The spectral form writes the ``F`` part in the eigenbasis of its Hessian
``Q`` (``Stilde kron H``, eigenpairs from those of ``Stilde`` and ``H``; time-invariant: the eigenpairs
of ``sum_k Stilde_k kron H_k``): ``vec F = f0 + U y`` with ``Q = U Diag(lam) U^T`` (``U`` orthogonal) and
reference point ``f0`` (the trust-region centre; the mean of the ``T`` centres for the time-invariant
variant; 0 without a trust region), so the objective is ``-1/2 sum_i lam_i y_i^2 + g^T y`` (plus the
constant ``-1/2 f0^T Q f0 + r^T f0``), a diagonal quadratic with no auxiliary variable or equality
constraint, and, ``U`` being orthogonal, ``||F - F_prev,j||_F = ||y - a_j||_2`` with
``a_j = U^T (vec F_prev,j - f0)``: the trust region is an SOC on the variable itself.  The offset
column of ``F`` is ``f0n + Un y`` with ``Un`` the corresponding ``m`` rows of ``U``.  ``F`` is recovered as
``f0 + U y`` (an exact change of variables; the solver's duals are those of the original
constraints).

Why.  With Clarabel's default step length (``max_step_fraction=0.99``) the factored and Kronecker
forms with a trust region ended as ``optimal_inaccurate`` on 12-50% of random well-posed instances
(``T = 4``; sizes ``(n, m) = (3, 2), (6, 2), (26, 7)``; both variants).  The failures occur when the
trust region is active with a multiplier comparable to the curvature (``mu/delta <~ 10
lambda_max(Q)``): the duality gap keeps decreasing but the primal residual stalls near 1e-11 and
then grows about 10x per iteration as the barrier parameter goes to 0, so the gap reaches
``clarabel_tol`` only after the residual has left it.  The same happens on an 8-variable ball-
constrained QP as soon as its Hessian is not isotropic (condition number 100: 35-67% failures, also
with a diagonal Hessian; isotropic: ~1%).  That anisotropy between ``Q`` and the ball is invariant
under linear changes of variables (whitening ``F`` makes the objective ``||G - C||^2`` and the trust
region an ellipsoid), and no reformulation removed the failures: whitened variable, epigraph of
the objective (fewer failures for small sizes, more for ``(26, 7)``, ``F`` errors up to 2e-5), norm
epigraph (no failures, ``F`` errors up to 2e-5: a linear objective on a curved boundary), the SOC
without the auxiliary ``Z``, unit-radius scaling, squared-norm trust region; nor did Clarabel's
regularisation, iterative refinement or equilibration settings.  The cause is the path following:
as the multiplier decreases the boundary point of the ball turns (it does not when ``Q`` is
isotropic), long steps leave the central path (``sqrt(det s det z)/(s^T z)`` of the SOC block
0.3-0.75 instead of 1) and the Newton systems near the solution lose accuracy.  Trust-region
problems are therefore solved with ``max_step_fraction=0.8`` (that ratio stays at 0.999), and with
a fresh Clarabel solver per solve: CVXPY's default warm start updates the cached solver's data in
place, which keeps the Ruiz equilibration of the first instance solved, so that whether an
instance solved depended on the instances solved before it.  A solve that still ends inaccurately
is repeated once with ``max_step_fraction=0.5``.  Tolerances are never changed and no closed form is
involved.  Shorter steps alone fix the factored form too; the spectral form is more accurate and
faster: against the More-Sorensen (secular equation) solution the largest relative error of ``F``
over 720 time-varying steps is 1e-7 (factored form at 0.8: 5e-7; at the default steps, solved
cases only: 2e-6), for ``(26, 7)`` 3e-9 (6e-8; 1e-6); and a ``(26, 7)`` step takes ~1/3 of the
time (time-varying) and ~1/20 (time-invariant, which had a dense ``d x d`` parameter).  Remaining
limitation: time-invariant problems whose ``T`` centres are about ``delta`` apart (pairwise ~1.4
``delta``: a small lens-shaped intersection with all spheres active) still fail on ~10% of random
``(26, 7)`` instances, mostly for ``delta >= 0.1`` (24% before).

Entropy floor in CVXPY.  ``log det Sigma >= c`` is not written with ``cp.log_det`` (which CVXPY
lowers to a PSD cone plus exponential cones) but as the equivalent ``det(Sigma)^(1/m) >= e^(c/m)``
in the standard SDP + geometric-mean form, with only PSD and second-order cones: for ``Sigma > 0``,
``det(Sigma)^(1/m) = max geo_mean(diag Z)`` over lower-triangular ``Z`` with
``[[Sigma, Z], [Z^T, Diag(diag Z)]] >= 0``.  (The block condition gives ``Sigma >= Z D^-1 Z^T``,
``D = Diag(diag Z) > 0``, so ``det Sigma >= det(Z)^2 / det D = prod diag Z``; the Cholesky factor
``Sigma = L L^T`` attains it with ``Z = L Diag(diag L)``.)  The constraint is applied to the
whitened ``Sw = Lh^T Sigma Lh`` (``H = Lh Lh^T``; ``log det Sw = log det Sigma + log det H``, so
the right-hand side becomes ``t = exp((c + log det H)/m)``, a parameter); ``Y = Sigma Lh`` is an
auxiliary variable so that every product stays DPP.  The reported ``entropy_floor`` dual is that
of ``log det Sigma >= c``: ``nu = mu t/m`` from the dual ``mu`` of ``geo_mean >= t`` (both are the
sensitivities of the optimal value, and ``dt/dc = t/m``).

Accuracy: the objective is linear in ``Sigma`` and the boundary ``det Sigma = e^c`` curved, so the
value is flat to first order along the boundary and an interior-point solution with duality gap
``g`` can be ``~sqrt(g)`` away from the maximiser unless its iterates stay near the central
path.  With ``cp.log_det`` and the default settings Clarabel returned ``Sigma`` only to ~1e-5
(value ~1e-10).  For problems with an entropy floor Clarabel is therefore run with only symmetric
cones (the construction above), ``max_step_fraction=0.8``, no chordal decomposition of the PSD
block and gap tolerances ``clarabel_tol / 100`` (1e-12 by default; tighter, never looser, and
retried at ``clarabel_tol`` if round-off ends the tighter solve as ``optimal_inaccurate``).
Measured: ``Sigma`` to ~1e-8 (time-varying) and ~1e-7 (time-invariant) relative for
``n=26, m=7``, better for smaller ``m``; ~1.4x the solve time of the ``log_det`` form there.
No closed form is used.  SCS, which stops on KKT residuals, reaches ~1e-8 in either form.

Time-varying sweep and time-invariant variant
---------------------------------------------
The Proposition's DP sweep runs ``j = T-1 .. 0`` maximising ``Lbar_j`` with the future terms fixed.
With the smoothed moments fixed, ``Lbar_j`` depends on ``phi_j`` only and the future terms do not
depend on ``phi_j``, so the sweep decouples into ``T`` independent problems: the CVXPY path runs the
backward sweep literally, the closed form is batched over ``T`` (the order is immaterial).
The time-invariant variant maximises ``sum_k Lbar_k`` over one shared ``phi``: the normal
equations ``sum_k H_k F Stilde_k = sum_k R_k`` read ``(sum_k Stilde_k kron H_k) vec F = vec(sum_k R_k)``
(the paper's ``M = sum_k M_k``), and ``Sigma`` comes from the constraint set with ``H = sum_k H_k``.
A time-invariant trust region bounds ``||F - F_prev,k||_F <= delta`` at every step ``k``.

Exact-EM objective (``objective="exact"``)
------------------------------------------
``exact_k = E[log N(zeta; M s + m, S)]`` with the action integrated out (SPEC §4):
``M stilde = (Atil + B F) stilde``, ``S = So + B Sigma B^T``.  Since
``N(zeta; M s + m, S) = int N(a; F stilde, Sigma) N(zeta; Atil stilde + B a, So) da``, Jensen's
inequality gives ``Lbar_k - (n+1)/2 log(2 pi) <= exact_k``: the paper's surrogate is (up to this
constant) a lower bound of the exact objective, and the gap is the expected KL divergence between
the action prior and its posterior.  Maximising ``sum_k exact_k`` is the M-step under which
``log p(Y)`` is provably non-decreasing (the EM lemma).

It is maximised by inner EM iterations with the action as the latent variable (a generalized-EM
step started from ``previous``).  Given ``(s, zeta)`` the action posterior is Gaussian with mean
``G zeta + J stilde`` (``G = Sigma B^T S^{-1}``, ``J = F - G M``) and covariance
``V = Sigma - G B Sigma``, so ``E[a stilde^T] = G Szs + J Stilde`` and
``E[a a^T] = V + (G, J) [[Szz, Szs], [Szs^T, Stilde]] (G, J)^T`` follow from the moments.  The inner
M-step is ``F' = E[a stilde^T] Stilde^{-1}``, ``Sigma' = E[(a - F' stilde)(a - F' stilde)^T] =: W``.
Constraints are applied to the inner M-step: ``cov_floor``/``cov_ceiling`` by clipping the
eigenvalues of ``W`` whitened by the bound (the Gaussian-likelihood maximiser over the Loewner
half-space), ``entropy_floor`` by ``max(1, e^{(c - log det W)/m}) W``, floor and ceiling together
by the relaxation rule or a CVXPY log-det program in the precision, and ``offset_bound``/``trust_region``
by a CVXPY step in ``F`` with ``Sigma`` held at its current value (an ECM step).  Every inner step
does not decrease ``sum_k exact_k`` (from a feasible start); iteration stops when the relative
change is below ``MStepConfig.exact_tol``.  ``entropy_floor`` combined with another covariance
constraint is not supported for the exact objective.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from typing import Literal, NamedTuple

import cvxpy as cp
import numpy as np

from ..config import Config, ConfigError
from ..estep import Moments, moments
from ..models import (
    AugmentedModel,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    ShapeError,
    Smoothed,
    symmetrize,
)

__all__ = [
    "SolverError",
    "NonUniqueMaximizerError",
    "InfeasibleConstraintsError",
    "ClosedFormUnavailableError",
    "MStepConstraints",
    "MStepConfig",
    "MStepResult",
    "GradHess",
    "LOG_2PI",
    "surrogate",
    "surrogate_from_moments",
    "exact_objective",
    "exact_objective_from_moments",
    "surrogate_grad_hess",
    "maximize",
    "maximize_moments",
]

LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------- errors


class SolverError(RuntimeError):
    """A CVXPY solve failed; ``status`` is the solver's status and ``step`` the time step (or None)."""

    def __init__(self, message: str, status: str | None = None, step: int | None = None):
        super().__init__(message)
        self.status = status
        self.step = step


class NonUniqueMaximizerError(ValueError):
    """The M-step maximiser is not unique (``B_k`` rank deficient or ``P_k`` singular); names the step."""


class InfeasibleConstraintsError(ConfigError):
    """The constraint set is empty; the message names the conflicting constraints."""


class ClosedFormUnavailableError(ValueError):
    """The requested constraint set has no closed-form maximiser; use ``method="cvxpy"``."""


# --------------------------------------------------------------------------- configuration

_Matrix = float | tuple[tuple[float, ...], ...] | tuple[tuple[tuple[float, ...], ...], ...] | None


def _as_matrix_field(name: str, value):
    """Normalise a scalar / matrix / per-step-matrices config value (floats and nested tuples)."""
    if value is None:
        return None
    if isinstance(value, bool):
        raise ConfigError(f"{name}: expected a number or a square matrix, got {value!r}")
    if isinstance(value, (int, float, np.floating, np.integer)):
        v = float(value)
        if not math.isfinite(v) or v < 0.0:
            raise ConfigError(f"{name}: a scalar must be finite and >= 0, got {v}")
        return v
    a = np.asarray(value, dtype=float)
    if a.ndim not in (2, 3) or a.shape[-1] != a.shape[-2] or a.shape[-1] == 0 or a.shape[0] == 0:
        raise ConfigError(f"{name}: expected a scalar, an (m, m) matrix or (T, m, m) matrices, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: contains NaN or inf")
    scale = max(1.0, float(np.abs(a).max()))
    if np.abs(a - _T(a)).max() > 1e-10 * scale:
        raise ConfigError(f"{name}: matrix is not symmetric")
    a = symmetrize(a)
    ev = np.linalg.eigvalsh(a)[..., 0]
    if np.min(ev) < -1e-12 * scale:
        where = f" (step {int(np.argmin(ev))})" if a.ndim == 3 else ""
        raise ConfigError(f"{name}: matrix is not positive semidefinite{where} (smallest eigenvalue {np.min(ev):.3e})")
    return _nested_tuple(a)


def _nested_tuple(a: np.ndarray):
    if a.ndim == 1:
        return tuple(float(x) for x in a)
    return tuple(_nested_tuple(x) for x in a)


def _matrices(name: str, value, m: int, T: int) -> np.ndarray | None:
    """(T, m, m) from a scalar, an (m, m) matrix or (T, m, m) matrices."""
    if value is None:
        return None
    if isinstance(value, float):
        return np.broadcast_to(value * np.eye(m), (T, m, m))
    a = np.asarray(value, dtype=float)
    if a.shape == (m, m):
        return np.broadcast_to(a, (T, m, m))
    if a.shape != (T, m, m):
        raise ShapeError(
            f"constraint {name} must have shape ({m}, {m}) or (T, m, m) = ({T}, {m}, {m}), got {a.shape}"
        )
    return a


@dataclass(frozen=True)
class _Resolved:
    """Constraint set resolved for an action dimension ``m`` and ``T`` steps (numpy arrays, per step)."""

    m: int
    T: int
    Smin: np.ndarray | None  # (T, m, m)
    Smax: np.ndarray | None  # (T, m, m)
    c: np.ndarray | None  # (T,)
    b: np.ndarray | None  # (m,)
    delta: float | None
    allow_singular: bool

    @property
    def sigma_key(self) -> tuple[bool, bool, bool]:
        return (self.Smin is not None, self.c is not None, self.Smax is not None)

    @property
    def f_constrained(self) -> bool:
        return self.b is not None or self.delta is not None

    def names(self) -> list[str]:
        out = []
        for name, v in (("cov_floor", self.Smin), ("entropy_floor", self.c), ("cov_ceiling", self.Smax),
                        ("offset_bound", self.b), ("trust_region", self.delta)):
            if v is not None:
                out.append(name)
        return out

    def time_invariant(self) -> "_Resolved":
        """The covariance constraints on one ``Sigma`` shared by all steps (``T = 1``).

        ``log det Sigma >= c_k`` for all ``k`` is ``log det Sigma >= max_k c_k``; per-step floors
        (ceilings) reduce exactly to one floor that dominates (is dominated by) all others.
        """
        if self.T == 1:
            return self

        def reduce(S, name, upper):
            if S is None:
                return None
            for j in range(self.T):
                D = (S - S[j]) if upper else (S[j] - S)
                scale = max(1.0, float(np.abs(S).max()))
                if np.linalg.eigvalsh(D)[:, 0].min() >= -1e-12 * scale:
                    return S[j : j + 1]
            raise ValueError(
                f"time-invariant M-step with per-step {name}: no step's {name} "
                f"{'lies below' if upper else 'dominates'} all others, so the shared Sigma's feasible "
                f"set is not a single {name}; pass one ({self.m}, {self.m}) {name}"
            )

        c = None if self.c is None else np.array([self.c.max()])
        return dataclasses.replace(self, T=1, Smin=reduce(self.Smin, "cov_floor", False),
                                   Smax=reduce(self.Smax, "cov_ceiling", True), c=c)


@dataclass(frozen=True)
class MStepConstraints(Config):
    """The feasible set ``Phi`` of the M-step (SPEC §5).  All fields default to "absent".

    Fields:
        cov_floor: ``Sigma_k >= Sigma_min`` (Loewner order).  A scalar ``v`` means ``v I``; a matrix
            is an ``m x m`` symmetric PSD nested list; ``T`` such matrices give a per-step floor.
            Surrogate optimum: ``Sigma_min``.
        entropy_floor: ``log det Sigma_k >= c`` (nats; any real), one value or ``T`` per-step values.
            Surrogate optimum ``alpha H^{-1}`` with ``log det = c``.
        offset_bound: ``|k_i| <= b_i`` for every action component; a scalar or ``m`` values ``>= 0``.
            CVXPY only.
        trust_region: ``||[K k] - [K k]_prev||_F <= delta`` (``delta >= 0``) at every step;
            needs the ``previous`` policy.  CVXPY only.
        cov_ceiling: ``Sigma_k <= Sigma_max`` (scalar, matrix or per-step, as ``cov_floor``).  Must
            be combined with ``cov_floor`` or ``entropy_floor`` (alone, the surrogate optimum is
            ``Sigma = 0``).
        allow_singular: accept a singular optimum ``Sigma = 0`` (no covariance floor; a
            deterministic policy) instead of raising.

    Sets that are empty whatever ``m`` and ``T`` (floor not below ceiling, both given as
    matrices or both as scalars) are rejected at construction; the others when the set is resolved
    for the model (entropy floor above ``log det`` of the ceiling, scalar vs matrix bounds).  Both
    raise :class:`InfeasibleConstraintsError`.  The time-invariant variant needs per-step floors
    (ceilings) to have one dominating (dominated) member and uses ``max_k c_k`` as entropy floor.
    """

    cov_floor: _Matrix = None
    entropy_floor: float | tuple[float, ...] | None = None
    offset_bound: float | tuple[float, ...] | None = None
    trust_region: float | None = None
    cov_ceiling: _Matrix = None
    allow_singular: bool = False

    def __post_init__(self):
        object.__setattr__(self, "cov_floor", _as_matrix_field("cov_floor", self.cov_floor))
        object.__setattr__(self, "cov_ceiling", _as_matrix_field("cov_ceiling", self.cov_ceiling))
        if self.entropy_floor is not None:
            c = self.entropy_floor
            if isinstance(c, (int, float, np.floating, np.integer)) and not isinstance(c, bool):
                c = float(c)
                ok = math.isfinite(c)
            else:
                c = tuple(float(x) for x in np.asarray(c, dtype=float).ravel())
                ok = len(c) > 0 and all(math.isfinite(x) for x in c)
            if not ok:
                raise ConfigError(f"entropy_floor must be finite, got {self.entropy_floor!r}")
            object.__setattr__(self, "entropy_floor", c)
        if self.offset_bound is not None:
            b = self.offset_bound
            if isinstance(b, (int, float, np.floating, np.integer)) and not isinstance(b, bool):
                b = float(b)
                ok = math.isfinite(b) and b >= 0
            else:
                b = tuple(float(x) for x in np.asarray(b, dtype=float).ravel())
                ok = len(b) > 0 and all(math.isfinite(x) and x >= 0 for x in b)
            if not ok:
                raise ConfigError(f"offset_bound must be finite and >= 0, got {self.offset_bound!r}")
            object.__setattr__(self, "offset_bound", b)
        if self.trust_region is not None:
            d = float(self.trust_region)
            if not (math.isfinite(d) and d >= 0):
                raise ConfigError(f"trust_region must be finite and >= 0, got {self.trust_region!r}")
            object.__setattr__(self, "trust_region", d)
        lo, hi = self.cov_floor, self.cov_ceiling
        if lo is not None and hi is not None:
            if isinstance(lo, float) and isinstance(hi, float):
                if lo > hi:
                    raise InfeasibleConstraintsError(
                        f"infeasible constraint set: cov_floor ({lo:g} I) exceeds cov_ceiling ({hi:g} I)"
                    )
            elif not isinstance(lo, float) and not isinstance(hi, float):
                a, b = np.asarray(lo), np.asarray(hi)
                m = a.shape[-1]
                T = a.shape[0] if a.ndim == 3 else (b.shape[0] if b.ndim == 3 else 1)
                self.resolve(m, T)

    def resolve(self, m: int, T: int = 1) -> _Resolved:
        """Per-step arrays for action dimension ``m`` and ``T`` steps; checks shapes and feasibility."""
        Smin = _matrices("cov_floor", self.cov_floor, m, T)
        Smax = _matrices("cov_ceiling", self.cov_ceiling, m, T)
        b = None
        if self.offset_bound is not None:
            if isinstance(self.offset_bound, float):
                b = np.full(m, self.offset_bound)
            else:
                b = np.asarray(self.offset_bound, dtype=float)
                if b.shape != (m,):
                    raise ShapeError(f"constraint offset_bound must have {m} entries for m={m}, got {b.shape[0]}")
        c = None
        if self.entropy_floor is not None:
            c = np.broadcast_to(np.asarray(self.entropy_floor, dtype=float), (T,)) \
                if isinstance(self.entropy_floor, float) or len(self.entropy_floor) == T else None
            if c is None:
                raise ShapeError(
                    f"constraint entropy_floor must be one value or T={T} values, got {len(self.entropy_floor)}"
                )
        if Smin is not None and Smax is not None:
            scale = max(1.0, float(np.abs(Smax).max()))
            ev = np.linalg.eigvalsh(Smax - Smin)[:, 0]
            if ev.min() < -1e-12 * scale:
                k = int(np.argmin(ev))
                raise InfeasibleConstraintsError(
                    f"infeasible constraint set: cov_floor is not below cov_ceiling "
                    f"(Sigma_max - Sigma_min has eigenvalue {ev[k]:.3e} < 0{f' at step {k}' if T > 1 else ''})"
                )
        if c is not None and Smax is not None:
            sign, ld = np.linalg.slogdet(Smax)
            ld = np.where(sign > 0, ld, -np.inf)
            if np.any(ld < c):
                k = int(np.argmax(c - ld))
                raise InfeasibleConstraintsError(
                    f"infeasible constraint set: entropy_floor c={c[k]:g} exceeds log det(cov_ceiling)={ld[k]:g}, "
                    f"the largest log det allowed by the ceiling{f' (step {k})' if T > 1 else ''}"
                )
        return _Resolved(m, T, Smin, Smax, c, b, self.trust_region, self.allow_singular)


@dataclass(frozen=True)
class MStepConfig(Config):
    """Solver choice, tolerances and iteration limits of the M-step.

    Fields:
        solver: default CVXPY solver for ``method="cvxpy"`` ("CLARABEL" or "SCS").
        clarabel_tol: Clarabel ``tol_gap_abs``, ``tol_gap_rel`` and ``tol_feas`` (default 1e-10).
            Note: where the optimum lies on a curved boundary with a linear objective (the
            ``entropy_floor`` on Sigma) an interior-point solver locates the maximiser only to
            about the square root of the duality gap when its iterates leave the central path;
            problems with an entropy floor therefore use gap tolerances ``clarabel_tol / 100``
            (not below 1e-13 unless ``clarabel_tol`` is; falling back to ``clarabel_tol`` if that
            ends in round-off), shorter steps and no chordal decomposition (module docstring,
            "Entropy floor in CVXPY").
            Problems with a trust region are solved with shorter steps (``max_step_fraction`` 0.8,
            retried at 0.5) and a fresh Clarabel solver per solve (module docstring, "Trust region
            in CVXPY"); their tolerances are the same.
        clarabel_max_iter: Clarabel iteration limit (default 200).
        scs_eps: SCS ``eps_abs`` and ``eps_rel`` (default 1e-9; SCS is first order, so tight).
        scs_max_iters: SCS iteration limit (default 200000).
        accept_inaccurate: accept CVXPY status ``optimal_inaccurate`` (default False: raise).
        eig_tol: relative eigenvalue threshold below which ``H_k``, ``P_k`` (and the
            time-invariant Kronecker sum) count as singular (default 1e-10).
        feas_tol: tolerance of the feasibility checks of closed-form candidates (default 1e-9).
        exact_tol: exact-EM inner iterations stop when the change of the exact objective is
            below ``exact_tol * (1 + |objective|)`` at every step (default 1e-9).
            EM converges slowly (sublinearly) when the optimal Sigma approaches singularity.
        exact_max_iter: maximum number of exact-EM inner iterations (default 1000).
        verbose: pass ``verbose=True`` to the CVXPY solver.
    """

    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"
    clarabel_tol: float = 1e-10
    clarabel_max_iter: int = 200
    scs_eps: float = 1e-9
    scs_max_iters: int = 200_000
    accept_inaccurate: bool = False
    eig_tol: float = 1e-10
    feas_tol: float = 1e-9
    exact_tol: float = 1e-9
    exact_max_iter: int = 1000
    verbose: bool = False

    def __post_init__(self):
        if self.solver not in ("CLARABEL", "SCS"):
            raise ConfigError(f"solver: {self.solver!r} is not one of ['CLARABEL', 'SCS']")
        for name in ("clarabel_tol", "scs_eps", "eig_tol", "feas_tol", "exact_tol"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("clarabel_max_iter", "scs_max_iters", "exact_max_iter"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class MStepResult:
    """Everything an M-step produced (``maximize_moments(..., return_result=True)``).

    Fields:
        policy: the maximiser.
        objective: (T,) the maximised objective (``Lbar_k`` or ``exact_k``) at ``policy``.
        solver_value: optimal value reported by CVXPY plus the constants it omits: (T,) for the
            time-varying surrogate, (1,) for the time-invariant surrogate (``sum_k Lbar_k``);
            None for closed forms and the exact objective.
        status: solver statuses, one per CVXPY solve in order of solution (empty for closed forms).
        duals: per CVXPY surrogate solve (indexed like ``solver_value``), the dual values by
            constraint name (``offset_upper``, ``offset_lower``, ``trust`` (array over centres),
            ``cov_floor``, ``cov_ceiling``, ``entropy_floor`` (the multiplier of
            ``log det Sigma >= c``)).
        solve_time: wall time (s) of each CVXPY surrogate solve, indexed like ``solver_value``.
        history: exact objective only: (iterations+1, T) ``exact_k`` before and after each inner step.
        iterations: number of exact-EM inner iterations (0 otherwise).
        converged: exact-EM stopping rule met (True otherwise).
    """

    policy: LinearGaussianPolicy
    objective: np.ndarray
    solver_value: np.ndarray | None = None
    status: tuple[str, ...] = ()
    duals: tuple[dict, ...] = ()
    solve_time: np.ndarray | None = None
    history: np.ndarray | None = None
    iterations: int = 0
    converged: bool = True


class GradHess(NamedTuple):
    """Analytic derivatives of ``Lbar_k`` (``vec`` is column-major, i.e. ``order="F"``).

    grad:       (m(n+1),)             gradient w.r.t. ``vec([K k])``: ``vec(R - H F Stilde)``.
    hess:       (m(n+1), m(n+1))      Hessian w.r.t. ``vec([K k])``: ``-(Stilde kron H)``.
    grad_sigma: (m, m)                gradient w.r.t. ``Sigma``: ``-H/2`` (constant).
    """

    grad: np.ndarray
    hess: np.ndarray
    grad_sigma: np.ndarray


# --------------------------------------------------------------------------- linear algebra


def _T(X: np.ndarray) -> np.ndarray:
    return np.swapaxes(X, -1, -2)


def _chol(A: np.ndarray, name: str) -> np.ndarray:
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        ev = np.linalg.eigvalsh(A)[..., 0]
        idx = np.argwhere(np.atleast_1d(ev) <= 0)
        where = f" at step {int(idx[0][0])}" if A.ndim == 3 and len(idx) else ""
        raise NotPositiveDefiniteError(
            f"{name}{where} is not positive definite (smallest eigenvalue {float(np.min(ev)):.3e})"
        ) from None


def _tri_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``L^{-1} B`` for triangular ``L`` (batched).

    ``numpy.linalg.solve`` is used because it is batched in compiled code; the batched
    ``scipy.linalg.solve_triangular`` has a large per-call overhead for small matrices.
    """
    return np.linalg.solve(L, B)


def _cho_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^{-1} B`` from the lower Cholesky factor ``L`` of ``A`` (batched)."""
    return _tri_solve(_T(L), _tri_solve(L, B))


def _right_cho_solve(X: np.ndarray, L: np.ndarray) -> np.ndarray:
    """``X A^{-1}`` for symmetric ``A = L L^T`` (batched)."""
    return _T(_cho_solve(L, _T(X)))


def _logdet_chol(L: np.ndarray) -> np.ndarray:
    return 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)


def _tr(A: np.ndarray) -> np.ndarray:
    return np.trace(A, axis1=-2, axis2=-1)


def _inv_from_chol(L: np.ndarray) -> np.ndarray:
    eye = np.broadcast_to(np.eye(L.shape[-1]), L.shape)
    return symmetrize(_cho_solve(L, eye))


def _vec(F: np.ndarray) -> np.ndarray:
    return F.reshape(-1, order="F")


def _unvec(v: np.ndarray, m: int, n1: int) -> np.ndarray:
    return v.reshape((m, n1), order="F")


def _min_eig_rel(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest eigenvalue and smallest/largest ratio (batched, symmetric)."""
    ev = np.linalg.eigvalsh(A)
    big = np.maximum(np.abs(ev).max(-1), np.finfo(float).tiny)
    return ev[..., 0], ev[..., 0] / big


# --------------------------------------------------------------------------- inputs


def _policy_F(policy: LinearGaussianPolicy) -> np.ndarray:
    return np.concatenate([policy.K, policy.k[..., None]], axis=-1)


def _check_moments(model: AugmentedModel, mom: Moments) -> None:
    if not isinstance(model, AugmentedModel):
        raise TypeError(f"model must be an AugmentedModel, got {type(model).__name__}")
    T, n1 = model.T, model.n + 1
    for name in ("Szz", "Szs", "Sss"):
        a = np.asarray(getattr(mom, name))
        if a.shape != (T, n1, n1):
            raise ShapeError(
                f"moments {name} must have shape (T, n+1, n+1) = ({T}, {n1}, {n1}) to match the model, got {a.shape}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(f"moments {name} contains NaN or inf")


def _check_policy(model: AugmentedModel, policy: LinearGaussianPolicy, name: str = "policy") -> None:
    if not isinstance(policy, LinearGaussianPolicy):
        raise TypeError(f"{name} must be a LinearGaussianPolicy, got {type(policy).__name__}")
    want = (model.T, model.m, model.n)
    if policy.K.shape != want:
        raise ShapeError(f"{name} K must have shape (T, m, n) = {want} to match the model, got {policy.K.shape}")


def _Atil(model: AugmentedModel) -> np.ndarray:
    """(T, n+1, n+1) ``[A_s co]`` so that ``A_s s + co = Atil stilde``."""
    return np.concatenate([model.As, model.co[..., None]], axis=-1)


def _residual_second_moment(mom: Moments, Mt: np.ndarray) -> np.ndarray:
    """``E[(zeta - Mt stilde)(zeta - Mt stilde)^T]`` from the moments."""
    X = mom.Szs @ _T(Mt)
    return symmetrize(mom.Szz - X - _T(X) + Mt @ mom.Sss @ _T(Mt))


@dataclass(frozen=True)
class _Stats:
    """Per-step quadratic form ``Lbar = const - 1/2 tr(H F S F^T) + tr(F^T R) - 1/2 tr(H Sigma)``."""

    H: np.ndarray  # (T, m, m)
    R: np.ndarray  # (T, m, n+1)
    S: np.ndarray  # (T, n+1, n+1)
    const: np.ndarray  # (T,)


def _stats(model: AugmentedModel, mom: Moments) -> _Stats:
    B, Atil = model.Bs, _Atil(model)
    Lo = _chol(model.So, "augmented So")
    SoiB = _cho_solve(Lo, B)
    H = symmetrize(_T(B) @ SoiB)
    R = _T(SoiB) @ (mom.Szs - Atil @ mom.Sss)
    E0 = _residual_second_moment(mom, Atil)
    const = -0.5 * _tr(_cho_solve(Lo, E0)) - 0.5 * _logdet_chol(Lo)
    return _Stats(H, R, symmetrize(np.asarray(mom.Sss, dtype=float)), const)


# --------------------------------------------------------------------------- objectives


def surrogate_from_moments(model: AugmentedModel, mom: Moments, policy: LinearGaussianPolicy,
                           include_constant: bool = False) -> np.ndarray:
    """The paper's surrogate ``Lbar_k`` (T,) evaluated from its definition (see module docstring).

    ``-1/2 tr(So^{-1} (E[e e^T] + B Sigma B^T)) - 1/2 log|So|`` with ``e = zeta - (Atil + B F) stilde``;
    the ``B Sigma B^T`` term is the action noise ``B L w`` integrated out.  With
    ``include_constant=True`` the term ``-(n+1)/2 log(2 pi)`` is added, making it the expected
    complete-data log density, a lower bound of :func:`exact_objective_from_moments` (Jensen).
    """
    _check_moments(model, mom)
    _check_policy(model, policy)
    B = model.Bs
    Mt = _Atil(model) + B @ _policy_F(policy)
    E = _residual_second_moment(mom, Mt) + B @ policy.cov @ _T(B)
    Lo = _chol(model.So, "augmented So")
    val = -0.5 * _tr(_cho_solve(Lo, E)) - 0.5 * _logdet_chol(Lo)
    if include_constant:
        val = val - 0.5 * (model.n + 1) * LOG_2PI
    return val


def surrogate(model: AugmentedModel, smoothed: Smoothed, y: np.ndarray, policy: LinearGaussianPolicy,
              include_constant: bool = False) -> np.ndarray:
    """The paper's surrogate ``Lbar_k`` (T,) under smoothed moments; see :func:`surrogate_from_moments`."""
    return surrogate_from_moments(model, moments(smoothed, y), policy, include_constant)


def exact_objective_from_moments(model: AugmentedModel, mom: Moments, policy: LinearGaussianPolicy) -> np.ndarray:
    """``E[log N(zeta_k; M_k s_k + m_k, S_k)]`` (T,), the action integrated out (SPEC §4, §5).

    ``S_k = So_k + B Sigma_k B^T``; includes ``-(n+1)/2 log(2 pi)``.  The paper's surrogate is a
    Jensen lower bound: ``Lbar_k - (n+1)/2 log(2 pi) <= exact_k``, with equality iff the action
    posterior equals its prior (e.g. ``B Sigma B^T = 0``).
    """
    _check_moments(model, mom)
    _check_policy(model, policy)
    B = model.Bs
    Mt = _Atil(model) + B @ _policy_F(policy)
    E = _residual_second_moment(mom, Mt)
    S = symmetrize(model.So + B @ policy.cov @ _T(B))
    L = _chol(S, "closed-loop covariance S")
    return -0.5 * (model.n + 1) * LOG_2PI - 0.5 * _logdet_chol(L) - 0.5 * _tr(_cho_solve(L, E))


def exact_objective(model: AugmentedModel, smoothed: Smoothed, y: np.ndarray,
                    policy: LinearGaussianPolicy) -> np.ndarray:
    """Exact-EM objective (T,) under smoothed moments; see :func:`exact_objective_from_moments`."""
    return exact_objective_from_moments(model, moments(smoothed, y), policy)


def surrogate_grad_hess(model: AugmentedModel, mom: Moments, k: int, policy: LinearGaussianPolicy) -> GradHess:
    """Analytic gradient and Hessian of ``Lbar_k`` w.r.t. ``vec([K_k k_k])`` and gradient w.r.t. ``Sigma_k``.

    The Hessian ``-(Stilde_k kron H_k)`` is negative definite iff ``B_k`` has full column rank and
    ``P_k > 0`` (SPEC §9 claim 1).
    """
    _check_moments(model, mom)
    _check_policy(model, policy)
    if not 0 <= k < model.T:
        raise IndexError(f"time step k={k} out of range 0..{model.T - 1}")
    st = _stats(model, mom)
    H, R, S = st.H[k], st.R[k], st.S[k]
    F = _policy_F(policy)[k]
    return GradHess(_vec(R - H @ F @ S), -np.kron(S, H), -0.5 * H)


# --------------------------------------------------------------------------- uniqueness


def _degeneracy(model: AugmentedModel, st: _Stats, cfg: MStepConfig):
    """Per-step flags: H singular, P singular; plus the numbers for the message."""
    n = model.n
    h_min, h_rel = _min_eig_rel(st.H)
    S = st.S
    P = symmetrize(S[:, :n, :n] - S[:, :n, n:] @ S[:, n:, :n] / S[:, n:, n:])
    s_scale = np.maximum(np.abs(np.linalg.eigvalsh(S)).max(-1), np.finfo(float).tiny)
    p_min = np.linalg.eigvalsh(P)[:, 0]
    h_bad = h_rel <= cfg.eig_tol
    p_bad = p_min <= cfg.eig_tol * s_scale
    return h_bad, p_bad, h_min, p_min


_MIN_NORM_HINT = " Pass min_norm=True for the minimum-norm maximiser."
_CVXPY_HINT = " The minimum-norm maximiser (min_norm=True) needs method='closed_form'."


def _nonunique_message(model: AugmentedModel, k: int, h_bad: bool, p_bad: bool, h_min: float, p_min: float,
                       others: list[int], hint: str = _MIN_NORM_HINT) -> str:
    m = model.m
    parts = []
    if h_bad:
        rank = int(np.linalg.matrix_rank(model.Bs[k]))
        parts.append(
            f"B_{k} = [B; By] has rank {rank} < m={m} (not full column rank; smallest eigenvalue of "
            f"H_{k} = B^T So^-1 B is {h_min:.3e})"
        )
    if p_bad:
        parts.append(f"P_{k} = Cov(s_{k} | Y) is not positive definite (smallest eigenvalue {p_min:.3e})")
    msg = f"M-step maximiser is not unique at time step k={k}: " + "; ".join(parts)
    if others:
        msg += f" (also at steps {others[:10]}{'...' if len(others) > 10 else ''})"
    return msg + "." + hint


def _raise_if_degenerate(model, st, cfg, hint=_MIN_NORM_HINT):
    h_bad, p_bad, h_min, p_min = _degeneracy(model, st, cfg)
    bad = np.flatnonzero(h_bad | p_bad)
    if bad.size:
        k = int(bad[-1])  # the backward sweep meets the last one first
        others = [int(j) for j in bad if j != k]
        raise NonUniqueMaximizerError(
            _nonunique_message(model, k, bool(h_bad[k]), bool(p_bad[k]), float(h_min[k]), float(p_min[k]), others, hint)
        )


# --------------------------------------------------------------------------- Sigma (surrogate)


def _require_pd_covariance(rc: _Resolved) -> None:
    """The surrogate's Sigma optimum must be PD unless the user allowed a singular one."""
    if rc.allow_singular:
        return
    if rc.Smin is None and rc.c is None:
        extra = (" cov_ceiling alone does not help: with only an upper bound the optimum is still Sigma = 0."
                 if rc.Smax is not None else "")
        raise ValueError(
            "no covariance constraint: the surrogate Lbar_k decreases linearly in Sigma_k, so its "
            "unconstrained optimum is Sigma_k = 0, which is not a valid (positive definite) policy."
            + extra + " Set cov_floor or entropy_floor in MStepConstraints, or allow_singular=True for a "
            "deterministic policy."
        )
    if rc.c is None and float(np.linalg.eigvalsh(rc.Smin)[:, 0].min()) <= 0.0:
        raise ValueError(
            "cov_floor is singular, so the optimum Sigma = Sigma_min is not positive definite; use a "
            "positive definite floor, add entropy_floor, or set allow_singular=True"
        )


def _feasible_sigma(X: np.ndarray, rc: _Resolved, k: int, cfg: MStepConfig, skip: str) -> bool:
    """Is ``X`` feasible for step ``k``'s covariance constraints other than ``skip``?"""
    scale = max(1.0, float(np.abs(X).max()))
    if skip != "cov_floor" and rc.Smin is not None:
        if np.linalg.eigvalsh(X - rc.Smin[k])[0] < -cfg.feas_tol * scale:
            return False
    if skip != "cov_ceiling" and rc.Smax is not None:
        if np.linalg.eigvalsh(rc.Smax[k] - X)[0] < -cfg.feas_tol * scale:
            return False
    if skip != "entropy_floor" and rc.c is not None:
        sign, ld = np.linalg.slogdet(X)
        if sign <= 0 or ld < rc.c[k] - cfg.feas_tol * (1.0 + abs(rc.c[k])):
            return False
    return True


def _entropy_sigma(H: np.ndarray, c: float, label: str) -> np.ndarray:
    """``alpha H^{-1}`` with ``log det = c``: the maximiser of ``-tr(H Sigma)/2`` s.t. ``log det Sigma >= c``."""
    m = H.shape[-1]
    try:
        Lh = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        Lh = None
    if Lh is None or np.min(np.diagonal(Lh)) <= 0:
        raise NonUniqueMaximizerError(
            f"{label}: entropy_floor needs H = B^T So^-1 B positive definite (B full column rank); with H "
            f"singular the supremum of -tr(H Sigma)/2 over log det Sigma >= c is not attained"
        )
    log_alpha = (c + _logdet_chol(Lh)) / m
    return math.exp(log_alpha) * _inv_from_chol(Lh)


def _sigma_closed(Hs: np.ndarray, rc: _Resolved, cfg: MStepConfig, labels: list[str]) -> np.ndarray:
    """Closed-form Sigma maximiser of ``-tr(H Sigma)/2`` over the covariance constraints (batched;
    ``rc`` resolved for ``N`` steps)."""
    N, m = Hs.shape[0], rc.m
    assert rc.T == N
    if rc.Smin is None and rc.c is None:
        return np.zeros((N, m, m))  # allow_singular was checked
    out = np.empty((N, m, m))
    for i in range(N):
        cands = []
        if rc.Smin is not None:
            cands.append(("cov_floor", rc.Smin[i]))
        if rc.c is not None:
            cands.append(("entropy_floor", _entropy_sigma(Hs[i], float(rc.c[i]), labels[i])))
        for name, X in cands:
            if _feasible_sigma(X, rc, i, cfg, skip=name):
                out[i] = X
                break
        else:
            active = [name for name in rc.names() if name in ("cov_floor", "entropy_floor", "cov_ceiling")]
            raise ClosedFormUnavailableError(
                f"{labels[i]}: the covariance constraints {active} are active together, which has no "
                f"closed-form maximiser; use method='cvxpy'"
            )
    return out


# --------------------------------------------------------------------------- CVXPY problems


@dataclass
class _CvxProblem:
    problem: cp.Problem
    F: cp.Variable | None  # None for the spectral form (F is recovered from ``y``) and "prec"
    Sigma: cp.Variable | None
    params: dict
    cons: dict
    y: cp.Variable | None = None  # spectral form: coordinates of vec(F - F0) in the eigenbasis


_CACHE: dict[tuple, _CvxProblem] = {}

# Clarabel settings for problems with an entropy floor (see "Entropy floor in CVXPY" in the module
# docstring).  Shorter steps (Clarabel's default max_step_fraction is 0.99) and no chordal
# decomposition of the PSD block keep the interior-point iterates close to the central path, and
# the duality-gap tolerances are ``clarabel_tol * _ENTROPY_GAP_FACTOR`` (but not below
# ``_ENTROPY_GAP_MIN``, where double precision runs out, unless clarabel_tol itself is): the
# maximiser on the curved boundary ``det Sigma = e^c`` is located only to about the square root
# of the gap when the iterates are off the central path.  tol_feas stays ``clarabel_tol``.
_ENTROPY_CLARABEL_SETTINGS = dict(max_step_fraction=0.8, chordal_decomposition_enable=False)
_ENTROPY_GAP_FACTOR = 1e-2
_ENTROPY_GAP_MIN = 1e-13

# Clarabel settings for problems with a trust region (see "Trust region in CVXPY" in the module
# docstring).  Clarabel's default max_step_fraction (0.99) lets the iterates leave the central path
# of the trust-region SOC, whose boundary point turns as the multiplier decreases whenever the
# Hessian is not isotropic; the Newton systems near the solution then lose accuracy and the solve
# ends as optimal_inaccurate.  Every attempt builds a fresh Clarabel solver (CVXPY's warm_start
# would update the cached solver's data in place and keep the Ruiz equilibration computed for the
# first instance it saw, so that the outcome depended on the history of solves).  If the first
# attempt still ends inaccurately (a nearly degenerate active set, e.g. a barely active one of the
# time-invariant variant's T trust regions) it is repeated once with still shorter steps.
# Tolerances are never changed.
_TRUST_CLARABEL_SETTINGS = dict(max_step_fraction=0.8, warm_start=False)
_TRUST_RETRY_STEP = 0.5


def _entropy_floor_constraint(Sigma: cp.Variable, m: int, p: dict, aux: list) -> cp.Constraint:
    """``log det Sigma >= c`` as a (whitened) SDP + geometric-mean constraint, SOC/PSD cones only.

    With ``H = Lh Lh^T`` (parameter ``LentT = Lh^T``) and ``Y = Sigma Lh`` (an auxiliary variable,
    so that every product stays DPP), ``Sw = Lh^T Y = Lh^T Sigma Lh`` and the constraint is
    ``det(Sw)^(1/m) >= t`` with ``t = exp((c + log det H)/m)`` (parameter ``t_ent``), written as
    ``[[Sw, Z], [Z^T, Diag(diag Z)]] >= 0`` (PSD), ``Z`` lower triangular, ``geo_mean(diag Z) >= t``.
    Appends the auxiliary constraints to ``aux`` and returns the geometric-mean constraint (its
    dual is converted to the dual of ``log det Sigma >= c`` in :func:`_duals`).
    """
    p["LentT"] = cp.Parameter((m, m), name="LentT")
    p["t_ent"] = cp.Parameter(nonneg=True, name="t_ent")
    Y = cp.Variable((m, m), name="Y_ent")
    z = cp.Variable(m * (m + 1) // 2, name="z_ent")
    Z = cp.vec_to_upper_tri(z, strict=False).T  # lower triangular
    d = cp.diag(Z)
    Sw = p["LentT"] @ Y  # symmetric whenever Y = Sigma Lh; PSD constrains the symmetric part
    aux.append(Y == Sigma @ p["LentT"].T)
    aux.append(cp.bmat([[Sw, Z], [Z.T, cp.diag(d)]]) >> 0)
    return cp.geo_mean(d) >= p["t_ent"]


def _build_problem(key: tuple) -> _CvxProblem:
    """Build a DPP problem.  ``key = (form, n, m, sigma, offset, n_trust)`` with ``form`` one of
    ``"factored"`` (``||LhT F Ls - C||``), ``"kron"`` (``||LqT vec F - c||``), both for an
    unconstrained ``F``, ``"spectral"`` (``F`` constrained by an offset bound and/or trust regions:
    ``-1/2 sum_i lam_i y_i^2 + g^T y`` in the eigenbasis of the Hessian, see "Trust region in CVXPY")
    or ``"prec"`` (exact Sigma-step in the precision ``P``: ``max log det P - <W, P>`` s.t.
    ``Pmin <= P <= Pmax``)."""
    form, n, m, sigma, offset, n_trust = key
    n1 = n + 1
    p: dict = {}
    cons: dict = {}
    if form == "prec":
        P = cp.Variable((m, m), symmetric=True, name="P")
        p["W"] = cp.Parameter((m, m), symmetric=True, name="W")
        p["Pmax"] = cp.Parameter((m, m), symmetric=True, name="Pmax")
        p["Pmin"] = cp.Parameter((m, m), symmetric=True, name="Pmin")
        cons["upper"] = p["Pmax"] - P >> 0
        cons["lower"] = P - p["Pmin"] >> 0
        prob = cp.Problem(cp.Maximize(cp.log_det(P) - cp.sum(cp.multiply(p["W"], P))), list(cons.values()))
        if not prob.is_dpp():  # pragma: no cover
            raise RuntimeError(f"internal error: M-step CVXPY problem {key} is not DPP")
        return _CvxProblem(prob, None, P, p, cons)
    if form in ("factored", "kron") and (offset or n_trust):  # pragma: no cover - internal misuse
        raise RuntimeError(f"internal error: {form} form is for an unconstrained F; use the spectral form")
    F = y = None
    aux: list = []
    if form == "spectral":
        d = m * n1
        y = cp.Variable(d, name="y")
        p["lam"] = cp.Parameter(d, nonneg=True, name="lam")
        p["g"] = cp.Parameter(d, name="g")
        # diagonal quadratic: Clarabel receives P = Diag(lam), no auxiliary variables or equalities
        obj = -0.5 * cp.sum(cp.multiply(p["lam"], cp.square(y))) + p["g"] @ y
        if offset:  # the offset column of F = F0 + unvec(U y): rows n*m .. n*m+m-1 of vec F
            p["b"] = cp.Parameter(m, nonneg=True, name="b")
            p["Un"] = cp.Parameter((m, d), name="Un")
            p["f0n"] = cp.Parameter(m, name="f0n")
            kn = p["Un"] @ y + p["f0n"]
            cons["offset_upper"] = kn <= p["b"]
            cons["offset_lower"] = -kn <= p["b"]
        if n_trust:  # ||F - Fp_j||_F = ||y - a_j||_2, a_j = U^T vec(Fp_j - F0) (U orthogonal)
            p["delta"] = cp.Parameter(nonneg=True, name="delta")
            p["a"] = [cp.Parameter(d, name=f"a{j}") for j in range(n_trust)]
            cons["trust"] = [cp.norm(y - a, 2) <= p["delta"] for a in p["a"]]
    elif form == "factored":
        F = cp.Variable((m, n1), name="F")
        p["LhT"] = cp.Parameter((m, m), name="LhT")
        p["Ls"] = cp.Parameter((n1, n1), name="Ls")
        p["C"] = cp.Parameter((m, n1), name="C")
        # parameter @ variable @ parameter is not DPP (a product of two parameter-dependent
        # factors); an auxiliary variable Z = F Ls keeps every product parameter-affine x
        # parameter-free.
        Z = cp.Variable((m, n1), name="Z")
        aux = [Z == F @ p["Ls"]]
        resid = p["LhT"] @ Z - p["C"]
        obj = -0.5 * cp.sum_squares(resid)
    else:
        F = cp.Variable((m, n1), name="F")
        d = m * n1
        p["LqT"] = cp.Parameter((d, d), name="LqT")
        p["c"] = cp.Parameter(d, name="c")
        resid = p["LqT"] @ cp.vec(F, order="F") - p["c"]
        obj = -0.5 * cp.sum_squares(resid)
    Sigma = None
    if sigma is not None:
        floor, entropy, ceiling = sigma
        Sigma = (cp.Variable((m, m), symmetric=True, name="Sigma") if (floor or entropy)
                 else cp.Variable((m, m), PSD=True, name="Sigma"))
        p["H"] = cp.Parameter((m, m), symmetric=True, name="H")
        obj = obj - 0.5 * cp.sum(cp.multiply(p["H"], Sigma))
        if floor:
            p["Smin"] = cp.Parameter((m, m), symmetric=True, name="Smin")
            cons["cov_floor"] = Sigma - p["Smin"] >> 0
        if ceiling:
            p["Smax"] = cp.Parameter((m, m), symmetric=True, name="Smax")
            cons["cov_ceiling"] = p["Smax"] - Sigma >> 0
        if entropy:
            cons["entropy_floor"] = _entropy_floor_constraint(Sigma, m, p, aux)
    flat = list(aux)
    for v in cons.values():
        flat.extend(v if isinstance(v, list) else [v])
    prob = cp.Problem(cp.Maximize(obj), flat)
    if not prob.is_dpp():  # pragma: no cover - a construction bug, not a user error
        raise RuntimeError(f"internal error: M-step CVXPY problem {key} is not DPP")
    return _CvxProblem(prob, F, Sigma, p, cons, y)


def _get_problem(key: tuple) -> _CvxProblem:
    prob = _CACHE.get(key)
    if prob is None:
        prob = _CACHE[key] = _build_problem(key)
    return prob


def _solver_options(solver: str, cfg: MStepConfig, entropy: bool = False, trust: bool = False) -> list[dict]:
    """Solver options, one dict per attempt (a later attempt is tried only if the earlier failed)."""
    if solver == "CLARABEL":
        t = cfg.clarabel_tol
        opts = dict(tol_gap_abs=t, tol_gap_rel=t, tol_feas=t, max_iter=cfg.clarabel_max_iter)
        # trust region: shorter steps and a fresh solver, then a retry with still shorter steps
        # (see _TRUST_CLARABEL_SETTINGS); the tolerances are the same in every attempt
        if trust:
            opts.update(_TRUST_CLARABEL_SETTINGS)
        if entropy:
            opts.update(_ENTROPY_CLARABEL_SETTINGS)
        retry = [dict(opts, max_step_fraction=_TRUST_RETRY_STEP)] if trust else []
        if not entropy:
            return [opts] + retry
        # see "Entropy floor in CVXPY" in the module docstring; the gap is tightened, never loosened
        g = max(t * _ENTROPY_GAP_FACTOR, min(t, _ENTROPY_GAP_MIN))
        tight = dict(opts, tol_gap_abs=g, tol_gap_rel=g)
        # if the tightened gap runs into round-off (status optimal_inaccurate), retry at clarabel_tol
        return ([tight, opts] if g < t else [opts]) + retry
    return [dict(eps_abs=cfg.scs_eps, eps_rel=cfg.scs_eps, max_iters=cfg.scs_max_iters)]


def _solve(prob: _CvxProblem, solver: str, cfg: MStepConfig, where: str, step: int | None) -> str:
    ok = {cp.OPTIMAL} | ({cp.OPTIMAL_INACCURATE} if cfg.accept_inaccurate else set())
    attempts = _solver_options(solver, cfg, entropy="t_ent" in prob.params, trust="delta" in prob.params)
    for i, opts in enumerate(attempts):
        last = i == len(attempts) - 1
        try:
            with warnings.catch_warnings():  # an inaccurate solution is reported through SolverError
                warnings.filterwarnings("ignore", message="Solution may be inaccurate")
                # the entropy floor's geo_mean has equal weights 1/m: its SOC tower is exact
                warnings.filterwarnings("ignore", message="geo_mean is being approximated")
                prob.problem.solve(solver=solver, verbose=cfg.verbose, **opts)
        except cp.error.SolverError as e:
            if last:
                raise SolverError(f"{where}: CVXPY solver {solver} failed ({e})", status="solver_error",
                                  step=step) from e
            continue
        status = prob.problem.status
        if status in ok:
            return status
        if last:
            raise SolverError(f"{where}: CVXPY solver {solver} returned status {status!r}", status=status, step=step)
    raise AssertionError("unreachable")  # pragma: no cover


def _duals(prob: _CvxProblem) -> dict:
    out = {}
    for name, c in prob.cons.items():
        if isinstance(c, list):
            out[name] = np.array([float(np.asarray(ci.dual_value)) for ci in c])
        else:
            out[name] = np.array(c.dual_value, dtype=float)
    if "entropy_floor" in out:
        # dual mu of det(Sw)^(1/m) >= t  ->  dual nu of log det Sigma >= c: the optimal value's
        # sensitivities satisfy nu = -dV/dc = -dV/dt * dt/dc = mu t/m  (t = exp((c + log det H)/m))
        m = prob.params["LentT"].shape[0]
        out["entropy_floor"] = out["entropy_floor"] * float(prob.params["t_ent"].value) / m
    return out


def _set_sigma_params(prob: _CvxProblem, H: np.ndarray, rc: _Resolved, j: int) -> None:
    prob.params["H"].value = symmetrize(H)
    if rc.Smin is not None:
        prob.params["Smin"].value = rc.Smin[j]
    if rc.Smax is not None:
        prob.params["Smax"].value = rc.Smax[j]
    if rc.c is not None:
        Lh = _chol(symmetrize(H), "H = B^T So^-1 B (entropy floor)")
        m = H.shape[-1]
        prob.params["LentT"].value = Lh.T
        prob.params["t_ent"].value = math.exp((float(rc.c[j]) + float(_logdet_chol(Lh))) / m)


def _vec_batch(X: np.ndarray) -> np.ndarray:
    """Column-major ``vec`` over the last two axes (batched)."""
    return _T(X).reshape(X.shape[:-2] + (-1,))


_THREADPOOLS = None  # threadpoolctl.ThreadpoolController, created on first use (it scans the loaded libraries)


def _blas_one_thread():
    """Context: BLAS limited to one thread.  The eigendecompositions of the spectral form are of
    small matrices, where threaded BLAS (LAPACK ``syevd``) gains nothing and, on a loaded machine,
    made them erratic (0.5 to ~100 ms for a few 27 x 27 matrices; spin-waiting threads)."""
    global _THREADPOOLS
    if _THREADPOOLS is None:
        from threadpoolctl import ThreadpoolController

        _THREADPOOLS = ThreadpoolController()
    return _THREADPOOLS.limit(limits=1, user_api="blas")


def _kron_eig(H: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``S kron H = U Diag(lam) U^T`` (batched; ``U`` orthogonal) from the factors' eigenpairs.

    ``S kron H`` is the Hessian of ``1/2 tr(H F S F^T)`` in column-major ``vec F``; with
    ``H = Uh Diag(dh) Uh^T`` and ``S = Us Diag(ds) Us^T``, ``U = Us kron Uh`` and ``lam = ds kron dh``.
    """
    with _blas_one_thread():
        dh, Uh = np.linalg.eigh(symmetrize(H))
        ds, Us = np.linalg.eigh(symmetrize(S))
    m, n1 = dh.shape[-1], ds.shape[-1]
    lead = dh.shape[:-1]
    lam = (ds[..., :, None] * dh[..., None, :]).reshape(lead + (n1 * m,))
    U = (Us[..., :, None, :, None] * Uh[..., None, :, None, :]).reshape(lead + (n1 * m, n1 * m))
    return lam, U


def _spectral_data(lam: np.ndarray, U: np.ndarray, r: np.ndarray, f0: np.ndarray):
    """Data of the spectral form of ``-1/2 f^T Q f + r^T f`` around ``f0`` (batched).

    With ``Q = U Diag(lam) U^T`` and ``f = f0 + U y`` the quadratic is ``q0 - 1/2 sum_i lam_i y_i^2 + g^T y``,
    ``g = U^T r - lam * (U^T f0)`` and ``q0 = -1/2 f0^T Q f0 + r^T f0``.  Returns ``(lam, g, q0)``.
    """
    lam = np.maximum(lam, 0.0)  # round-off only: Q > 0 was checked by the callers
    Ut = _T(U)
    w0 = (Ut @ f0[..., None])[..., 0]
    g = (Ut @ r[..., None])[..., 0] - lam * w0
    q0 = -0.5 * np.sum(lam * w0 * w0, -1) + np.sum(r * f0, -1)
    return lam, g, q0


def _set_spectral_params(prob: _CvxProblem, rc: _Resolved, n: int, lam: np.ndarray, g: np.ndarray,
                         U: np.ndarray, f0: np.ndarray, centres: np.ndarray | None) -> None:
    """One solve of the spectral form: ``centres`` are the vec'd trust-region centres (one per
    trust constraint of the problem) or None."""
    m = rc.m
    prob.params["lam"].value = lam
    prob.params["g"].value = g
    if rc.b is not None:
        prob.params["b"].value = rc.b
        prob.params["Un"].value = U[n * m : (n + 1) * m]
        prob.params["f0n"].value = f0[n * m : (n + 1) * m]
    if rc.delta is not None:
        prob.params["delta"].value = rc.delta
        if len(prob.params["a"]) != len(centres):  # pragma: no cover - internal misuse
            raise RuntimeError("internal error: number of trust-region centres does not match the problem")
        for a, c in zip(prob.params["a"], centres):
            a.value = _T(U) @ (c - f0)


def _spectral_F(prob: _CvxProblem, U: np.ndarray, f0: np.ndarray, m: int, n1: int) -> np.ndarray:
    """``F = unvec(f0 + U y)`` from the spectral form's solution."""
    return _unvec(f0 + U @ np.asarray(prob.y.value, dtype=float), m, n1)


def _factored_data(H: np.ndarray, S: np.ndarray, R: np.ndarray):
    """``(Lh^T, Ls, C)`` with ``C = Lh^{-1} R Ls^{-T}`` (batched)."""
    Lh = _chol(H, "H = B^T So^-1 B")
    Ls = _chol(S, "Stilde")
    C = _T(_tri_solve(Ls, _T(_tri_solve(Lh, R))))
    return _T(Lh), Ls, C


def _pd_guaranteed(rc: _Resolved) -> bool:
    """An entropy floor or a PD covariance floor makes the surrogate's Sigma optimum PD."""
    return rc.c is not None or (rc.Smin is not None and np.linalg.eigvalsh(rc.Smin)[:, 0].min() > 0)


def _clean_sigma(X: np.ndarray, rc: _Resolved) -> np.ndarray:
    """Symmetrise a solver's Sigma; project onto the PSD cone when a singular optimum is allowed."""
    X = symmetrize(np.asarray(X, dtype=float))
    if not _pd_guaranteed(rc):
        w, V = np.linalg.eigh(X)
        X = symmetrize((V * np.clip(w, 0.0, None)) @ V.T)
    return X


# --------------------------------------------------------------------------- surrogate maximisers


def _closed_form_tv(model, st, rc, cfg, min_norm):
    T = model.T
    h_bad, p_bad, _, _ = _degeneracy(model, st, cfg)
    degenerate = bool(np.any(h_bad | p_bad))
    if degenerate and not min_norm:
        _raise_if_degenerate(model, st, cfg)
    if degenerate:
        Hp = np.linalg.pinv(st.H, rcond=cfg.eig_tol, hermitian=True)
        Sp = np.linalg.pinv(st.S, rcond=cfg.eig_tol, hermitian=True)
        F = Hp @ st.R @ Sp
    else:
        Lh, Ls = _chol(st.H, "H"), _chol(st.S, "Stilde")
        F = _right_cho_solve(_cho_solve(Lh, st.R), Ls)
    Sigma = _sigma_closed(st.H, rc, cfg, [f"time step k={k}" for k in range(T)])
    return F, Sigma


def _ti_normal_equations(st: _Stats):
    Q = np.einsum("kab,kij->aibj", st.S, st.H)  # sum_k S_k kron H_k, indices (a,i),(b,j)
    n1, m = st.S.shape[1], st.H.shape[1]
    Q = symmetrize(Q.reshape(n1 * m, n1 * m))
    r = _vec(st.R.sum(0))
    return Q, r


def _ti_degenerate(model, st, cfg, Q, min_norm, hint=_MIN_NORM_HINT):
    ev = np.linalg.eigvalsh(Q)
    bad = ev[0] <= cfg.eig_tol * max(abs(ev[-1]), np.finfo(float).tiny)
    if bad and not min_norm:
        h_bad, p_bad, h_min, p_min = _degeneracy(model, st, cfg)
        steps = np.flatnonzero(h_bad | p_bad)
        detail = ""
        if steps.size:
            k = int(steps[-1])
            detail = " Per step: " + _nonunique_message(
                model, k, bool(h_bad[k]), bool(p_bad[k]), float(h_min[k]), float(p_min[k]),
                [int(j) for j in steps if j != k], hint="").split(": ", 1)[1]
        raise NonUniqueMaximizerError(
            f"time-invariant M-step maximiser is not unique: sum_k (Stilde_k kron H_k) is singular "
            f"(smallest eigenvalue {ev[0]:.3e}).{detail}{hint}"
        )
    return bool(bad)


def _closed_form_ti(model, st, rc, cfg, min_norm):
    m, n1 = model.m, model.n + 1
    Q, r = _ti_normal_equations(st)
    if _ti_degenerate(model, st, cfg, Q, min_norm):
        vF = np.linalg.pinv(Q, rcond=cfg.eig_tol, hermitian=True) @ r
    else:
        vF = _cho_solve(_chol(Q, "sum_k Stilde_k kron H_k"), r[:, None])[:, 0]
    F = _unvec(vF, m, n1)
    Sigma = _sigma_closed(st.H.sum(0)[None], rc.time_invariant(), cfg, ["time-invariant M-step"])[0]
    return F, Sigma


def _cvxpy_tv(model, st, rc, cfg, solver, Fprev):
    T, n, m = model.T, model.n, model.m
    n1 = n + 1
    spectral = rc.f_constrained
    if spectral:  # offset bound / trust region: the spectral form (module docstring)
        key = ("spectral", n, m, rc.sigma_key, rc.b is not None, 1 if rc.delta is not None else 0)
        lam, U = _kron_eig(st.H, st.S)
        f0 = _vec_batch(Fprev) if rc.delta is not None else np.zeros((T, m * n1))
        lam, g, q0 = _spectral_data(lam, U, _vec_batch(st.R), f0)
    else:
        key = ("factored", n, m, rc.sigma_key, False, 0)
        LhT, Ls, C = _factored_data(st.H, st.S, st.R)
    prob = _get_problem(key)
    F = np.empty((T, m, n1))
    Sigma = np.empty((T, m, m))
    value = np.empty(T)
    status = []
    duals: list = [None] * T
    times = np.empty(T)
    for j in range(T - 1, -1, -1):  # the Proposition's backward sweep
        t0 = time.perf_counter()
        if spectral:
            _set_spectral_params(prob, rc, n, lam[j], g[j], U[j], f0[j],
                                 None if rc.delta is None else f0[j : j + 1])
        else:
            prob.params["LhT"].value = LhT[j]
            prob.params["Ls"].value = Ls[j]
            prob.params["C"].value = C[j]
        _set_sigma_params(prob, st.H[j], rc, j)
        status.append(_solve(prob, solver, cfg, f"M-step (cvxpy, time step k={j})", j))
        times[j] = time.perf_counter() - t0
        if spectral:
            F[j] = _spectral_F(prob, U[j], f0[j], m, n1)
            value[j] = st.const[j] + q0[j] + float(prob.problem.value)
        else:
            F[j] = prob.F.value
            value[j] = st.const[j] + 0.5 * float(np.sum(C[j] ** 2)) + float(prob.problem.value)
        Sigma[j] = _clean_sigma(prob.Sigma.value, rc)
        duals[j] = _duals(prob)
    return F, Sigma, value, tuple(status), tuple(duals), times


def _cvxpy_ti(model, st, rc, cfg, solver, Fprev, hint=_MIN_NORM_HINT):
    n, m, T = model.n, model.m, model.T
    n1 = n + 1
    Q, r = _ti_normal_equations(st)
    _ti_degenerate(model, st, cfg, Q, min_norm=False, hint=hint)
    spectral = rc.f_constrained
    if spectral:  # offset bound / trust regions: the spectral form (module docstring)
        key = ("spectral", n, m, rc.sigma_key, rc.b is not None, T if rc.delta is not None else 0)
        with _blas_one_thread():
            lam, U = np.linalg.eigh(Q)
        centres = _vec_batch(Fprev) if rc.delta is not None else None
        f0 = centres.mean(0) if centres is not None else np.zeros(m * n1)
        lam, g, q0 = _spectral_data(lam, U, r, f0)
    else:
        key = ("kron", n, m, rc.sigma_key, False, 0)
        Lq = _chol(Q, "sum_k Stilde_k kron H_k")
        c = _tri_solve(Lq, r)
    prob = _get_problem(key)
    t0 = time.perf_counter()
    if spectral:
        _set_spectral_params(prob, rc, n, lam, g, U, f0, centres)
    else:
        prob.params["LqT"].value = Lq.T
        prob.params["c"].value = c
    _set_sigma_params(prob, st.H.sum(0), rc.time_invariant(), 0)
    status = _solve(prob, solver, cfg, "time-invariant M-step (cvxpy)", None)
    times = np.array([time.perf_counter() - t0])
    if spectral:
        F = _spectral_F(prob, U, f0, m, n1)
        value = float(st.const.sum()) + float(q0) + float(prob.problem.value)
    else:
        F = np.asarray(prob.F.value)
        value = float(st.const.sum()) + 0.5 * float(c @ c) + float(prob.problem.value)
    return (F, _clean_sigma(prob.Sigma.value, rc), np.array([value]), (status,), (_duals(prob),), times)


# --------------------------------------------------------------------------- exact EM


def _action_posterior(model: AugmentedModel, mom: Moments, F: np.ndarray, Sigma: np.ndarray):
    """``E[a stilde^T]`` (T, m, n+1) and ``E[a a^T]`` (T, m, m) under the action posterior."""
    B = model.Bs
    Mt = _Atil(model) + B @ F
    S = symmetrize(model.So + B @ Sigma @ _T(B))
    L = _chol(S, "closed-loop covariance S")
    G = _T(_cho_solve(L, B @ Sigma))  # Sigma B^T S^{-1}
    J = F - G @ Mt
    V = symmetrize(Sigma - G @ B @ Sigma)
    Eas = G @ mom.Szs + J @ mom.Sss
    X = G @ mom.Szs @ _T(J)
    Eaa = symmetrize(V + G @ mom.Szz @ _T(G) + X + _T(X) + J @ mom.Sss @ _T(J))
    return Eas, Eaa


def _clip_whitened(W: np.ndarray, S0: np.ndarray, lower: bool) -> np.ndarray:
    """Maximiser of ``-log|X| - tr(X^{-1} W)`` over ``X >= S0`` (lower) or ``X <= S0`` (upper)."""
    L = np.linalg.cholesky(S0)
    Wt = _tri_solve(L, _T(_tri_solve(L, W)))
    d, U = np.linalg.eigh(symmetrize(Wt))
    d = np.maximum(d, 1.0) if lower else np.minimum(d, 1.0)
    Y = (U * d[..., None, :]) @ _T(U)
    return symmetrize(L @ Y @ _T(L))


def _sigma_exact(W: np.ndarray, rc: _Resolved, method: str, solver: str, cfg: MStepConfig, labels: list[str]):
    """Inner M-step for Sigma: maximise ``-1/2 (log|Sigma| + tr(Sigma^{-1} W))`` over the covariance set
    (batched; ``rc`` resolved for as many steps as ``W`` has)."""
    floor, entropy, ceiling = rc.sigma_key
    W = symmetrize(W)
    m = W.shape[-1]
    if not (floor or entropy or ceiling):
        return W
    if entropy:
        L = _chol(W, "inner-EM action covariance W")
        beta = np.exp(np.maximum(0.0, (rc.c - _logdet_chol(L)) / m))
        return beta[:, None, None] * W
    if floor and not ceiling:
        return _clip_whitened(W, rc.Smin, lower=True)
    if ceiling and not floor:
        return _clip_whitened(W, rc.Smax, lower=False)
    out = np.empty_like(W)
    for i in range(W.shape[0]):
        X = _clip_whitened(W[i], rc.Smin[i], lower=True)
        if _feasible_sigma(X, rc, i, cfg, skip="cov_floor"):
            out[i] = X
            continue
        X = _clip_whitened(W[i], rc.Smax[i], lower=False)
        if _feasible_sigma(X, rc, i, cfg, skip="cov_ceiling"):
            out[i] = X
            continue
        if method != "cvxpy":
            raise ClosedFormUnavailableError(
                f"{labels[i]}: cov_floor and cov_ceiling are active together in the exact-EM covariance "
                f"step, which has no closed form; use method='cvxpy'"
            )
        prob = _get_problem(("prec", 0, m, None, False, 0))
        prob.params["W"].value = W[i]
        prob.params["Pmax"].value = _inv_from_chol(np.linalg.cholesky(rc.Smin[i]))
        prob.params["Pmin"].value = _inv_from_chol(np.linalg.cholesky(rc.Smax[i]))
        _solve(prob, solver, cfg, f"{labels[i]} (exact-EM covariance step)", None)
        out[i] = _inv_from_chol(_chol(symmetrize(prob.Sigma.value), "precision P"))
    return out


def _f_step_exact(model, Eas, S, Sigma, rc, method, solver, cfg, Fprev, min_norm, labels):
    """Inner M-step for F: unconstrained ``E[a stilde^T] Stilde^{-1}``; with offset/trust constraints a
    CVXPY step weighted by ``Sigma^{-1}`` (Sigma held fixed: ECM).  Batched over the leading axis."""
    n, m = model.n, model.m
    p_min, p_rel = _min_eig_rel(S)
    if np.any(p_rel <= cfg.eig_tol):
        if not min_norm:
            i = int(np.flatnonzero(p_rel <= cfg.eig_tol)[-1])
            raise NonUniqueMaximizerError(
                f"exact-EM M-step is not unique at {labels[i]}: Stilde (P_k) is not positive definite "
                f"(smallest eigenvalue {p_min[i]:.3e}). Pass min_norm=True for the minimum-norm maximiser."
            )
        F = Eas @ np.linalg.pinv(S, rcond=cfg.eig_tol, hermitian=True)
    else:
        F = _right_cho_solve(Eas, _chol(S, "Stilde"))
    if not rc.f_constrained:
        return F
    if method != "cvxpy":
        raise ClosedFormUnavailableError(
            "offset_bound and trust_region have no closed form (also in the exact-EM step); use method='cvxpy'"
        )
    N = F.shape[0]
    n1 = n + 1
    n_trust = 0 if rc.delta is None else (1 if N == model.T else model.T)
    prob = _get_problem(("spectral", n, m, None, rc.b is not None, n_trust))
    _chol(S, "Stilde")  # the constrained step needs Stilde > 0
    H = _inv_from_chol(_chol(Sigma, "Sigma"))  # Sigma^{-1}
    # E[log N(a; F stilde, Sigma)] = const - 1/2 tr(H F S F^T) + tr(F^T H E[a stilde^T])
    lam, U = _kron_eig(H, S)
    if rc.delta is not None:
        Fp = _vec_batch(Fprev)
        centres = [Fp[i : i + 1] if n_trust == 1 else Fp for i in range(N)]
        f0 = np.stack([c.mean(0) for c in centres])
    else:
        centres = [None] * N
        f0 = np.zeros((N, m * n1))
    lam, g, _ = _spectral_data(lam, U, _vec_batch(H @ Eas), f0)
    out = np.empty_like(F)
    for i in range(N - 1, -1, -1):
        _set_spectral_params(prob, rc, n, lam[i], g[i], U[i], f0[i], centres[i])
        _solve(prob, solver, cfg, f"{labels[i]} (exact-EM mean step)", None)
        out[i] = _spectral_F(prob, U[i], f0[i], m, n1)
    return out


def _exact_em(model, mom, rc, cfg, method, solver, variant, previous, min_norm):
    T, n = model.T, model.n
    if previous is None:
        raise ValueError("objective='exact' needs previous= (the current policy): the exact-EM M-step "
                         "is an iteration started from it")
    if previous.allow_singular or np.any(np.linalg.eigvalsh(previous.cov)[:, 0] <= 0):
        raise ValueError("objective='exact' needs a previous policy with positive definite covariances")
    if rc.c is not None and (rc.Smin is not None or rc.Smax is not None):
        raise ValueError("objective='exact' supports entropy_floor only on its own, not combined with "
                         "cov_floor or cov_ceiling")
    for name, S0 in (("cov_floor", rc.Smin), ("cov_ceiling", rc.Smax)):
        if S0 is not None and np.linalg.eigvalsh(S0)[:, 0].min() <= 0:
            raise ValueError(f"objective='exact' needs a positive definite {name}")
    F = _policy_F(previous).copy()
    Sigma = np.array(previous.cov)
    Fprev = _policy_F(previous)
    ti = variant == "time_invariant"
    if ti:  # start from the time average of the previous policy
        F = np.broadcast_to(F.mean(0), F.shape).copy()
        Sigma = np.broadcast_to(symmetrize(Sigma.mean(0)), Sigma.shape).copy()
        labels = ["time-invariant M-step"]
    else:
        labels = [f"time step k={k}" for k in range(T)]

    def policy_of(F, Sigma):
        return LinearGaussianPolicy(F[..., :n], F[..., n], Sigma)

    hist = [exact_objective_from_moments(model, mom, policy_of(F, Sigma))]
    converged = False
    it = 0
    Sss = symmetrize(np.asarray(mom.Sss, dtype=float))
    for it in range(1, cfg.exact_max_iter + 1):
        Eas, Eaa = _action_posterior(model, mom, F, Sigma)
        if ti:
            Fn = _f_step_exact(model, Eas.sum(0)[None], Sss.sum(0)[None], Sigma[:1], rc, method, solver, cfg,
                               Fprev, min_norm, labels)
            Fn = np.broadcast_to(Fn, F.shape)
        else:
            Fn = _f_step_exact(model, Eas, Sss, Sigma, rc, method, solver, cfg, Fprev, min_norm, labels)
        X = Fn @ _T(Eas)
        W = symmetrize(Eaa - X - _T(X) + Fn @ Sss @ _T(Fn))
        if ti:
            Sn = _sigma_exact(W.mean(0)[None], rc.time_invariant(), method, solver, cfg, labels)
            Sn = np.broadcast_to(Sn, Sigma.shape)
        else:
            Sn = _sigma_exact(W, rc, method, solver, cfg, labels)
        F, Sigma = np.array(Fn), np.array(symmetrize(Sn))
        hist.append(exact_objective_from_moments(model, mom, policy_of(F, Sigma)))
        a, b = hist[-2], hist[-1]
        if ti:
            a, b = a.sum(keepdims=True), b.sum(keepdims=True)
        if np.all(np.abs(b - a) <= cfg.exact_tol * (1.0 + np.abs(b))):
            converged = True
            break
    return policy_of(F, Sigma), np.array(hist), it, converged


# --------------------------------------------------------------------------- entry points


def maximize_moments(
    model: AugmentedModel,
    mom: Moments,
    constraints: MStepConstraints | None = None,
    method: str = "closed_form",
    solver: str | None = None,
    variant: str = "time_varying",
    objective: str = "surrogate",
    previous: LinearGaussianPolicy | None = None,
    min_norm: bool = False,
    config: MStepConfig | None = None,
    return_result: bool = False,
) -> LinearGaussianPolicy | MStepResult:
    """The M-step from precomputed :class:`Moments` (see :func:`maximize`)."""
    cfg = config if config is not None else MStepConfig()
    if method not in ("closed_form", "cvxpy"):
        raise ValueError(f"method must be 'closed_form' or 'cvxpy', got {method!r}")
    if variant not in ("time_varying", "time_invariant"):
        raise ValueError(f"variant must be 'time_varying' or 'time_invariant', got {variant!r}")
    if objective not in ("surrogate", "exact"):
        raise ValueError(f"objective must be 'surrogate' or 'exact', got {objective!r}")
    solver = (solver if solver is not None else cfg.solver).upper()
    if solver not in ("CLARABEL", "SCS"):
        raise ValueError(f"solver must be 'CLARABEL' or 'SCS', got {solver!r}")
    if constraints is None:
        constraints = MStepConstraints()
    if not isinstance(constraints, MStepConstraints):
        raise TypeError(f"constraints must be MStepConstraints, got {type(constraints).__name__}")
    _check_moments(model, mom)
    if previous is not None:
        _check_policy(model, previous, "previous")
    T, n, m = model.T, model.n, model.m
    rc = constraints.resolve(m, T)
    if rc.delta is not None and previous is None:
        raise ValueError("trust_region needs previous= (the policy whose [K k] is the trust-region centre)")

    if objective == "exact":
        policy, hist, it, conv = _exact_em(model, mom, rc, cfg, method, solver, variant, previous, min_norm)
        if not return_result:
            return policy
        return MStepResult(policy, hist[-1], history=hist, iterations=it, converged=conv)

    _require_pd_covariance(rc)
    if method == "closed_form" and rc.f_constrained:
        raise ClosedFormUnavailableError(
            f"the constraint set {rc.names()} has no closed-form maximiser (offset_bound and trust_region are "
            f"CVXPY only); use method='cvxpy'"
        )
    st = _stats(model, mom)
    Fprev = None if previous is None else _policy_F(previous)
    extra: dict = {}
    if method == "closed_form":
        if variant == "time_varying":
            F, Sigma = _closed_form_tv(model, st, rc, cfg, min_norm)
        else:
            F, Sigma = _closed_form_ti(model, st, rc, cfg, min_norm)
    else:
        hint = _CVXPY_HINT if min_norm else _MIN_NORM_HINT + " (closed form only)"
        if variant == "time_varying":
            _raise_if_degenerate(model, st, cfg, hint=hint)
            F, Sigma, val, status, duals, times = _cvxpy_tv(model, st, rc, cfg, solver, Fprev)
        else:
            F, Sigma, val, status, duals, times = _cvxpy_ti(model, st, rc, cfg, solver, Fprev, hint=hint)
        extra = dict(solver_value=val, status=status, duals=duals, solve_time=times)
    if variant == "time_invariant":
        F = np.broadcast_to(F, (T, m, n + 1))
        Sigma = np.broadcast_to(Sigma, (T, m, m))
    # without a PD guarantee _require_pd_covariance only let us through with allow_singular=True
    policy = LinearGaussianPolicy(np.array(F[..., :n]), np.array(F[..., n]), np.array(Sigma),
                                  allow_singular=not _pd_guaranteed(rc))
    if not return_result:
        return policy
    return MStepResult(policy, surrogate_from_moments(model, mom, policy), **extra)


def maximize(
    model: AugmentedModel,
    smoothed: Smoothed,
    y: np.ndarray,
    constraints: MStepConstraints | None = None,
    method: str = "closed_form",
    solver: str | None = None,
    variant: str = "time_varying",
    objective: str = "surrogate",
    previous: LinearGaussianPolicy | None = None,
    min_norm: bool = False,
    config: MStepConfig | None = None,
    return_result: bool = False,
) -> LinearGaussianPolicy | MStepResult:
    """The DP M-step (SPEC §5): maximise ``Lbar_k`` (or the exact objective) over the feasible set.

    Args:
        model: the augmented model (``Ao, co, So``).
        smoothed, y: smoothed states and observations; reduced to :class:`Moments` by
            :func:`soc_opt.estep.moments` (use :func:`maximize_moments` for precomputed moments).
        constraints: the feasible set (:class:`MStepConstraints`; default: none, which is an error
            for the surrogate unless ``allow_singular``, because its optimum is ``Sigma = 0``).
        method: ``"closed_form"`` (batched Cholesky solves) or ``"cvxpy"`` (DPP problem per step).
        solver: CVXPY solver, ``"CLARABEL"`` or ``"SCS"`` (default ``config.solver``).
        variant: ``"time_varying"`` (one ``phi_k`` per step, the Proposition's sweep) or
            ``"time_invariant"`` (one shared ``phi`` maximising ``sum_k``).
        objective: ``"surrogate"`` (the paper's ``Lbar``) or ``"exact"`` (action integrated out,
            inner EM started from ``previous``; the time-invariant variant starts from the time
            average of ``previous``).  The number of inner iterations and convergence are in the
            :class:`MStepResult`.
        previous: the current policy; trust-region centre and exact-EM starting point.
        min_norm: return the minimum-norm maximiser when it is not unique (closed form only).
        config: :class:`MStepConfig` (tolerances, solver options).
        return_result: return an :class:`MStepResult` instead of just the policy.

    Raises:
        NonUniqueMaximizerError: ``B_k`` rank deficient or ``P_k`` singular (names the step).
        InfeasibleConstraintsError: empty constraint set.
        ClosedFormUnavailableError: ``method="closed_form"`` with a set needing CVXPY.
        SolverError: CVXPY failed (status and step in the message).
        ShapeError: inconsistent shapes.
    """
    return maximize_moments(model, moments(smoothed, y), constraints, method, solver, variant, objective,
                            previous, min_norm, config, return_result)
