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
"""

from __future__ import annotations

import numpy as np

from ...models import AugmentedModel, LinearGaussianDynamics, ShapeError, symmetrize
from .filter import KinematicFilter

__all__ = ["structured_dynamics", "with_dynamics"]


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
