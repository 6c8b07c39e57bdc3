"""Pieces shared by the claim checks (docs/math.md §9): the result row, RNG streams, small helpers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..linalg import chol, logdet_chol
from ..models import symmetrize


@dataclass(frozen=True)
class ClaimResult:
    """One row of the verification table.

    Fields:
        claim:          short identifier, e.g. ``"1a uniqueness, well-posed, per-step"``.
        description:    what was checked and what "held" means for this row.
        instances:      number of random instances tried.
        held:           number of instances on which the row's statement held.
        worst_margin:   the worst value of the row's margin over the instances.
        margin_meaning: what the margin is and which sign/size means "held".
        counterexample: a small instance (arrays as nested lists) where the statement
                        failed, or, for the ill-posed rows, the explicit non-uniqueness
                        example docs/math.md §9.1 asks for; ``None`` otherwise.
        notes:          tolerances, auxiliary numbers, caveats.
    """

    claim: str
    description: str
    instances: int
    held: int
    worst_margin: float
    margin_meaning: str
    counterexample: dict | None
    notes: str


def logdet(X: np.ndarray, name: str = "matrix") -> float:
    """``log|X|`` of one symmetric positive definite matrix (symmetrised, by Cholesky);
    :class:`~soc_opt.models.NotPositiveDefiniteError` naming ``name`` otherwise."""
    return float(logdet_chol(chol(symmetrize(X), name)))


def is_pd(X: np.ndarray) -> bool:
    """Whether the symmetrised ``X`` has a Cholesky factor."""
    try:
        np.linalg.cholesky(symmetrize(X))
    except np.linalg.LinAlgError:
        return False
    return True


def tolist(x):
    """Arrays and numpy scalars -> plain Python (for counterexample dicts)."""
    if isinstance(x, np.ndarray):
        return np.round(x.astype(float), 12).tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, dict):
        return {k: tolist(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [tolist(v) for v in x]
    return x


def child_rng(seed: int, tag: int) -> np.random.Generator:
    """Independent, reproducible stream per claim: ``Generator(PCG64([seed, tag]))``."""
    return np.random.Generator(np.random.PCG64([int(seed), int(tag)]))


def mstep_module():
    """``soc_opt.mstep``, imported lazily so that claim 4 runs even if the M-step module is broken."""
    try:
        from .. import mstep
    except ImportError:
        return None
    return mstep
