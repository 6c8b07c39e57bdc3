"""Solver choice, tolerances and iteration limits of the M-step (:class:`MStepConfig`, docs/math.md §5)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..config import Config, Interval, Options, config_error

__all__ = ["MStepConfig", "MSTEP_METHODS", "MSTEP_SOLVERS", "MSTEP_VARIANTS", "MSTEP_OBJECTIVES"]

#: ``maximize(method=...)``: the closed form or the CVXPY program (docs/math.md §5).
MSTEP_METHODS = ("closed_form", "cvxpy")
#: CVXPY solvers of ``method="cvxpy"``.
MSTEP_SOLVERS = ("CLARABEL", "SCS")
#: ``maximize(variant=...)``: one policy per step (the DP sweep) or one shared policy.
MSTEP_VARIANTS = ("time_varying", "time_invariant")
#: ``maximize(objective=...)``: the paper's surrogate or exact EM.
MSTEP_OBJECTIVES = ("surrogate", "exact")


@dataclass(frozen=True)
class MStepConfig(Config):
    """Solver choice, tolerances and iteration limits of the M-step.

    Fields:
        solver: default CVXPY solver for ``method="cvxpy"`` ("CLARABEL" or "SCS").
        clarabel_tol: Clarabel ``tol_gap_abs``, ``tol_gap_rel`` and ``tol_feas`` (default 1e-10).
            Note: where the optimum lies on a curved boundary with a linear objective (the
            ``entropy_floor`` on Sigma) an interior-point solver locates the maximiser only to
            about the square root of the duality gap when its iterates leave the central path;
            problems with an entropy floor therefore use gap tolerances ``clarabel_tol / 100``
            (not below 1e-13 unless ``clarabel_tol`` is; falling back to ``clarabel_tol`` if that
            ends in round-off), shorter steps and no chordal decomposition (:mod:`soc_opt.mstep.cvx`,
            "Entropy floor"; the measurements behind these settings are in docs/choices.md).
            Problems with a trust region are solved with shorter steps (``max_step_fraction`` 0.8,
            retried at 0.5) and a fresh Clarabel solver per solve (:mod:`soc_opt.mstep.cvx`, "Trust
            region and offset bound"; docs/choices.md); their tolerances are the same.
        clarabel_max_iter: Clarabel iteration limit (default 200).
        scs_eps: SCS ``eps_abs`` and ``eps_rel`` (default 1e-9; SCS is first order, so tight).
        scs_max_iters: SCS iteration limit (default 200000).
        accept_inaccurate: accept CVXPY status ``optimal_inaccurate`` (default False: raise).
        eig_tol: relative eigenvalue threshold at or below which ``H_k``, ``P_k`` (and the
            time-invariant Kronecker sum) count as ill-conditioned: the closed form then solves the step
            in exact rational arithmetic instead of by Cholesky, CVXPY and the time-invariant variant
            refuse it (default 1e-10; docs/math.md §5, "Conditioning").
        sing_tol: relative eigenvalue threshold at or below which they count as singular to working
            precision: the maximiser is not unique (minimum-norm maximiser with ``min_norm=True``,
            else an error) (default ``2**-40``, about 9.1e-13, 4096 units of roundoff; must be below
            ``eig_tol``).
        feas_tol: tolerance of the feasibility checks of closed-form candidates (default 1e-9).
        exact_tol: exact-EM inner iterations stop when the change of the exact objective is
            below ``exact_tol * (1 + |objective|)`` at every step (default 1e-9).
            EM converges slowly (sublinearly) when the optimal Sigma approaches singularity.
        exact_max_iter: maximum number of exact-EM inner iterations (default 1000).
        verbose: pass ``verbose=True`` to the CVXPY solver.
    """

    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"
    clarabel_tol: float = 1e-10
    clarabel_max_iter: int = 200
    scs_eps: float = 1e-9
    scs_max_iters: int = 200_000
    accept_inaccurate: bool = False
    eig_tol: float = 1e-10
    sing_tol: float = 2.0**-40
    feas_tol: float = 1e-9
    exact_tol: float = 1e-9
    exact_max_iter: int = 1000
    verbose: bool = False

    _constraints = {
        "solver": [Options(MSTEP_SOLVERS)],
        **{name: [Interval(0, None, "neither")] for name in ("clarabel_tol", "scs_eps", "eig_tol", "sing_tol",
                                                              "feas_tol", "exact_tol")},
        **{name: [Interval(1)] for name in ("clarabel_max_iter", "scs_max_iters", "exact_max_iter")},
    }

    def __post_init__(self):
        if not self.sing_tol < self.eig_tol:
            raise config_error("sing_tol", f"must be below eig_tol = {self.eig_tol:g}, got {self.sing_tol:g}")
