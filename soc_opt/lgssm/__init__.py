"""The Gaussian core: Kalman filter, RTS smoother and log-likelihood of a linear-Gaussian
state-space model (docs/math.md §4; used by the E-step, the §10.1 fits and the §11.2 estimator).

Model (time-varying, ``k = 0..T-1`` transitions, ``K = T`` or ``T+1`` observations)::

    z_0 ~ N(mu0, P0)
    z_{k+1} = F_k z_k + b_k + w_k,      w_k ~ N(0, Q_k)
    y_k     = H_k z_k + d_k + v_k,      v_k ~ N(0, R_k),     Cov(w_k, v_k) = C_k   (correlated noise)

With ``K = T`` the last state ``z_T`` is not observed (the E-step's closed loop, §4); with
``K = T + 1`` every state is (the §10 measurements ``s_k``, the §11 measurements of ``h(z_k)``).

Parameters are bundled as :class:`Params` (:class:`Initial`, :class:`Dynamics`,
:class:`Emissions` and the noise cross-covariance ``C``).  ``M`` sequences are processed at once: the
observations are ``y (M, K, p)``; means (``mu0``, ``b``, ``d``) may carry a leading ``M`` axis.
When every matrix (``P0, F, Q, H, R, C``) is shared by the sequences, so are all covariances and
gains: they are computed once and only the means are per sequence (the E-step's case, where all
sequences share the closed loop).  A matrix with a leading ``M`` axis (the §11 estimator's
emissions, linearised per rollout) makes the covariances per sequence.

Algorithm (all steps batched over the sequences and, outside the two recursions, over time):

1. Correlated noise is removed by decorrelation: ``G_k = C_k R_k^{-1}``,
   ``F'_k = F_k - G_k H_k``, ``Q'_k = Q_k - G_k C_k^T`` and the data-dependent bias
   ``b'_k = b_k + G_k (y_k - d_k)``; then ``z_{k+1} = F'_k z_k + b'_k + w'_k`` with ``w'_k``
   independent of ``v_k`` (and of ``z_k``, ``y_0..y_k``).
2. Covariance recursion (data independent): ``S_k = H_k P_k H_k^T + R_k``,
   ``K_k = P_k H_k^T S_k^{-1}`` (Cholesky solve), filtered ``P^f_k = P_k - K_k S_k K_k^T``,
   predicted ``P_{k+1} = F'_k P^f_k F'^T_k + Q'_k`` (the stacks symmetrised once after the
   recursion).  With more observations than states (``p > n``) and ``R_k`` positive definite, the
   update is taken in information form, ``P^f_k = (I + P_k G_k)^{-1} P_k`` with
   ``G_k = H_k^T R_k^{-1} H_k`` (``R_k`` whitened once), and ``log|S_k|``, ``v^T S_k^{-1} v`` follow from
   the determinant lemma and Woodbury's identity: ``n x n`` work instead of ``p x p``.
3. Means: the predicted means follow the affine recursion ``m_{k+1} = F'_k (I - K_k H_k) m_k
   + F'_k K_k (y_k - d_k) + b'_k`` (one matrix product per step for all sequences); filtered means,
   innovations ``v_k = y_k - H_k m_k - d_k`` and ``log p(Y) = -1/2 sum_k (p log 2 pi + log|S_k|
   + v_k^T S_k^{-1} v_k)`` are then computed for all steps at once.
4. RTS smoother: ``J_k = P^f_k F'^T_k P_{k+1}^{-1}`` (one batched solve for all steps, ``P_{k+1}``
   checked positive definite by its Cholesky factorisation) and, from
   the last state back, ``P^s_k = (I - J_k F'_k) P^f_k (I - J_k F'_k)^T + J_k (Q'_k + P^s_{k+1}) J_k^T``
   (the Joseph-like form of ``P^f_k + J_k (P^s_{k+1} - P_{k+1}) J_k^T``, a sum of PSD terms),
   ``zs_k = m^f_k + J_k (zs_{k+1} - m_{k+1})``, ``Cov(z_{k+1}, z_k | Y) = P^s_{k+1} J_k^T``.

An extended filter (the §11 estimator's first pass) passes ``linearize(k, m_k) -> (H_k, d_k)``,
called with the predicted means ``m_k (M, n)`` at each step; the emissions are then per sequence.

Covariances per sequence run the same steps one sequence at a time in compiled loops
(:mod:`soc_opt.compiled.lgssm_kernels`, numba) when numba is installed: ``kernels=None`` (default)
takes the path :func:`soc_opt.compiled.backend` names, ``"numpy"`` or ``"numba"`` force one.  The numpy
loops below are the reference; the two agree to rounding (``tests/test_compiled.py``).  Shared
covariances always take the numpy path (one recursion for all sequences).

Public API:
    Initial, Dynamics, Emissions, Params                      parameter bundles
    kalman_filter(params, y, linearize=None, kernels=None)    -> Filtered
    rts_smoother(params, y, linearize=None, kernels=None)     -> Posterior
    log_likelihood(params, y, kernels=None)                   -> (M,)
"""

from .inference import kalman_filter, log_likelihood, rts_smoother
from .model import Dynamics, Emissions, Filtered, Initial, Params, Posterior

__all__ = ["Initial", "Dynamics", "Emissions", "Params", "Filtered", "Posterior", "kalman_filter", "rts_smoother",
           "log_likelihood"]
