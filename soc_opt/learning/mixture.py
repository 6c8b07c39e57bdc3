"""The variational-Bayes mixture prior over transition tuples (docs/math.md §2 steps 1-2).

:class:`MixturePrior` is the fitted mixture (pruned components, point estimates) with the
tuple buffer and the variational posterior (:class:`VBState`) from which the next fit is
warm-started; :func:`soc_opt.learning.fit.update_prior` fits it and
:func:`soc_opt.learning.fit.joint_posterior` turns it into per-step NIW priors.  The helpers here map
the variational posterior between original units and the standardised coordinates each fit
works in (sklearn's ``BayesianGaussianMixture`` attributes), and :class:`Subspace` the directions
a fit runs on when coordinates are exactly related (docs/math.md §2 step 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import logsumexp

from ..linalg import T as _T
from ..linalg import chol, tri_solve
from ..models import ShapeError, check_array, symmetrize

__all__ = ["VBState", "MixturePrior", "Subspace", "standardisation", "varying_columns", "DEGENERATE_RTOL"]


class VBState(NamedTuple):
    """Variational posterior of the VB mixture's kept components, in original units.

    Kept by :class:`MixturePrior` so that the next :func:`soc_opt.learning.fit.update_prior` can start VB from it
    (``FitConfig.prior_warm_start``).  Only the ``C`` components whose weight reached
    ``FitConfig.min_weight`` are stored (the components of the prior).  The names follow
    sklearn's fitted attributes (Bishop §10.2: ``alpha_c``, ``beta_c``, ``m_c``, ``nu_c`` and
    ``W_c^{-1} / nu_c``).

    Fields:
        weight_concentration: (C,)       Dirichlet posterior parameters ``alpha_c``.
        mean_precision:       (C,)       ``beta_c`` (scale of the mean's precision).
        means:                (C, D)     ``m_c``.
        degrees_of_freedom:   (C,)       Wishart degrees of freedom ``nu_c``.
        covariances:          (C, D, D)  ``W_c^{-1} / nu_c`` (sklearn's ``covariances_``).
    """

    weight_concentration: np.ndarray
    mean_precision: np.ndarray
    means: np.ndarray
    degrees_of_freedom: np.ndarray
    covariances: np.ndarray

    @classmethod
    def from_sklearn(cls, bgm, center: np.ndarray, scale: np.ndarray, keep: np.ndarray,
                     subspace: "Subspace | None" = None) -> "VBState":
        """The posterior of the ``keep`` components of a fitted ``BayesianGaussianMixture``
        (fitted on ``(x - center) / scale``, or with ``subspace`` on its coordinates
        ``((x - center) / scale) @ subspace.basis``), in original units.

        With ``subspace`` the means and covariances are embedded back into all ``D`` standardised
        coordinates: ``m = U m_y`` and ``S = U S_y U^T + null_var W W^T`` (:class:`Subspace`).
        """
        means, cov = bgm.means_[keep], bgm.covariances_[keep]
        if subspace is not None:
            means, cov = subspace.embed(means, cov)
        return cls(
            weight_concentration=np.array(bgm.weight_concentration_[keep], dtype=float),
            mean_precision=np.array(bgm.mean_precision_[keep], dtype=float),
            means=center + means * scale,
            degrees_of_freedom=np.array(bgm.degrees_of_freedom_[keep], dtype=float),
            covariances=cov * scale[None, :, None] * scale[None, None, :],
        )

    def to_sklearn(self, bgm, center: np.ndarray, scale: np.ndarray, subspace: "Subspace | None" = None) -> None:
        """Set the fitted attributes of ``bgm`` (sklearn ``warm_start`` continues from them) to
        this posterior in the coordinates ``(x - center) / scale`` (with ``subspace``: projected
        on its basis ``U``, means ``U^T m`` and covariances ``U^T S U``).

        sklearn's ``precisions_cholesky_`` is the upper-triangular ``U = L^{-T}`` of the
        covariance ``L L^T`` (precision ``U U^T``).  ``lower_bound_ = -inf`` makes the first VB
        iteration count as a change, so the bound reached on the previous (different) data
        never stops VB early.  The Wishart degrees of freedom are raised to at least the number
        of coordinates fitted (sklearn's prior value, which a posterior fitted in those
        coordinates always exceeds; one fitted in a :class:`Subspace` of fewer may not).
        """
        cov = self.covariances / (scale[None, :, None] * scale[None, None, :])
        means = (self.means - center) / scale
        if subspace is not None:
            means, cov = subspace.project(means, cov)
        dof = np.maximum(np.array(self.degrees_of_freedom), float(cov.shape[-1]))
        L = chol(cov, "warm-start component covariance")
        eye = np.broadcast_to(np.eye(cov.shape[-1]), cov.shape)
        bgm.weight_concentration_ = np.array(self.weight_concentration)
        bgm.mean_precision_ = np.array(self.mean_precision)
        bgm.means_ = means
        bgm.degrees_of_freedom_ = dof
        bgm.covariances_ = cov
        bgm.precisions_cholesky_ = _T(tri_solve(L, eye))
        bgm.converged_ = False
        bgm.lower_bound_ = -np.inf


def _check_vb(vb: VBState, D: int) -> VBState:
    if not isinstance(vb, VBState):
        raise TypeError(f"prior vb must be a VBState or None, got {type(vb).__name__}")
    a = check_array("vb weight_concentration", vb.weight_concentration, (None,))
    C = a.shape[0]
    out = VBState(
        a,
        check_array("vb mean_precision", vb.mean_precision, (C,)),
        check_array("vb means", vb.means, (C, D)),
        check_array("vb degrees_of_freedom", vb.degrees_of_freedom, (C,)),
        symmetrize(check_array("vb covariances", vb.covariances, (C, D, D))),
    )
    for x in out:
        x.setflags(write=False)
    return out


@dataclass(frozen=True)
class MixturePrior:
    """A Gaussian mixture over tuples ``(s_k, a_k, s_{k+1}, y_k)`` (docs/math.md §2 step 1).

    Fields:
        weights:     (C,)       mixture weights (sum to 1, pruned components removed).
        means:       (C, D)     component means, ``D = 2n+m+1``, original (unstandardised) units.
        covariances: (C, D, D)  component covariances (the variational posterior's expected
                                covariance, as sklearn's ``covariances_``).
        buffer:      (N, D)     tuples kept for the next :func:`update_prior` (newest last).
        n, m:        state and action dimensions.
        converged:   whether VB met sklearn's tolerance within ``max_iter``.
        n_iter:      VB iterations run.
        vb:          the variational posterior of the ``C`` components (:class:`VBState`) the
                     next :func:`update_prior` warm-starts from; None: no warm start.
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    buffer: np.ndarray
    n: int
    m: int
    converged: bool = True
    n_iter: int = 0
    vb: VBState | None = None

    def __post_init__(self):
        n, m = int(self.n), int(self.m)
        D = 2 * n + m + 1
        w = check_array("prior weights", self.weights, (None,))
        C = w.shape[0]
        if C < 1:
            raise ShapeError("prior must have at least one component")
        mu = check_array("prior means", self.means, (C, D))
        S = check_array("prior covariances", self.covariances, (C, D, D))
        buf = check_array("prior buffer", self.buffer, (None, D))
        if np.any(w < 0) or abs(w.sum() - 1.0) > 1e-8:
            raise ValueError(f"prior weights must be non-negative and sum to 1 (sum {w.sum():.6g})")
        S = symmetrize(S)
        for a in (w, mu, S, buf):
            a.setflags(write=False)
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "means", mu)
        object.__setattr__(self, "covariances", S)
        object.__setattr__(self, "buffer", buf)
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "m", m)
        if self.vb is not None:
            object.__setattr__(self, "vb", _check_vb(self.vb, D))

    @property
    def n_components(self) -> int:
        return self.weights.shape[0]

    @property
    def dim(self) -> int:
        return 2 * self.n + self.m + 1

    def marginal(self, include_y: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(weights, means, covariances)`` of the mixture over ``(s, a, s')[, y]``.

        Dropping ``y`` marginalises it out of every component exactly.
        """
        if include_y:
            return self.weights, self.means, self.covariances
        d = self.dim - 1
        return self.weights, self.means[:, :d], self.covariances[:, :d, :d]

    def responsibilities(self, X: np.ndarray, include_y: bool = True) -> np.ndarray:
        """Posterior component probabilities ``(N, C)`` of points ``X (N, D)`` (or ``D-1`` without ``y``).

        Computed from the stored point estimates (plug-in Gaussian densities), so
        they apply equally to the marginal mixture without ``y``.  Batched over the
        components: one stacked Cholesky factorisation ``S_c = L_c L_c^T``, then the
        whitened residuals ``L_c^{-1} (x - mu_c)`` of all points by one product per
        component with the (small, triangular) ``L_c^{-1}``.
        """
        w, mu, S = self.marginal(include_y)
        X = np.asarray(X, dtype=float)
        L = chol(S, "prior component covariance")  # (C, d, d)
        Li = tri_solve(L, np.broadcast_to(np.eye(L.shape[-1]), L.shape))  # (C, d, d) lower
        r = Li @ X.T - (Li @ mu[:, :, None])  # (C, d, N)
        with np.errstate(divide="ignore"):
            logw = np.log(w)
        logdet = np.log(np.diagonal(L, axis1=1, axis2=2)).sum(axis=1)  # (C,) half log-determinants
        logp = (logw - logdet)[None, :] - 0.5 * _T(np.square(r).sum(axis=1))
        return np.exp(logp - logsumexp(logp, axis=1, keepdims=True))

    def step_prior(self, X: np.ndarray, include_y: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Per-step NIW centre ``mu0 (T, d)`` and covariance ``S0 (T, d, d)`` from tuples ``X (M, T, d)``.

        ``w_c^k`` is the mean responsibility of the ``M`` step-``k`` tuples;
        ``S0_k`` is the mixture's second moment about ``mu0_k`` (docs/math.md §2 step 2),
        computed for all steps at once with batched products.
        """
        Mr, T, d = X.shape
        _, mu, S = self.marginal(include_y)
        r = self.responsibilities(X.reshape(Mr * T, d), include_y).reshape(Mr, T, -1)
        wk = r.mean(axis=0)  # (T, C)
        mu0 = wk @ mu
        diff = mu[None, :, :] - mu0[:, None, :]  # (T, C, d)
        S0 = (wk @ S.reshape(S.shape[0], d * d)).reshape(T, d, d) + _T(diff * wk[:, :, None]) @ diff
        return mu0, symmetrize(S0)


# --------------------------------------------------------------------------- standardised coordinates


def standardisation(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column ``(center, scale)`` of ``data (N, D)``; constant columns get scale 1.

    Each VB fit works on ``(data - center) / scale``.
    """
    center = data.mean(axis=0)
    scale = data.std(axis=0)
    scale = np.where(varying_columns(scale, center), scale, 1.0)
    return center, scale


def varying_columns(std: np.ndarray, center: np.ndarray) -> np.ndarray:
    """``(D,)`` bool: the columns of standard deviation ``std`` and mean ``center`` that are not
    constant (``std > 1e-12 max(1, |center|)``; :func:`standardisation` gives the others scale 1)."""
    return std > 1e-12 * np.maximum(1.0, np.abs(center))


#: A direction of the standardised tuples is degenerate when its variance is at most this fraction
#: of the largest: exactly collinear coordinates leave round-off (~1e-16 of it), while the nearest
#: to degenerate the existing tasks come is ~1e-9 (peg's smoothed states, which lie on the
#: kinematics' manifold, at rho^2 = 0 in short test runs).
DEGENERATE_RTOL = 1e-12


class Subspace(NamedTuple):
    """The directions of standardised tuples the mixture is fitted on, when some are degenerate.

    Fields:
        basis:    (D, r) orthonormal ``U``: every constant column (as its unit vector: sklearn fits it
                  as a zero column, decoupled from the rest, with variance ``reg_covar``, as without
                  a subspace), and the directions of the varying columns whose variance exceeds
                  :data:`DEGENERATE_RTOL` times the largest.
        null:     (D, D - r) orthonormal ``W``: the other directions of the varying columns: exact
                  linear relations between coordinates (e.g. a point's position and the slide joint
                  that moves it, or its height and the hinge angle that does not), where the data do
                  not vary although each coordinate does.
        null_var: the variance every component gets along ``W`` (``FitConfig.mixture_reg``, what
                  sklearn's ``reg_covar`` gives a constant column).
    """

    basis: np.ndarray
    null: np.ndarray
    null_var: float

    @property
    def rank(self) -> int:
        return self.basis.shape[1]

    @classmethod
    def of(cls, Z: np.ndarray, varying: np.ndarray, null_var: float,
           rtol: float = DEGENERATE_RTOL) -> "Subspace | None":
        """The :class:`Subspace` of standardised data ``Z (N, D)`` whose ``varying (D,)`` columns are
        not constant (:func:`varying_columns`), or None when no direction of them is degenerate (the
        mixture is then fitted on all ``D`` coordinates).  With no more
        tuples than varying columns the covariance is singular for want of data, not because of
        the coordinates: None too."""
        idx = np.flatnonzero(varying)
        if idx.size < 2 or Z.shape[0] <= idx.size:
            return None
        Zv = Z[:, idx] - Z[:, idx].mean(axis=0)
        lam, V = np.linalg.eigh(_T(Zv) @ Zv / Z.shape[0])
        null = lam <= rtol * float(lam[-1])
        null[-1] = False
        if not np.any(null):
            return None
        D = Z.shape[1]
        const = np.flatnonzero(~np.asarray(varying, dtype=bool))
        keep = V[:, ~null]
        U = np.zeros((D, keep.shape[1] + const.size))
        U[idx, : keep.shape[1]] = keep
        U[const, keep.shape[1] + np.arange(const.size)] = 1.0
        W = np.zeros((D, int(null.sum())))
        W[idx] = V[:, null]
        return cls(U, W, float(null_var))

    def project(self, means: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Standardised ``means (C, D)``, ``cov (C, D, D)`` in the basis: ``(m U, U^T S U)``."""
        U = self.basis
        return means @ U, symmetrize(_T(U)[None] @ cov @ U[None])

    def embed(self, means: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Subspace ``means (C, r)``, ``cov (C, r, r)`` in all ``D`` standardised coordinates:
        ``(m U^T, U S U^T + null_var W W^T)`` (along ``W`` the mean is the data's: zero)."""
        U, W = self.basis, self.null
        full = U[None] @ cov @ _T(U)[None] + self.null_var * (W @ _T(W))[None]
        return means @ _T(U), symmetrize(full)
