"""Random well-posed instances shared by the tests, the benchmarks and ``soc_opt.verification``.

Every generator takes a ``numpy.random.Generator`` first and draws from it only, in a fixed
order.  That order is part of the contract: seeded tests, benchmark tables and the
``soc-opt verify`` output depend on it, so a change of order (or of an extra draw) changes
their numbers.  Shapes follow docs/math.md §0 (time-major, ``T`` steps, state ``n``, action ``m``).

Covariances are built as Gram matrices plus a floor, or from a random orthogonal basis and a
prescribed spectrum, and symmetrised.  Nothing here is used by the algorithms themselves.
"""

from __future__ import annotations

import numpy as np

from .estep import moments
from .models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    QuadraticCost,
    Rollouts,
    Smoothed,
    symmetrize,
)

__all__ = [
    "random_spd",
    "random_spd_spectrum",
    "random_augmented_model",
    "random_policy",
    "random_initial_state",
    "sample_model_trajectory",
    "random_estep_instance",
    "random_closed_loop",
    "random_smoothed",
    "random_ltv_system",
    "random_linear_dynamics",
    "random_quadratic_cost",
    "random_kl_step_problem",
    "random_trajectory",
    "random_gaussian_quadratic",
    "make_kl_instance",
    "random_mstep_instance",
    "simulate_linear",
    "simulate_pendulum",
]


# --------------------------------------------------------------------------- matrices


def random_spd(rng: np.random.Generator, d: int, *, scale: float = 1.0, floor: float = 0.1) -> np.ndarray:
    """``(d, d)`` SPD matrix ``R R^T + floor I`` with ``R = scale N(0, 1)^{d x d} / sqrt(d)``.

    Eigenvalues are at least ``floor``; ``scale^2`` sets the size of the random part.
    """
    R = rng.normal(size=(d, d)) * scale / np.sqrt(d)
    return symmetrize(R @ R.T) + floor * np.eye(d)


def random_spd_spectrum(rng: np.random.Generator, d: int, lo: float, hi: float) -> np.ndarray:
    """``(d, d)`` SPD matrix with a uniformly random orthogonal basis and eigenvalues uniform in ``[lo, hi]``."""
    Q, _ = np.linalg.qr(rng.standard_normal((d, d)))
    w = rng.uniform(lo, hi, size=d)
    return symmetrize((Q * w) @ Q.T)


# --------------------------------------------------------------------------- augmented model (docs/math.md §1)


def _null_space_rows(rng: np.random.Generator, m: int, b_rank: int, b_null) -> np.ndarray:
    """Integer ``V`` (``b_rank x m``) with ``V @ b_null == 0`` exactly.

    ``b_null`` (an integer vector with ``b_null[0] != 0``; by default random nonzero integers
    in ``[-3, 3]``) spans the null space; the rows are ``b_null[0] e_j - b_null[j] e_0``
    (``j = 1..b_rank``), so with small integers every product ``U @ V`` of dyadic ``U`` is exact
    in binary floating point and the rank deficiency is exact, not numerical (docs/math.md §9.1).
    """
    if not 0 <= b_rank < m:
        raise ValueError(f"b_rank must be in [0, m) = [0, {m}), got {b_rank}")
    if b_null is None:
        b_null = rng.integers(1, 4, size=m) * rng.choice([-1, 1], size=m)
    w = np.asarray(b_null)
    if w.shape != (m,) or not np.all(w == np.round(w)) or w[0] == 0:
        raise ValueError(f"b_null must be {m} integers with b_null[0] != 0, got {b_null!r}")
    w = w.astype(np.int64)
    V = np.zeros((b_rank, m))
    for j in range(1, b_rank + 1):
        V[j - 1, 0], V[j - 1, j] = -w[j], w[0]
    return V


def random_augmented_model(
    rng: np.random.Generator,
    n: int,
    m: int,
    T: int,
    *,
    b_rank: int | None = None,
    b_null: np.ndarray | None = None,
) -> AugmentedModel:
    """A random augmented model ``zeta_k | z_k ~ N(Ao_k z_k + co_k, So_k)`` (docs/math.md §1).

    ``A_k = 0.9 Q_k`` plus a small perturbation (``Q_k`` orthogonal, so the state block is
    stable-ish), ``B_k`` and the cost row ``[Ay_k, By_k]`` standard normal scaled by
    ``1/sqrt(n)``, bias ``co_k ~ N(0, 0.25 I)`` and a full ``So_k`` (cross term between
    ``s_{k+1}`` and ``y_k`` present) with eigenvalues in ``[0.05, 0.5]``.

    ``b_rank < m`` makes the action columns ``[B_k; By_k]`` exactly rank-deficient: they are
    ``U_k V`` with a dyadic ``U_k`` and a fixed integer ``V`` (``b_rank x m``) shared by all
    steps, so ``[B_k; By_k] b_null == 0`` holds exactly in floating point at every step
    (``b_null``: integers, or random ones; see :func:`_null_space_rows`).
    """
    Ao = np.zeros((T, n + 1, n + m))
    co = np.zeros((T, n + 1))
    So = np.zeros((T, n + 1, n + 1))
    V = None if b_rank is None else _null_space_rows(rng, m, b_rank, b_null)
    for k in range(T):
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        Ao[k, :n, :n] = 0.9 * Q + 0.05 * rng.standard_normal((n, n))
        Ao[k, n, :n] = rng.standard_normal(n) / np.sqrt(n)
        if V is None:
            Ao[k, :, n:] = rng.standard_normal((n + 1, m)) / np.sqrt(n)
        else:
            # dyadic U (multiples of 2^-12) times the integer V: exact in float, so B_k b_null == 0 exactly
            U = rng.standard_normal((n + 1, b_rank)) / (np.sqrt(n) * np.linalg.norm(V, axis=1))
            Ao[k, :, n:] = (np.round(U * 4096) / 4096) @ V
        co[k] = 0.5 * rng.standard_normal(n + 1)
        So[k] = random_spd_spectrum(rng, n + 1, 0.05, 0.5)
    return AugmentedModel(Ao, co, So, n)


def random_policy(rng: np.random.Generator, T: int, n: int, m: int) -> LinearGaussianPolicy:
    """Random linear-Gaussian policy: ``K ~ 0.3 N(0,1)``, ``k ~ 0.5 N(0,1)``, ``Sigma`` eigenvalues in ``[0.2, 1]``."""
    K = 0.3 * rng.standard_normal((T, m, n))
    kk = 0.5 * rng.standard_normal((T, m))
    cov = np.stack([random_spd_spectrum(rng, m, 0.2, 1.0) for _ in range(T)])
    return LinearGaussianPolicy(K, kk, cov)


def random_initial_state(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``mu0 ~ N(0, I)`` (``(n,)``) and ``P0`` (``(n, n)``) with eigenvalues in ``[0.1, 1]``."""
    return rng.standard_normal(n), random_spd_spectrum(rng, n, 0.1, 1.0)


def sample_model_trajectory(
    rng: np.random.Generator,
    model: AugmentedModel,
    policy: LinearGaussianPolicy,
    mu0: np.ndarray,
    P0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate the augmented model in closed loop: returns ``s (T+1, n)`` and ``y (T,)``.

    ``s_0 ~ N(mu0, P0)``, ``a_k ~ policy(.|s_k)``, ``(s_{k+1}, y_k) ~ N(Ao_k (s_k, a_k) + co_k, So_k)``.
    """
    n, T = model.n, model.T
    s = np.zeros((T + 1, n))
    y = np.zeros(T)
    s[0] = rng.multivariate_normal(mu0, P0)
    for k in range(T):
        a = policy.sample_action(k, s[k], rng)
        mean = model.Ao[k] @ np.concatenate([s[k], a]) + model.co[k]
        zeta = mean + np.linalg.cholesky(model.So[k]) @ rng.standard_normal(n + 1)
        s[k + 1] = zeta[:n]
        y[k] = zeta[n]
    return s, y


def random_estep_instance(
    rng: np.random.Generator,
    n: int,
    m: int,
    T: int,
    *,
    cross: bool = True,
    rho: float = 0.85,
    policy_var: float = 0.3,
) -> tuple[AugmentedModel, LinearGaussianPolicy, np.ndarray, np.ndarray]:
    """A stable augmented model, a policy and an initial state ``(model, policy, mu0, P0)`` (docs/math.md §1, §4).

    ``A_k`` has spectral norm ``rho``; ``B_k ~ 0.5 N/sqrt(n)``, cost row ``[Ay, By]`` scaled
    ``1/sqrt(n)``, ``1/sqrt(m)``; ``co_k ~ N(0, I)``; ``So_k = random_spd(scale=0.7)`` with the
    ``(s_{k+1}, y_k)`` cross block zeroed unless ``cross``.  Policy: ``K ~ 0.3 N/sqrt(n)``,
    ``k ~ N(0, 1)``, ``Sigma_k = random_spd(scale=sqrt(policy_var), floor=0.05)``;
    ``mu0 ~ N(0, I)``, ``P0 = random_spd(floor=0.2)``.
    """
    A = rng.normal(size=(T, n, n))
    A *= rho / np.linalg.norm(A, 2, axis=(1, 2))[:, None, None]
    B = 0.5 * rng.normal(size=(T, n, m)) / np.sqrt(n)
    Ay = rng.normal(size=(T, 1, n)) / np.sqrt(n)
    By = rng.normal(size=(T, 1, m)) / np.sqrt(m)
    Ao = np.concatenate([np.concatenate([A, B], axis=2), np.concatenate([Ay, By], axis=2)], axis=1)
    co = rng.normal(size=(T, n + 1))
    So = np.stack([random_spd(rng, n + 1, scale=0.7) for _ in range(T)])
    if not cross:
        So[:, :n, n] = 0.0
        So[:, n, :n] = 0.0
    model = AugmentedModel(Ao, co, So, n)
    K = 0.3 * rng.normal(size=(T, m, n)) / np.sqrt(n)
    k = rng.normal(size=(T, m))
    cov = np.stack([random_spd(rng, m, scale=np.sqrt(policy_var), floor=0.05) for _ in range(T)])
    policy = LinearGaussianPolicy(K, k, cov)
    mu0 = rng.normal(size=n)
    P0 = random_spd(rng, n, floor=0.2)
    return model, policy, mu0, P0


def random_closed_loop(rng: np.random.Generator, n: int, m: int, T: int) -> tuple[AugmentedModel, LinearGaussianPolicy]:
    """A stable augmented model with weak action coupling and a policy ``(model, policy)`` (docs/math.md §1).

    ``A_k = 0.95 Q_k`` (orthogonal ``Q_k``), ``B_k`` and the cost row ``0.1 N(0, 1)``,
    ``So_k = L L^T + 0.01 I`` with ``L ~ 0.1 N``, ``co_k ~ 0.1 N``; policy ``K ~ 0.1 N``,
    ``k ~ N(0, 1)``, ``Sigma_k = 0.1 I``.  Sized for benchmarks (``n = 26`` is fine).
    """
    A = 0.95 * np.linalg.qr(rng.standard_normal((T, n, n)))[0]
    Ao = np.concatenate([np.concatenate([A, 0.1 * rng.standard_normal((T, n, m))], axis=2),
                         0.1 * rng.standard_normal((T, 1, n + m))], axis=1)
    Lo = 0.1 * rng.standard_normal((T, n + 1, n + 1))
    So = symmetrize(Lo @ np.swapaxes(Lo, 1, 2)) + 0.01 * np.eye(n + 1)
    model = AugmentedModel(Ao, 0.1 * rng.standard_normal((T, n + 1)), So, n)
    policy = LinearGaussianPolicy(0.1 * rng.standard_normal((T, m, n)), rng.standard_normal((T, m)),
                                  np.broadcast_to(0.1 * np.eye(m), (T, m, m)).copy())
    return model, policy


def random_smoothed(rng: np.random.Generator, n: int, T: int, *, singular_step: int | None = None,
                    M: int | None = None) -> Smoothed:
    """Smoothed-state moments that are the blocks of a random joint Gaussian over ``(s_0..s_T)`` (docs/math.md §4).

    The joint covariance is ``L L^T`` with ``L = N/sqrt(n) + 0.3 I`` (``(T+1) n`` square); the
    means are ``N(0, 1)``.  ``singular_step`` zeroes the rows of ``L`` of that step, so ``s_j`` is
    deterministic there (``P_j = 0``).  ``M`` sequences give a batched ``Smoothed`` (leading
    ``M`` axis); ``loglik`` is 0.
    """

    def one():
        L = rng.normal(size=((T + 1) * n, (T + 1) * n)) / np.sqrt(n)
        L += 0.3 * np.eye((T + 1) * n)
        if singular_step is not None:
            L[singular_step * n : (singular_step + 1) * n] = 0.0
        C = (L @ L.T).reshape(T + 1, n, T + 1, n)
        cov = np.stack([C[t, :, t, :] for t in range(T + 1)])
        cross = np.stack([C[t + 1, :, t, :] for t in range(T)])
        return rng.normal(size=(T + 1, n)), cov, cross

    if M is None:
        mean, cov, cross = one()
        return Smoothed(mean, cov, cross, 0.0)
    parts = [one() for _ in range(M)]
    return Smoothed(*(np.stack([p[i] for p in parts]) for i in range(3)), np.zeros(M))


# --------------------------------------------------------------------------- dynamics, costs, KL step


def random_ltv_system(rng: np.random.Generator, n: int, m: int, T: int, *, variation: float = 0.1) -> dict:
    """A random stable time-varying linear-Gaussian system ``x' = A_k x + B_k a + c_k + w``, ``w ~ N(0, W_k)``.

    ``A_k`` is a rotation scaled to spectral radius 0.9 plus a smooth (sinusoidal in ``k``)
    perturbation of relative size ``variation``; ``B_k``, ``c_k`` and ``W_k`` vary smoothly too
    (``variation = 0`` gives a time-invariant system).  Returns ``dict(A (T,n,n), B (T,n,m),
    c (T,n), W (T,n,n))`` (docs/math.md §2).
    """
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A0 = 0.9 * Q
    E = rng.standard_normal((n, n)) / np.sqrt(n)
    B0 = rng.standard_normal((n, m)) / np.sqrt(m)
    F = rng.standard_normal((n, m)) / np.sqrt(m)
    c0 = 0.3 * rng.standard_normal(n)
    c1 = 0.3 * rng.standard_normal(n)
    G = rng.standard_normal((n, n)) / np.sqrt(n)
    W0 = 0.02 * symmetrize(G @ G.T) + 0.01 * np.eye(n)
    ph = 2 * np.pi * np.arange(T) / max(T, 1)
    sk, ck = np.sin(ph), np.cos(ph)
    A = A0[None] + variation * sk[:, None, None] * E[None]
    B = B0[None] + variation * ck[:, None, None] * F[None]
    c = c0[None] + (variation / 0.1 if variation else 0.0) * sk[:, None] * c1[None]
    W = W0[None] * (1.0 + 5 * variation * sk[:, None, None] ** 2)
    return {"A": A, "B": B, "c": c, "W": W}


def random_linear_dynamics(rng: np.random.Generator, n: int, m: int, T: int, *, gain: float = 0.9,
                           perturbation: float = 0.1) -> LinearGaussianDynamics:
    """Time-varying dynamics ``s' ~ N(A_k s + B_k a + c_k, W_k)`` (docs/math.md §6).

    ``A_k = gain Q_k + perturbation N/sqrt(n)`` (``Q_k`` orthogonal), ``B_k ~ N/sqrt(n)``,
    ``c_k ~ 0.1 N``, ``W_k = G G^T + 0.01 I`` with ``G ~ 0.1 N``.
    """
    A = np.empty((T, n, n))
    for t in range(T):
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        A[t] = gain * Q + perturbation * rng.standard_normal((n, n)) / np.sqrt(n)
    B = rng.standard_normal((T, n, m)) / np.sqrt(n)
    c = 0.1 * rng.standard_normal((T, n))
    Wf = 0.1 * rng.standard_normal((T, n, n))
    W = symmetrize(Wf @ np.swapaxes(Wf, 1, 2)) + 0.01 * np.eye(n)
    return LinearGaussianDynamics(A, B, c, W)


def random_quadratic_cost(
    rng: np.random.Generator,
    n: int,
    m: int,
    T: int,
    *,
    normalize: bool = True,
    floor: float = 0.1,
    action_shift: float = 0.0,
    c0: np.ndarray | None = None,
) -> QuadraticCost:
    """Quadratic stage costs ``1/2 z^T C_k z + z^T c_k + c0_k``, ``z = (s, a)`` (docs/math.md §6).

    ``C_k = G G^T (/ (n+m) if normalize) + floor I - action_shift I_action`` with ``G ~ N(0, 1)``;
    ``c_k ~ N(0, I)``; ``c0_k ~ N(0, 1)`` unless ``c0`` (``(T,)``) is given.  ``action_shift > 0``
    makes the action block indefinite (a non-convex cost).
    """
    G = rng.standard_normal((T, n + m, n + m))
    C = symmetrize(G @ np.swapaxes(G, 1, 2))
    if normalize:
        C = C / (n + m)
    C = C + floor * np.eye(n + m)
    if action_shift:
        C[:, n:, n:] -= action_shift * np.eye(m)
    c = rng.standard_normal((T, n + m))
    if c0 is None:
        c0 = rng.standard_normal(T)
    return QuadraticCost(C, c, n, c0=c0)


def random_kl_step_problem(
    rng: np.random.Generator,
    n: int = 3,
    m: int = 2,
    T: int = 8,
    *,
    ref_var: float = 0.5,
    convex: bool = True,
) -> tuple[LinearGaussianDynamics, QuadraticCost, LinearGaussianPolicy, np.ndarray, np.ndarray]:
    """A KL-constrained LQG step instance ``(dynamics, cost, reference, mu0, P0)`` (docs/math.md §6).

    :func:`random_linear_dynamics` (gain 0.9, perturbation 0.1), :func:`random_quadratic_cost`
    (PD action block, or shifted by ``-2 I`` when not ``convex``), a reference policy with
    ``K ~ 0.3 N/sqrt(n)``, ``k ~ 0.5 N``, ``Sigma = L L^T + ref_var I`` (``L ~ 0.3 N``),
    ``mu0 ~ N(0, I)`` and ``P0 = 0.1 I``.
    """
    dyn = random_linear_dynamics(rng, n, m, T)
    cost = random_quadratic_cost(rng, n, m, T, action_shift=0.0 if convex else 2.0)
    Kh = 0.3 * rng.standard_normal((T, m, n)) / np.sqrt(n)
    kh = 0.5 * rng.standard_normal((T, m))
    Lf = 0.3 * rng.standard_normal((T, m, m))
    Sh = symmetrize(Lf @ np.swapaxes(Lf, 1, 2)) + ref_var * np.eye(m)
    ref = LinearGaussianPolicy(Kh, kh, Sh)
    mu0 = rng.standard_normal(n)
    return dyn, cost, ref, mu0, 0.1 * np.eye(n)


def random_trajectory(rng: np.random.Generator, n: int, m: int, T: int) -> tuple[np.ndarray, np.ndarray]:
    """States ``s (T+1, n)`` then actions ``a (T, m)``, all ``N(0, 1)``."""
    return rng.standard_normal((T + 1, n)), rng.standard_normal((T, m))


def random_gaussian_quadratic(rng: np.random.Generator, d: int):
    """A Gaussian ``P = N(mu, S)`` and a quadratic ``J(x) = 1/2 x^T A x + b^T x + c`` (docs/math.md §9, claim 4).

    ``mu ~ N(0, I)``, ``S`` eigenvalues in ``[0.3, 2]``, ``A = R R^T/d + 0.1 I`` (cost-like,
    ``J`` bounded below), ``b ~ N(0, I)``, ``c ~ N(0, 1)``.  Returns ``(mu, S, A, b, c)``.
    """
    mu = rng.standard_normal(d)
    S = random_spd_spectrum(rng, d, 0.3, 2.0)
    R = rng.standard_normal((d, d))
    A = symmetrize(R @ R.T / d + 0.1 * np.eye(d))
    b = rng.standard_normal(d)
    c = float(rng.standard_normal())
    return mu, S, A, b, c


# --------------------------------------------------------------------------- benchmark instances
# (moved from soc_opt.bench, which imports them from here; the draws are unchanged)


def make_kl_instance(n: int, m: int, T: int, rng: np.random.Generator):
    """A random stable, convex KL-step instance ``(dynamics, cost, reference, mu0, P0)``."""
    A = np.empty((T, n, n))
    for t in range(T):
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        A[t] = 0.95 * Q + 0.05 * rng.standard_normal((n, n)) / np.sqrt(n)
    B = rng.standard_normal((T, n, m)) / np.sqrt(n)
    c = 0.1 * rng.standard_normal((T, n))
    Wf = 0.1 * rng.standard_normal((T, n, n))
    W = Wf @ np.swapaxes(Wf, 1, 2) + 0.01 * np.eye(n)
    M = rng.standard_normal((T, n + m, n + m))
    C = M @ np.swapaxes(M, 1, 2) / (n + m) + 0.1 * np.eye(n + m)
    cost = QuadraticCost(C, rng.standard_normal((T, n + m)), n)
    Lf = 0.3 * rng.standard_normal((T, m, m))
    ref = LinearGaussianPolicy(0.3 * rng.standard_normal((T, m, n)) / np.sqrt(n), 0.5 * rng.standard_normal((T, m)),
                               Lf @ np.swapaxes(Lf, 1, 2) + 0.5 * np.eye(m))
    return LinearGaussianDynamics(A, B, c, W), cost, ref, rng.standard_normal(n), 0.1 * np.eye(n)


def _mstep_spd(rng: np.random.Generator, d: int, floor: float) -> np.ndarray:
    R = rng.normal(size=(d, d)) / np.sqrt(d)
    return R @ R.T + floor * np.eye(d)


def random_mstep_instance(n: int, m: int, T: int, rng: np.random.Generator):
    """A random augmented model and the moments of a random smoothing distribution.

    Returns ``(model, Moments)``.  The model has ``||A_k||_2 = 0.9`` and PD ``So_k``; the smoothed
    states are the blocks of a random PD covariance over ``(s_0..s_T)`` with random means, and
    ``y_k`` is uniform in ``(0.05, 1)``.
    """
    A = rng.normal(size=(T, n + 1, n))
    A *= 0.9 / np.linalg.norm(A[:, :n], 2, axis=(1, 2))[:, None, None]
    B = rng.normal(size=(T, n + 1, m)) / np.sqrt(n)
    Ao = np.concatenate([A, B], axis=2)
    co = rng.normal(size=(T, n + 1))
    So = np.stack([_mstep_spd(rng, n + 1, 0.1) for _ in range(T)])
    model = AugmentedModel(Ao, co, So, n)
    L = rng.normal(size=((T + 1) * n, (T + 1) * n)) / np.sqrt((T + 1) * n) + 0.3 * np.eye((T + 1) * n)
    C = (L @ L.T).reshape(T + 1, n, T + 1, n)
    cov = np.stack([C[t, :, t, :] for t in range(T + 1)])
    cross = np.stack([C[t + 1, :, t, :] for t in range(T)])
    sm = Smoothed(rng.normal(size=(T + 1, n)), cov, cross, 0.0)
    y = rng.uniform(0.05, 1.0, size=T)
    return model, moments(sm, y)


def _rollouts(x: np.ndarray, a: np.ndarray, rng: np.random.Generator, rho2: float, target: np.ndarray) -> Rollouts:
    s = x + np.sqrt(rho2) * rng.standard_normal(x.shape) if rho2 > 0 else x.copy()
    d = s[:, :-1] - target
    cost = 0.05 * np.sum(d * d, axis=-1) + 0.005 * np.sum(a * a, axis=-1)
    return Rollouts(x=x, s=s, a=a, cost=cost, y=np.exp(-cost))


def simulate_linear(
    system: dict,
    M: int,
    rng: np.random.Generator,
    rho2: float = 0.0,
    action_std: float = 1.0,
    x0_std: float = 1.0,
) -> Rollouts:
    """``M`` rollouts of ``system`` under the exploratory policy ``a ~ N(0, action_std^2 I)``.

    ``x_0 ~ N(0, x0_std^2 I)``; measured ``s = x + N(0, rho2 I)``; stage cost
    ``Y = 0.05 |s|^2 + 0.005 |a|^2`` and ``y = exp(-Y)``.
    """
    A, B, c, W = system["A"], system["B"], system["c"], system["W"]
    T, n, m = B.shape[0], B.shape[1], B.shape[2]
    LW = np.linalg.cholesky(W)
    x = np.empty((M, T + 1, n))
    a = action_std * rng.standard_normal((M, T, m))
    x[:, 0] = x0_std * rng.standard_normal((M, n))
    for k in range(T):
        w = rng.standard_normal((M, n)) @ LW[k].T
        x[:, k + 1] = x[:, k] @ A[k].T + a[:, k] @ B[k].T + c[k] + w
    return _rollouts(x, a, rng, rho2, np.zeros(n))


def _pendulum_f(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    g_over_l, damping = 9.81, 0.3
    th, om = x[..., 0], x[..., 1]
    return np.stack([om, -g_over_l * np.sin(th) - damping * om + u[..., 0]], axis=-1)


def simulate_pendulum(
    M: int,
    rng: np.random.Generator,
    T: int = 60,
    dt: float = 0.05,
    rho2: float = 1e-3,
    action_std: float = 2.0,
    proc_std: float = 0.01,
) -> Rollouts:
    """``M`` rollouts of a damped pendulum ``th'' = -9.81 sin th - 0.3 th' + u`` (n=2, m=1).

    RK4 with step ``dt``; open-loop exploratory torque ``u_k = 6 sin(2 pi k / T) + N(0, action_std^2)``
    so that the swings cover the nonlinear range; start ``th_0 ~ N(pi/2, 0.3^2)``,
    ``th'_0 ~ N(0, 0.3^2)``; additive process noise ``N(0, proc_std^2 I)`` per step and
    measurement noise ``N(0, rho2 I)``.
    """
    n = 2
    x = np.empty((M, T + 1, n))
    x[:, 0, 0] = np.pi / 2 + 0.3 * rng.standard_normal(M)
    x[:, 0, 1] = 0.3 * rng.standard_normal(M)
    u_nom = 6.0 * np.sin(2 * np.pi * np.arange(T) / T)
    a = u_nom[None, :, None] + action_std * rng.standard_normal((M, T, 1))
    for k in range(T):
        xk, uk = x[:, k], a[:, k]
        k1 = _pendulum_f(xk, uk)
        k2 = _pendulum_f(xk + 0.5 * dt * k1, uk)
        k3 = _pendulum_f(xk + 0.5 * dt * k2, uk)
        k4 = _pendulum_f(xk + dt * k3, uk)
        x[:, k + 1] = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4) + proc_std * rng.standard_normal((M, n))
    return _rollouts(x, a, rng, rho2, np.array([np.pi, 0.0]))
