"""Error types shared by every solver path.

``SolverError`` is the one base class for numerical solver failures: the M-step's CVXPY
solves (:class:`soc_opt.mstep.SolverError`) and the KL-constrained LQG step's dual and
IPOPT solves (:class:`soc_opt.lqg.SolverError`) both derive from it, so
``except soc_opt.errors.SolverError`` catches a failure from either.
Shape and positive-definiteness errors live in :mod:`soc_opt.models`.
"""

from __future__ import annotations

__all__ = ["SolverError"]


class SolverError(RuntimeError):
    """A numerical solver failed.

    Attributes:
        status: the solver's own status string (or ``None``).
        step:   the time step the failure belongs to (or ``None``).
    """

    def __init__(self, message: str, status: str | None = None, step: int | None = None):
        super().__init__(message)
        self.status = status
        self.step = step
