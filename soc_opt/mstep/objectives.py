"""The paper's surrogate ``Lbar_k``, the exact-EM objective, their derivatives and the uniqueness
of the surrogate's maximiser (docs/math.md §5).

Notation (time step ``k``; the index is dropped inside formulas)
-----------------------------------------------------------------
``zeta = (s_{k+1}, y_k)`` and ``stilde = (s_k, 1)`` both have ``n+1`` components.  The
smoothed second moments (:class:`soc_opt.estep.Moments`) are ``Szz = E[zeta zeta^T]``,
``Szs = E[zeta stilde^T]`` and ``Stilde = Sss = E[stilde stilde^T]``.  The policy is
``phi = (F, Sigma)`` with ``F = [K k]`` (``m x (n+1)``) so that the mean action is ``F stilde``.
From the augmented model: ``B = Bs_k = [B_k; By_k]`` (``(n+1) x m``), ``A_s = As_k``,
``So = So_k`` and ``Atil = [A_s co_k]`` so that ``A_s s + co = Atil stilde``.

Surrogate (the paper's ``Lbar_k``)
----------------------------------
With ``z = (s, F stilde + L w)``, ``w ~ N(0, I)`` independent of the smoothed state::

    Lbar = -1/2 E[(zeta - Ao z - co)^T So^{-1} (zeta - Ao z - co)] - 1/2 log|So|
         = -1/2 tr(So^{-1} E[e e^T]) - 1/2 tr(H Sigma) - 1/2 log|So|,
    e = zeta - (Atil + B F) stilde,   H = B^T So^{-1} B.

Expanding ``E[e e^T]`` gives ``Lbar = c0 - 1/2 tr(H F Stilde F^T) + tr(F^T R) - 1/2 tr(H Sigma)``
with ``R = B^T So^{-1} E[(zeta - Atil stilde) stilde^T] = B^T So^{-1} (Szs - Atil Stilde)``.
Its gradient in ``F`` is ``R - H F Stilde``; its Hessian in ``vec(F)`` (column-major) is
``-(Stilde kron H)``, negative definite iff ``H > 0`` (``B`` full column rank) and ``Stilde > 0``
(equivalently ``P_k > 0``: ``P_k`` is the Schur complement of the corner 1 in ``Stilde``).
Hence the closed form ``F = H^{-1} R Stilde^{-1}``: Cholesky solves on well-conditioned steps, exact
rational arithmetic on ill-conditioned ones; where it is not unique, ``min_norm=True`` (the default)
returns ``H^+ R Stilde^+``, the minimum Frobenius-norm maximiser (``(S kron H)^+ = S^+ kron H^+``),
and ``min_norm=False`` raises a :class:`NonUniqueMaximizerError` naming the step
(:mod:`soc_opt.mstep.conditioning` decides which, docs/math.md §5 "Conditioning").
The time-invariant variant's normal equations ``sum_k H_k F Stilde_k = sum_k R_k`` read
``(sum_k Stilde_k kron H_k) vec F = vec(sum_k R_k)`` (the paper's ``M = sum_k M_k``).

Exact-EM objective (``objective="exact"``)
------------------------------------------
``exact_k = E[log N(zeta; M s + m, S)]`` with the action integrated out (docs/math.md §4):
``M stilde = (Atil + B F) stilde``, ``S = So + B Sigma B^T``.  Since
``N(zeta; M s + m, S) = int N(a; F stilde, Sigma) N(zeta; Atil stilde + B a, So) da``, Jensen's
inequality gives ``Lbar_k - (n+1)/2 log(2 pi) <= exact_k``: the paper's surrogate is (up to this
constant) a lower bound of the exact objective, and the gap is the expected KL divergence between
the action prior and its posterior.  Maximising ``sum_k exact_k`` is the M-step under which
``log p(Y)`` is provably non-decreasing (the EM lemma).

Its maximisation is in :mod:`soc_opt.mstep.exact_em`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .. import linalg as la
from ..estep import Moments, moments
from ..models import AugmentedModel, LinearGaussianPolicy, ShapeError, Smoothed, symmetrize

__all__ = [
    "GradHess",
    "LOG_2PI",
    "surrogate",
    "surrogate_from_moments",
    "exact_objective",
    "exact_objective_from_moments",
    "surrogate_grad_hess",
]

LOG_2PI = math.log(2.0 * math.pi)


class GradHess(NamedTuple):
    """Analytic derivatives of ``Lbar_k`` (``vec`` is column-major, i.e. ``order="F"``).

    grad:       (m(n+1),)             gradient w.r.t. ``vec([K k])``: ``vec(R - H F Stilde)``.
    hess:       (m(n+1), m(n+1))      Hessian w.r.t. ``vec([K k])``: ``-(Stilde kron H)``.
    grad_sigma: (m, m)                gradient w.r.t. ``Sigma``: ``-H/2`` (constant).
    """

    grad: np.ndarray
    hess: np.ndarray
    grad_sigma: np.ndarray


def min_eig_rel(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest eigenvalue and smallest/largest ratio (batched, symmetric)."""
    ev = np.linalg.eigvalsh(A)
    big = np.maximum(np.abs(ev).max(-1), np.finfo(float).tiny)
    return ev[..., 0], ev[..., 0] / big


# --------------------------------------------------------------------------- inputs


def policy_F(policy: LinearGaussianPolicy) -> np.ndarray:
    return np.concatenate([policy.K, policy.k[..., None]], axis=-1)


def check_moments(model: AugmentedModel, mom: Moments) -> None:
    if not isinstance(model, AugmentedModel):
        raise TypeError(f"model must be an AugmentedModel, got {type(model).__name__}")
    T, n1 = model.T, model.n + 1
    for name in ("Szz", "Szs", "Sss"):
        a = np.asarray(getattr(mom, name))
        if a.shape != (T, n1, n1):
            raise ShapeError(
                f"moments {name} must have shape (T, n+1, n+1) = ({T}, {n1}, {n1}) to match the model, got {a.shape}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(f"moments {name} contains NaN or inf")


def check_policy(model: AugmentedModel, policy: LinearGaussianPolicy, name: str = "policy") -> None:
    if not isinstance(policy, LinearGaussianPolicy):
        raise TypeError(f"{name} must be a LinearGaussianPolicy, got {type(policy).__name__}")
    want = (model.T, model.m, model.n)
    if policy.K.shape != want:
        raise ShapeError(f"{name} K must have shape (T, m, n) = {want} to match the model, got {policy.K.shape}")


def atil(model: AugmentedModel) -> np.ndarray:
    """(T, n+1, n+1) ``[A_s co]`` so that ``A_s s + co = Atil stilde``."""
    return np.concatenate([model.As, model.co[..., None]], axis=-1)


def _residual_second_moment(mom: Moments, Mt: np.ndarray) -> np.ndarray:
    """``E[(zeta - Mt stilde)(zeta - Mt stilde)^T]`` from the moments."""
    X = mom.Szs @ la.T(Mt)
    return symmetrize(mom.Szz - X - la.T(X) + Mt @ mom.Sss @ la.T(Mt))


@dataclass(frozen=True)
class _Stats:
    """Per-step quadratic form ``Lbar = const - 1/2 tr(H F S F^T) + tr(F^T R) - 1/2 tr(H Sigma)``."""

    H: np.ndarray  # (T, m, m)
    R: np.ndarray  # (T, m, n+1)
    S: np.ndarray  # (T, n+1, n+1)
    const: np.ndarray  # (T,)


def moment_stats(model: AugmentedModel, mom: Moments) -> _Stats:
    B, Atil = model.Bs, atil(model)
    Lo = la.chol(model.So, "augmented So")
    SoiB = la.cho_solve(Lo, B)
    H = symmetrize(la.T(B) @ SoiB)
    R = la.T(SoiB) @ (mom.Szs - Atil @ mom.Sss)
    E0 = _residual_second_moment(mom, Atil)
    const = -0.5 * la.tr(la.cho_solve(Lo, E0)) - 0.5 * la.logdet_chol(Lo)
    return _Stats(H, R, symmetrize(np.asarray(mom.Sss, dtype=float)), const)


# --------------------------------------------------------------------------- objectives


def surrogate_from_moments(model: AugmentedModel, mom: Moments, policy: LinearGaussianPolicy,
                           include_constant: bool = False) -> np.ndarray:
    """The paper's surrogate ``Lbar_k`` (T,) evaluated from its definition (see module docstring).

    ``-1/2 tr(So^{-1} (E[e e^T] + B Sigma B^T)) - 1/2 log|So|`` with ``e = zeta - (Atil + B F) stilde``;
    the ``B Sigma B^T`` term is the action noise ``B L w`` integrated out.  With
    ``include_constant=True`` the term ``-(n+1)/2 log(2 pi)`` is added, making it the expected
    complete-data log density, a lower bound of :func:`exact_objective_from_moments` (Jensen).
    """
    check_moments(model, mom)
    check_policy(model, policy)
    B = model.Bs
    Mt = atil(model) + B @ policy_F(policy)
    E = _residual_second_moment(mom, Mt) + B @ policy.cov @ la.T(B)
    Lo = la.chol(model.So, "augmented So")
    val = -0.5 * la.tr(la.cho_solve(Lo, E)) - 0.5 * la.logdet_chol(Lo)
    if include_constant:
        val = val - 0.5 * (model.n + 1) * LOG_2PI
    return val


def surrogate(model: AugmentedModel, smoothed: Smoothed, y: np.ndarray, policy: LinearGaussianPolicy,
              include_constant: bool = False) -> np.ndarray:
    """The paper's surrogate ``Lbar_k`` (T,) under smoothed moments; see :func:`surrogate_from_moments`."""
    return surrogate_from_moments(model, moments(smoothed, y), policy, include_constant)


def exact_objective_from_moments(model: AugmentedModel, mom: Moments, policy: LinearGaussianPolicy) -> np.ndarray:
    """``E[log N(zeta_k; M_k s_k + m_k, S_k)]`` (T,), the action integrated out (docs/math.md §4, §5).

    ``S_k = So_k + B Sigma_k B^T``; includes ``-(n+1)/2 log(2 pi)``.  The paper's surrogate is a
    Jensen lower bound: ``Lbar_k - (n+1)/2 log(2 pi) <= exact_k``, with equality iff the action
    posterior equals its prior (e.g. ``B Sigma B^T = 0``).
    """
    check_moments(model, mom)
    check_policy(model, policy)
    B = model.Bs
    Mt = atil(model) + B @ policy_F(policy)
    E = _residual_second_moment(mom, Mt)
    S = symmetrize(model.So + B @ policy.cov @ la.T(B))
    L = la.chol(S, "closed-loop covariance S")
    return -0.5 * (model.n + 1) * LOG_2PI - 0.5 * la.logdet_chol(L) - 0.5 * la.tr(la.cho_solve(L, E))


def exact_objective(model: AugmentedModel, smoothed: Smoothed, y: np.ndarray,
                    policy: LinearGaussianPolicy) -> np.ndarray:
    """Exact-EM objective (T,) under smoothed moments; see :func:`exact_objective_from_moments`."""
    return exact_objective_from_moments(model, moments(smoothed, y), policy)


def surrogate_grad_hess(model: AugmentedModel, mom: Moments, k: int, policy: LinearGaussianPolicy) -> GradHess:
    """Analytic gradient and Hessian of ``Lbar_k`` w.r.t. ``vec([K_k k_k])`` and gradient w.r.t. ``Sigma_k``.

    The Hessian ``-(Stilde_k kron H_k)`` is negative definite iff ``B_k`` has full column rank and
    ``P_k > 0`` (docs/math.md §9 claim 1).
    """
    check_moments(model, mom)
    check_policy(model, policy)
    if not 0 <= k < model.T:
        raise IndexError(f"time step k={k} out of range 0..{model.T - 1}")
    st = moment_stats(model, mom)
    H, R, S = st.H[k], st.R[k], st.S[k]
    F = policy_F(policy)[k]
    return GradHess(la.vec(R - H @ F @ S), -np.kron(S, H), -0.5 * H)


# --------------------------------------------------------------------------- time-invariant normal equations


def ti_normal_equations(st: _Stats):
    Q = np.einsum("kab,kij->aibj", st.S, st.H)  # sum_k S_k kron H_k, indices (a,i),(b,j)
    n1, m = st.S.shape[1], st.H.shape[1]
    Q = symmetrize(Q.reshape(n1 * m, n1 * m))
    r = la.vec(st.R.sum(0))
    return Q, r
