"""The online filter the policy acts on: an extended Kalman filter of the structured model
(``docs/math.md §11.3``), saved with the policy as plain arrays.

The filter is linearised along a nominal trajectory ``zbar_k`` (the mean smoothed trajectory of
the iteration that produced the policy): ``s_k ~ h(zbar_k) + H_k (z_k - zbar_k) + eps_k``.  Its
gains are then data-independent (computed once, like those of docs/math.md §10.2), and one step is::

    z^-_k  = A_{k-1} zhat_{k-1} + Bz_{k-1} a_{k-1} + cz_{k-1}            (z^-_0 = z_0)
    zhat_k = z^-_k + G_k (s_k - h(zbar_k) - H_k (z^-_k - zbar_k))

With ``online`` (``gains = "online"``) and ``h`` attached, the update is relinearised at each
rollout's own prediction instead: ``H = dh/dz(z^-_k)`` and, with the nominal predicted information
``Lm_k = (P^-_k)^{-1}`` and ``R = rho^2 I``::

    zhat_k = z^-_k + (Lm_k + H^T H / rho^2)^{-1} H^T (s_k - h(z^-_k)) / rho^2

(the extended Kalman update with the prior covariance of the nominal pass; it needs nothing but
``xhat_{k-1}`` from the previous step, so the rollout loop is unchanged).  On widely spread rollouts
the nominal gains err: on a weak peg seed 0.073-0.089 rad against 0.054-0.059 relinearised.

The policy acts on the task-state estimate ``xhat_k = h(zbar_k) + H_k (zhat_k - zbar_k)``, whose
joint coordinates are ``zhat_k`` exactly (so the rollout loop, which passes ``xhat_{k-1}`` back,
needs nothing else) and whose point coordinates are ``h(zhat_k)`` to first order in the distance
from the nominal.  ``P_k`` and ``P^-_k`` are the filter's covariances (``z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ... import compiled
from ...models import LinearGaussianPolicy, ShapeError, check_array
from ..estimator import FilteredPolicy
from .model import AccelMap

__all__ = ["KinematicFilter", "KinematicFilteredPolicy", "build_filter"]

_FIELDS = ("A", "Bz", "cz", "Q", "z0", "P0", "zbar", "h0", "H", "R", "zidx", "accel_B", "accel_D", "accel_c",
           "accel_S", "online")


@dataclass(frozen=True)
class KinematicFilter:
    """Fixed-gain extended Kalman filter in ``z`` (module docstring).

    Fields (``nz`` latent, ``n`` task state, ``m`` actions):
        A (T, nz, nz), Bz (T, nz, m), cz (T, nz), Q (T, nz, nz)   transition in ``z``
        z0 (nz,), P0 (nz, nz)                                    start
        zbar (T+1, nz), h0 (T+1, n), H (T+1, n, nz)              nominal, ``h(zbar)``, ``dh/dz(zbar)``
        R (n, n)                                                 measurement noise
        zidx (nz,)                                               positions of ``z`` in the task state
        accel_B, accel_D, accel_c, accel_S                       the learned map (warm start of EM)
        online (bool)                                            relinearise the update per rollout
        G (T+1, nz, n), P (T+1, nz, nz)                          gains and filtered covariances
        Lm (T+1, nz, nz)                                         nominal predicted information
    """

    A: np.ndarray
    Bz: np.ndarray
    cz: np.ndarray
    Q: np.ndarray
    z0: np.ndarray
    P0: np.ndarray
    zbar: np.ndarray
    h0: np.ndarray
    H: np.ndarray
    R: np.ndarray
    zidx: np.ndarray
    accel_B: np.ndarray
    accel_D: np.ndarray
    accel_c: np.ndarray
    accel_S: np.ndarray
    online: bool = False
    G: np.ndarray = None
    P: np.ndarray = None
    Lm: np.ndarray = None

    def __post_init__(self):
        T, nz, m = np.shape(self.Bz)
        n = np.shape(self.h0)[1]
        nq = nz // 2
        shapes = {"A": (T, nz, nz), "Bz": (T, nz, m), "cz": (T, nz), "Q": (T, nz, nz), "z0": (nz,),
                  "P0": (nz, nz), "zbar": (T + 1, nz), "h0": (T + 1, n), "H": (T + 1, n, nz), "R": (n, n),
                  "zidx": (nz,), "accel_B": (T, nq, m), "accel_D": (T, nq, nz), "accel_c": (T, nq),
                  "accel_S": (T, nq, nq)}
        for name, shape in shapes.items():
            arr = check_array(f"kinematic filter {name}", getattr(self, name), shape).copy()
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "zidx", self.zidx.astype(int))
        object.__setattr__(self, "online", bool(self.online))
        if self.online and np.any(self.R) and not np.allclose(self.R, self.R[0, 0] * np.eye(n)):
            raise ValueError("kinematic filter: the online update needs R = rho^2 I")
        G, P, Lm = _gains(self)
        for name, arr in (("G", G), ("P", P), ("Lm", Lm)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def T(self) -> int:
        return self.A.shape[0]

    @property
    def n(self) -> int:
        return self.h0.shape[1]

    @property
    def m(self) -> int:
        return self.Bz.shape[2]

    def accel(self) -> AccelMap:
        return AccelMap(self.accel_B, self.accel_D, self.accel_c, self.accel_S)

    def step(self, k: int, s_k, xhat_prev=None, a_prev=None) -> np.ndarray:
        """``xhat_k (..., n)`` from ``s_k (..., n)`` and, for ``k >= 1``, ``xhat_{k-1}``, ``a_{k-1}``.

        The rows are independent to the last bit: a batch of ``B`` rollouts gives each row exactly what
        that rollout gives alone (the vector-matrix products of a batch are stacked matrix-vector
        products, :func:`_vm`; ``h``, the solves and the reductions are per row), so rollouts stepped
        in lockstep (:meth:`KinematicFilteredPolicy.estimate_rows`) equal rollouts stepped one at a time."""
        s_k = np.asarray(s_k, dtype=float)
        if s_k.shape[-1] != self.n:
            raise ShapeError(f"measurement s_k must have shape (..., {self.n}), got {s_k.shape}")
        if not np.any(self.R):  # rho^2 = 0: the measurement is the state
            return s_k.copy()
        if k == 0:
            pred = np.broadcast_to(self.z0, s_k.shape[:-1] + self.z0.shape)
        else:
            if xhat_prev is None or a_prev is None:
                raise ValueError(f"kinematic filter step {k} needs the previous estimate and action")
            zp = np.asarray(xhat_prev, dtype=float)[..., self.zidx]
            pred = _vm(zp, self.A[k - 1].T) + _vm(np.asarray(a_prev, dtype=float), self.Bz[k - 1].T) + self.cz[k - 1]
        km = self.__dict__.get("_km")
        if km is not None and self.online:
            hx, H = km.measure(pred)
            return km.measure(pred + _online_update(s_k, hx, H, self.Lm[k], self.R[0, 0]), False)
        if km is None:
            dz = pred - self.zbar[k]
            nu = s_k - self.h0[k] - _vm(dz, self.H[k].T)
            return self.h0[k] + _vm(dz + _vm(nu, self.G[k].T), self.H[k].T)
        return km.measure(pred + _vm(s_k - km.measure(pred, False), self.G[k].T), False)

    def attach(self, km) -> "KinematicFilter":
        """Evaluate ``h`` exactly (MuJoCo, ``km`` a :class:`~soc_opt.noise.kinematic.model.KinematicModel` of
        the task) at the prediction and the estimate instead of its linearisation along ``zbar``;
        returns ``self``.  The gains stay those of the nominal linearisation."""
        if km.zidx.shape != self.zidx.shape or np.any(km.zidx != self.zidx) or km.n != self.n:
            raise ShapeError(f"kinematic filter: task state layout (n = {km.n}) does not match the filter's (n = {self.n})")
        object.__setattr__(self, "_km", km)
        return self

    def states(self, s, a) -> np.ndarray:
        """Filtered task-state estimates ``(..., T+1, n)`` of whole trajectories."""
        s = np.asarray(s, dtype=float)
        out = np.empty(s.shape)
        out[..., 0, :] = self.step(0, s[..., 0, :])
        for k in range(1, self.T + 1):
            out[..., k, :] = self.step(k, s[..., k, :], out[..., k - 1, :], a[..., k - 1, :])
        return out

    def to_dict(self) -> dict:
        return {k: np.array(getattr(self, k)) for k in _FIELDS}

    @staticmethod
    def from_dict(d) -> "KinematicFilter":
        """From :meth:`to_dict` output (a file saved before ``online`` existed reads as nominal gains)."""
        return KinematicFilter(**{k: np.asarray(d[k]) for k in _FIELDS if k in d or k != "online"})


def _online_update(s_k, hx, H, Lm, r2: float, kernels: str | None = None) -> np.ndarray:
    """``(Lm + H^T H / r2)^{-1} H^T (s_k - hx) / r2`` per row of ``s_k, hx (..., n)``, ``H (..., n, nz)``: the
    relinearised update of the module docstring.  With numba, one compiled loop over the rows
    (:mod:`soc_opt.compiled.kinematic_kernels`; ``kernels`` as in :func:`soc_opt.compiled.backend`),
    which agrees with the numpy reference below to rounding; each row computed alone either way."""
    if compiled.backend(kernels) == "numba":
        from ...compiled import kinematic_kernels

        lead, (n, nz) = H.shape[:-2], H.shape[-2:]
        out = np.empty(lead + (nz,))
        ok = kinematic_kernels.online_update(np.ascontiguousarray(np.broadcast_to(s_k, lead + (n,))).reshape(-1, n),
                                             np.ascontiguousarray(hx).reshape(-1, n), np.ascontiguousarray(H).reshape(-1, n, nz),
                                             np.ascontiguousarray(Lm), float(r2), out.reshape(-1, nz))
        if not ok:
            raise np.linalg.LinAlgError("kinematic filter: singular update matrix Lm + H^T H / rho^2")
        return out
    Ht = np.swapaxes(H, -1, -2)
    g = np.einsum("...ij,...j->...i", Ht, s_k - hx) / r2
    return np.linalg.solve(Lm + Ht @ H / r2, g[..., None])[..., 0]


def _vm(x: np.ndarray, A: np.ndarray) -> np.ndarray:
    """``x @ A`` for ``x (..., i)`` and ``A (i, j)``, each row of a batch computed as the single vector is.

    One vector ``(i,)`` is multiplied as ``x @ A`` (a matrix-vector BLAS call); a batch ``(..., i)`` as the
    stack of ``(1, i)`` rows ``(x[..., None, :] @ A)[..., 0, :]``, which numpy's matmul evaluates with the
    same call per row (a single ``(B, i) @ (i, j)`` product would be a matrix-matrix call, whose rounding
    differs).  So a row's result does not depend on the batch it is in (tested bit for bit)."""
    return x @ A if x.ndim == 1 else (x[..., None, :] @ A)[..., 0, :]


def _gains(f: KinematicFilter):
    T1, nz = f.zbar.shape
    G = np.empty((T1, nz, f.n))
    P = np.empty((T1, nz, nz))
    Lm = np.empty((T1, nz, nz))
    Pm = f.P0
    eye = np.eye(nz)
    for k in range(T1):
        if k > 0:
            Pm = f.A[k - 1] @ P[k - 1] @ f.A[k - 1].T + f.Q[k - 1]
        Lm[k] = np.linalg.inv(0.5 * (Pm + Pm.T))
        Lm[k] = 0.5 * (Lm[k] + Lm[k].T)
        H = f.H[k]
        S = H @ Pm @ H.T + f.R
        S = 0.5 * (S + S.T)
        G[k] = np.linalg.lstsq(S, H @ Pm, rcond=None)[0].T if not np.any(f.R) else np.linalg.solve(S, H @ Pm).T
        IG = eye - G[k] @ H
        P[k] = IG @ Pm @ IG.T + G[k] @ f.R @ G[k].T
        P[k] = 0.5 * (P[k] + P[k].T)
    return G, P, Lm


def build_filter(km, accel: AccelMap, lg, zbar, rho2: float, online: bool = False) -> KinematicFilter:
    """The policy's filter from the learned ``accel`` (its transition ``lg``) linearised along ``zbar (T+1, nz)``;
    ``online``: relinearise the update at each rollout's prediction (module docstring)."""
    h0, H = km.measure(zbar)
    return KinematicFilter(A=lg.A, Bz=lg.Bz, cz=lg.cz, Q=lg.Q, z0=lg.z0, P0=lg.P0, zbar=zbar, h0=h0, H=H,
                           R=rho2 * np.eye(km.n), zidx=km.zidx, accel_B=accel.B, accel_D=accel.D,
                           accel_c=accel.c, accel_S=accel.S, online=online)


@dataclass(frozen=True)
class KinematicFilteredPolicy(FilteredPolicy):
    """``a_k = K_k xhat_k + k_k + L_k w_k`` with ``xhat_k`` from a :class:`KinematicFilter`.

    Saved flat (``numpy.savez``): the policy's ``K, k, cov`` and ``kfilter_<field>``.
    """

    filter: KinematicFilter

    def __post_init__(self):
        if not isinstance(self.policy, LinearGaussianPolicy):
            raise TypeError(f"policy must be a LinearGaussianPolicy, got {type(self.policy).__name__}")
        if not isinstance(self.filter, KinematicFilter):
            raise TypeError(f"filter must be a KinematicFilter, got {type(self.filter).__name__}")
        p, f = self.policy, self.filter
        if (p.T, p.n, p.m) != (f.T, f.n, f.m):
            raise ShapeError(f"policy has (T, n, m) = {(p.T, p.n, p.m)} but its kinematic filter has {(f.T, f.n, f.m)}")

    def for_task(self, task) -> "KinematicFilteredPolicy":
        """The policy with its filter evaluating ``h`` through ``task``'s MuJoCo model, as in the loop
        that made it: a filter read back from a checkpoint (data only, no model) is attached here, on
        first use by the task's rollouts; an attached one is returned as is."""
        if self.filter.__dict__.get("_km") is None:
            from .model import KinematicModel

            self.filter.attach(KinematicModel(task))
        return self

    def estimate(self, k: int, s_k, xhat_prev=None, a_prev=None) -> np.ndarray:
        return self.filter.step(k, s_k, xhat_prev, a_prev)

    def estimate_rows(self, k: int, s_k, xhat_prev=None, a_prev=None) -> np.ndarray:
        """:meth:`estimate` of ``B`` rollouts in one call: :meth:`KinematicFilter.step` on the batch, whose
        rows are those of one rollout at a time bit for bit."""
        return self.filter.step(k, s_k, xhat_prev, a_prev)

    def to_dict(self) -> dict:
        return {**self.policy.to_dict(), **{f"kfilter_{k}": v for k, v in self.filter.to_dict().items()}}

    @staticmethod
    def from_dict(d, task=None) -> "KinematicFilteredPolicy":
        """Rebuild from :meth:`to_dict` output; with ``task`` the filter evaluates ``h`` through its
        MuJoCo model (:meth:`KinematicFilter.attach`, as in the loop), else its linearisation."""
        from .model import KinematicModel

        cov = np.asarray(d["cov"], dtype=float)
        singular = bool(cov.size) and bool(np.any(np.linalg.eigvalsh(cov)[..., 0] <= 0.0))
        pol = LinearGaussianPolicy(d["K"], d["k"], cov, allow_singular=singular)
        f = KinematicFilter.from_dict({k: d[f"kfilter_{k}"] for k in _FIELDS if f"kfilter_{k}" in d})
        return KinematicFilteredPolicy(pol, f if task is None else f.attach(KinematicModel(task)))
