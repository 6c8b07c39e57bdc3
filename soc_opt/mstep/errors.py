"""Errors of the M-step (docs/math.md §5).

The bottom of the package: imported by every other module of :mod:`soc_opt.mstep`, imports
none of them.
"""

from __future__ import annotations

from .. import errors as _errors
from ..config import ConfigError

__all__ = [
    "SolverError",
    "NonUniqueMaximizerError",
    "InfeasibleConstraintsError",
    "ClosedFormUnavailableError",
    "IllConditionedMaximizerError",
    "MinNormWarning",
]


class SolverError(_errors.SolverError):
    """A CVXPY solve of the M-step failed; ``status`` is the solver's status and ``step`` the time
    step (or None).  A :class:`soc_opt.errors.SolverError`."""


class NonUniqueMaximizerError(ValueError):
    """The M-step maximiser is not unique: ``H_k`` or ``P_k`` is singular to working precision (relative
    smallest eigenvalue <= ``MStepConfig.sing_tol``); names the step, the threshold and the condition
    number (docs/math.md §5, "Conditioning")."""


class IllConditionedMaximizerError(ValueError):
    """The M-step maximiser is unique but ill-conditioned (relative smallest eigenvalue of ``H_k`` or
    ``P_k`` in ``(sing_tol, eig_tol]``) on a route without exact arithmetic (CVXPY, the time-invariant
    variant); names the step, the thresholds and the condition number (docs/math.md §5, "Conditioning")."""


class MinNormWarning(UserWarning):
    """The M-step returned the minimum-norm maximiser at steps where the maximiser is not unique
    (``min_norm=True``); names the steps, the threshold and the condition number."""


class InfeasibleConstraintsError(ConfigError):
    """The constraint set is empty; the message names the conflicting constraints."""


class ClosedFormUnavailableError(ValueError):
    """The requested constraint set has no closed-form maximiser; use ``method="cvxpy"``."""
