"""Small dense factorisations for the compiled kernels (docs/math.md §0 conventions; numba, C-ordered 2-D arrays, results written
into arrays the caller owns, so that the loops allocate nothing).

Cholesky and LU with partial pivoting (docs/architecture.md, "Conventions": covariances by Cholesky;
the LU only where the reference uses ``numpy.linalg.solve`` on a matrix that is not symmetric) and their
solves, the innermost loops over contiguous memory (independent sums: vectorised without reassociation).
Matrix products are ``numpy.dot`` into an output array, which numba hands to the BLAS (``dgemm``):
at these sizes (``n = 6..26``) 3-4 times the speed of a compiled triple loop.
"""

from __future__ import annotations

import math

from . import jit

__all__ = ["symmetrize", "cholesky", "chol_solve_lower", "chol_solve", "lu", "lu_solve"]


@jit
def symmetrize(A):
    """``A = (A + A.T) / 2`` in place."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            v = 0.5 * (A[i, j] + A[j, i])
            A[i, j] = v
            A[j, i] = v


@jit
def cholesky(A, L) -> bool:
    """Lower Cholesky factor ``L`` of ``A`` (lower triangle read); ``False`` when ``A`` is not positive
    definite (a pivot ``<= 0`` or not finite)."""
    n = A.shape[0]
    for j in range(n):
        d = A[j, j]
        for s in range(j):
            d -= L[j, s] * L[j, s]
        if not d > 0.0 or not math.isfinite(d):
            return False
        d = math.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, n):
            v = A[i, j]
            for s in range(j):
                v -= L[i, s] * L[j, s]
            L[i, j] = v / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@jit
def chol_solve_lower(L, B):
    """``B = L^{-1} B`` in place (forward substitution, every column of ``B``)."""
    n, m = B.shape[0], B.shape[1]
    for i in range(n):
        for s in range(i):
            a = L[i, s]
            for j in range(m):
                B[i, j] -= a * B[s, j]
        d = 1.0 / L[i, i]
        for j in range(m):
            B[i, j] *= d


@jit
def chol_solve(L, B):
    """``B = (L L^T)^{-1} B`` in place."""
    chol_solve_lower(L, B)
    n, m = B.shape[0], B.shape[1]
    for i in range(n - 1, -1, -1):
        for s in range(i + 1, n):
            a = L[s, i]
            for j in range(m):
                B[i, j] -= a * B[s, j]
        d = 1.0 / L[i, i]
        for j in range(m):
            B[i, j] *= d


@jit
def lu(A, piv) -> bool:
    """In-place LU factorisation with partial pivoting (``P A = L U``, unit ``L`` below the diagonal,
    row swaps in ``piv``); ``False`` on a zero (or non-finite) pivot."""
    n = A.shape[0]
    for j in range(n):
        p, big = j, abs(A[j, j])
        for i in range(j + 1, n):
            if abs(A[i, j]) > big:
                p, big = i, abs(A[i, j])
        if not big > 0.0 or not math.isfinite(big):
            return False
        piv[j] = p
        if p != j:
            for s in range(n):
                A[j, s], A[p, s] = A[p, s], A[j, s]
        d = 1.0 / A[j, j]
        for i in range(j + 1, n):
            f = A[i, j] * d
            A[i, j] = f
            for s in range(j + 1, n):
                A[i, s] -= f * A[j, s]
    return True


@jit
def lu_solve(A, piv, B):
    """``B = A^{-1} B`` in place from :func:`lu`'s factors."""
    n, m = B.shape[0], B.shape[1]
    for j in range(n):
        p = piv[j]
        if p != j:
            for s in range(m):
                B[j, s], B[p, s] = B[p, s], B[j, s]
    for i in range(n):
        for s in range(i):
            a = A[i, s]
            for j in range(m):
                B[i, j] -= a * B[s, j]
    for i in range(n - 1, -1, -1):
        for s in range(i + 1, n):
            a = A[i, s]
            for j in range(m):
                B[i, j] -= a * B[s, j]
        d = 1.0 / A[i, i]
        for j in range(m):
            B[i, j] *= d
