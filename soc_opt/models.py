"""Model and data types shared by every module (docs/math.md §0, §1, §6).

All types are frozen dataclasses whose arrays are validated once, at
construction: shapes, finiteness, symmetry and positive definiteness of
covariances.  Arrays are time-major: a gain sequence is ``(T, m, n)``, a state
trajectory ``(T+1, n)``, a batch of samples ``(M, T, ...)``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from .reading import read_regular

#: Largest policy file :meth:`LinearGaussianPolicy.load` reads: 1 GiB.
MAX_POLICY_BYTES = 1 << 30

__all__ = [
    "ShapeError",
    "NotPositiveDefiniteError",
    "LinearGaussianPolicy",
    "AugmentedModel",
    "LinearGaussianDynamics",
    "QuadraticCost",
    "Rollouts",
    "Smoothed",
    "check_array",
    "check_covariances",
    "symmetrize",
]


class ShapeError(ValueError):
    """An array has the wrong shape; the message names it and both shapes."""


class NotPositiveDefiniteError(ValueError):
    """A covariance is not symmetric positive definite; the message names it and the step."""


def symmetrize(X: np.ndarray) -> np.ndarray:
    """Return ``(X + X^T)/2`` over the last two axes."""
    return 0.5 * (X + np.swapaxes(X, -1, -2))


def check_array(name: str, x, shape: tuple, *, allow_nan: bool = False) -> np.ndarray:
    """Convert ``x`` to a float array and check its shape and finiteness.

    ``shape`` may contain ``None`` for a free axis.  Raises :class:`ShapeError`
    naming ``name`` on a shape mismatch and ``ValueError`` on NaN/inf.
    """
    a = np.asarray(x, dtype=float)
    ok = a.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, a.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"{name} must have shape {want}, got {a.shape}")
    if not allow_nan and not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise ValueError(f"{name} contains NaN or inf (first at index {tuple(int(i) for i in bad)})")
    return a


def check_covariances(name: str, S: np.ndarray, *, sym_tol: float = 1e-8, psd_only: bool = False) -> np.ndarray:
    """Check a stack ``(..., d, d)`` of covariances: symmetric and positive definite.

    Returns the symmetrised stack.  With ``psd_only`` semidefinite matrices are
    accepted.  Errors name the covariance and the first offending index.
    """
    S = np.asarray(S, dtype=float)
    asym = np.abs(S - np.swapaxes(S, -1, -2))
    scale = np.maximum(1.0, np.abs(S).max(axis=(-1, -2), initial=0.0))
    bad = asym.max(axis=(-1, -2), initial=0.0) > sym_tol * scale
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(np.atleast_1d(bad))[0])
        raise NotPositiveDefiniteError(f"{name}{list(idx)} is not symmetric")
    S = symmetrize(S)
    if S.shape[-1] == 0:
        return S
    eig_min = np.linalg.eigvalsh(S)[..., 0]
    thresh = -1e-12 * scale if psd_only else 0.0
    bad = eig_min < thresh if psd_only else eig_min <= 0.0
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(np.atleast_1d(bad))[0])
        kind = "positive semidefinite" if psd_only else "positive definite"
        ev = float(np.atleast_1d(eig_min)[idx] if idx else eig_min)
        raise NotPositiveDefiniteError(
            f"{name}{list(idx)} is not {kind} (smallest eigenvalue {ev:.3e})"
        )
    return S


def _freeze(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


@dataclass(frozen=True)
class LinearGaussianPolicy:
    """Time-varying linear-Gaussian policy ``a_k = K_k s_k + k_k + L_k w_k`` (docs/math.md §0).

    Fields:
        K:   (T, m, n) feedback gains.
        k:   (T, m)    offsets.
        cov: (T, m, m) action covariances ``Sigma_k = L_k L_k^T`` (positive definite;
             pass ``allow_singular=True`` for a deterministic policy, ``Sigma = 0``).
    """

    K: np.ndarray
    k: np.ndarray
    cov: np.ndarray
    allow_singular: bool = field(default=False, repr=False, compare=False)

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float)
        if K.ndim != 3:
            raise ShapeError(f"policy K must have shape (T, m, n), got {K.shape}")
        T, m, n = K.shape
        K = check_array("policy K", K, (T, m, n))
        k = check_array("policy k", self.k, (T, m))
        cov = check_array("policy cov", self.cov, (T, m, m))
        cov = check_covariances("policy cov", cov, psd_only=self.allow_singular)
        _freeze(K, k, cov)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "cov", cov)

    @property
    def T(self) -> int:
        return self.K.shape[0]

    @property
    def m(self) -> int:
        return self.K.shape[1]

    @property
    def n(self) -> int:
        return self.K.shape[2]

    @property
    def chol(self) -> np.ndarray:
        """(T, m, m) lower Cholesky factors ``L_k`` of ``Sigma_k`` (zero rows where singular)."""
        if self.allow_singular:
            w, V = np.linalg.eigh(self.cov)
            return V * np.sqrt(np.clip(w, 0.0, None))[:, None, :]
        return np.linalg.cholesky(self.cov)

    def mean_action(self, k: int, s: np.ndarray) -> np.ndarray:
        """Mean action ``K_k s + k_k`` for states ``s (..., n)`` -> ``(..., m)``."""
        return s @ self.K[k].T + self.k[k]

    def sample_action(self, k: int, s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Sample ``a_k`` for states ``s (..., n)``; ``w ~ N(0, I)`` drawn from ``rng``."""
        s = np.asarray(s, dtype=float)
        w = rng.standard_normal(s.shape[:-1] + (self.m,))
        return self.mean_action(k, s) + w @ self.chol[k].T

    def with_cov(self, cov: np.ndarray) -> "LinearGaussianPolicy":
        return LinearGaussianPolicy(self.K, self.k, cov)

    def mean_policy(self) -> "LinearGaussianPolicy":
        """The deterministic policy ``a_k = K_k s_k + k_k`` (``Sigma = 0``): the policy's mean action,
        what model-free peers report as their "deterministic" policy (docs/math.md §12.3)."""
        return LinearGaussianPolicy(self.K, self.k, np.zeros_like(self.cov), allow_singular=True)

    @staticmethod
    def zeros(T: int, n: int, m: int, var: float = 1.0) -> "LinearGaussianPolicy":
        """A zero-mean policy with isotropic covariance ``var * I``."""
        return LinearGaussianPolicy(
            np.zeros((T, m, n)), np.zeros((T, m)), np.broadcast_to(var * np.eye(m), (T, m, m)).copy()
        )

    def to_dict(self) -> dict:
        return {"K": np.array(self.K), "k": np.array(self.k), "cov": np.array(self.cov)}

    def save(self, path) -> None:
        """Write ``K``, ``k``, ``cov`` to the ``.npz`` file ``path`` (the format of a run directory's
        ``policies/iter_XXX.npz`` and ``best_policy.npz``)."""
        np.savez_compressed(path, **self.to_dict())

    @classmethod
    def load(cls, path, allow_singular: bool = False) -> "LinearGaussianPolicy":
        """The policy in the ``.npz`` file ``path``: :meth:`save`'s output, or a run directory's
        ``policies/iter_XXX.npz`` / ``best_policy.npz`` (their other arrays are ignored).

        The arrays are checked like any policy's (shapes, symmetric positive definite ``cov``;
        ``allow_singular`` for a deterministic policy).  A file without ``K``, ``k`` and ``cov``
        raises :class:`ShapeError` naming what is missing.
        """
        data = read_regular(path, MAX_POLICY_BYTES, what="policy file", follow=True)  # never blocks, bounded
        with np.load(io.BytesIO(data), allow_pickle=False) as f:
            missing = [key for key in ("K", "k", "cov") if key not in f.files]
            if missing:
                raise ShapeError(f"{path}: not a policy file (no {', '.join(missing)}; it holds {f.files})")
            return cls(f["K"], f["k"], f["cov"], allow_singular=allow_singular)


@dataclass(frozen=True)
class AugmentedModel:
    """Joint model of ``zeta_k = (s_{k+1}, y_k)`` given ``z_k = (s_k, a_k)`` (docs/math.md §1).

    ``zeta_k | z_k ~ N(Ao_k z_k + co_k, So_k)``.

    Fields:
        Ao: (T, n+1, n+m) ``[[A_k, B_k], [Ay_k, By_k]]``.
        co: (T, n+1)      bias.
        So: (T, n+1, n+1) full covariance (cross term of ``s_{k+1}`` and ``y_k`` kept).
        n:  state dimension (needed to split ``Ao``'s columns).
    """

    Ao: np.ndarray
    co: np.ndarray
    So: np.ndarray
    n: int

    def __post_init__(self):
        Ao = np.asarray(self.Ao, dtype=float)
        n = int(self.n)
        if Ao.ndim != 3 or Ao.shape[1] != n + 1 or Ao.shape[2] <= n:
            raise ShapeError(f"augmented Ao must have shape (T, n+1, n+m) with n={n}, got {Ao.shape}")
        T, _, nm = Ao.shape
        Ao = check_array("augmented Ao", Ao, (T, n + 1, nm))
        co = check_array("augmented co", self.co, (T, n + 1))
        So = check_array("augmented So", self.So, (T, n + 1, n + 1))
        So = check_covariances("augmented So", So)
        _freeze(Ao, co, So)
        object.__setattr__(self, "Ao", Ao)
        object.__setattr__(self, "co", co)
        object.__setattr__(self, "So", So)
        object.__setattr__(self, "n", n)

    @property
    def T(self) -> int:
        return self.Ao.shape[0]

    @property
    def m(self) -> int:
        return self.Ao.shape[2] - self.n

    @property
    def As(self) -> np.ndarray:
        """(T, n+1, n) state columns ``[A_k; Ay_k]``."""
        return self.Ao[:, :, : self.n]

    @property
    def Bs(self) -> np.ndarray:
        """(T, n+1, m) action columns ``[B_k; By_k]``."""
        return self.Ao[:, :, self.n :]

    def dynamics(self) -> "LinearGaussianDynamics":
        """The state rows only: ``s_{k+1} ~ N(A s + B a + c, W)``."""
        n = self.n
        return LinearGaussianDynamics(
            self.Ao[:, :n, :n], self.Ao[:, :n, n:], self.co[:, :n], self.So[:, :n, :n]
        )


@dataclass(frozen=True)
class LinearGaussianDynamics:
    """``s_{k+1} ~ N(A_k s_k + B_k a_k + c_k, W_k)`` (docs/math.md §6).

    Fields:
        A:   (T, n, n)
        B:   (T, n, m)
        c:   (T, n)
        cov: (T, n, n) process noise ``W_k`` (positive semidefinite).
    """

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray
    cov: np.ndarray

    def __post_init__(self):
        A = np.asarray(self.A, dtype=float)
        if A.ndim != 3 or A.shape[1] != A.shape[2]:
            raise ShapeError(f"dynamics A must have shape (T, n, n), got {A.shape}")
        T, n, _ = A.shape
        A = check_array("dynamics A", A, (T, n, n))
        B = np.asarray(self.B, dtype=float)
        if B.ndim != 3:
            raise ShapeError(f"dynamics B must have shape (T, n, m), got {B.shape}")
        B = check_array("dynamics B", B, (T, n, B.shape[2]))
        c = check_array("dynamics c", self.c, (T, n))
        cov = check_array("dynamics cov", self.cov, (T, n, n))
        cov = check_covariances("dynamics cov", cov, psd_only=True)
        _freeze(A, B, c, cov)
        for name, val in (("A", A), ("B", B), ("c", c), ("cov", cov)):
            object.__setattr__(self, name, val)

    @property
    def T(self) -> int:
        return self.A.shape[0]

    @property
    def n(self) -> int:
        return self.A.shape[1]

    @property
    def m(self) -> int:
        return self.B.shape[2]


@dataclass(frozen=True)
class QuadraticCost:
    """Stage costs ``l_k(z) = 1/2 z^T C_k z + z^T c_k + c0_k`` with ``z = (s_k, a_k)`` (docs/math.md §6).

    There is no terminal cost: the state ``s_T`` is not charged.

    Fields:
        C:  (T, n+m, n+m) symmetric Hessians.
        c:  (T, n+m)      linear terms.
        c0: (T,)          constants (default zeros).
        n:  state dimension (splits ``z``).
    """

    C: np.ndarray
    c: np.ndarray
    n: int
    c0: np.ndarray | None = None

    def __post_init__(self):
        C = np.asarray(self.C, dtype=float)
        if C.ndim != 3 or C.shape[1] != C.shape[2]:
            raise ShapeError(f"cost C must have shape (T, n+m, n+m), got {C.shape}")
        T, d, _ = C.shape
        if not 0 < int(self.n) < d:
            raise ShapeError(f"cost n={self.n} must be between 1 and n+m-1={d - 1}")
        C = check_array("cost C", C, (T, d, d))
        asym = np.abs(C - np.swapaxes(C, 1, 2)).max(initial=0.0)
        if asym > 1e-8 * max(1.0, np.abs(C).max(initial=0.0)):
            raise ValueError(f"cost C is not symmetric (max asymmetry {asym:.3e})")
        C = symmetrize(C)
        c = check_array("cost c", self.c, (T, d))
        c0 = np.zeros(T) if self.c0 is None else check_array("cost c0", self.c0, (T,))
        _freeze(C, c, c0)
        object.__setattr__(self, "C", C)
        object.__setattr__(self, "c", c)
        object.__setattr__(self, "c0", c0)
        object.__setattr__(self, "n", int(self.n))

    @property
    def T(self) -> int:
        return self.C.shape[0]

    @property
    def m(self) -> int:
        return self.C.shape[1] - self.n

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Stage costs for ``s (..., T, n)`` (or ``(..., T+1, n)``, last state ignored), ``a (..., T, m)`` -> ``(..., T)``."""
        s = np.asarray(s, dtype=float)[..., : self.T, :]
        z = np.concatenate([s, np.asarray(a, dtype=float)], axis=-1)
        return 0.5 * np.einsum("...ti,tij,...tj->...t", z, self.C, z) + np.einsum("...ti,ti->...t", z, self.c) + self.c0


@dataclass(frozen=True)
class Rollouts:
    """``M`` sampled trajectories of a task under a policy (docs/math.md §0, §2).

    Fields:
        x:    (M, T+1, n) true simulator states.
        s:    (M, T+1, n) measured states ``s = x + eps``, ``eps ~ N(0, rho^2 I)``.
        a:    (M, T, m)   actions.
        cost: (M, T)      stage costs ``Y_k``.
        y:    (M, T)      observed costs ``y_k = exp(-Y_k)``.
    """

    x: np.ndarray
    s: np.ndarray
    a: np.ndarray
    cost: np.ndarray
    y: np.ndarray

    def __post_init__(self):
        x = np.asarray(self.x, dtype=float)
        if x.ndim != 3:
            raise ShapeError(f"rollouts x must have shape (M, T+1, n), got {x.shape}")
        M, T1, n = x.shape
        T = T1 - 1
        a = np.asarray(self.a, dtype=float)
        if a.ndim != 3:
            raise ShapeError(f"rollouts a must have shape (M, T, m), got {a.shape}")
        m = a.shape[2]
        arrs = {
            "x": check_array("rollouts x", x, (M, T + 1, n)),
            "s": check_array("rollouts s", self.s, (M, T + 1, n)),
            "a": check_array("rollouts a", a, (M, T, m)),
            "cost": check_array("rollouts cost", self.cost, (M, T)),
            "y": check_array("rollouts y", self.y, (M, T)),
        }
        for name, val in arrs.items():
            val.setflags(write=False)
            object.__setattr__(self, name, val)

    @property
    def M(self) -> int:
        return self.x.shape[0]

    @property
    def T(self) -> int:
        return self.a.shape[1]

    @property
    def n(self) -> int:
        return self.x.shape[2]

    @property
    def m(self) -> int:
        return self.a.shape[2]

    def total_cost(self) -> np.ndarray:
        """(M,) sum of stage costs per sample."""
        return self.cost.sum(axis=1)

    def to_dict(self) -> dict:
        return {k: np.array(getattr(self, k)) for k in ("x", "s", "a", "cost", "y")}

    @staticmethod
    def concatenate(parts: "list[Rollouts]") -> "Rollouts":
        return Rollouts(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("x", "s", "a", "cost", "y")))


@dataclass(frozen=True)
class Smoothed:
    """Output of the RTS smoother (docs/math.md §4).

    For one observation sequence:
        mean:   (T+1, n)    ``s_hat_k = E[s_k | Y]``
        cov:    (T+1, n, n) ``P_k = Cov(s_k | Y)``
        cross:  (T, n, n)   ``Cov(s_{k+1}, s_k | Y)``
        loglik: float       ``log p(Y)``
    For ``M`` sequences every field has a leading ``M`` axis and ``loglik`` is ``(M,)``.
    """

    mean: np.ndarray
    cov: np.ndarray
    cross: np.ndarray
    loglik: float | np.ndarray

    @property
    def batched(self) -> bool:
        return self.mean.ndim == 3

    @property
    def T(self) -> int:
        return self.cross.shape[-3]

    @property
    def n(self) -> int:
        return self.mean.shape[-1]
