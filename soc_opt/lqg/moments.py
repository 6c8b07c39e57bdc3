"""Moments of a linear-Gaussian closed loop in closed form: forward pass, expected cost and
the expected KL against a reference policy (SPEC §6)."""

from __future__ import annotations

import numpy as np
from scipy.linalg import blas

from ..linalg import logdet_pd
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost, symmetrize
from .problem import Marginals, check_dims, check_init, ref_inverse, reference_chol


def forward_arrays(dynamics: LinearGaussianDynamics, K, k, S, mu0, P0, Bt=None) -> Marginals:
    """:func:`forward` on arrays (no validation); ``Bt`` is ``B^T`` (T, m, n) C-contiguous if the
    caller has it (``KLProblem.Bt``)."""
    T, n = dynamics.T, dynamics.n
    A, B = dynamics.A, dynamics.B
    if Bt is None:
        Bt = np.ascontiguousarray(np.swapaxes(B, 1, 2))
    Acl = A + B @ K  # (T, n, n) closed-loop state matrices
    # state moments as one (T+1, n+1, n) array, rows [Cov(s_k); E[s_k]^T]: per step
    # [Cov'; E'^T] = blkdiag(Acl, 1) [Cov; E^T] Acl^T + [B Sigma B^T + W; (B k + c)^T].
    # The products are not exactly symmetric; the covariances are symmetrised once at the end (the
    # symmetric part of the recursion does not depend on the antisymmetric roundoff).
    # Per step two BLAS calls on the Fortran-ordered views Cm[t].T = [Cov | E] (n, n+1) of the
    # C-ordered stack: Tmp = Acl [Cov | E], then Cm[t+1].T += Tmp blkdiag(Acl, 1)^T (prefilled with
    # the additive terms).
    Aaug = np.zeros((T, n + 1, n + 1))
    Aaug[:, :n, :n] = Acl
    Aaug[:, n, n] = 1.0
    Cm = np.empty((T + 1, n + 1, n))
    Cm[0, :n] = P0
    Cm[0, n] = mu0
    Cm[1:, :n] = (B @ S) @ Bt + dynamics.cov  # (contiguous operands: numpy's batched matmul is faster)
    Cm[1:, n] = (B @ k[:, :, None])[:, :, 0] + dynamics.c
    dgemm = blas.dgemm
    tmp = np.empty((n, n + 1), order="F")
    for t in range(T):
        dgemm(1.0, Acl[t].T, Cm[t].T, 0.0, tmp, 1, 0, 1)  # Acl [Cov | E]  (Acl[t].T is Acl^T in F order)
        dgemm(1.0, tmp, Aaug[t].T, 1.0, Cm[t + 1].T, 0, 0, 1)
    cov = symmetrize(Cm[:, :n])
    mean = np.ascontiguousarray(Cm[:, n])
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
