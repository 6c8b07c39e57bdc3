"""When the surrogate's maximiser is unique, and how each step is solved (docs/math.md §5, "Conditioning").

The maximiser of ``Lbar_k`` in ``F = [K k]`` is unique exactly when ``H_k = B^T So^-1 B`` (stacked
``B = [B_k; By_k]``) and ``Stilde_k`` are positive definite; ``Stilde_k > 0`` is ``P_k = Cov(s_k | Y) > 0``
(``P_k`` is the Schur complement of the corner 1 in ``Stilde_k``).  In doubles the code classifies each
step by two relative thresholds of :class:`~soc_opt.mstep.config.MStepConfig`:

* ``h_rel`` = smallest / largest eigenvalue of ``H_k``, computed as the squared ratio of the extreme
  singular values of the whitened ``Lo^-1 B`` (``So = Lo Lo^T``): accurate down to about ``eps^2``
  instead of the ``eps`` of an eigenvalue of the formed ``H_k``;
* ``p_rel`` = smallest eigenvalue of ``P_k`` / largest eigenvalue of ``Stilde_k``.

A step is **singular** when ``h_rel <= sing_tol`` or ``p_rel <= sing_tol`` (the matrix is singular to
working precision: the maximiser is not unique); **ill-conditioned** when it is not singular but
``h_rel <= eig_tol`` or ``p_rel <= eig_tol`` (unique, but a Cholesky solve in doubles loses about
``log10(1/rel)`` digits); **well-conditioned** otherwise.  The closed form solves well-conditioned
steps by Cholesky, ill-conditioned ones in exact rational arithmetic (:mod:`soc_opt.mstep.exact`) and
singular ones by the minimum-norm maximiser with a :class:`~soc_opt.mstep.errors.MinNormWarning`
(``min_norm=True``) or raises :class:`~soc_opt.mstep.errors.NonUniqueMaximizerError`
(``min_norm=False``).  The CVXPY route and the time-invariant closed form refuse ill-conditioned
steps with :class:`~soc_opt.mstep.errors.IllConditionedMaximizerError` (the time-invariant closed form solves
them exactly up to ``EXACT_TI_MAX = 64`` unknowns ``m (n+1)``).  Every message names the
step, the threshold and the condition number.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .. import linalg as la
from ..models import AugmentedModel, symmetrize
from .config import MStepConfig
from .errors import IllConditionedMaximizerError, MinNormWarning, NonUniqueMaximizerError
from .exact import EXACT_TI_MAX

__all__ = ["Conditioning", "conditioning", "check_time_varying", "check_time_invariant", "MIN_NORM_HINT",
           "CVXPY_HINT"]

MIN_NORM_HINT = " Pass min_norm=True for the minimum-norm maximiser."
CVXPY_HINT = " The minimum-norm maximiser (min_norm=True) needs method='closed_form'."
_TINY = np.finfo(float).tiny


@dataclass(frozen=True)
class Conditioning:
    """Per-step conditioning of ``H_k`` and ``P_k`` (module docstring); arrays of shape (T,)."""

    h_min: np.ndarray  # smallest eigenvalue of H_k
    h_rel: np.ndarray  # smallest / largest eigenvalue of H_k
    p_min: np.ndarray  # smallest eigenvalue of P_k
    p_rel: np.ndarray  # p_min / largest eigenvalue of Stilde_k
    h_ratios: np.ndarray  # (T, m) eigenvalues of H_k over the largest, descending

    def singular(self, cfg: MStepConfig) -> np.ndarray:
        return (self.h_rel <= cfg.sing_tol) | (self.p_rel <= cfg.sing_tol)

    def ill(self, cfg: MStepConfig) -> np.ndarray:
        return ~self.singular(cfg) & ((self.h_rel <= cfg.eig_tol) | (self.p_rel <= cfg.eig_tol))


def conditioning(model: AugmentedModel, S: np.ndarray) -> Conditioning:
    """The :class:`Conditioning` of every step from the model and ``Stilde`` (T, n+1, n+1)."""
    n = model.n
    C = la.tri_solve(la.chol(model.So, "augmented So"), model.Bs)  # Lo^-1 B, (T, n+1, m)
    sv = np.linalg.svd(C, compute_uv=False)  # min(n+1, m) values: with m > n+1, H_k has m - (n+1) zero eigenvalues
    sv = np.concatenate([sv, np.zeros((model.T, model.m - sv.shape[1]))], axis=1)
    h_max = sv[:, 0] ** 2
    h_min = sv[:, -1] ** 2
    P = symmetrize(S[:, :n, :n] - S[:, :n, n:] @ S[:, n:, :n] / S[:, n:, n:])
    s_scale = np.maximum(np.abs(np.linalg.eigvalsh(S)).max(-1), _TINY)
    p_min = np.linalg.eigvalsh(P)[:, 0] if n else np.full(model.T, np.inf)
    ratios = sv**2 / np.maximum(h_max, _TINY)[:, None]
    return Conditioning(h_min, h_min / np.maximum(h_max, _TINY), p_min, p_min / s_scale, ratios)


def _cond(rel: float) -> str:
    return "inf" if rel <= 0 else f"{1.0 / rel:.3e}"


def describe(model: AugmentedModel, c: Conditioning, k: int, cfg: MStepConfig) -> str:
    """What makes step ``k`` singular or ill-conditioned, with the thresholds and condition numbers."""
    parts = []
    h, p = float(c.h_rel[k]), float(c.p_rel[k])
    if h <= cfg.eig_tol:
        rank = int(np.sum(c.h_ratios[k] > cfg.sing_tol))
        which = (f"singular to working precision (numerical rank {rank} < m={model.m} at sing_tol = {cfg.sing_tol:g}: "
                 f"relative smallest eigenvalue {h:.3e})"
                 if h <= cfg.sing_tol else
                 f"ill-conditioned (relative smallest eigenvalue {h:.3e} <= eig_tol = {cfg.eig_tol:g}, above "
                 f"sing_tol = {cfg.sing_tol:g})")
        parts.append(f"H_{k} = B^T So^-1 B with the stacked B_{k} = [B; By] ({model.n + 1}x{model.m}) is {which}, "
                     f"condition number {_cond(h)}")
    if p <= cfg.eig_tol:
        which = (f"singular to working precision (<= sing_tol = {cfg.sing_tol:g})" if p <= cfg.sing_tol else
                 f"ill-conditioned (<= eig_tol = {cfg.eig_tol:g}, above sing_tol = {cfg.sing_tol:g})")
        parts.append(f"Stilde_{k} = E[(s_{k},1)(s_{k},1)^T] is {which}: P_{k} = Cov(s_{k} | Y), the Schur complement "
                     f"of its corner 1, has smallest eigenvalue {float(c.p_min[k]):.3e}, {p:.3e} of Stilde_{k}'s largest "
                     f"(condition number {_cond(p)})")
    return "; ".join(parts)


def _others(steps, k) -> str:
    rest = [int(j) for j in steps if j != k]
    return f" (also at steps {rest[:10]}{'...' if len(rest) > 10 else ''})" if rest else ""


def check_time_varying(model: AugmentedModel, S: np.ndarray, cfg: MStepConfig, *, min_norm: bool, cvxpy: bool,
                       hint: str = MIN_NORM_HINT) -> tuple[np.ndarray, np.ndarray]:
    """``(singular, ill)`` step masks of the time-varying M-step, after raising what the route cannot do.

    Raises :class:`NonUniqueMaximizerError` for a singular step unless ``min_norm`` on the closed form
    (then a :class:`MinNormWarning` names the steps), and :class:`IllConditionedMaximizerError` for an
    ill-conditioned step on the CVXPY route.  The last offending step is named first (the backward sweep
    meets it first).
    """
    c = conditioning(model, S)
    sing, ill = c.singular(cfg), c.ill(cfg)
    bad = np.flatnonzero(sing)
    if bad.size and (cvxpy or not min_norm):
        k = int(bad[-1])
        raise NonUniqueMaximizerError(
            f"M-step maximiser is not unique at time step k={k}: {describe(model, c, k, cfg)}{_others(bad, k)}.{hint}")
    hard = np.flatnonzero(ill)
    if cvxpy and hard.size:
        k = int(hard[-1])
        raise IllConditionedMaximizerError(
            f"M-step at time step k={k}: {describe(model, c, k, cfg)}{_others(hard, k)}; the maximiser is unique but "
            "CVXPY does not resolve it at this conditioning: method='closed_form' computes it in exact arithmetic.")
    if bad.size:
        warnings.warn(MinNormWarning(
            f"M-step maximiser is not unique at time steps {bad.tolist()[:10]}{'...' if bad.size > 10 else ''}: "
            f"{describe(model, c, int(bad[-1]), cfg)}; returning the minimum-norm maximiser there "
            "(min_norm=True)."), stacklevel=5)
    return sing, ill


def check_time_invariant(model: AugmentedModel, S: np.ndarray, Q: np.ndarray, cfg: MStepConfig, *, min_norm: bool,
                         hint: str = MIN_NORM_HINT, exact: bool = False) -> str:
    """How to solve the time-invariant normal equations ``Q vec F = r`` (``Q = sum_k Stilde_k kron H_k``):
    ``"cholesky"`` (``Q``'s relative smallest eigenvalue above ``eig_tol``); below it, ``Q`` counts as singular
    only when it is at most ``sing_tol`` and every step is singular on its own (a step that is not makes the
    sum positive definite); otherwise ``"exact"`` (ill-conditioned, ``exact`` allowed: the closed form with at most
    ``EXACT_TI_MAX`` unknowns) or ``"min_norm"`` (singular, ``min_norm``, with a :class:`MinNormWarning`).
    Raises :class:`NonUniqueMaximizerError` for a singular ``Q`` without ``min_norm`` and
    :class:`IllConditionedMaximizerError` for an ill-conditioned one without ``exact``."""
    ev = np.linalg.eigvalsh(Q)
    rel = float(ev[0] / max(abs(ev[-1]), _TINY))
    if rel > cfg.eig_tol:
        return "cholesky"
    c = conditioning(model, S)
    steps = np.flatnonzero((c.h_rel <= cfg.eig_tol) | (c.p_rel <= cfg.eig_tol))
    detail = ""
    if steps.size:
        k = int(steps[-1])
        detail = f" Per step: {describe(model, c, k, cfg)}{_others(steps, k)}."
    what = (f"sum_k (Stilde_k kron H_k) has relative smallest eigenvalue {rel:.3e} (condition number {_cond(rel)})")
    # one step whose own H_k and P_k are not singular makes the sum positive definite (its term alone is)
    if rel > cfg.sing_tol or not c.singular(cfg).all():
        if exact:
            return "exact"
        raise IllConditionedMaximizerError(
            f"time-invariant M-step is ill-conditioned: {what} <= eig_tol = {cfg.eig_tol:g}, above sing_tol = "
            f"{cfg.sing_tol:g}; the maximiser is unique but this route has no exact solve (the closed form has one up "
            f"to {EXACT_TI_MAX} unknowns m(n+1), here {Q.shape[0]}).{detail}")
    if not min_norm:
        raise NonUniqueMaximizerError(
            f"time-invariant M-step maximiser is not unique: {what} <= sing_tol = {cfg.sing_tol:g}.{detail}{hint}")
    warnings.warn(MinNormWarning(f"time-invariant M-step maximiser is not unique: {what} <= sing_tol = "
                                 f"{cfg.sing_tol:g}; returning the minimum-norm maximiser (min_norm=True).{detail}"),
                  stacklevel=5)
    return "min_norm"
