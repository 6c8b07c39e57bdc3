"""Brute-force Gaussian oracle for the noise-aware tests (docs/math.md §10).

Every random variable of a linear-Gaussian closed loop is an affine function of a finite vector of
independent standard normals ``xi``: ``v = const + coef @ xi``.  Building the closed loop with
:class:`Lin` values gives exact means and (cross-)covariances of anything in it, without any of the
recursions under test (no filter covariance recursion, no moment propagation, no innovation form).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg


class Lin:
    """``const + coef @ xi`` with ``xi`` the first ``coef.shape[1]`` primitive standard normals."""

    __array_ufunc__ = None  # make ``ndarray @ Lin`` and ``ndarray + Lin`` defer to Lin

    def __init__(self, const, coef):
        self.const = np.asarray(const, dtype=float)
        self.coef = np.asarray(coef, dtype=float).reshape(self.const.shape[0], -1)

    @staticmethod
    def _pad(a: np.ndarray, N: int) -> np.ndarray:
        return np.hstack([a, np.zeros((a.shape[0], N - a.shape[1]))]) if a.shape[1] < N else a

    def __add__(self, other):
        if isinstance(other, Lin):
            N = max(self.coef.shape[1], other.coef.shape[1])
            return Lin(self.const + other.const, self._pad(self.coef, N) + self._pad(other.coef, N))
        return Lin(self.const + np.asarray(other, dtype=float), self.coef)

    __radd__ = __add__

    def __sub__(self, other):
        return self + (-1.0) * other if isinstance(other, Lin) else self + (-np.asarray(other, dtype=float))

    def __rmul__(self, a: float):
        return Lin(a * self.const, a * self.coef)

    def __rmatmul__(self, M):
        M = np.asarray(M, dtype=float)
        return Lin(M @ self.const, M @ self.coef)

    @property
    def dim(self) -> int:
        return self.const.shape[0]


class Noise:
    """Allocator of fresh primitive standard normals."""

    def __init__(self):
        self.N = 0

    def draw(self, cov) -> Lin:
        """A fresh ``N(0, cov)`` vector (cov PSD)."""
        cov = np.atleast_2d(np.asarray(cov, dtype=float))
        w, V = np.linalg.eigh(cov)
        L = V * np.sqrt(np.clip(w, 0.0, None))
        d = cov.shape[0]
        coef = np.zeros((d, self.N + d))
        coef[:, self.N :] = L
        self.N += d
        return Lin(np.zeros(d), coef)


def stack(vs) -> Lin:
    N = max(v.coef.shape[1] for v in vs)
    return Lin(np.concatenate([v.const for v in vs]), np.vstack([Lin._pad(v.coef, N) for v in vs]))


def cov(u: Lin, v: Lin | None = None) -> np.ndarray:
    v = u if v is None else v
    N = max(u.coef.shape[1], v.coef.shape[1])
    return Lin._pad(u.coef, N) @ Lin._pad(v.coef, N).T


def condition(target: Lin, obs: Lin, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of ``target`` given ``obs = value`` (Gaussian conditioning, Cholesky solve)."""
    Soo = cov(obs)
    Sto = cov(target, obs)
    c = scipy.linalg.cho_factor(Soo, lower=True)
    mean = target.const + Sto @ scipy.linalg.cho_solve(c, value - obs.const)
    C = cov(target) - Sto @ scipy.linalg.cho_solve(c, Sto.T)
    return mean, 0.5 * (C + C.T)


def sample(vs: list[Lin], rng: np.random.Generator) -> list[np.ndarray]:
    """One joint draw of the given variables."""
    N = max(v.coef.shape[1] for v in vs)
    xi = rng.standard_normal(N)
    return [v.const + Lin._pad(v.coef, N) @ xi for v in vs]


def random_ltv(n: int, m: int, T: int, rng: np.random.Generator, radius: float = 0.9) -> dict:
    """A random time-varying system ``A (T,n,n), B (T,n,m), c (T,n), W (T,n,n)`` (W PD)."""
    A = np.empty((T, n, n))
    for k in range(T):
        M = rng.standard_normal((n, n))
        A[k] = radius * M / max(1e-9, np.abs(np.linalg.eigvals(M)).max())
    B = rng.standard_normal((T, n, m))
    c = 0.3 * rng.standard_normal((T, n))
    Wf = rng.standard_normal((T, n, n)) * 0.2
    W = Wf @ np.swapaxes(Wf, 1, 2) + 0.05 * np.eye(n)
    return {"A": A, "B": B, "c": c, "W": W}


def random_pd(d: int, rng: np.random.Generator, scale: float = 1.0, floor: float = 0.1) -> np.ndarray:
    M = rng.standard_normal((d, d))
    return scale * (M @ M.T / d + floor * np.eye(d))


def closed_loop(sys: dict, R, mu0, P0, K, k, Sigma, *, filt: dict | None = None, y_row: dict | None = None,
                actions: np.ndarray | None = None):
    """Build the closed loop with :class:`Lin` values.

    ``filt`` (``A, B, c, G (T+1), mu0``) makes the policy act on the predictor-corrector estimate
    ``xhat_k = xhat^-_k + G_k (s_k - xhat^-_k)`` (any gains, not necessarily Kalman's); otherwise it
    acts on ``s_k``.  ``actions (T, m)`` fixes the actions instead (open loop).  ``y_row``
    (``Ay (T,1,n), By (T,1,m), cy (T,1), joint (T, n+1, n+1)`` = joint covariance of ``(w_k, eta_k)``)
    adds ``y_k = Ay x_k + By a_k + cy + eta_k``.  Returns a dict of lists of :class:`Lin`:
    ``x, s, eps, a, xhat`` (``xhat`` only with ``filt``), ``y``.
    """
    noise = Noise()
    T, n = sys["A"].shape[0], sys["A"].shape[1]
    x = [noise.draw(P0) + mu0]
    out = {"x": x, "s": [], "eps": [], "a": [], "xhat": [], "y": []}
    for t in range(T + 1):
        eps = noise.draw(R)
        s = x[t] + eps
        out["eps"].append(eps)
        out["s"].append(s)
        if filt is not None:
            if t == 0:
                pred = Lin(np.asarray(filt["mu0"], dtype=float), np.zeros((n, 0)))
            else:
                pred = filt["A"][t - 1] @ out["xhat"][t - 1] + filt["B"][t - 1] @ out["a"][t - 1] + filt["c"][t - 1]
            out["xhat"].append(pred + filt["G"][t] @ (s - pred))
        if t == T:
            break
        if actions is not None:
            a = Lin(actions[t], np.zeros((actions.shape[1], 0)))
        else:
            state = out["xhat"][t] if filt is not None else s
            a = K[t] @ state + k[t] + noise.draw(Sigma[t])
        out["a"].append(a)
        if y_row is not None:
            we = noise.draw(y_row["joint"][t])
            w = Lin(we.const[:n], we.coef[:n])
            eta = Lin(we.const[n:], we.coef[n:])
            out["y"].append(y_row["Ay"][t] @ x[t] + y_row["By"][t] @ a + y_row["cy"][t] + eta)
        else:
            w = noise.draw(sys["W"][t])
        x.append(sys["A"][t] @ x[t] + sys["B"][t] @ a + sys["c"][t] + w)
    return out
