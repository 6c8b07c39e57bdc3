"""Error types shared by every solver path.

``SolverError`` is the one base class for numerical solver failures: the M-step's CVXPY
solves (:class:`soc_opt.mstep.SolverError`) and the KL-constrained LQG step's dual and
IPOPT solves (:class:`soc_opt.lqg.SolverError`) both derive from it, so
``except soc_opt.errors.SolverError`` catches a failure from either.
Shape and positive-definiteness errors live in :mod:`soc_opt.models`.
"""

from __future__ import annotations

__all__ = ["SolverError", "FlatCostError", "WorkerDiedError", "resumable"]


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


class FlatCostError(ValueError):
    """The task's cost expansion around a batch is zero at every step (no gradient, no curvature in the
    state or the action): a sample-based method has nothing to follow (docs/math.md §7).  A property of the
    task's cost, so a rerun repeats it."""


class WorkerDiedError(RuntimeError):
    """A worker process ended without a result (killed, out of memory): a rerun may get past it."""


def resumable(exc: BaseException) -> bool:
    """Whether running the same command again can get past ``exc``: failures of the machine (files and
    disks, memory, a worker process that died), not of the computation, which a resumed run repeats from
    the same checkpoint bit for bit (docs/reproducibility.md)."""
    return isinstance(exc, (OSError, MemoryError, WorkerDiedError, EOFError))
