"""Small batched linear-algebra kernels shared by the solvers (docs/math.md §0 conventions).

Everything works on stacks of matrices (leading axes are batch axes).  Covariances are
factored by Cholesky and solved with triangular solves, never inverted explicitly.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from .models import NotPositiveDefiniteError, symmetrize

__all__ = [
    "T",
    "chol",
    "tri_solve",
    "cho_solve",
    "right_cho_solve",
    "logdet_chol",
    "logdet_pd",
    "tr",
    "inv_from_chol",
    "vec",
    "unvec",
    "single_thread_blas",
    "single_thread_blas_cached",
    "as_generator",
    "symmetrize",
    "schur_pd_margin",
    "as_index",
]


def T(X: np.ndarray) -> np.ndarray:
    """Transpose of the last two axes."""
    return np.swapaxes(X, -1, -2)


def chol(A: np.ndarray, name: str) -> np.ndarray:
    """Lower Cholesky factor of ``A`` (batched); raises :class:`NotPositiveDefiniteError`
    naming ``name`` and, for a ``(T, d, d)`` stack, the first step that is not PD."""
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        ev = np.linalg.eigvalsh(A)[..., 0]
        idx = np.argwhere(np.atleast_1d(ev) <= 0)
        where = f" at step {int(idx[0][0])}" if A.ndim == 3 and len(idx) else ""
        raise NotPositiveDefiniteError(
            f"{name}{where} is not positive definite (smallest eigenvalue {float(np.min(ev)):.3e})"
        ) from None


def tri_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``L^{-1} B`` for triangular ``L`` (batched).

    ``numpy.linalg.solve`` is used because it is batched in compiled code; the batched
    ``scipy.linalg.solve_triangular`` has a large per-call overhead for small matrices.
    """
    return np.linalg.solve(L, B)


def cho_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^{-1} B`` from the lower Cholesky factor ``L`` of ``A`` (batched)."""
    return tri_solve(T(L), tri_solve(L, B))


def right_cho_solve(X: np.ndarray, L: np.ndarray) -> np.ndarray:
    """``X A^{-1}`` for symmetric ``A = L L^T`` (batched)."""
    return T(cho_solve(L, T(X)))


def logdet_chol(L: np.ndarray) -> np.ndarray:
    """``log|A|`` from the Cholesky factor ``L`` of ``A`` (batched)."""
    return 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)


def logdet_pd(S: np.ndarray) -> np.ndarray:
    """(N,) log-determinants of a ``(N, d, d)`` stack by Cholesky; ``-inf`` where a matrix is
    not positive definite."""
    S = np.asarray(S, dtype=float)
    out = np.empty(S.shape[0])
    for t in range(S.shape[0]):
        L, info = lapack.dpotrf(S[t], lower=1, clean=1)
        out[t] = 2.0 * np.log(np.diag(L)).sum() if info == 0 else -np.inf
    return out


def tr(A: np.ndarray) -> np.ndarray:
    """Trace of the last two axes (batched)."""
    return np.trace(A, axis1=-2, axis2=-1)


def inv_from_chol(L: np.ndarray) -> np.ndarray:
    """``A^{-1}`` (symmetrised) from the Cholesky factor of ``A``; for the few places that need
    the matrix itself (information forms), not for solving."""
    eye = np.broadcast_to(np.eye(L.shape[-1]), L.shape)
    return symmetrize(cho_solve(L, eye))


def vec(F: np.ndarray) -> np.ndarray:
    """Column-major vectorisation ``vec(F)``."""
    return F.reshape(-1, order="F")


def unvec(v: np.ndarray, m: int, n1: int) -> np.ndarray:
    """Inverse of :func:`vec` for an ``(m, n1)`` matrix."""
    return v.reshape((m, n1), order="F")


def single_thread_blas():
    """Context manager limiting BLAS to one thread (restored on exit).

    The kernels work on many small matrices, where threaded BLAS gains nothing and, on a
    loaded 2-core machine, spin-waiting threads made them erratic and up to ~20x slower.
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


_THREADPOOLS = None  # threadpoolctl.ThreadpoolController, created on first use (it scans the loaded libraries)


def single_thread_blas_cached():
    """:func:`single_thread_blas` with one ``threadpoolctl.ThreadpoolController`` created on first
    use and reused: creating it scans the loaded libraries, a cost that matters around a few small
    decompositions per call (the M-step's spectral form, where threaded LAPACK ``syevd`` on a loaded
    machine took 0.5 to ~100 ms for a few 27 x 27 matrices).  BLAS libraries loaded after the first
    call are not limited."""
    global _THREADPOOLS
    if _THREADPOOLS is None:
        from threadpoolctl import ThreadpoolController

        _THREADPOOLS = ThreadpoolController()
    return _THREADPOOLS.limit(limits=1, user_api="blas")


def as_generator(rng, seed: int | None = None) -> np.random.Generator:
    """``rng`` itself when it is a ``numpy.random.Generator``; a new one from ``seed`` when
    ``rng`` is ``None``; ``TypeError`` naming the type otherwise."""
    if rng is None:
        return np.random.default_rng(seed)
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    return rng


def schur_pd_margin(M: np.ndarray, split: int) -> np.ndarray:
    """Scale-free positive-definiteness margin of a symmetric ``M`` (batched over leading axes).

    Write ``M = [[A, C], [C^T, D]]`` with ``A`` the leading ``split x split`` block.  ``M > 0`` iff
    ``D > 0`` and ``S = A - C D^-1 C^T > 0`` (block LDL^T congruence), and each of ``D`` and ``S``
    is judged by its own ratio ``lambda_min / lambda_max``.  Unlike ``lambda_min(M) / lambda_max(M)``
    this does not drift when the blocks live on different scales (``A`` ~ c^2, ``C`` ~ c, ``D`` ~ 1
    when a state is rescaled by c) or when a mean shift makes ``C`` large: uncentred second moments
    ``[[P + mu mu^T, mu], [mu^T, 1]]`` have margin ``min(1, lambda_min(P) / lambda_max(P))`` whatever
    ``mu``.  ``S`` is formed by a subtraction, so it is known only to about ``eps * ||A||``; an ``S``
    whose smallest eigenvalue is below that rounding level gets a margin ``<= 0`` (singular).

    Returns the margin (shape of the batch axes): ``> 0`` when both ``D`` and ``S`` are positive
    definite, and compared with a relative tolerance by the callers.
    """
    M = symmetrize(np.asarray(M, dtype=float))
    d = M.shape[-1]
    if not 0 < split < d:
        raise ValueError(f"split must be in 1..{d - 1}, got {split}")
    tiny = np.finfo(float).tiny
    A, C, D = M[..., :split, :split], M[..., :split, split:], M[..., split:, split:]
    wD, VD = np.linalg.eigh(D)
    topD = np.maximum(np.abs(wD).max(-1), tiny)
    ratio_D = wD[..., 0] / topD
    # pseudo-inverse of D on its numerically nonzero spectrum (D singular is already decided by ratio_D)
    keep = wD > d * np.finfo(float).eps * topD[..., None]
    inv_w = np.where(keep, 1.0 / np.where(keep, wD, 1.0), 0.0)
    CV = C @ VD
    S = symmetrize(A - (CV * inv_w[..., None, :]) @ T(CV))
    wS = np.linalg.eigvalsh(S)
    topS = np.maximum(np.abs(wS).max(-1), tiny)
    ratio_S = wS[..., 0] / topS
    rounding = 8 * d * np.finfo(float).eps * np.maximum(np.abs(np.linalg.eigvalsh(A)).max(-1), tiny)
    ratio_S = np.where(wS[..., 0] <= rounding, np.minimum(ratio_S, 0.0), ratio_S)
    return np.minimum(ratio_D, ratio_S)


def as_index(idx) -> slice | np.ndarray:
    """A slice when ``idx`` is a contiguous ascending range (indexing with it copies less), else the array."""
    idx = np.asarray(idx, dtype=int)
    if idx.size and np.all(np.diff(idx) == 1):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx
