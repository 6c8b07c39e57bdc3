"""The Gaussian core's recursions with covariances per sequence, compiled (docs/math.md §4; the §11.2
smoother's case).  :mod:`soc_opt.lgssm` prepares the model (decorrelation, whitening, shapes) and calls
these for ``lgssm`` with a sequence axis on a matrix; its numpy loops are the reference they are
tested against (``tests/test_compiled.py``).

Arrays are sequence-major and C-ordered; a matrix shared by the sequences or the steps has length 1
on that axis (``F (M|1, T|1, n, n)``, ``y (M, K, p)``, ...).  Per step ``k`` and sequence ``i`` (module docstring of
:mod:`soc_opt.lgssm`, steps 2-4, one sequence at a time instead of stacks over the sequences):

* the update in covariance form (``p <= n``): ``S = H P H^T + R = L L^T``, ``W = L^{-1} H P``,
  ``P^f = P - W^T W``, ``m^f = m + W^T L^{-1} v`` with ``v = y - H m - d``; ``log|S| = 2 sum log L_jj``;
* in information form (``p > n``, ``R`` whitened by ``Wr = L_R^{-1}``): ``Hw = Wr H``, ``G = Hw^T Hw``,
  ``P^f = (I + P G)^{-1} P`` (LU), ``g = Hw^T Wr v``, ``m^f = m + P^f g``, ``log|S| = log|R| + log|I + P G|``,
  ``v^T S^{-1} v = |Wr v|^2 - g^T P^f g``;
* the prediction ``P_{k+1} = F P^f F^T + Q``, ``m_{k+1} = F m^f + b`` (``F P^f`` kept for the smoother);
* the smoother ``J^T = P_{k+1}^{-1} F P^f`` (Cholesky), ``Cov(z_{k+1}, z_k) = P^s_{k+1} J^T`` and
  ``P^s_k = P^f_k + J (P^s_{k+1} - P_{k+1}) J^T = P^f_k + J (Cov(z_{k+1}, z_k) - F P^f_k)`` (as
  ``P_{k+1} J^T = F P^f_k``), ``zs_k = m^f_k + J (zs_{k+1} - m_{k+1})``.

Two differences from the reference, both at rounding level (``tests/test_compiled.py``): the smoothed
covariance in the textbook form above (two matrix products per step instead of the reference's
Joseph-like sum of positive semidefinite terms, which needs five; equal in exact arithmetic), and
covariances symmetrised as they are made (the reference symmetrises its stacks once, after the loops).

:func:`smooth` runs the filter and the smoother of one sequence after the other, so that a sequence's
filtered and predicted covariances are read back while they are still in the cache (the reference
makes each pass over all sequences); :func:`forward` and :func:`smoother` are the two passes apart, for
the extended filter (whose linearisation needs every sequence's prediction at each step) and for
:func:`soc_opt.lgssm.kalman_filter`.  A failure is reported in ``status`` (``[code, k]``: 1 an innovation
covariance not positive definite, 2 a singular ``I + P G``, 3 a predicted covariance not positive
definite), and the caller raises the error the numpy path raises.
"""

from __future__ import annotations

import math

import numpy as np

from . import jit
from .dense import chol_solve, chol_solve_lower, cholesky, lu, lu_solve, symmetrize

__all__ = ["forward", "smoother", "smooth"]


@jit
def _at(length, j):
    """Index ``j`` on an axis of ``length`` 1 (shared) or the full length."""
    return j if length > 1 else 0


@jit
def _work(n, p):
    """Scratch arrays of :func:`_update`."""
    return (np.empty((p, n)), np.empty((n, n)), np.empty((n, n)), np.empty(n, dtype=np.int64), np.empty(p),
            np.empty(p), np.empty(n), np.empty(n), np.empty((p, p)), np.empty((p, p)), np.empty((p, n)))


@jit
def _update(k, i, P, m, H, d, y, W, wdiag, R, info, X, fm, work):
    """The measurement update of sequence ``i`` at step ``k`` (module docstring): ``X = P^f``, ``fm = m^f``;
    returns ``(code, log|S| + v^T S^{-1} v)`` with ``code`` 0, or 1 / 2 on a failure."""
    Hw, G, A, piv, v, w, g, Pg, S, L, Wm = work
    n, p = P.shape[0], y.shape[2]
    Hk = H[_at(H.shape[0], i), _at(H.shape[1], k)]
    dk = d[i, k]
    yk = y[i, k]
    for r in range(p):
        acc = yk[r] - dk[r]
        for c in range(n):
            acc -= Hk[r, c] * m[c]
        v[r] = acc
    if info:
        Wk = W[_at(W.shape[0], i), _at(W.shape[1], k)]
        logdet = 0.0
        if wdiag:
            for r in range(p):
                wr = Wk[r, r]
                logdet -= 2.0 * math.log(abs(wr))
                w[r] = wr * v[r]
                for c in range(n):
                    Hw[r, c] = wr * Hk[r, c]
        else:
            for r in range(p):
                logdet -= 2.0 * math.log(abs(Wk[r, r]))
            np.dot(Wk, Hk, Hw)
            np.dot(Wk, v, w)
        np.dot(Hw.T, Hw, G)  # H^T R^{-1} H
        np.dot(P, G, A)
        for j in range(n):
            A[j, j] += 1.0
        X[:, :] = P
        if not lu(A, piv):
            return 2, 0.0
        lu_solve(A, piv, X)  # P^f = (I + P G)^{-1} P
        symmetrize(X)
        for j in range(n):
            logdet += math.log(abs(A[j, j]))
        np.dot(Hw.T, w, g)
        quad = 0.0
        for r in range(p):
            quad += w[r] * w[r]
        for a in range(n):  # P^f g, P^f's columns in turn (P^f symmetric)
            Pg[a] = 0.0
        for c in range(n):
            u = g[c]
            for a in range(n):
                Pg[a] += X[c, a] * u
        for a in range(n):
            quad -= g[a] * Pg[a]
            fm[a] = m[a] + Pg[a]
        return 0, logdet + quad
    Rk = R[_at(R.shape[0], i), _at(R.shape[1], k)]
    for r in range(p):  # (H P)[r] = sum_c H[r, c] P[c] (P symmetric: the rows of (P H^T)^T)
        for a in range(n):
            Wm[r, a] = 0.0
        for c in range(n):
            h = Hk[r, c]
            for a in range(n):
                Wm[r, a] += h * P[c, a]
    for r in range(p):  # S = H P H^T + R
        for t in range(p):
            acc = Rk[r, t]
            for c in range(n):
                acc += Wm[r, c] * Hk[t, c]
            S[r, t] = acc
    if not cholesky(S, L):
        return 1, 0.0
    chol_solve_lower(L, Wm)  # W = L^{-1} H P
    logdet = 0.0
    quad = 0.0
    for r in range(p):
        for t in range(r):
            v[r] -= L[r, t] * v[t]
        v[r] /= L[r, r]
        logdet += 2.0 * math.log(L[r, r])
        quad += v[r] * v[r]
    if p > 4:
        np.dot(Wm.T, Wm, X)
        for a in range(n):
            for c in range(n):
                X[a, c] = P[a, c] - X[a, c]
        symmetrize(X)
    else:  # P - W^T W, the lower triangle mirrored (exactly symmetric, as P is)
        for a in range(n):
            for c in range(a + 1):
                acc = P[a, c]
                for r in range(p):
                    acc -= Wm[r, a] * Wm[r, c]
                X[a, c] = acc
                X[c, a] = acc
    for a in range(n):
        fm[a] = m[a]
    for r in range(p):
        u = v[r]
        for a in range(n):
            fm[a] += Wm[r, a] * u
    return 0, logdet + quad


@jit
def _predict(k, i, F, FT, Q, b, X, fm, FP, Pn, pn):
    """``FP = F P^f``, ``Pn = F P^f F^T + Q``, ``pn = F m^f + b`` of sequence ``i`` at step ``k``."""
    n = X.shape[0]
    FTk = FT[_at(FT.shape[0], i), _at(FT.shape[1], k)]
    Qk = Q[_at(Q.shape[0], i), _at(Q.shape[1], k)]
    np.dot(F[_at(F.shape[0], i), _at(F.shape[1], k)], X, FP)
    np.dot(FP, FTk, Pn)
    for a in range(n):
        for c in range(n):
            Pn[a, c] += Qk[a, c]
    symmetrize(Pn)
    for a in range(n):
        pn[a] = b[i, k, a]
    for c in range(n):  # F m^f, F's columns in turn (the rows of F^T)
        u = fm[c]
        for a in range(n):
            pn[a] += FTk[c, a] * u


@jit
def _back(Pn, FP, Pf, fm, pn, Cn, mn, L, JT, D, C, Cr, mk) -> bool:
    """One smoother step (module docstring): ``C = P^s_k``, ``Cr = Cov(z_{k+1}, z_k)``, ``mk = zs_k`` from
    ``Pn = P_{k+1}``, ``FP = F P^f_k``, ``Pf = P^f_k``, ``fm = m^f_k``, ``pn = m_{k+1}``, ``Cn = P^s_{k+1}``,
    ``mn = zs_{k+1}``; ``False`` when ``P_{k+1}`` is not positive definite."""
    n = Pn.shape[0]
    if not cholesky(Pn, L):
        return False
    JT[:, :] = FP
    chol_solve(L, JT)  # J^T = P_{k+1}^{-1} F P^f
    np.dot(Cn, JT, Cr)
    for a in range(n):
        for c in range(n):
            D[a, c] = Cr[a, c] - FP[a, c]
    np.dot(JT.T, D, C)
    for a in range(n):
        for c in range(n):
            C[a, c] += Pf[a, c]
    symmetrize(C)
    for a in range(n):
        mk[a] = fm[a]
    for c in range(n):  # J (zs_{k+1} - m_{k+1}), J's columns in turn (the rows of J^T)
        u = mn[c] - pn[c]
        for a in range(n):
            mk[a] += JT[c, a] * u
    return True


@jit
def forward(k0, k1, T, F, FT, Q, b, H, d, y, W, wdiag, R, info, Pp, Pf, pm, fm, FPf, ll, status):
    """Filter steps ``k0 .. k1-1`` of every sequence (module docstring); ``FT`` holds ``F^T`` (C-ordered).

    The outputs are sequence-major: ``Pp (M, T+1, n, n)``, ``Pf (M, K, n, n)``, ``pm (M, T+1, n)``,
    ``fm (M, K, n)``, ``FPf (M, T, n, n)``.  Reads ``Pp[:, k0]``, ``pm[:, k0]``; writes ``Pf[:, k], fm[:, k]``
    and, for ``k < T``, ``Pp[:, k+1], pm[:, k+1], FPf[:, k]``; adds ``log|S_k| + v_k^T S_k^{-1} v_k`` to ``ll``.
    ``info``: information form with the whitening ``W (M|1, K|1, p, p)`` (``wdiag``: ``W`` diagonal); else
    covariance form with ``R``.  Returns after writing ``status`` on the first failure.
    """
    M, n, p = pm.shape[0], pm.shape[2], y.shape[2]
    work = _work(n, p)
    for i in range(M):
        for k in range(k0, k1):
            code, term = _update(k, i, Pp[i, k], pm[i, k], H, d, y, W, wdiag, R, info, Pf[i, k], fm[i, k], work)
            if code:
                status[0], status[1] = code, k
                return
            ll[i] += term
            if k < T:
                _predict(k, i, F, FT, Q, b, Pf[i, k], fm[i, k], FPf[i, k], Pp[i, k + 1], pm[i, k + 1])


@jit
def smoother(T, Pp, Pf, pm, fm, FPf, cov, mean, cross, status):
    """RTS pass of every sequence (module docstring; :func:`forward`'s sequence-major arrays) into
    ``cov (M, T+1, n, n)``, ``mean (M, T+1, n)``, ``cross (M, T, n, n)``, whose entry ``T`` the caller has
    set (filtered or predicted).  When a predicted covariance ``P_1 .. P_T`` is not positive definite,
    ``status = [3, k]`` names the first step that is not (the smallest ``k`` over the sequences), as the
    reference's check of them all does."""
    M, n = pm.shape[0], pm.shape[2]
    L, JT, D = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    for i in range(M):
        for k in range(T - 1, -1, -1):
            if not _back(Pp[i, k + 1], FPf[i, k], Pf[i, k], fm[i, k], pm[i, k + 1], cov[i, k + 1], mean[i, k + 1],
                         L, JT, D, cov[i, k], cross[i, k], mean[i, k]):
                _first_not_pd(Pp, L, status)
                return


@jit
def _first_not_pd(Pp, L, status):
    """``status = [3, k]`` for the first ``k >= 1`` at which a sequence's ``Pp[:, k]`` is not positive definite."""
    for k in range(1, Pp.shape[1]):
        for i in range(Pp.shape[0]):
            if not cholesky(Pp[i, k], L):
                status[0], status[1] = 3, k
                return


@jit
def smooth(T, F, FT, Q, b, H, d, y, W, wdiag, R, info, P0, mu0, cov, mean, cross, ll, status):
    """Filter and smoother of each sequence in turn (module docstring): ``P0 (M|1, n, n)``, ``mu0 (M, n)``;
    results as :func:`smoother`'s, ``ll`` as :func:`forward`'s.  On a failure ``status`` is set as those do
    (for a predicted covariance: the first step over the sequences smoothed so far, then the rest filtered)."""
    M, n, p, K = mu0.shape[0], mu0.shape[1], y.shape[2], y.shape[1]
    work = _work(n, p)
    Pp, Pf, FPf = np.empty((T + 1, n, n)), np.empty((K, n, n)), np.empty((T, n, n))
    pm, fm = np.empty((T + 1, n)), np.empty((K, n))
    L, JT, D = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    bad = -1
    for i in range(M):
        Pp[0] = P0[_at(P0.shape[0], i)]
        pm[0] = mu0[i]
        for k in range(K):
            code, term = _update(k, i, Pp[k], pm[k], H, d, y, W, wdiag, R, info, Pf[k], fm[k], work)
            if code:
                status[0], status[1] = code, k
                return
            ll[i] += term
            if k < T:
                _predict(k, i, F, FT, Q, b, Pf[k], fm[k], FPf[k], Pp[k + 1], pm[k + 1])
        if K == T + 1:
            cov[i, T], mean[i, T] = Pf[T], fm[T]
        else:
            cov[i, T], mean[i, T] = Pp[T], pm[T]
        for k in range(T - 1, -1, -1):
            if not _back(Pp[k + 1], FPf[k], Pf[k], fm[k], pm[k + 1], cov[i, k + 1], mean[i, k + 1], L, JT, D,
                         cov[i, k], cross[i, k], mean[i, k]):
                for kk in range(1, T + 1):
                    if not cholesky(Pp[kk], L):
                        bad = kk if bad < 0 else min(bad, kk)
                        break
                break
    if bad >= 0:
        status[0], status[1] = 3, bad
