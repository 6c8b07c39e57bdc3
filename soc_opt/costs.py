"""Cost terms with analytic derivatives (docs/math.md §0, §6, §8).

Every term is a stage cost ``l_k(s_k, a_k)`` for ``k = 0..T-1``; the state
``s_T`` after the last action is never charged (the :class:`QuadraticCost`
convention).  Terms take states ``s (..., T, n)`` -- or ``(..., T+1, n)``, the
last state is then ignored -- and actions ``a (..., T, m)``.

Terms (each multiplied by ``weight * r_k`` with the ramp ``r`` below):

* :class:`PointCost` -- ``1/2 l2 d^2 + l1 sqrt(alpha + d^2)`` with
  ``d^2 = sum_i wp_i (p_i - p*_i)^2``; ``p`` are state components (e.g. the
  positions of one or several sites, stacked) and ``p*`` is a fixed target or
  other state components (``target_idx``: distance between two points that
  both live in the state, e.g. a hook and a moving door handle).
* :class:`TorqueCost` -- ``1/2 a^T diag(wu) a``.
* :class:`StateCost` -- ``1/2 sum_i w_i (s_{idx_i} - s*_i)^2``.
* :class:`QuadraticStateActionCost` -- the docs/math.md §0 cost
  ``(s - s*)^T Qs (s - s*) + (a - a*)^T Qa (a - a*)`` (no factor 1/2).

Ramps over ``k = 0..T-1`` with ``t_k = (k + 1) / T`` (the GPS definitions):

* ``constant``:   ``r_k = 1``
* ``linear``:     ``r_k = t_k``
* ``quadratic``:  ``r_k = t_k^2``
* ``final_only``: ``r_k = 0`` except ``r_{T-1} = 1``

and afterwards ``r_{T-1} *= final_multiplier`` (default 1).  A ``window = (w0, w1)``
(fractions of the horizon, ``0 <= w0 < w1 <= 1``) keeps the term on stages
``ceil(w0 T) <= k < ceil(w1 T)`` only (``r_k = 0`` elsewhere): a cost in phases, e.g. reach a
point first and push from it afterwards.

:class:`CostSum` adds terms, returns the derivatives ``lx (T,n)``, ``lu (T,m)``,
``lxx (T,n,n)``, ``luu (T,m,m)``, ``lux (T,m,n)`` at a trajectory, and
:meth:`CostSum.expand` turns the second-order Taylor expansion around
``(s_bar, a_bar)`` into the absolute form ``1/2 z^T C z + z^T c + c0`` of
:class:`soc_opt.models.QuadraticCost`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .models import QuadraticCost, ShapeError, check_array, symmetrize

__all__ = [
    "RAMPS",
    "ramp",
    "window_mask",
    "Derivatives",
    "CostTerm",
    "PointCost",
    "TorqueCost",
    "StateCost",
    "QuadraticStateActionCost",
    "CostSum",
]

RAMPS = ("constant", "linear", "quadratic", "final_only")


def ramp(kind: str, T: int, final_multiplier: float = 1.0) -> np.ndarray:
    """Ramp multipliers ``r (T,)`` over the stage costs (definitions in the module docstring)."""
    if T < 1:
        raise ValueError(f"ramp needs T >= 1, got {T}")
    t = np.arange(1, T + 1) / T
    if kind == "constant":
        r = np.ones(T)
    elif kind == "linear":
        r = t.copy()
    elif kind == "quadratic":
        r = t**2
    elif kind == "final_only":
        r = np.zeros(T)
        r[-1] = 1.0
    else:
        raise ValueError(f"unknown ramp {kind!r}; allowed: {', '.join(RAMPS)}")
    r[-1] *= final_multiplier
    return r


def window_mask(window: tuple[float, float] | None, T: int) -> np.ndarray:
    """``(T,)`` 0/1 mask of the stages ``ceil(w0 T) <= k < ceil(w1 T)`` of ``window = (w0, w1)``
    (all ones for ``None``)."""
    if window is None:
        return np.ones(T)
    w0, w1 = window
    k = np.arange(T)
    return ((k >= np.ceil(w0 * T - 1e-9)) & (k < np.ceil(w1 * T - 1e-9))).astype(float)


def check_window(name: str, window) -> tuple[float, float] | None:
    """``window`` as a ``(w0, w1)`` tuple with ``0 <= w0 < w1 <= 1`` (or ``None``); errors name the term."""
    if window is None:
        return None
    w = tuple(float(v) for v in window)
    if len(w) != 2 or not (0.0 <= w[0] < w[1] <= 1.0):
        raise ValueError(f"{name}: window must be two fractions of the horizon 0 <= w0 < w1 <= 1, got {list(window)}")
    return w


@lru_cache(maxsize=256)
def _ramp_cached(kind: str, T: int, final_multiplier: float, window: tuple[float, float] | None = None) -> np.ndarray:
    """:func:`ramp` times :func:`window_mask`, computed once per arguments (read-only: it is shared)."""
    r = ramp(kind, T, final_multiplier) * window_mask(window, T)
    r.flags.writeable = False
    return r


@dataclass(frozen=True)
class Derivatives:
    """Stage costs and their derivatives along one trajectory.

    l (T,), lx (T,n), lu (T,m), lxx (T,n,n), luu (T,m,m), lux (T,m,n).
    """

    l: np.ndarray
    lx: np.ndarray
    lu: np.ndarray
    lxx: np.ndarray
    luu: np.ndarray
    lux: np.ndarray

    def __add__(self, other: "Derivatives") -> "Derivatives":
        return Derivatives(*(getattr(self, f) + getattr(other, f) for f in ("l", "lx", "lu", "lxx", "luu", "lux")))


def _zeros(T: int, n: int, m: int) -> Derivatives:
    return Derivatives(
        np.zeros(T), np.zeros((T, n)), np.zeros((T, m)), np.zeros((T, n, n)), np.zeros((T, m, m)), np.zeros((T, m, n))
    )


def _one_stage(name: str, n: int, m: int, s_k, a_k, k: int, T: int) -> tuple[np.ndarray, np.ndarray]:
    """``(s_k (1, n), a_k (1, m))`` as float rows, after checking the shapes and ``0 <= k < T``."""
    s_k = np.asarray(s_k, dtype=float)
    a_k = np.asarray(a_k, dtype=float)
    if s_k.shape != (n,) or a_k.shape != (m,):
        raise ShapeError(f"{name}: one stage needs s_k ({n},) and a_k ({m},), got {s_k.shape}, {a_k.shape}")
    if not 0 <= k < T:
        raise ValueError(f"{name}: stage {k} outside 0..{T - 1}")
    return s_k[None], a_k[None]


class CostTerm(ABC):
    """Base class: ``weight * r_k * l_k(s_k, a_k)``.

    Subclasses implement ``_value(s (...,T,n), a (...,T,m)) -> (...,T)`` and
    ``_derivatives(s (T,n), a (T,m)) -> Derivatives`` without weight or ramp.
    """

    name = "term"

    def __init__(self, n: int, m: int, *, ramp: str = "constant", final_multiplier: float = 1.0, weight: float = 1.0,
                 window: tuple[float, float] | None = None):
        if ramp not in RAMPS:
            raise ValueError(f"{self.name} cost: unknown ramp {ramp!r}; allowed: {', '.join(RAMPS)}")
        self.n, self.m = int(n), int(m)
        self.ramp = ramp
        self.window = check_window(f"{self.name} cost", window)
        self.final_multiplier = float(final_multiplier)
        self.weight = float(weight)

    def multipliers(self, T: int) -> np.ndarray:
        """``weight * r (T,)`` (``r``: the ramp, zero outside the ``window``)."""
        return self.weight * _ramp_cached(self.ramp, T, self.final_multiplier, self.window)

    def stage(self, s_k, a_k, k: int, T: int) -> np.float64:
        """``weight * r_k * l_k(s_k, a_k)`` of one stage ``k`` of a horizon-``T`` trajectory, in O(1).

        ``s_k (n,)``, ``a_k (m,)``.  Equal bit for bit to ``self(s, a)[..., k]`` for any
        trajectory ``s``, ``a`` through ``(s_k, a_k)`` at stage ``k``: the same kernel
        (``_value``) on a one-stage slice -- every kernel reduces each stage's own row only, so
        its rounding does not depend on the number of stages -- times the same multiplier
        (docs/gym.md, "Reward").
        """
        return self._stage(*_one_stage(f"{self.name} cost", self.n, self.m, s_k, a_k, k, T), k, T)

    def _stage(self, s1, a1, k: int, T: int) -> np.float64:
        """:meth:`stage` of checked one-row arrays ``s1 (1, n)``, ``a1 (1, m)``."""
        return self._value(s1, a1)[0] * (self.weight * _ramp_cached(self.ramp, T, self.final_multiplier, self.window)[k])

    def _split(self, s, a):
        s = np.asarray(s, dtype=float)
        a = np.asarray(a, dtype=float)
        if a.ndim < 2 or a.shape[-1] != self.m:
            raise ShapeError(f"{self.name} cost: actions must have shape (..., T, {self.m}), got {a.shape}")
        T = a.shape[-2]
        if s.ndim < 2 or s.shape[-1] != self.n or s.shape[-2] not in (T, T + 1):
            raise ShapeError(f"{self.name} cost: states must have shape (..., {T} or {T + 1}, {self.n}), got {s.shape}")
        return s[..., :T, :], a, T

    def __call__(self, s, a) -> np.ndarray:
        s, a, T = self._split(s, a)
        return self._value(s, a) * self.multipliers(T)

    def derivatives(self, s, a) -> Derivatives:
        s, a, T = self._split(s, a)
        if s.ndim != 2:
            raise ShapeError(f"{self.name} cost: derivatives need one trajectory s (T+1, n), got {s.shape}")
        d = self._derivatives(s, a)
        r = self.multipliers(T)
        return Derivatives(
            d.l * r, d.lx * r[:, None], d.lu * r[:, None], d.lxx * r[:, None, None], d.luu * r[:, None, None],
            d.lux * r[:, None, None],
        )

    @abstractmethod
    def _value(self, s, a) -> np.ndarray:
        """Unramped stage values ``(..., T)``."""

    @abstractmethod
    def _derivatives(self, s, a) -> Derivatives:
        """Unramped value and derivatives along one trajectory."""


def _vec(name: str, v, size: int) -> np.ndarray:
    """Broadcast a scalar or a vector whose length divides ``size`` (repeated) to ``(size,)``."""
    v = np.atleast_1d(np.asarray(v, dtype=float))
    if v.ndim != 1 or v.size == 0 or size % v.size:
        raise ShapeError(f"{name} must be a scalar or have length {size} (or a divisor of it), got shape {v.shape}")
    return np.tile(v, size // v.size)


class PointCost(CostTerm):
    """``1/2 l2 d^2 + l1 sqrt(alpha + d^2)``, ``d^2 = sum_i wp_i (s[idx_i] - p*_i)^2``.

    Args:
        n, m: state and action dimensions.
        idx: state indices of the point coordinates (``3 P`` for ``P`` stacked points).
        target: fixed target ``(len(idx),)``; or
        target_idx: state indices of a second, moving point (then ``d`` is the
            weighted distance between the two points of the state);
        target_offset: with ``target_idx``, a constant ``(len(idx),)`` added to the moving point
            (e.g. a point 8 cm behind an object to push it from there; default 0).
        wp: per-coordinate weights (scalar, length 3 repeated per point, or ``len(idx)``).
        l1, l2, alpha: as in the formula (``alpha > 0`` keeps the root smooth).
    """

    name = "point"

    def __init__(self, n, m, idx, *, target=None, target_idx=None, target_offset=None, wp=1.0, l1=0.0, l2=1.0,
                 alpha=1e-5, **kw):
        super().__init__(n, m, **kw)
        idx = np.asarray(idx, dtype=int).ravel()
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n:
            raise ValueError(f"point cost: state indices {idx.tolist()} out of range for n={n}")
        p = idx.size
        S = np.zeros((p, n))
        S[np.arange(p), idx] += 1.0
        if (target is None) == (target_idx is None):
            raise ValueError("point cost: give exactly one of target (a fixed point) or target_idx (a point in the state)")
        if target_idx is not None:
            tidx = np.asarray(target_idx, dtype=int).ravel()
            if tidx.size != p or tidx.min() < 0 or tidx.max() >= n:
                raise ValueError(f"point cost: target indices {tidx.tolist()} must be {p} indices below n={n}")
            S[np.arange(p), tidx] -= 1.0
            self.target = np.zeros(p) if target_offset is None else _vec("point cost target_offset", target_offset, p)
        elif target_offset is not None:
            raise ValueError("point cost: target_offset needs target_idx (a moving point to offset)")
        else:
            self.target = _vec("point cost target", target, p)
        self.S = S
        self.idx = idx
        self.wp = _vec("point cost wp", wp, p)
        if np.any(self.wp < 0):
            raise ValueError("point cost: wp must be non-negative")
        self.l1, self.l2, self.alpha = float(l1), float(l2), float(alpha)
        if self.l1 < 0 or self.l2 < 0:
            raise ValueError("point cost: l1 and l2 must be non-negative")
        if self.l1 > 0 and self.alpha <= 0:
            raise ValueError("point cost: alpha must be positive when l1 > 0")

    def _err(self, s):
        return s @ self.S.T - self.target

    def _value(self, s, a):
        e = self._err(s)
        d2 = np.sum(self.wp * e * e, axis=-1)
        return 0.5 * self.l2 * d2 + self.l1 * np.sqrt(self.alpha + d2)

    def _derivatives(self, s, a):
        T = s.shape[0]
        e = self._err(s)  # (T, p)
        we = self.wp * e
        d2 = np.sum(we * e, axis=-1)
        out = _zeros(T, self.n, self.m)
        if self.l1 > 0:
            root = np.sqrt(self.alpha + d2)
            l = 0.5 * self.l2 * d2 + self.l1 * root
            coef = self.l2 + self.l1 / root  # (T,)
            He = coef[:, None, None] * np.diag(self.wp) - (self.l1 / root**3)[:, None, None] * we[:, :, None] * we[:, None, :]
        else:
            l = 0.5 * self.l2 * d2
            coef = np.full(T, self.l2)
            He = np.broadcast_to(self.l2 * np.diag(self.wp), (T,) + (self.wp.size,) * 2)
        ge = coef[:, None] * we
        lx = ge @ self.S
        lxx = np.einsum("ai,tab,bj->tij", self.S, He, self.S)
        return Derivatives(l, lx, out.lu, symmetrize(lxx), out.luu, out.lux)


class TorqueCost(CostTerm):
    """``1/2 a^T diag(wu) a``."""

    name = "torque"

    def __init__(self, n, m, wu=1.0, **kw):
        super().__init__(n, m, **kw)
        self.wu = _vec("torque cost wu", wu, m)

    def _value(self, s, a):
        return 0.5 * np.sum(self.wu * a * a, axis=-1)

    def _derivatives(self, s, a):
        T = a.shape[0]
        out = _zeros(T, self.n, self.m)
        luu = np.broadcast_to(np.diag(self.wu), (T, self.m, self.m)).copy()
        return Derivatives(self._value(s, a), out.lx, a * self.wu, out.lxx, luu, out.lux)


class StateCost(CostTerm):
    """``1/2 sum_i w_i (s[idx_i] - s*_i)^2`` (``idx`` defaults to the whole state)."""

    name = "state"

    def __init__(self, n, m, *, idx=None, target=0.0, weights=1.0, **kw):
        super().__init__(n, m, **kw)
        idx = np.arange(n) if idx is None else np.asarray(idx, dtype=int).ravel()
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n:
            raise ValueError(f"state cost: indices {idx.tolist()} out of range for n={n}")
        self.idx = idx
        self.target = _vec("state cost target", target, idx.size)
        self.w = _vec("state cost weights", weights, idx.size)
        self.Wfull = np.zeros((n, n))
        np.add.at(self.Wfull, (idx, idx), self.w)
        self.gfull = np.zeros(n)

    def _value(self, s, a):
        e = s[..., self.idx] - self.target
        return 0.5 * np.sum(self.w * e * e, axis=-1)

    def _derivatives(self, s, a):
        T = s.shape[0]
        out = _zeros(T, self.n, self.m)
        e = s[:, self.idx] - self.target
        lx = np.zeros((T, self.n))
        np.add.at(lx, (slice(None), self.idx), self.w * e)
        lxx = np.broadcast_to(self.Wfull, (T, self.n, self.n)).copy()
        return Derivatives(self._value(s, a), lx, out.lu, lxx, out.luu, out.lux)


def _matrix(name: str, Q, d: int) -> np.ndarray:
    Q = np.asarray(Q, dtype=float)
    if Q.ndim == 0:
        return float(Q) * np.eye(d)
    if Q.ndim == 1:
        if Q.size != d:
            raise ShapeError(f"{name} diagonal must have length {d}, got {Q.size}")
        return np.diag(Q)
    if Q.shape != (d, d):
        raise ShapeError(f"{name} must have shape ({d}, {d}), got {Q.shape}")
    return symmetrize(Q)


class QuadraticStateActionCost(CostTerm):
    """docs/math.md §0: ``(s - s*)^T Qs (s - s*) + (a - a*)^T Qa (a - a*)`` (no factor 1/2).

    ``Qs``/``Qa`` may be scalars (times identity), diagonals or full matrices.
    """

    name = "quadratic"

    def __init__(self, n, m, *, Qs=1.0, Qa=0.0, target=0.0, action_target=0.0, **kw):
        super().__init__(n, m, **kw)
        self.Qs = _matrix("quadratic cost Qs", Qs, n)
        self.Qa = _matrix("quadratic cost Qa", Qa, m)
        self.target = _vec("quadratic cost target", target, n)
        self.action_target = _vec("quadratic cost action_target", action_target, m)

    def _value(self, s, a):
        e = s - self.target
        f = a - self.action_target
        return np.einsum("...i,ij,...j->...", e, self.Qs, e) + np.einsum("...i,ij,...j->...", f, self.Qa, f)

    def _derivatives(self, s, a):
        T = s.shape[0]
        e = s - self.target
        f = a - self.action_target
        return Derivatives(
            self._value(s, a),
            2.0 * e @ self.Qs,
            2.0 * f @ self.Qa,
            np.broadcast_to(2.0 * self.Qs, (T, self.n, self.n)).copy(),
            np.broadcast_to(2.0 * self.Qa, (T, self.m, self.m)).copy(),
            np.zeros((T, self.m, self.n)),
        )


class CostSum:
    """A sum of cost terms: ``l_k = sum_j term_j(s_k, a_k)``."""

    def __init__(self, terms, n: int, m: int):
        self.terms = list(terms)
        self.n, self.m = int(n), int(m)
        for t in self.terms:
            if (t.n, t.m) != (self.n, self.m):
                raise ShapeError(f"{t.name} cost has dimensions (n={t.n}, m={t.m}), expected (n={self.n}, m={self.m})")

    def __call__(self, s, a) -> np.ndarray:
        """Stage costs ``(..., T)`` for ``s (..., T+1 or T, n)`` and ``a (..., T, m)``."""
        a = np.asarray(a, dtype=float)
        out = np.zeros(a.shape[:-1])
        for t in self.terms:
            out = out + t(s, a)
        return out

    def stage(self, s_k, a_k, k: int, T: int) -> float:
        """Stage cost ``l_k(s_k (n,), a_k (m,))`` of stage ``k`` of a horizon-``T`` trajectory, in O(1).

        Equal bit for bit to ``self(s, a)[..., k]`` of any trajectory through ``(s_k, a_k)`` at
        stage ``k`` (:meth:`CostTerm.stage`, added in the same order from the same zero); what
        :class:`soc_opt.envs.SocOptEnv` charges per step (docs/gym.md, "Reward").
        """
        s1, a1 = _one_stage("cost", self.n, self.m, s_k, a_k, k, T)
        out = 0.0
        for t in self.terms:
            out = out + t._stage(s1, a1, k, T)
        return float(out)

    def derivatives(self, s, a) -> Derivatives:
        """Costs and derivatives along one trajectory ``s (T+1 or T, n)``, ``a (T, m)``."""
        a = check_array("cost actions a", a, (None, self.m))
        T = a.shape[0]
        s = np.asarray(s, dtype=float)
        if s.ndim != 2 or s.shape[1] != self.n or s.shape[0] not in (T, T + 1):
            raise ShapeError(f"cost states s must have shape ({T + 1}, {self.n}), got {s.shape}")
        out = _zeros(T, self.n, self.m)
        for t in self.terms:
            out = out + t.derivatives(s, a)
        return out

    def expand(self, s, a) -> QuadraticCost:
        """Second-order Taylor expansion around ``(s_bar, a_bar)`` in absolute coordinates.

        With ``z = (s_k, a_k)``, ``g = (lx, lu)`` and ``H = [[lxx, lux^T], [lux, luu]]``:
        ``l(z) ~ l_bar + g^T (z - z_bar) + 1/2 (z - z_bar)^T H (z - z_bar)
                = 1/2 z^T H z + z^T (g - H z_bar) + (l_bar - g^T z_bar + 1/2 z_bar^T H z_bar)``.
        """
        a = np.asarray(a, dtype=float)
        T = a.shape[0]
        d = self.derivatives(s, a)
        s = np.asarray(s, dtype=float)[:T]
        n = self.n
        H = np.zeros((T, n + self.m, n + self.m))
        H[:, :n, :n] = d.lxx
        H[:, n:, n:] = d.luu
        H[:, n:, :n] = d.lux
        H[:, :n, n:] = np.swapaxes(d.lux, 1, 2)
        H = symmetrize(H)
        g = np.concatenate([d.lx, d.lu], axis=1)
        zbar = np.concatenate([s, a], axis=1)
        Hz = np.einsum("tij,tj->ti", H, zbar)
        c = g - Hz
        c0 = d.l - np.einsum("ti,ti->t", g, zbar) + 0.5 * np.einsum("ti,ti->t", zbar, Hz)
        return QuadraticCost(H, c, n, c0)
