"""The M-step recipe (docs/math.md §5): one config for what the EM phase asks of the M-step.

:class:`MStepRecipe` holds the method (closed form or CVXPY), the variant (time-varying or
time-invariant), the objective (surrogate or exact EM), the constraint recipe relative to the
current policy (covariance floor scale, or entropy floor, plus an optional trust region), the
minimum-norm option and the solver settings (:class:`~soc_opt.mstep.config.MStepConfig`).
:meth:`MStepRecipe.constraints` builds the feasible set for a policy and :meth:`MStepRecipe.maximize`
runs the M-step with it.  The run configuration's ``[em]`` table is this recipe plus the EM
phase's own settings (:class:`soc_opt.methods.config.EMConfig`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..config import Config, Interval, Options
from ..estep import moments
from ..models import AugmentedModel, LinearGaussianPolicy, Smoothed
from .config import MSTEP_METHODS, MSTEP_OBJECTIVES, MSTEP_VARIANTS, MStepConfig
from .constraints import MStepConstraints
from .maximize import maximize

__all__ = ["MStepRecipe"]


@dataclass(frozen=True)
class MStepRecipe(Config):
    """What the M-step does with a policy ``phi^i`` (docs/math.md §5).

    method:        ``"closed_form"`` or ``"cvxpy"`` (:data:`~soc_opt.mstep.config.MSTEP_METHODS`).
    variant:       ``"time_varying"`` (the Proposition's DP sweep) or ``"time_invariant"``.
    objective:     ``"surrogate"`` (the paper's Lbar) or ``"exact"`` (exact EM).
    cov_floor_scale:  ``Sigma_k >= scale * Sigma_k^i`` (covariance floor relative to the
                   current policy); ignored when ``entropy_floor`` is true.
    entropy_floor: use the entropy floor ``log det Sigma_k >= log det Sigma_k^i`` instead.
    trust_region:  optional Frobenius trust region on ``[K k]`` around the current policy (cvxpy only).
    min_norm:      minimum-norm M-step where the maximiser is not unique.
    mstep:         the solver tolerances and limits (:class:`~soc_opt.mstep.config.MStepConfig`;
                   its ``solver`` picks the CVXPY solver).
    """

    method: str = "closed_form"
    variant: str = "time_varying"
    objective: str = "surrogate"
    cov_floor_scale: float = 0.5
    entropy_floor: bool = False
    trust_region: float | None = None
    min_norm: bool = True
    mstep: MStepConfig = field(default_factory=MStepConfig)

    _constraints = {
        "method": [Options(MSTEP_METHODS)],
        "variant": [Options(MSTEP_VARIANTS)],
        "objective": [Options(MSTEP_OBJECTIVES)],
        "cov_floor_scale": [Interval(0, None, "neither")],
        "trust_region": [None, Interval(0, None, "neither")],
    }

    def constraints(self, policy: LinearGaussianPolicy) -> MStepConstraints:
        """The feasible set relative to ``policy``: the covariance floor (or the entropy floor) and
        the optional trust region."""
        if self.entropy_floor:
            cons = MStepConstraints(entropy_floor=np.linalg.slogdet(policy.cov)[1].tolist())
        else:
            cons = MStepConstraints(cov_floor=(self.cov_floor_scale * np.asarray(policy.cov)).tolist())
        if self.trust_region is not None:
            cons = dataclasses.replace(cons, trust_region=self.trust_region)
        return cons

    def maximize(self, model: AugmentedModel, smoothed: Smoothed, y: np.ndarray,
                 previous: LinearGaussianPolicy) -> LinearGaussianPolicy:
        """The M-step of this recipe from ``previous`` (:func:`~soc_opt.mstep.maximize.maximize`)."""
        return maximize(model, moments(smoothed, y), constraints=self.constraints(previous), method=self.method,
                        variant=self.variant, objective=self.objective, previous=previous,
                        min_norm=self.min_norm, config=self.mstep).policy
