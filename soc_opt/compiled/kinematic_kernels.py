"""The kinematic filter's online measurement update, compiled (docs/math.md §11.3, item 2).

Per rollout (row) ``b``, with ``H = dh/dz(z^-)`` and ``h(z^-)`` evaluated by MuJoCo beforehand, the
nominal predicted information ``Lm`` and ``R = rho^2 I``::

    dz_b = (Lm + H_b^T H_b / rho^2)^{-1} H_b^T (s_b - h(z^-_b)) / rho^2

solved by Cholesky (the matrix is positive definite; the reference,
:meth:`soc_opt.noise.kinematic.filter.KinematicFilter.step`, solves it by LU, and an LU here takes over
should the Cholesky factorisation fail).  Each row is computed alone, so a row's result does not depend
on the batch it is in (the lockstep rollouts rely on it).
"""

from __future__ import annotations

import numpy as np

from . import jit
from .dense import chol_solve, cholesky, lu, lu_solve

__all__ = ["online_update"]


@jit
def online_update(s, hx, H, Lm, r2, out) -> bool:
    """``out[b] = dz_b`` (module docstring) for ``s, hx (B, n)``, ``H (B, n, nz)``, ``Lm (nz, nz)``;
    ``False`` when a row's matrix is singular (the caller raises what ``numpy.linalg.solve`` raises)."""
    B, n, nz = H.shape[0], H.shape[1], H.shape[2]
    A = np.empty((nz, nz))
    L = np.empty((nz, nz))
    g = np.empty((nz, 1))
    piv = np.empty(nz, dtype=np.int64)
    inv = 1.0 / r2
    for b in range(B):
        Hb = H[b]
        np.dot(Hb.T, Hb, A)
        for i in range(nz):
            for j in range(nz):
                A[i, j] = Lm[i, j] + A[i, j] * inv
            acc = 0.0
            for r in range(n):
                acc += Hb[r, i] * (s[b, r] - hx[b, r])
            g[i, 0] = acc * inv
        if cholesky(A, L):
            chol_solve(L, g)
        elif lu(A, piv):
            lu_solve(A, piv, g)
        else:
            return False
        for i in range(nz):
            out[b, i] = g[i, 0]
    return True
