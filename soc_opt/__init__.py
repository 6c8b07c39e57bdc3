"""soc_opt: EM-based stochastic optimal control (DPSOC-EM) with KL-constrained iLQG.

See ``docs/`` and the SPEC sections cited in each module's docstring.  The submodules are
attributes of the package (``import soc_opt; soc_opt.lqg.kl_step(...)``), imported on first use.
"""

import importlib as _importlib

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

#: Submodules reachable as ``soc_opt.<name>`` without importing them first (PEP 562).
SUBMODULES = (
    "algorithms", "compare", "config", "config_doc", "costs", "envs", "errors", "estep", "experiment", "fit",
    "ilqg", "linalg", "lqg", "models", "mstep", "report", "rundir", "tasks", "testing", "verification", "bench",
)


def __getattr__(name: str):
    if name in SUBMODULES:
        return _importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(SUBMODULES))

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
