"""The feasible set of the M-step and its closed-form covariance rules (docs/math.md §5).

:class:`MStepConstraints` is the user-facing set; :meth:`MStepConstraints.resolve` turns it into
per-step arrays (:class:`Resolved`) for an action dimension ``m`` and ``T`` steps.

Covariance optimum of the surrogate
-----------------------------------
``Lbar`` is linear and non-increasing in ``Sigma`` (``-1/2 tr(H Sigma)``, ``H = B^T So^{-1} B``), so
its unconstrained optimum is ``Sigma = 0`` -- not a valid (positive definite) policy.  Supported sets:

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
  ``||[K k] - [K k]_prev||_F <= delta``: no closed form; CVXPY only (:mod:`soc_opt.mstep.cvx`).

Combined covariance constraints use the relaxation rule: the closed-form optimum of a single
constraint (``Sigma_min``, ``alpha H^{-1}``) that satisfies all the other constraints is optimal
for the whole set.  If no such candidate exists at some step (two constraints active at once)
``method="closed_form"`` raises :class:`ClosedFormUnavailableError` and ``method="cvxpy"`` is
needed.  Infeasible sets (floor not below ceiling, entropy floor above ``log det`` of the ceiling, a
negative ``offset_bound``)
raise :class:`InfeasibleConstraintsError` naming them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .. import linalg as la
from ..config import Config, ConfigError
from ..models import ShapeError, symmetrize
from .config import MStepConfig
from .errors import ClosedFormUnavailableError, InfeasibleConstraintsError, NonUniqueMaximizerError

__all__ = ["MStepConstraints"]


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
    if np.abs(a - la.T(a)).max() > 1e-10 * scale:
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
class Resolved:
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

    def time_invariant(self) -> "Resolved":
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
    """The feasible set ``Phi`` of the M-step (docs/math.md §5).  All fields default to "absent".

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
                vals = [b] if isinstance(b, float) else list(b)
                if all(math.isfinite(x) for x in vals) and vals:  # finite but negative: |k_i| <= b_i is empty
                    raise InfeasibleConstraintsError(
                        f"infeasible constraint set: offset_bound {self.offset_bound!r} has an entry < 0, "
                        f"so |k_i| <= b_i has no solution (offset_bound must be >= 0)")
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

    def resolve(self, m: int, T: int = 1) -> Resolved:
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
        return Resolved(m, T, Smin, Smax, c, b, self.trust_region, self.allow_singular)


# --------------------------------------------------------------------------- Sigma (surrogate)


def require_pd_covariance(rc: Resolved) -> None:
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


def feasible_sigma(X: np.ndarray, rc: Resolved, k: int, cfg: MStepConfig, skip: str) -> bool:
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
    log_alpha = (c + la.logdet_chol(Lh)) / m
    return math.exp(log_alpha) * la.inv_from_chol(Lh)


def sigma_closed(Hs: np.ndarray, rc: Resolved, cfg: MStepConfig, labels: list[str]) -> np.ndarray:
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
            if feasible_sigma(X, rc, i, cfg, skip=name):
                out[i] = X
                break
        else:
            active = [name for name in rc.names() if name in ("cov_floor", "entropy_floor", "cov_ceiling")]
            raise ClosedFormUnavailableError(
                f"{labels[i]}: the covariance constraints {active} are active together, which has no "
                f"closed-form maximiser; use method='cvxpy'"
            )
    return out


def pd_guaranteed(rc: Resolved) -> bool:
    """An entropy floor or a PD covariance floor makes the surrogate's Sigma optimum PD."""
    return rc.c is not None or (rc.Smin is not None and np.linalg.eigvalsh(rc.Smin)[:, 0].min() > 0)


def clean_sigma(X: np.ndarray, rc: Resolved) -> np.ndarray:
    """Symmetrise a solver's Sigma; project onto the PSD cone when a singular optimum is allowed."""
    X = symmetrize(np.asarray(X, dtype=float))
    if not pd_guaranteed(rc):
        w, V = np.linalg.eigh(X)
        X = symmetrize((V * np.clip(w, 0.0, None)) @ V.T)
    return X
