"""Exact rational arithmetic for the M-step's ill-conditioned steps (docs/math.md §5, "Conditioning").

A double is a rational number, so the data of one step (the model's ``B = [B; By]``, ``So``,
``Atil = [A_s co]`` and the moments ``Szs``, ``Stilde``) define the surrogate's maximiser exactly.
Where ``H_k`` or ``P_k`` is numerically nonsingular but ill-conditioned (relative smallest
eigenvalue in ``(sing_tol, eig_tol]``, :class:`~soc_opt.mstep.config.MStepConfig`), the Cholesky
solve in doubles loses about ``log10(cond)`` digits; :func:`unique_maximiser` instead computes
``F = H^-1 R Stilde^-1`` (``H = B^T So^-1 B``, ``R = B^T So^-1 (Szs - Atil Stilde)``) in rationals
(python-flint ``fmpq_mat``) and rounds each entry once, so the result is the unique maximiser of the
step as given, correctly rounded.  ``Stilde`` enters as the exact symmetric part of its doubles.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to_fmpq_mat", "to_float", "unique_maximiser", "unique_maximiser_ti", "EXACT_TI_MAX"]

#: the time-invariant variant is solved exactly up to this many unknowns ``m (n+1)`` (the exact Kronecker
#: system grows as its square; at 189 unknowns, n = 26, m = 7, one solve took 31 s)
EXACT_TI_MAX = 64


def to_fmpq_mat(a: np.ndarray):
    """The exact rational matrix of a 2-D array of doubles (each double read as the rational it is)."""
    from flint import fmpq, fmpq_mat

    a = np.atleast_2d(np.asarray(a, dtype=float))
    if not np.all(np.isfinite(a)):
        raise ValueError("exact arithmetic needs finite numbers (NaN or inf in the step's data)")
    return fmpq_mat([[fmpq(*float(v).as_integer_ratio()) for v in row] for row in a])


def to_float(M) -> np.ndarray:
    """A rational matrix rounded entrywise to the nearest double (Python's correctly rounded ``int / int``)."""
    out = np.empty((M.nrows(), M.ncols()))
    for i in range(M.nrows()):
        for j in range(M.ncols()):
            q = M[i, j]
            out[i, j] = int(q.p) / int(q.q)
    return out


def unique_maximiser(B: np.ndarray, So: np.ndarray, Atil: np.ndarray, Szs: np.ndarray, Sss: np.ndarray) -> np.ndarray:
    """``[K k]`` (m, n+1) maximising ``Lbar`` of one step, computed exactly and rounded once (module docstring).

    ``B`` (n+1, m), ``So`` (n+1, n+1), ``Atil`` (n+1, n+1), ``Szs`` and ``Sss`` (n+1, n+1).  Raises
    ``ZeroDivisionError`` (from python-flint) if ``H`` or ``Stilde`` is exactly singular; callers only use it
    where the relative smallest eigenvalue is above ``sing_tol``, far above the rounding of the estimate.
    """
    Bq, Soq, Aq = to_fmpq_mat(B), to_fmpq_mat(So), to_fmpq_mat(Atil)
    Zq, Sraw = to_fmpq_mat(Szs), to_fmpq_mat(Sss)
    S = (Sraw + Sraw.transpose()) / 2
    SoiB = Soq.solve(Bq)
    H = Bq.transpose() * SoiB
    R = SoiB.transpose() * (Zq - Aq * Sraw)
    X = H.solve(R)  # H^-1 R, (m, n+1)
    F = S.solve(X.transpose()).transpose()  # (H^-1 R) S^-1 with S symmetric
    return to_float(F)


def _step_terms(B, So, Atil, Szs, Sss):
    Bq, Soq, Aq = to_fmpq_mat(B), to_fmpq_mat(So), to_fmpq_mat(Atil)
    Zq, Sraw = to_fmpq_mat(Szs), to_fmpq_mat(Sss)
    SoiB = Soq.solve(Bq)
    return Bq.transpose() * SoiB, SoiB.transpose() * (Zq - Aq * Sraw), (Sraw + Sraw.transpose()) / 2


def unique_maximiser_ti(Bs, So, Atil, Szs, Sss) -> np.ndarray:
    """The time-invariant variant's unique ``[K k]`` (m, n+1): the exact solution of
    ``(sum_k Stilde_k kron H_k) vec F = vec(sum_k R_k)`` (column-major ``vec``), rounded once; arrays
    stacked over the ``T`` steps as in :func:`unique_maximiser`."""
    from flint import fmpq_mat

    T, n1, m = Bs.shape
    d = m * n1
    Q, r = fmpq_mat(d, d), fmpq_mat(d, 1)
    for k in range(T):
        H, R, S = _step_terms(Bs[k], So[k], Atil[k], Szs[k], Sss[k])
        for a in range(n1):
            for i in range(m):
                r[a * m + i, 0] += R[i, a]
                for b in range(n1):
                    s_ab = S[a, b]
                    for j in range(m):
                        Q[a * m + i, b * m + j] += s_ab * H[i, j]
    v = Q.solve(r)
    return to_float(fmpq_mat(m, n1, [v[a * m + i, 0] for i in range(m) for a in range(n1)]))
