"""DPSOC-EM's own settings, the ``[em]`` table of a run configuration (docs/math.md §3–§5, paper
Algorithm 1).  Data only: the core may read it (``pyproject.toml``, "The core imports no plug-in")."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ...config import Interval, Options
from ...learning.fit import COST_MODES
from ...mstep.recipe import MStepRecipe
from ..limits import MAX_ITERATIONS, MAX_SAMPLES

__all__ = ["EMConfig"]


@dataclass(frozen=True)
class EMConfig(MStepRecipe):
    """The EM phase of DPSOC-EM (docs/math.md §3–§5, paper Algorithm 1): the M-step recipe
    (:class:`soc_opt.mstep.recipe.MStepRecipe`, whose fields are method, variant, objective,
    cov_floor_scale, entropy_floor, trust_region, min_norm and mstep) plus:

    n_em:          EM recursions at the switch (each samples ``M`` rollouts of the current EM policy).
    y_mode:        cost observations ``Y``: "model" (the paper), "measured", "optimistic" (docs/math.md §3).
    y_samples:     number of ``Y`` sequences drawn in "model" mode (default: ``samples``).
    """

    n_em: int = 1
    y_mode: Literal["model", "measured", "optimistic"] = "model"
    y_samples: int | None = None

    _constraints = {
        **MStepRecipe._constraints,
        "n_em": [Interval(1, MAX_ITERATIONS)],
        "y_mode": [Options(COST_MODES)],
        "y_samples": [None, Interval(1, MAX_SAMPLES)],
    }
