"""The robot's contact-free rigid-body acceleration map, an EM start (``docs/math.md §11.2``, "Start").

With ``kinematic.start_map = "rigid_body"`` the estimator also assumes the robot's masses, inertia,
damping and gravity known (MuJoCo's model of it), but not its contacts: the acceleration of the
latent joints over one control step is simulated by MuJoCo with every constraint disabled,

    u(z, a) = (qd_{k+1} - qd_k) / dt     (one control step from z under a, no contacts, no limits),

which is ``M(q)^{-1} (tau(a) + f_passive(z) - f_bias(z))`` integrated over the step by the task's
own integrator, and its linearisation along a nominal trajectory ``zbar_k`` gives the map
``(B_k, D_k, c_k)`` of ``u_k = B_k a_k + D_k z_k + c_k`` (central differences in ``z``; ``tau`` is
linear in ``a`` for motors, one difference per action).  Contact (the door's handle, the peg in the hole) is what EM
then learns from the data.  Joints outside ``z`` stay at their initial angle with zero velocity,
as in ``h``.
"""

from __future__ import annotations

import numpy as np

from ...models import ShapeError
from .model import AccelMap, KinematicModel

__all__ = ["rigid_body_map"]


def rigid_body_map(km: KinematicModel, zbar, S, eps: float = 1e-6) -> AccelMap:
    """The map ``(B, D, c)`` of :meth:`KinematicModel.free_accel` linearised at ``zbar (T, nz)`` (at
    ``a = 0``), with noise ``S (T, nq, nq)``.

    ``B_k = du/da``, ``D_k = du/dz`` (central differences of step ``eps``), ``c_k = u(zbar_k, 0) - D_k zbar_k``.
    """
    zbar = np.asarray(zbar, dtype=float)
    T, nq, nz, ma = km.T, km.nq, km.nz, km.m
    if zbar.shape != (T, nz):
        raise ShapeError(f"nominal latent trajectory zbar must have shape ({T}, {nz}), got {zbar.shape}")
    a0 = np.zeros(ma)
    B, D, c = np.zeros((T, nq, ma)), np.zeros((T, nq, nz)), np.zeros((T, nq))
    for k in range(T):
        u0 = km.free_accel(zbar[k], a0)
        for j in range(ma):
            e = np.zeros(ma)
            e[j] = 1.0
            B[k, :, j] = km.free_accel(zbar[k], e) - u0
        for j in range(nz):
            dz = np.zeros(nz)
            dz[j] = eps
            D[k, :, j] = (km.free_accel(zbar[k] + dz, a0) - km.free_accel(zbar[k] - dz, a0)) / (2.0 * eps)
        c[k] = u0 - D[k] @ zbar[k]
    return AccelMap(B, D, c, S)
