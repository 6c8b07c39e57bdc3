"""Moments of a linear-Gaussian closed loop in closed form: forward pass, expected cost and
the expected KL against a reference policy (docs/math.md §6)."""

from __future__ import annotations

import numpy as np
from scipy.linalg import blas

from ..linalg import logdet_pd
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost, symmetrize
from .problem import Marginals, check_dims, check_init, ref_inverse, reference_chol


class ForwardWorkspace:
    """Buffers of :func:`forward_arrays` for one ``dynamics``, reusable by every call, and their
    per-step Fortran-ordered views, built once (``X[t].T`` of C-ordered stacks).

    The state moments are kept as ``M_k = [[Cov(s_k), E[s_k]], [0, 1]]`` (n+1, n+1), so that with
    ``Aaug = blkdiag(A + B K, 1)`` the recursion is ``M' = Aaug M Aaug^T + [[B Sigma B^T + W,
    B k + c], [0, 0]]``: two ``gemm`` per step.  ``Mc[k] = M_k^T`` (T+1, n+1, n+1) C-ordered, so
    ``Mc[k, :n, :n] = Cov`` and ``Mc[k, n, :n] = E^T``; ``Aaug`` (T, n+1, n+1) keeps its last row
    and column ``e_n``; ``Bt = B^T`` (T, m, n) C-contiguous.
    """

    def __init__(self, dynamics: LinearGaussianDynamics):
        T, n = dynamics.T, dynamics.n
        self.Bt = np.ascontiguousarray(np.swapaxes(dynamics.B, 1, 2))
        self.BK = np.empty((T, n, n))
        self.Aaug = np.zeros((T, n + 1, n + 1))
        self.Aaug[:, n, n] = 1.0
        self.Mc = np.empty((T + 1, n + 1, n + 1))
        self.tmp = np.empty((n + 1, n + 1), order="F")
        self.steps = [(self.Aaug[t].T, self.Mc[t].T, self.Mc[t + 1].T) for t in range(T)]


def forward_arrays(dynamics: LinearGaussianDynamics, K, k, S, mu0, P0,
                   ws: ForwardWorkspace | None = None) -> Marginals:
    """:func:`forward` on arrays (no validation); ``ws`` a :class:`ForwardWorkspace` of
    ``dynamics`` to reuse (none of the returned arrays is a view of it)."""
    T, n = dynamics.T, dynamics.n
    A, B = dynamics.A, dynamics.B
    if ws is None:
        ws = ForwardWorkspace(dynamics)
    Aaug, Mc, tmp = ws.Aaug, ws.Mc, ws.tmp
    np.matmul(B, K, out=ws.BK)
    np.add(A, ws.BK, out=Aaug[:, :n, :n])  # closed-loop state matrices A + B K
    # The products are not exactly symmetric; the covariances are symmetrised once at the end (the
    # symmetric part of the recursion does not depend on the antisymmetric roundoff).  The last
    # row of M stays exactly (0, ..., 0, 1).
    Mc[0, :n, :n] = P0
    Mc[0, n, :n] = mu0
    Mc[:, :, n] = 0.0
    Mc[0, n, n] = 1.0
    Mc[1:, :n, :n] = (B @ S) @ ws.Bt + dynamics.cov  # (contiguous operands: numpy's batched matmul is faster)
    Mc[1:, n, :n] = (B @ k[:, :, None])[:, :, 0] + dynamics.c
    dgemm = blas.dgemm
    for Aa, M, Mn in ws.steps:  # Aa = Aaug^T, M, Mn in Fortran order
        dgemm(1.0, Aa, M, 0.0, tmp, 1, 0, 1)  # Aaug M
        dgemm(1.0, tmp, Aa, 1.0, Mn, 0, 0, 1)  # M' = Aaug M Aaug^T + prefill
    cov = symmetrize(Mc[:, :n, :n])
    mean = np.ascontiguousarray(Mc[:, n, :n])
    sa_cov = cov[:T] @ np.ascontiguousarray(np.swapaxes(K, 1, 2))  # Cov(s, a) = P K^T, (T, n, m)
    a_mean = (K @ mean[:T, :, None])[:, :, 0] + k
    a_cov = symmetrize(K @ sa_cov + S)
    return Marginals(mean, cov, a_mean, a_cov, sa_cov)


def forward(dynamics: LinearGaussianDynamics, policy: LinearGaussianPolicy, mu0, P0) -> Marginals:
    """State-action marginals of ``policy`` on ``dynamics`` from ``s_0 ~ N(mu0, P0)``.

    ``E[s_{k+1}] = (A + B K) E[s_k] + B k + c``,
    ``Cov(s_{k+1}) = (A + B K) P_k (A + B K)^T + B Sigma B^T + W``; action moments
    ``E[a] = K E[s] + k``, ``Cov(a) = K P K^T + Sigma``, ``Cov(s, a) = P K^T``.
    """
    T, n, m = check_dims(dynamics, policy=policy)
    mu0, P0 = check_init(mu0, P0, n)
    return forward_arrays(dynamics, policy.K, policy.k, policy.cov, mu0, P0)


def expected_cost_marg(cost: QuadraticCost, marg: Marginals) -> np.ndarray:
    n, T = cost.n, cost.T
    zbar = np.concatenate([marg.mean[:T], marg.a_mean], axis=1)
    C = cost.C
    # tr(C Cov(z)) with Cov(z) = [[P, Psa], [Psa^T, Pa]] (C symmetric)
    tr = (
        np.einsum("tij,tij->t", C[:, :n, :n], marg.cov[:T])
        + 2.0 * np.einsum("tij,tij->t", C[:, :n, n:], marg.sa_cov)
        + np.einsum("tij,tij->t", C[:, n:, n:], marg.a_cov)
    )
    quad = np.einsum("ti,ti->t", (C @ zbar[:, :, None])[:, :, 0], zbar)
    return 0.5 * tr + 0.5 * quad + np.einsum("ti,ti->t", zbar, cost.c) + cost.c0


def expected_cost(dynamics, cost, policy, mu0, P0) -> np.ndarray:
    """(T,) closed-form ``E[l_k(s_k, a_k)] = 1/2 tr(C_k Cov(z_k)) + l_k(E[z_k])``."""
    check_dims(dynamics, cost=cost, policy=policy)
    return expected_cost_marg(cost, forward(dynamics, policy, mu0, P0))


def kl_batched(K, k, S, logdetS, Kh, kh, Shinv, logdetSh, mean, cov) -> np.ndarray:
    """(T,) ``E_{s~N(mean, cov)} KL(N(K s + k, S) || N(Kh s + kh, Sh))``.

    ``KL = 1/2 [tr(Sh^-1 S) - m + log|Sh| - log|S| + (dK mu + dk)^T Sh^-1 (dK mu + dk)
    + tr(dK^T Sh^-1 dK P)]`` with ``dK = K - Kh``, ``dk = k - kh``.
    """
    T, m, _ = K.shape
    dK = K - Kh
    dm = (dK @ mean[:T, :, None])[:, :, 0] + (k - kh)
    tr1 = np.einsum("tij,tij->t", Shinv, S)
    RdK = Shinv @ dK
    quad = np.einsum("tij,tij->t", RdK @ cov[:T], dK) + np.einsum("ti,ti->t", (Shinv @ dm[:, :, None])[:, :, 0], dm)
    return 0.5 * (tr1 - m + logdetSh - logdetS + quad)


def kl_divergence(dynamics, policy, reference, mu0, P0) -> np.ndarray:
    """(T,) ``KL_k = E_{p(s_k)} KL(p(.|s_k) || phat(.|s_k))`` in closed form.

    ``p(s_k)`` is the state marginal of ``policy`` (it enters through the gain difference
    ``K - Kh``); ``inf`` where the policy covariance is singular.
    """
    check_dims(dynamics, policy=policy, reference=reference)
    Lh = reference_chol(reference)
    Shinv, logdetSh = ref_inverse(Lh)
    marg = forward(dynamics, policy, mu0, P0)
    logdetS = logdet_pd(policy.cov)
    return kl_batched(policy.K, policy.k, policy.cov, logdetS, reference.K, reference.k, Shinv, logdetSh,
                       marg.mean, marg.cov)
