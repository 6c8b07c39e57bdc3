"""The M-step's entry point (docs/math.md §5) and the surrogate's closed-form maximisers.

:func:`maximize` takes the smoothed moments (:class:`~soc_opt.estep.Moments`) and returns the whole
:class:`MStepResult` (the policy is ``.policy``): ``maximize(model, moments(smoothed, y), ...)``.

Time-varying sweep and time-invariant variant
---------------------------------------------
The Proposition's DP sweep runs ``j = T-1 .. 0`` maximising ``Lbar_j`` with the future terms fixed.
With the smoothed moments fixed, ``Lbar_j`` depends on ``phi_j`` only and the future terms do not
depend on ``phi_j``, so the sweep decouples into ``T`` independent problems: the CVXPY path runs the
backward sweep literally, the closed form is batched over ``T`` (the order is immaterial).
The time-invariant variant maximises ``sum_k Lbar_k`` over one shared ``phi``: the normal
equations ``sum_k H_k F Stilde_k = sum_k R_k`` read ``(sum_k Stilde_k kron H_k) vec F = vec(sum_k R_k)``
(the paper's ``M = sum_k M_k``), and ``Sigma`` comes from the constraint set with ``H = sum_k H_k``.
A time-invariant trust region bounds ``||F - F_prev,k||_F <= delta`` at every step ``k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import linalg as la
from ..estep import Moments
from ..models import AugmentedModel, LinearGaussianPolicy
from .conditioning import CVXPY_HINT, MIN_NORM_HINT, check_time_invariant, check_time_varying
from .config import MSTEP_METHODS, MSTEP_OBJECTIVES, MSTEP_SOLVERS, MSTEP_VARIANTS, MStepConfig
from .constraints import MStepConstraints, pd_guaranteed, require_pd_covariance, sigma_closed
from .errors import ClosedFormUnavailableError
from .exact import EXACT_TI_MAX, unique_maximiser, unique_maximiser_ti
from .exact_em import run_exact_em
from .objectives import (
    atil,
    check_moments,
    check_policy,
    moment_stats,
    policy_F,
    surrogate_from_moments,
    ti_normal_equations,
)

__all__ = ["MStepResult", "maximize"]


@dataclass(frozen=True)
class MStepResult:
    """Everything an M-step produced (:func:`maximize`).

    Fields:
        policy: the maximiser.
        objective: (T,) the maximised objective (``Lbar_k`` or ``exact_k``) at ``policy``.
        solver_value: optimal value reported by CVXPY plus the constants it omits: (T,) for the
            time-varying surrogate, (1,) for the time-invariant surrogate (``sum_k Lbar_k``);
            None for closed forms and the exact objective.
        status: solver statuses, one per CVXPY solve in order of solution (empty for closed forms).
        duals: per CVXPY surrogate solve (indexed like ``solver_value``), the dual values by
            constraint name (``offset_upper``, ``offset_lower``, ``trust`` (array over centres),
            ``cov_floor``, ``cov_ceiling``, ``entropy_floor`` (the multiplier of
            ``log det Sigma >= c``)).
        solve_time: wall time (s) of each CVXPY surrogate solve, indexed like ``solver_value``.
        history: exact objective only: (iterations+1, T) ``exact_k`` before and after each inner step.
        iterations: number of exact-EM inner iterations (0 otherwise).
        converged: exact-EM stopping rule met (True otherwise).
        min_norm_steps: closed form: the steps where the maximiser is not unique (singular to working
            precision) and the minimum-norm maximiser was returned (``min_norm=True``; a
            :class:`~soc_opt.mstep.errors.MinNormWarning` names them too); the time-invariant variant
            lists every step.
        exact_steps: closed form: the ill-conditioned steps whose unique maximiser was computed in exact
            rational arithmetic (docs/math.md §5, "Conditioning"); the time-invariant variant lists every step.
    """

    policy: LinearGaussianPolicy
    objective: np.ndarray
    solver_value: np.ndarray | None = None
    status: tuple[str, ...] = ()
    duals: tuple[dict, ...] = ()
    solve_time: np.ndarray | None = None
    history: np.ndarray | None = None
    iterations: int = 0
    converged: bool = True
    min_norm_steps: tuple[int, ...] = ()
    exact_steps: tuple[int, ...] = ()


def maximize(
    model: AugmentedModel,
    moments: Moments,
    *,
    constraints: MStepConstraints | None = None,
    method: str = "closed_form",
    solver: str | None = None,
    variant: str = "time_varying",
    objective: str = "surrogate",
    previous: LinearGaussianPolicy | None = None,
    min_norm: bool = True,
    config: MStepConfig | None = None,
) -> MStepResult:
    """The DP M-step (docs/math.md §5): maximise ``Lbar_k`` (or the exact objective) over the feasible set.

    The M-step's one entry point; returns the whole :class:`MStepResult` (the maximiser ``.policy``,
    objective values, solver statuses, duals, exact-EM history).

    Args:
        model: the augmented model (``Ao, co, So``).
        moments: the smoothed sufficient statistics (:class:`~soc_opt.estep.Moments`); from the
            smoother's output and the observations, ``soc_opt.estep.moments(smoothed, y)``.
        constraints: the feasible set (:class:`MStepConstraints`; default: none, which is an error
            for the surrogate unless ``MStepConstraints(allow_singular=True)``, because its optimum is
            ``Sigma = 0``).
        method: ``"closed_form"`` (batched Cholesky solves) or ``"cvxpy"`` (DPP problem per step).
        solver: CVXPY solver, ``"CLARABEL"`` or ``"SCS"`` (default ``config.solver``).
        variant: ``"time_varying"`` (one ``phi_k`` per step, the Proposition's sweep) or
            ``"time_invariant"`` (one shared ``phi`` maximising ``sum_k``).
        objective: ``"surrogate"`` (the paper's ``Lbar``) or ``"exact"`` (action integrated out,
            inner EM started from ``previous``; the time-invariant variant starts from the time
            average of ``previous``; the number of inner iterations and convergence are in the result).
        previous: the current policy; trust-region centre and exact-EM starting point.
        min_norm: return the minimum-norm maximiser where it is not unique (closed form only; the
            default, as in the EM loop's :class:`~soc_opt.mstep.recipe.MStepRecipe`), with a
            :class:`~soc_opt.mstep.errors.MinNormWarning`; ``False`` raises
            :class:`NonUniqueMaximizerError` instead.  Unique but ill-conditioned steps are solved in
            exact arithmetic either way (docs/math.md §5, "Conditioning").
        config: :class:`MStepConfig` (tolerances, solver options).

    Raises:
        NonUniqueMaximizerError: ``H_k`` or ``P_k`` singular to working precision (names the step, the
            threshold ``MStepConfig.sing_tol`` and the condition number) with ``min_norm=False`` or
            ``method="cvxpy"``.
        IllConditionedMaximizerError: a unique but ill-conditioned step (``MStepConfig.eig_tol``) with
            ``method="cvxpy"`` or ``variant="time_invariant"``.
        InfeasibleConstraintsError: empty constraint set.
        ClosedFormUnavailableError: ``method="closed_form"`` with a set needing CVXPY.
        SolverError: CVXPY failed (status and step in the message).
        ShapeError: inconsistent shapes.
    """
    return _maximize(model, moments, constraints, method, solver, variant, objective, previous, min_norm, config)


def _maximize(model: AugmentedModel, mom: Moments, constraints, method, solver, variant, objective, previous,
              min_norm: bool, config) -> MStepResult:
    """:func:`maximize` with its arguments positional."""
    cfg = config if config is not None else MStepConfig()
    for key, value, allowed in (("method", method, MSTEP_METHODS), ("variant", variant, MSTEP_VARIANTS),
                                ("objective", objective, MSTEP_OBJECTIVES)):
        if value not in allowed:
            raise ValueError(f"{key} must be one of {list(allowed)}, got {value!r}")
    solver = (solver if solver is not None else cfg.solver).upper()
    if solver not in MSTEP_SOLVERS:
        raise ValueError(f"solver must be one of {list(MSTEP_SOLVERS)}, got {solver!r}")
    if constraints is None:
        constraints = MStepConstraints()
    if not isinstance(constraints, MStepConstraints):
        raise TypeError(f"constraints must be MStepConstraints, got {type(constraints).__name__}")
    check_moments(model, mom)
    if previous is not None:
        check_policy(model, previous, "previous")
    T, n, m = model.T, model.n, model.m
    rc = constraints.resolve(m, T)
    if rc.delta is not None and previous is None:
        raise ValueError("trust_region needs previous= (the policy whose [K k] is the trust-region centre)")

    if objective == "exact":
        policy, hist, it, conv = run_exact_em(model, mom, rc, cfg, method, solver, variant, previous, min_norm)
        return MStepResult(policy, hist[-1], history=hist, iterations=it, converged=conv)

    require_pd_covariance(rc)
    if method == "closed_form" and rc.f_constrained:
        raise ClosedFormUnavailableError(
            f"the constraint set {rc.names()} has no closed-form maximiser (offset_bound and trust_region are "
            f"CVXPY only); use method='cvxpy'"
        )
    st = moment_stats(model, mom)
    Fprev = None if previous is None else policy_F(previous)
    extra: dict = {}
    if method == "closed_form":
        if variant == "time_varying":
            F, Sigma, sing, ill = _closed_form_tv(model, mom, st, rc, cfg, min_norm)
            extra = dict(min_norm_steps=tuple(int(k) for k in np.flatnonzero(sing)),
                         exact_steps=tuple(int(k) for k in np.flatnonzero(ill)))
        else:
            F, Sigma, route = _closed_form_ti(model, mom, st, rc, cfg, min_norm)
            extra = dict(min_norm_steps=tuple(range(T)) if route == "min_norm" else (),
                         exact_steps=tuple(range(T)) if route == "exact" else ())
    else:
        hint = CVXPY_HINT if min_norm else MIN_NORM_HINT + " (closed form only)"
        from .cvx import cvxpy_ti, cvxpy_tv  # cvxpy only when a CVXPY step runs: its import takes 0.5 s

        if variant == "time_varying":
            check_time_varying(model, st.S, cfg, min_norm=False, cvxpy=True, hint=hint)
            F, Sigma, val, status, duals, times = cvxpy_tv(model, st, rc, cfg, solver, Fprev)
        else:
            F, Sigma, val, status, duals, times = cvxpy_ti(model, st, rc, cfg, solver, Fprev, hint=hint)
        extra = dict(solver_value=val, status=status, duals=duals, solve_time=times)
    if variant == "time_invariant":
        F = np.broadcast_to(F, (T, m, n + 1))
        Sigma = np.broadcast_to(Sigma, (T, m, m))
    # without a PD guarantee require_pd_covariance only let us through with allow_singular=True
    policy = LinearGaussianPolicy(np.array(F[..., :n]), np.array(F[..., n]), np.array(Sigma),
                                  allow_singular=not pd_guaranteed(rc))
    return MStepResult(policy, surrogate_from_moments(model, mom, policy), **extra)


# --------------------------------------------------------------------------- closed forms


def _closed_form_tv(model, mom, st, rc, cfg, min_norm):
    """``(F, Sigma, singular, ill)``: Cholesky on well-conditioned steps, exact rational arithmetic on
    ill-conditioned ones, the minimum-norm maximiser on singular ones (:mod:`soc_opt.mstep.conditioning`)."""
    T = model.T
    sing, ill = check_time_varying(model, st.S, cfg, min_norm=min_norm, cvxpy=False)
    F = np.empty(st.R.shape)
    well = ~(sing | ill)
    if well.any():
        Lh, Ls = la.chol(st.H[well], "H"), la.chol(st.S[well], "Stilde")
        F[well] = la.right_cho_solve(la.cho_solve(Lh, st.R[well]), Ls)
    if sing.any():
        Hp = np.linalg.pinv(st.H[sing], rcond=cfg.sing_tol, hermitian=True)
        Sp = np.linalg.pinv(st.S[sing], rcond=cfg.sing_tol, hermitian=True)
        F[sing] = Hp @ st.R[sing] @ Sp
    if ill.any():
        At = atil(model)
        for k in np.flatnonzero(ill):
            F[k] = unique_maximiser(model.Bs[k], model.So[k], At[k], mom.Szs[k], mom.Sss[k])
    Sigma = sigma_closed(st.H, rc, cfg, [f"time step k={k}" for k in range(T)])
    return F, Sigma, sing, ill


def _closed_form_ti(model, mom, st, rc, cfg, min_norm):
    m, n1 = model.m, model.n + 1
    Q, r = ti_normal_equations(st)
    route = check_time_invariant(model, st.S, Q, cfg, min_norm=min_norm, exact=m * n1 <= EXACT_TI_MAX)
    if route == "exact":
        F = unique_maximiser_ti(model.Bs, model.So, atil(model), mom.Szs, mom.Sss)
    elif route == "min_norm":
        F = la.unvec(np.linalg.pinv(Q, rcond=cfg.sing_tol, hermitian=True) @ r, m, n1)
    else:
        F = la.unvec(la.cho_solve(la.chol(Q, "sum_k Stilde_k kron H_k"), r[:, None])[:, 0], m, n1)
    Sigma = sigma_closed(st.H.sum(0)[None], rc.time_invariant(), cfg, ["time-invariant M-step"])[0]
    return F, Sigma, route
