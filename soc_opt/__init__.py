"""soc_opt: EM-based stochastic optimal control (DPSOC-EM) with KL-constrained iLQG.

See ``docs/`` and the SPEC sections cited in each module's docstring.
"""

from .config import Config, ConfigError
from .models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    QuadraticCost,
    Rollouts,
    ShapeError,
    Smoothed,
)

__version__ = "0.1.0"

__all__ = [
    "AugmentedModel",
    "Config",
    "ConfigError",
    "LinearGaussianDynamics",
    "LinearGaussianPolicy",
    "NotPositiveDefiniteError",
    "QuadraticCost",
    "Rollouts",
    "ShapeError",
    "Smoothed",
]
