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
]


class SolverError(_errors.SolverError):
    """A CVXPY solve of the M-step failed; ``status`` is the solver's status and ``step`` the time
    step (or None).  A :class:`soc_opt.errors.SolverError`."""


class NonUniqueMaximizerError(ValueError):
    """The M-step maximiser is not unique (``B_k`` rank deficient or ``P_k`` singular); names the step."""


class InfeasibleConstraintsError(ConfigError):
    """The constraint set is empty; the message names the conflicting constraints."""


class ClosedFormUnavailableError(ValueError):
    """The requested constraint set has no closed-form maximiser; use ``method="cvxpy"``."""
