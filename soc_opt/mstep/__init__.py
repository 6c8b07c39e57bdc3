"""M-step: the paper's surrogate ``Lbar_k``, the exact-EM objective, and their maximisers (docs/math.md §5).

Every public name is importable from ``soc_opt.mstep``.  Modules, each importing only those
listed after it:

* :mod:`~soc_opt.mstep.maximize` -- the entry point :func:`maximize` (smoothed moments in, the whole
  :class:`MStepResult` out), the surrogate's closed-form maximisers and the time-varying sweep / time-invariant variant.
* :mod:`~soc_opt.mstep.exact_em` -- inner EM iterations for ``objective="exact"``.
* :mod:`~soc_opt.mstep.cvx` -- the CVXPY (DPP) problems: factored, Kronecker and spectral forms,
  the entropy floor as an SDP, caching, solver settings, duals.
* :mod:`~soc_opt.mstep.conditioning` -- which steps are singular, ill-conditioned or well-conditioned,
  and the errors and warnings that name them.
* :mod:`~soc_opt.mstep.exact` -- the unique maximiser of an ill-conditioned step in exact rational
  arithmetic (python-flint).
* :mod:`~soc_opt.mstep.objectives` -- notation; :func:`surrogate`, :func:`exact_objective`,
  :func:`surrogate_grad_hess`, the per-step quadratic form.
* :mod:`~soc_opt.mstep.constraints` -- :class:`MStepConstraints` (the feasible set), its
  per-step resolution and the closed-form covariance rules.
* :mod:`~soc_opt.mstep.config` -- :class:`MStepConfig` (solver choice, tolerances).
* :mod:`~soc_opt.mstep.errors` -- :class:`SolverError` (a :class:`soc_opt.errors.SolverError`),
  :class:`NonUniqueMaximizerError`, :class:`IllConditionedMaximizerError`, :class:`MinNormWarning`,
  :class:`InfeasibleConstraintsError`, :class:`ClosedFormUnavailableError`.

Why the CVXPY problems are solved with the settings they are: docs/choices.md, "M-step solver
choices".
"""

from __future__ import annotations

from .config import MSTEP_METHODS, MSTEP_OBJECTIVES, MSTEP_SOLVERS, MSTEP_VARIANTS, MStepConfig
from .constraints import MStepConstraints
from .errors import (
    ClosedFormUnavailableError,
    IllConditionedMaximizerError,
    InfeasibleConstraintsError,
    MinNormWarning,
    NonUniqueMaximizerError,
    SolverError,
)
from .maximize import MStepResult, maximize
from .objectives import (
    LOG_2PI,
    GradHess,
    exact_objective,
    exact_objective_from_moments,
    surrogate,
    surrogate_from_moments,
    surrogate_grad_hess,
)
from .recipe import MStepRecipe

__all__ = [
    "SolverError",
    "NonUniqueMaximizerError",
    "IllConditionedMaximizerError",
    "MinNormWarning",
    "InfeasibleConstraintsError",
    "ClosedFormUnavailableError",
    "MStepConstraints",
    "MStepConfig",
    "MStepRecipe",
    "MSTEP_METHODS",
    "MSTEP_SOLVERS",
    "MSTEP_VARIANTS",
    "MSTEP_OBJECTIVES",
    "MStepResult",
    "GradHess",
    "LOG_2PI",
    "surrogate",
    "surrogate_from_moments",
    "exact_objective",
    "exact_objective_from_moments",
    "surrogate_grad_hess",
    "maximize",
]
