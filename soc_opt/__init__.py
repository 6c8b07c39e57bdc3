"""soc_opt: EM-based stochastic optimal control (DPSOC-EM) with KL-constrained iLQG.

See ``docs/`` and the ``docs/math.md`` sections cited in each module's docstring.  The submodules are
attributes of the package (``import soc_opt; soc_opt.lqg.kl_step(...)``), imported on first use, and so is
the Python entry point of a comparison, ``soc_opt.compare(task, seeds=...) -> CompareResult``
(:mod:`soc_opt.api`).
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

def _submodules() -> set[str]:
    """The package's submodules and subpackages (found on disk, so new ones need no listing)."""
    import pkgutil

    return {m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")}


#: the Python entry point of a comparison (soc_opt.api; docs/interface.md), imported on first use
_API = ("compare", "CompareResult", "ClaimResult")


def __getattr__(name: str):
    if name in _API:
        return getattr(_importlib.import_module(".api", __name__), name)
    if not name.startswith("_") and name in _submodules():
        return _importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | _submodules() | set(_API))


__all__ = [
    "compare",
    "CompareResult",
    "ClaimResult",
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
