"""The Gaussian core's filter and smoother (docs/math.md §4): the preparation of the model, the numpy
recursions (the reference) and the calls into the compiled kernels (:mod:`soc_opt.lgssm`'s module docstring)."""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import numpy as np

from .. import compiled as _compiled
from ..linalg import T as _T
from ..linalg import chol, right_cho_solve, tri_solve
from ..models import NotPositiveDefiniteError, ShapeError, symmetrize
from .model import Filtered, Params, Posterior

__all__ = ["kalman_filter", "rts_smoother", "log_likelihood"]

_LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------- preparation


class _Prepared(NamedTuple):
    """Time-major arrays of the decorrelated model; ``B`` is ``()`` (shared) or ``(M,)``."""

    F: np.ndarray  # (T, *B, n, n) decorrelated F'
    Q: np.ndarray  # (T, *B, n, n) decorrelated Q'
    H: np.ndarray  # (K, *B, p, n)
    R: np.ndarray  # (K, *B, p, p)
    b: np.ndarray  # (T, M, n) decorrelated bias b' (data dependent)
    d: np.ndarray  # (K, M, p)
    y: np.ndarray  # (K, M, p)
    mu0: np.ndarray  # (M, n)
    P0: np.ndarray  # (*B, n, n)
    batch: tuple


def _time_major(name: str, x, shared_ndim: int, M: int, lead: tuple) -> tuple[np.ndarray, bool]:
    """``x`` shared ``lead + tail`` or per sequence ``(M,) + lead + tail``, returned time first."""
    x = np.asarray(x, dtype=float)
    if x.ndim == shared_ndim:
        ok, per = x.shape[: len(lead)] == lead, False
    elif x.ndim == shared_ndim + 1:
        ok, per = x.shape[: len(lead) + 1] == (M,) + lead, True
        if ok and lead:
            x = np.moveaxis(x, 0, 1)
    else:
        ok, per = False, False
    if not ok:
        raise ShapeError(f"lgssm: {name} has shape {x.shape}; expected leading axes {lead} or {(M,) + lead}")
    return x, per


def _prepare(params: Params, y, per_sequence: bool = False) -> _Prepared:
    if not isinstance(params, Params):
        raise TypeError(f"params must be an lgssm.Params, got {type(params).__name__}")
    y = np.asarray(y, dtype=float)
    if y.ndim != 3:
        raise ShapeError(f"lgssm: observations y must have shape (M, K, p), got {y.shape}")
    M, K, p = y.shape
    dyn, em, ini = params.dynamics, params.emissions, params.initial
    F0 = np.asarray(dyn.weights, dtype=float)
    T, n = F0.shape[-3], F0.shape[-1]
    if K not in (T, T + 1):
        raise ShapeError(f"lgssm: y has K={K} steps; the dynamics have T={T} (K must be T or T+1)")
    F, pF = _time_major("dynamics.weights", F0, 3, M, (T,))
    Q, pQ = _time_major("dynamics.cov", dyn.cov, 3, M, (T,))
    b, _ = _time_major("dynamics.bias", dyn.bias, 2, M, (T,))
    H, pH = _time_major("emissions.weights", em.weights, 3, M, (K,))
    R, pR = _time_major("emissions.cov", em.cov, 3, M, (K,))
    d, _ = _time_major("emissions.bias", em.bias, 2, M, (K,))
    P0, pP = _time_major("initial.cov", ini.cov, 2, M, ())
    mu0, _ = _time_major("initial.mean", ini.mean, 1, M, ())
    if F.shape[-2:] != (n, n) or Q.shape[-2:] != (n, n) or H.shape[-2:] != (p, n) or R.shape[-2:] != (p, p) \
            or b.shape[-1] != n or d.shape[-1] != p or P0.shape[-2:] != (n, n) or mu0.shape[-1] != n:
        raise ShapeError(f"lgssm: inconsistent sizes (state n={n}, observation p={p}): F {F.shape}, Q {Q.shape}, "
                         f"H {H.shape}, R {R.shape}, b {b.shape}, d {d.shape}, P0 {P0.shape}, mu0 {mu0.shape}")
    per = per_sequence or pF or pQ or pH or pR or pP
    b = np.broadcast_to(b if b.ndim == 3 else b[:, None], (T, M, n))
    d = np.broadcast_to(d if d.ndim == 3 else d[:, None], (K, M, p))
    mu0 = np.broadcast_to(mu0, (M, n))
    yt = np.swapaxes(y, 0, 1)
    if params.noise_cross_cov is not None and np.any(params.noise_cross_cov):  # (all-zero C: independent noises)
        C, pC = _time_major("noise_cross_cov", params.noise_cross_cov, 3, M, (T,))
        if C.shape[-2:] != (n, p):
            raise ShapeError(f"lgssm: noise_cross_cov must end in ({n}, {p}), got {C.shape}")
        per = per or pC
        if per:
            F, Q, H, R, C = (x if f else x[:, None] for x, f in ((F, pF), (Q, pQ), (H, pH), (R, pR), (C, pC)))
            pF = pQ = pH = pR = True
        Ht, Rt = H[:T], R[:T]
        G = C / Rt if p == 1 else right_cho_solve(C, chol(Rt, "emission covariance R"))  # C R^{-1}
        F = F - _mm(G, Ht)
        Q = symmetrize(Q - _mm(G, _T(C)))
        r = yt[:T] - d[:T]  # (T, M, p)
        b = b + (_mm(r[..., None, :], _T(G)))[..., 0, :] if G.ndim == 4 else b + _mm(r, _T(G))
    if per:  # shared matrices get a unit sequence axis, so that stacks over time broadcast against per-sequence ones
        F, Q, H, R = (x if f else x[:, None] for x, f in ((F, pF), (Q, pQ), (H, pH), (R, pR)))
    return _Prepared(F, Q, H, R, b, d, yt, mu0, P0, (M,) if per else ())


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` (batched); an outer product (inner size 1) by broadcasting, the same numbers without a
    matrix-product call per matrix of the stack."""
    return A * B if A.shape[-1] == 1 else A @ B


def _mv(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``A x`` for ``x (M, j)`` and ``A (i, j)`` (shared) or ``(M, i, j)`` (per sequence)."""
    return x @ A.T if A.ndim == 2 else (A @ x[:, :, None])[:, :, 0]


# --------------------------------------------------------------------------- filter


class _Pass(NamedTuple):
    """Forward pass, time-major (sequence-major when ``compiled`` is set): everything :func:`rts_smoother` needs."""

    pm: np.ndarray  # (T+1, M, n) predicted means
    Pp: np.ndarray  # (T+1, *B, n, n)
    fm: np.ndarray  # (K, M, n) filtered means
    Pf: np.ndarray  # (K, *B, n, n)
    loglik: np.ndarray  # (M,)
    prep: _Prepared
    compiled: np.ndarray | None = None  # F P^f (M, T, n, n) for the compiled smoother (_forward_compiled)


def _setup(params: Params, y, linearize: Callable | None) -> _Prepared:
    if linearize is not None and params.noise_cross_cov is not None:
        raise ValueError("lgssm: an extended filter (linearize) takes independent noises (noise_cross_cov=None)")
    return _prepare(params, y, per_sequence=linearize is not None)


def _compiled_path(pr: _Prepared, kernels: str | None) -> bool:
    """Whether this model runs in the compiled kernels: covariances per sequence and numba chosen."""
    return bool(pr.batch) and _compiled.backend(kernels) == "numba"


def _forward(params: Params, y, linearize: Callable | None, kernels: str | None = None) -> _Pass:
    pr = _setup(params, y, linearize)
    return _forward_compiled(pr, linearize) if _compiled_path(pr, kernels) else _forward_numpy(pr, linearize)


def _forward_numpy(pr: _Prepared, linearize: Callable | None) -> _Pass:
    """The forward pass in numpy (module docstring, steps 2-3): per step, the extended filter's
    linearisation (:func:`_linearize_step`), the measurement update in one of its forms
    (:func:`_update_information`, :func:`_update_scalar`, :func:`_update_covariance`) and the prediction
    (:func:`_predict`); then the means and ``log p(Y)`` for all steps at once (:func:`_means`)."""
    F, Q, H, R, b, d, yt, batch = pr.F, pr.Q, pr.H, pr.R, pr.b, pr.d, pr.y, pr.batch
    T, K, M, n, p = F.shape[0], yt.shape[0], yt.shape[1], F.shape[-1], yt.shape[2]
    extended = linearize is not None
    if extended:
        H, d = np.empty((K, M, p, n)), np.empty((K, M, p))
    FT, HT = _T(F), _T(H)
    # 2-D products by ndarray.dot (shared covariances): a third of matmul's call overhead at these sizes
    mm = np.matmul if batch else np.ndarray.dot
    Pp = np.empty((T + 1,) + batch + (n, n))
    Pf = np.empty((K,) + batch + (n, n))
    Pp[0] = pr.P0
    info = _information(H, R, n, p, extended)
    eye = np.eye(n)
    rs = R[:, 0, 0].tolist() if p == 1 and not batch and info is None else None  # scalar observation noises
    m, g = pr.mu0, None
    # The stacks are symmetrised once after the loop: inside it the covariances carry a rounding-level
    # antisymmetric part, which the products below propagate (bounded by the growth of the covariances
    # themselves) but never feed back into their symmetric part beyond rounding.
    for k in range(K):
        P = Pp[k]
        if extended:
            m = _linearize_step(k, m, g, linearize, F, b, H, d, yt, info)
        if info is not None:
            X, g = _update_information(P, k, info, eye, mm, extended)
        elif rs is not None:
            X = _update_scalar(P, H[k], HT[k], rs[k])
        else:
            X, g = _update_covariance(P, k, H[k], HT[k], R[k], mm, extended)
        Pf[k] = X
        if k < T:
            Pp[k + 1] = _predict(X, F[k], FT[k], Q[k], mm, batch)
    Pp, Pf = symmetrize(Pp), symmetrize(Pf)
    pm, fm, loglik = _means(F, b, H, HT, R, d, yt, Pp, Pf, info, pr.mu0, batch)
    return _Pass(pm, Pp, fm, Pf, loglik, pr._replace(H=H, d=d))


def _linearize_step(k: int, m, g, linearize: Callable, F, b, H, d, yt, info: _Information | None) -> np.ndarray:
    """Extended filter, step ``k``: the predicted means ``m_k (M, n)`` (the previous step's update with
    its gain ``g`` and prediction of ``m``; ``m_0 = mu0``), and ``H[k], d[k] = linearize(k, m_k)`` written
    into the stacks (with the information form's whitened rows ``Hw_k`` and ``G_k``).  Returns ``m_k``."""
    if k:
        m = _mv(F[k - 1], m + _mv(g, yt[k - 1] - _mv(H[k - 1], m) - d[k - 1])) + b[k - 1]
    H[k], d[k] = linearize(k, m)
    if info is not None:
        info.Hw[k] = Hw = info.W[k] @ H[k]
        info.G[k] = _T(Hw) @ Hw
    return m


def _update_information(P, k: int, info: _Information, eye, mm, gain: bool):
    """Information form (``p > n``, module docstring step 2): ``P^f = (P^{-1} + H^T R^{-1} H)^{-1}
    = (I + P G)^{-1} P``, in the ``n`` state dimensions.  Returns ``(P^f, K_k)`` with the gain
    ``K_k = P^f H^T R^{-1}`` when ``gain`` (the extended filter's), else ``None``."""
    X = np.linalg.solve(eye + mm(P, info.G[k]), P)
    return X, (X @ _T(info.Hw[k]) @ info.W[k] if gain else None)


def _update_scalar(P, Hk, HTk, r: float):
    """Covariance form for shared covariances and a scalar observation: ``P - a a^T / s`` with
    ``a = P H^T``, ``s = H P H^T + r``."""
    PHt = P.dot(HTk)
    return P - PHt.dot(PHt.T) / (Hk.dot(PHt)[0, 0] + r)


def _update_covariance(P, k: int, Hk, HTk, Rk, mm, gain: bool):
    """Covariance form (module docstring step 2): ``S = H P H^T + R``, ``P^f = P - P H^T S^{-1} H P``
    (``S`` scalar, or by its Cholesky factor ``L``: ``P - W^T W``, ``W = L^{-1} H P``).  Returns
    ``(P^f, K_k)`` with the gain ``K_k = P H^T S^{-1}`` when ``gain`` (the extended filter's), else ``None``."""
    PHt = mm(P, HTk)
    S = mm(Hk, PHt)
    S += Rk
    g = right_cho_solve(PHt, chol(S, f"innovation covariance S[{k}]")) if gain else None
    if S.shape[-1] == 1:
        return P - mm(PHt, PHt.swapaxes(-1, -2)) / S, g
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise NotPositiveDefiniteError(f"lgssm: innovation covariance S[{k}] is not positive definite") from None
    W = tri_solve(L, PHt.swapaxes(-1, -2))  # L^{-1} H P
    return P - mm(W.swapaxes(-1, -2), W), g


def _predict(X, Fk, FTk, Qk, mm, batch) -> np.ndarray:
    """Prediction: ``P_{k+1} = F'_k P^f_k F'^T_k + Q'_k``."""
    X = mm(mm(Fk, X), FTk) if batch else Fk.dot(X).dot(FTk)
    X += Qk
    return X


class _Information(NamedTuple):
    """The measurement in information form (when ``p > n``), whitened: ``W = L_R^{-1} (K, *, p, p)`` with
    ``R = L_R L_R^T`` (Cholesky), ``Hw = W H (K, *B, p, n)``, ``G = Hw^T Hw = H^T R^{-1} H (K, *B, n, n)``."""

    W: np.ndarray
    Hw: np.ndarray
    G: np.ndarray


def _information(H, R, n: int, p: int, extended: bool) -> _Information | None:
    """The update in the ``n`` state dimensions instead of the ``p`` observed ones when there are more
    observations than states and ``R`` is positive definite; ``None`` otherwise (covariance form)."""
    W = _whitening(R, n, p)
    if W is None:
        return None
    if extended:  # filled step by step as the emissions are linearised
        return _Information(W, np.empty(H.shape), np.empty(H.shape[:-2] + (n, n)))
    Hw = W @ H
    return _Information(W, Hw, _T(Hw) @ Hw)


def _whitening(R, n: int, p: int) -> np.ndarray | None:
    """``W = L_R^{-1}`` (the shape of ``R``) when the update goes in information form (``p > n``, ``R``
    positive definite), else ``None``."""
    if p <= n:
        return None
    # one R repeated over the leading axes (a broadcast view, stride 0: the §11 estimator's rho^2 I) is
    # factored once; the same matrix gives the same factor, so this is what factoring every copy gives
    shared = all(st == 0 for st in R.strides[:-2])
    R1 = R[(0,) * (R.ndim - 2)] if shared else R
    try:
        LR = np.linalg.cholesky(R1)
    except np.linalg.LinAlgError:
        return None
    # the whitening transform itself (a triangular solve per R, shared by every sequence and column of H)
    W = tri_solve(LR, np.broadcast_to(np.eye(p), LR.shape))
    return np.broadcast_to(W, R.shape) if shared else W


def _means(F, b, H, HT, R, d, yt, Pp, Pf, info: _Information | None, mu0, batch):
    """Predicted and filtered means and ``log p(Y)`` given the covariances (module docstring, step 3)."""
    T, (K, M, p), n = F.shape[0], yt.shape, F.shape[-1]
    r = yt - d  # (K, M, p)

    def mv(A, X):  # A_k X_k for stacks A (K, *B, i, j) and X (K, M, j)
        return (A @ X[..., None])[..., 0] if batch else _mm(X, _T(A))

    if info is not None:  # the gain K_k = P^f_k H_k^T R_k^{-1}, never formed (it is n x p)
        def gain(X):
            return mv(Pf, mv(_T(info.Hw), mv(info.W, X)))

        Abar = F - F @ (Pf[:T] @ info.G[:T])  # F'_k (I - K_k H_k), (T, *B, n, n)
    else:
        PHt = Pp[:K] @ HT  # (K, *B, n, p)
        S = H @ PHt + R  # innovation covariances (K, *B, p, p)
        if p == 1:
            Kg = PHt / S
        else:
            L = chol(symmetrize(S), "innovation covariance S")
            Kg = right_cho_solve(PHt, L)  # (K, *B, n, p)

        def gain(X):
            return mv(Kg, X)

        Abar = F - F @ _mm(Kg[:T], H[:T])
    u = b + mv(F, gain(r)[:T])  # m_{k+1} = Abar_k m_k + u_k
    pm = np.empty((T + 1, M, n))
    pm[0] = x = mu0
    if batch:
        for k in range(T):
            pm[k + 1] = x = (Abar[k] @ x[:, :, None])[:, :, 0] + u[k]
    else:
        AbarT = _T(Abar)
        for k in range(T):
            pm[k + 1] = x = x.dot(AbarT[k]) + u[k]
    mK = pm[:K]
    v = r - mv(H, mK)  # innovations (K, M, p)
    if info is not None:
        # log|S| = log|R| + log|I + G P| and v^T S^{-1} v = v^T R^{-1} v - g^T P^f g, g = H^T R^{-1} v (Woodbury)
        w = mv(info.W, v)  # whitened innovations
        g = mv(_T(info.Hw), w)
        Pg = mv(Pf, g)
        fm = mK + Pg
        logdet = -2.0 * np.log(np.diagonal(info.W, axis1=-2, axis2=-1)).sum(-1) + \
            np.linalg.slogdet(np.eye(n) + info.G @ Pp[:K])[1]
        ll = (logdet if batch else logdet[:, None]) + (w * w).sum(-1) - (g * Pg).sum(-1)
    else:
        fm = mK + gain(v)
        if p == 1:
            s = S[..., 0, 0] if batch else S[:, None, 0, 0]  # (K, M) or (K, 1)
            ll = np.log(s) + v[..., 0] ** 2 / s
        else:
            w = (np.linalg.solve(L, v[..., None])[..., 0]) if batch else _T(np.linalg.solve(L, _T(v)))
            logdet = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
            ll = (logdet if batch else logdet[:, None]) + (w * w).sum(-1)
    loglik = -0.5 * (K * p * _LOG_2PI + ll.sum(0))
    return pm, fm, np.broadcast_to(loglik, (M,)).copy()


def _c(x, cut: bool = True) -> np.ndarray:
    """A time-major array ``(K, M, ...)`` of the prepared model as the kernels take it: sequence-major
    ``(M, K, ...)``, writable, C-ordered and, with ``cut`` (the matrices), each of the two leading axes
    that repeats one entry (stride 0, a broadcast) cut to length 1 (the kernels index such an axis at 0).
    An array that was sequence-major to begin with (the §11 smoother's emissions) is not copied."""
    x = np.swapaxes(np.asarray(x, dtype=float), 0, 1)
    if cut:
        x = x[tuple(slice(0, 1) if st == 0 and sz > 1 else slice(None) for st, sz in zip(x.strides[:2], x.shape[:2]))]
    x = np.ascontiguousarray(x)
    return x if x.flags.writeable else x.copy()


def _raise(status):
    """Raise what the numpy path raises for a compiled kernel's ``status`` (:mod:`soc_opt.compiled.lgssm_kernels`)."""
    code, k = int(status[0]), int(status[1])
    if code == 1:
        raise NotPositiveDefiniteError(f"lgssm: innovation covariance S[{k}] is not positive definite")
    if code == 2:
        raise np.linalg.LinAlgError(f"lgssm: I + P G singular at step {k} (information form)")
    if code == 3:
        raise NotPositiveDefiniteError(
            f"predicted covariance P[{k}] (Cov(z_{k} | y_0..y_{k - 1})) is not positive definite")


class _KernelArgs(NamedTuple):
    """The prepared model as the compiled kernels take it (:mod:`soc_opt.compiled.lgssm_kernels`)."""

    F: np.ndarray
    FT: np.ndarray
    Q: np.ndarray
    b: np.ndarray
    H: np.ndarray
    d: np.ndarray
    y: np.ndarray
    W: np.ndarray
    wdiag: bool
    R: np.ndarray
    info: bool


def _kernel_args(pr: _Prepared, H=None, d=None) -> _KernelArgs:
    n, p = pr.F.shape[-1], pr.y.shape[2]
    W = _whitening(pr.R, n, p)
    info = W is not None
    W = _c(W) if info else np.zeros((1, 1, 1, 1))
    wdiag = bool(info and not np.any(W * (1.0 - np.eye(p))))
    F = _c(pr.F)
    return _KernelArgs(F, np.ascontiguousarray(_T(F)), _c(pr.Q), _c(pr.b, False), _c(pr.H) if H is None else H,
                       _c(pr.d, False) if d is None else d, _c(pr.y, False), W, wdiag, _c(pr.R), info)


def _forward_compiled(pr: _Prepared, linearize: Callable | None) -> _Pass:
    """The forward pass with covariances per sequence in the compiled kernel (module docstring); its
    arrays are sequence-major (``compiled`` is set), those of :func:`_forward_numpy` time-major."""
    from ..compiled import lgssm_kernels as kern

    T, (K, M, p), n = pr.F.shape[0], pr.y.shape, pr.F.shape[-1]
    H = d = None
    if linearize is not None:  # filled step by step, sequence-major
        H, d = np.empty((M, K, p, n)), np.empty((M, K, p))
    a = _kernel_args(pr, H, d)
    Pp, Pf = np.empty((M, T + 1, n, n)), np.empty((M, K, n, n))
    pm, fm = np.empty((M, T + 1, n)), np.empty((M, K, n))
    Pp[:, 0], pm[:, 0] = pr.P0, pr.mu0
    FPf, ll, status = np.empty((M, T, n, n)), np.zeros(M), np.zeros(2, dtype=np.int64)
    for k0, k1 in [(0, K)] if linearize is None else [(k, k + 1) for k in range(K)]:
        if linearize is not None:
            H[:, k0], d[:, k0] = linearize(k0, pm[:, k0].copy())
        kern.forward(k0, k1, T, a.F, a.FT, a.Q, a.b, a.H, a.d, a.y, a.W, a.wdiag, a.R, a.info, Pp, Pf, pm, fm, FPf, ll,
                     status)
        _raise(status)
    loglik = -0.5 * (K * p * _LOG_2PI + ll)
    return _Pass(pm, Pp, fm, Pf, loglik, pr._replace(H=np.swapaxes(a.H, 0, 1), d=np.swapaxes(a.d, 0, 1)), FPf)


def kalman_filter(params: Params, y, linearize: Callable | None = None, kernels: str | None = None) -> Filtered:
    """Filtered and predicted moments and ``log p(Y)`` of ``y (M, K, p)`` (module docstring, steps 1-3).

    ``linearize(k, m_k) -> (H_k (M, p, n), d_k (M, p))``: an extended filter, linearised at the
    predicted means ``m_k (M, n)``; the emissions of ``params`` are then ignored.  ``kernels``: the path
    of covariances per sequence (module docstring; ``None``: :func:`soc_opt.compiled.backend`).
    """
    fp = _forward(params, y, linearize, kernels)
    if fp.compiled is not None:  # sequence-major already
        return Filtered(fp.pm, fp.Pp, fp.fm, fp.Pf, fp.loglik)
    b = fp.prep.batch
    return Filtered(_seq_major(fp.pm), _seq_major(fp.Pp) if b else fp.Pp, _seq_major(fp.fm),
                    _seq_major(fp.Pf) if b else fp.Pf, fp.loglik)


def _seq_major(X: np.ndarray) -> np.ndarray:
    """A time-major ``(K, M, ...)`` array as ``(M, K, ...)`` (contiguous)."""
    return np.ascontiguousarray(np.swapaxes(X, 0, 1))


def log_likelihood(params: Params, y, kernels: str | None = None) -> np.ndarray:
    """``log p(y_0..y_{K-1})`` per sequence, ``(M,)`` (the filter pass only; ``kernels`` as in :func:`kalman_filter`)."""
    return _forward(params, y, None, kernels).loglik


# --------------------------------------------------------------------------- smoother


def rts_smoother(params: Params, y, linearize: Callable | None = None, kernels: str | None = None) -> Posterior:
    """Rauch-Tung-Striebel smoother of ``y (M, K, p)`` (module docstring, step 4); ``linearize`` and
    ``kernels`` as in :func:`kalman_filter`.  Raises :class:`~soc_opt.models.NotPositiveDefiniteError`
    when a predicted covariance is not positive definite."""
    pr = _setup(params, y, linearize)
    if _compiled_path(pr, kernels):
        return _smoother_compiled(pr, linearize)
    fp = _forward_numpy(pr, linearize)
    F, Q = fp.prep.F, fp.prep.Q
    Pp, Pf, pm, fm = fp.Pp, fp.Pf, fp.pm, fp.fm
    T, K = F.shape[0], fm.shape[0]
    M, n = pm.shape[1], pm.shape[2]
    eye = np.eye(n)
    try:
        np.linalg.cholesky(Pp[1:])
    except np.linalg.LinAlgError:
        bad = np.linalg.eigvalsh(Pp[1:])[..., 0].reshape(T, -1).min(1)
        k = int(np.argmax(bad <= 0)) + 1
        raise NotPositiveDefiniteError(
            f"predicted covariance P[{k}] (Cov(z_{k} | y_0..y_{k - 1})) is not positive definite") from None
    Pfk = Pf[:T]
    # J_k^T = P_{k+1}^{-1} F'_k P^f_k, (T, *B, n, n): P_{k+1} is positive definite (its Cholesky factor
    # above); one batched LU solve costs half the two triangular solves of linalg.cho_solve
    JT = np.linalg.solve(Pp[1:], F @ Pfk)
    J = _T(JT)
    IJF = eye - J @ F
    Cst = IJF @ Pfk @ _T(IJF) + J @ Q @ JT  # the P^s-independent part of P^s_k (symmetrised with P^s below)
    batch = fp.prep.batch
    cov = np.empty((T + 1,) + batch + (n, n))
    mean = np.empty((T + 1, M, n))
    if K == T + 1:
        cov[T], mean[T] = Pf[T], fm[T]
    else:
        cov[T], mean[T] = Pp[T], pm[T]
    off = fm[:T] - ((J @ pm[1:, :, :, None])[..., 0] if batch else pm[1:] @ JT)  # zs_k = J_k zs_{k+1} + off_k
    X, x = cov[T], mean[T]
    # linear in P^s: symmetrising the stack once at the end equals symmetrising every step
    if batch:
        for k in range(T - 1, -1, -1):
            cov[k] = X = J[k] @ X @ JT[k] + Cst[k]
            mean[k] = x = (J[k] @ x[:, :, None])[:, :, 0] + off[k]
    else:  # 2-D products by ndarray.dot, as in _forward
        for k in range(T - 1, -1, -1):
            cov[k] = X = J[k].dot(X).dot(JT[k]) + Cst[k]
            mean[k] = x = x.dot(JT[k]) + off[k]
    cov = symmetrize(cov)
    cross = cov[1:] @ JT
    if batch:
        cov, cross = _seq_major(cov), _seq_major(cross)
    return Posterior(_seq_major(mean), cov, cross, fp.loglik)


def _smoother_compiled(pr: _Prepared, linearize: Callable | None) -> Posterior:
    """:func:`rts_smoother` in the compiled kernels (sequence-major results): filter and smoother of one
    sequence after the other, or, for an extended filter, the forward pass of all sequences step by step
    and then the smoother."""
    from ..compiled import lgssm_kernels as kern

    T, (K, M, p), n = pr.F.shape[0], pr.y.shape, pr.F.shape[-1]
    cov, mean, cross = np.empty((M, T + 1, n, n)), np.empty((M, T + 1, n)), np.empty((M, T, n, n))
    status = np.zeros(2, dtype=np.int64)
    if linearize is None:
        a = _kernel_args(pr)
        P0 = np.ascontiguousarray(np.broadcast_to(pr.P0, (M if pr.P0.ndim == 3 else 1, n, n)))
        ll = np.zeros(M)
        kern.smooth(T, a.F, a.FT, a.Q, a.b, a.H, a.d, a.y, a.W, a.wdiag, a.R, a.info, P0,
                    np.ascontiguousarray(pr.mu0), cov, mean, cross, ll, status)
        _raise(status)
        return Posterior(mean, cov, cross, -0.5 * (K * p * _LOG_2PI + ll))
    fp = _forward_compiled(pr, linearize)
    last = (fp.Pf, fp.fm) if K == T + 1 else (fp.Pp, fp.pm)
    cov[:, T], mean[:, T] = last[0][:, T], last[1][:, T]
    kern.smoother(T, fp.Pp, fp.Pf, fp.pm, fp.fm, fp.compiled, cov, mean, cross, status)
    _raise(status)
    return Posterior(mean, cov, cross, fp.loglik)
