"""The standing hypotheses of the claims that use ``P_{j|T} > 0`` (docs/math.md §4, §9.1): the initial
state covariance ``P0`` and every observation-noise covariance ``So_k`` positive definite.

Why they suffice: ``(s_0, zeta_0, ..., zeta_{T-1})`` is an invertible (block-triangular) affine map of
``s_0`` and the model noises ``eo_k ~ N(0, So_k)`` plus the action noise, so with ``P0 > 0`` and
``So_k > 0`` the joint Gaussian of ``(s_0..s_T, y_0..y_{T-1})`` is non-degenerate and every
conditional covariance ``P_{j|T} = Cov(s_j | Y)`` is positive definite.  Without them it need not be:
``P0 = 0`` gives ``P_{0|T} = 0`` and the M-step's ``[K_0 k_0]`` is not unique.

The library accepts any ``P0`` whose smallest eigenvalue is ``> 0`` (``estep.smooth`` checks exactly
that): ``P0 = 1e-14 I`` with ``mu0 = O(1)`` is smoothed without complaint, and the M-step then raises a
``NonUniqueMaximizerError`` about ``P_0 = Cov(s_0 | Y)``, which does not name the input.  The
verification layer checks the hypotheses up front instead (:func:`require_standing_hypotheses`) and
names the matrix.  The library's own checks are unchanged.

The test is scale-free: each covariance is measured in the units of its own variables,
``D^{-1/2} X D^{-1/2}`` with ``D`` the diagonal of the variables' second moment (``P0 + mu0 mu0^T`` for
``s_0``, ``So_k`` itself for the zero-mean noise), so rescaling a coordinate does not change the verdict,
while a ``P0`` that is negligible next to the mean state (the state known to a relative ``1e-7``) is
flagged.
"""

from __future__ import annotations

import numpy as np

from ..models import symmetrize

__all__ = ["HypothesisError", "STANDING", "PD_REL_TOL", "scaled_pd_margin", "require_standing_hypotheses"]

#: the hypotheses as the claims table states them
STANDING = "P0 > 0 and So_k > 0 at every step (initial-state and observation-noise covariances positive definite)"
#: a covariance counts as positive definite when its scaled smallest eigenvalue exceeds this
#: (the M-step's own relative eigenvalue threshold, ``MStepConfig.eig_tol``)
PD_REL_TOL = 1e-10


class HypothesisError(ValueError):
    """An input violates a standing hypothesis of the claims (the message names the matrix)."""


def scaled_pd_margin(X: np.ndarray, second_moment: np.ndarray | None = None) -> float:
    """Smallest eigenvalue of ``D^{-1/2} X D^{-1/2}``, ``D = diag(second_moment)`` (default ``diag(X)``).

    ``1`` for a diagonal ``X`` measured against itself, ``<= 0`` when ``X`` is not positive definite;
    unchanged when a variable is rescaled (``X -> C X C``, ``second_moment -> C M C``, ``C`` diagonal).
    """
    X = symmetrize(np.asarray(X, dtype=float))
    M = X if second_moment is None else symmetrize(np.asarray(second_moment, dtype=float))
    d = np.sqrt(np.maximum(np.diagonal(M), np.finfo(float).tiny))
    return float(np.linalg.eigvalsh(X / d[:, None] / d[None, :])[0])


def require_standing_hypotheses(model, mu0: np.ndarray, P0: np.ndarray, rel_tol: float = PD_REL_TOL) -> None:
    """Raise :class:`HypothesisError`, naming the matrix, unless ``P0 > 0`` (against the second moment
    ``P0 + mu0 mu0^T`` of ``s_0``) and every ``So_k > 0`` (against its own diagonal), both with the
    scale-free margin of :func:`scaled_pd_margin` above ``rel_tol`` (docs/math.md §9.1)."""
    mu0 = np.asarray(mu0, dtype=float)
    P0 = np.asarray(P0, dtype=float)
    margin = scaled_pd_margin(P0, P0 + np.outer(mu0, mu0))
    if not margin > rel_tol:
        raise HypothesisError(
            f"P0 (the initial state covariance) is not positive definite at the scale of the state: the smallest "
            f"eigenvalue of P0 scaled by diag(P0 + mu0 mu0^T) is {margin:.3e} <= {rel_tol:g}; the claims that use "
            f"P_j|T > 0 assume {STANDING}")
    for k, So in enumerate(np.asarray(model.So, dtype=float)):
        margin = scaled_pd_margin(So)
        if not margin > rel_tol:
            raise HypothesisError(
                f"So_{k} (the observation-noise covariance of step {k}) is not positive definite: the smallest "
                f"eigenvalue of its correlation matrix is {margin:.3e} <= {rel_tol:g}; the claims that use "
                f"P_j|T > 0 assume {STANDING}")
