"""The structured model as the learner's local dynamics in task coordinates (``docs/math.md §11.3 (a)``).

``dynamics = "structured"`` of ``[baseline.noise.kinematic]``: instead of regressing ``x_{k+1}`` on
``(x_k, a_k)`` over the smoothed rollouts (§2), the KL step and the EM phase use the transition the
estimator learned (the kinematic rows and the acceleration map, in ``z``) carried into the task's
state vector through ``h`` linearised along the nominal ``zbar`` of the batch's filter::

    z_k     = Pi x_k                                      (the joint coordinates of x, exactly)
    z_{k+1} = A_k z_k + Bz_k a_k + cz_k + w_k,  w_k ~ N(0, Q_k)
    x_{k+1} = h(zbar_{k+1}) + H_{k+1} (z_{k+1} - zbar_{k+1})

so ``F_k = H_{k+1} A_k Pi``, ``G_k = H_{k+1} Bz_k``, ``f_k = h(zbar_{k+1}) + H_{k+1} (cz_k - zbar_{k+1})``
and ``W_k = H_{k+1} Q_k H_{k+1}^T + w_floor I`` (rank ``nz`` plus a floor: the site rows of ``x`` are
functions of ``z``).  The dynamics do not depend on the site columns of ``x_k``, so the KL step's
gains on them are zero when the reference policy's are: the policy acts on the filter's ``zhat``.

It is the model the policy's filter predicts with, so the KL step's predictions and the filter agree.
It cannot represent what the acceleration map cannot (contact that differs within a time segment).

``structured_prior > 0`` keeps the §2 regression and uses the same transition as a conjugate prior
on it (:func:`structured_prior`, ``docs/math.md §11.3``).
"""

from __future__ import annotations

import numpy as np

from ...models import AugmentedModel, LinearGaussianDynamics, ShapeError, symmetrize
from .filter import KinematicFilter

__all__ = ["structured_dynamics", "with_dynamics", "structured_prior"]


def structured_dynamics(f: KinematicFilter, w_floor: float) -> LinearGaussianDynamics:
    """The filter's transition in the task's state coordinates (module docstring), ``(T, n, n)`` etc."""
    if not w_floor > 0:
        raise ValueError(f"w_floor must be positive, got {w_floor!r}")
    T, nz, _ = f.A.shape
    n = f.n
    Pi = np.zeros((nz, n))
    Pi[np.arange(nz), f.zidx] = 1.0
    H1 = f.H[1:]                                               # (T, n, nz)
    F = H1 @ f.A @ Pi                                          # (T, n, n)
    G = H1 @ f.Bz                                              # (T, n, m)
    c = f.h0[1:] + np.einsum("tij,tj->ti", H1, f.cz - f.zbar[1:])
    W = symmetrize(H1 @ f.Q @ np.swapaxes(H1, -1, -2)) + w_floor * np.eye(n)
    return LinearGaussianDynamics(F, G, c, W)


def with_dynamics(model: AugmentedModel, dyn: LinearGaussianDynamics) -> AugmentedModel:
    """``model`` (the §1 augmented fit) with its state rows replaced by ``dyn``; the cost rows
    ``(Ay, By, cy, var y)`` kept, their cross-covariance with ``s_{k+1}`` set to zero."""
    n = model.n
    if (dyn.T, dyn.n, dyn.m) != (model.T, n, model.m):
        raise ShapeError(f"dynamics (T, n, m) = {(dyn.T, dyn.n, dyn.m)} do not match the augmented model's "
                         f"{(model.T, n, model.m)}")
    Ao = np.array(model.Ao)
    co = np.array(model.co)
    So = np.zeros_like(model.So)
    Ao[:, :n, :n], Ao[:, :n, n:], co[:, :n] = dyn.A, dyn.B, dyn.c
    So[:, :n, :n] = dyn.cov
    So[:, n, n] = model.So[:, n, n]
    return AugmentedModel(Ao, co, So, n)


def structured_prior(dyn: LinearGaussianDynamics, strength: float, count: float):
    """The ``correct`` hook of :func:`soc_opt.learning.fit.fit_dynamics`: the structured transition ``dyn``
    as a conjugate prior of ``strength`` pseudo-observations on the per-step fit whose joint moments
    ``(mu (T, d), Lam (T, d, d))`` of the tuples ``(x_k, a_k, x_{k+1}[, y_k])`` weigh ``count``
    (``docs/math.md §11.3``, *structured prior*).

    The prior's tuples share the data's ``(x_k, a_k)`` moments ``(mu_z, S_zz)`` and follow ``dyn``::

        mu_s  = (mu_z, F mu_z + f),   S_s = [[S_zz, S_zz F^T], [F S_zz, F S_zz F^T + W]]

    (the cost column ``y``, if present, keeps its moments, with ``Cov(x_{k+1}, y) = F Cov(z, y)``); the
    result is the moments of the pooled sample, ``w = strength / (strength + count)``::

        mu'  = (1 - w) mu + w mu_s
        Lam' = (1 - w) Lam + w S_s + w (1 - w) (mu - mu_s)(mu - mu_s)^T

    so the fit's regression lies between the data's and ``dyn``, nearer ``dyn`` where the batch says
    little, and its covariance carries their disagreement.
    """
    if not (strength >= 0 and count > 0):
        raise ValueError(f"structured_prior: need strength >= 0 and count > 0, got {strength!r}, {count!r}")
    n, m = dyn.n, dyn.m
    nz = n + m
    x1 = slice(nz, nz + n)
    F = np.concatenate([dyn.A, dyn.B], axis=-1)                      # (T, n, n + m)
    w = strength / (strength + count)

    def correct(mu, Lam):
        if mu.shape[-1] < nz + n or Lam.shape[-2:] != (mu.shape[-1],) * 2 or mu.shape[0] != dyn.T:
            raise ShapeError(f"structured_prior: moments {mu.shape}, {Lam.shape} do not fit dynamics "
                             f"(T, n, m) = {(dyn.T, n, m)}")
        Szz = Lam[:, :nz, :nz]
        mu_s = np.array(mu)
        mu_s[:, x1] = np.einsum("tij,tj->ti", F, mu[:, :nz]) + dyn.c
        S_s = np.array(Lam)
        FS = F @ Szz                                                  # (T, n, nz)
        S_s[:, x1, :nz] = FS
        S_s[:, :nz, x1] = np.swapaxes(FS, -1, -2)
        S_s[:, x1, x1] = FS @ np.swapaxes(F, -1, -2) + dyn.cov
        y = slice(nz + n, None)
        Fy = F @ Lam[:, :nz, y]                                       # (T, n, dy)
        S_s[:, x1, y] = Fy
        S_s[:, y, x1] = np.swapaxes(Fy, -1, -2)
        d = mu - mu_s
        out = (1 - w) * Lam + w * S_s + w * (1 - w) * (d[:, :, None] * d[:, None, :])
        return (1 - w) * mu + w * mu_s, symmetrize(out)

    return correct
