"""E-step: Kalman filter and RTS smoother on the closed loop (SPEC §4).

Also the sufficient statistics (:class:`Moments`) the M-step consumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .models import Smoothed, check_array, symmetrize

__all__ = ["Moments", "moments"]


@dataclass(frozen=True)
class Moments:
    """Smoothed second moments per step, averaged over observation sequences (SPEC §5).

    With ``zeta_k = (s_{k+1}, y_k)`` and ``stilde_k = (s_k, 1)``:
        Szz: (T, n+1, n+1)  E[zeta_k zeta_k^T | Y]
        Szs: (T, n+1, n+1)  E[zeta_k stilde_k^T | Y]
        Sss: (T, n+1, n+1)  E[stilde_k stilde_k^T | Y]   (``G_k`` and ``s_hat_k`` blocks, 1 in the corner)
        count: number of sequences averaged.
    """

    Szz: np.ndarray
    Szs: np.ndarray
    Sss: np.ndarray
    count: int = 1

    @property
    def T(self) -> int:
        return self.Szz.shape[0]

    @property
    def n(self) -> int:
        return self.Szz.shape[1] - 1


def moments(smoothed: Smoothed, y: np.ndarray) -> Moments:
    """Sufficient statistics of the M-step from smoothed moments and observations ``y``.

    ``y`` is ``(T,)`` for one sequence or ``(M, T)`` matching a batched ``smoothed``;
    statistics are averaged over the ``M`` sequences.
    """
    mean, cov, cross = smoothed.mean, smoothed.cov, smoothed.cross
    if mean.ndim == 2:
        mean, cov, cross = mean[None], cov[None], cross[None]
    M, T1, n = mean.shape
    T = T1 - 1
    y = check_array("y", np.atleast_2d(y), (M, T))
    mu_k, mu_k1 = mean[:, :-1], mean[:, 1:]
    G = cov + np.einsum("mti,mtj->mtij", mean, mean)  # E[s s^T], (M, T+1, n, n)
    C = cross + np.einsum("mti,mtj->mtij", mu_k1, mu_k)  # E[s_{k+1} s_k^T], (M, T, n, n)

    Szz = np.zeros((M, T, n + 1, n + 1))
    Szz[:, :, :n, :n] = G[:, 1:]
    Szz[:, :, :n, n] = y[..., None] * mu_k1
    Szz[:, :, n, :n] = y[..., None] * mu_k1
    Szz[:, :, n, n] = y**2

    Szs = np.zeros((M, T, n + 1, n + 1))
    Szs[:, :, :n, :n] = C
    Szs[:, :, :n, n] = mu_k1
    Szs[:, :, n, :n] = y[..., None] * mu_k
    Szs[:, :, n, n] = y

    Sss = np.zeros((M, T, n + 1, n + 1))
    Sss[:, :, :n, :n] = G[:, :-1]
    Sss[:, :, :n, n] = mu_k
    Sss[:, :, n, :n] = mu_k
    Sss[:, :, n, n] = 1.0

    return Moments(symmetrize(Szz.mean(0)), Szs.mean(0), symmetrize(Sss.mean(0)), count=M)
