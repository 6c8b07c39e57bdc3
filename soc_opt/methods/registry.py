"""The one table of methods: the CLI, experiments, ``soc-opt compare`` and sweeps read it.

A new method is one module defining a :class:`~soc_opt.methods.base.Method` (usually a subclass
of :class:`~soc_opt.methods.base.MethodBase`) plus one line in :data:`METHODS`; tests and scripts
can also call :func:`register`.
"""

from __future__ import annotations

from typing import Callable

from ..config import ConfigError
from .base import Method, run_method
from .dpsoc_em import DPSOC_EM
from .ilqg import ILQG_METHOD
from .lqr_flm import LQR_FLM

__all__ = ["METHODS", "get_method", "register", "check_config", "sections_of", "sample_based", "run"]

#: Every method by name (the order is the CLI's).
METHODS: dict[str, Method] = {
    DPSOC_EM.name: DPSOC_EM,
    LQR_FLM.name: LQR_FLM,
    ILQG_METHOD.name: ILQG_METHOD,
}


def get_method(name: str) -> Method:
    """The registered method ``name``; :class:`ConfigError` listing the known ones otherwise."""
    method = METHODS.get(name)
    if method is None:
        raise ConfigError(f"unknown method {name!r}; use one of {', '.join(map(repr, METHODS))}")
    return method


def register(method: Method, *, replace: bool = False) -> Method:
    """Add ``method`` to :data:`METHODS` (``replace`` to overwrite a name); returns it."""
    if not isinstance(method, Method):
        raise TypeError(f"{method!r} does not implement the Method protocol (soc_opt.methods.base.Method)")
    if method.name in METHODS and not replace:
        raise ValueError(f"a method named {method.name!r} is already registered")
    METHODS[method.name] = method
    return method


def check_config(name: str, cfg) -> None:
    """The method-specific checks of ``cfg`` for method ``name`` (``ConfigError`` naming the key)."""
    get_method(name).check_config(cfg)


def sections_of(name: str) -> tuple[str, ...]:
    """The top-level keys of the run configuration that method ``name`` reads."""
    return get_method(name).sections


def sample_based() -> tuple[str, ...]:
    """The names of the methods that learn from samples (``soc-opt compare`` and sweeps)."""
    return tuple(name for name, m in METHODS.items() if m.sample_based)


def run(task, name: str, cfg, seed: int = 0, state=None, on_iteration: Callable | None = None):
    """Run method ``name`` to the end from ``state`` (or a fresh start); :func:`~soc_opt.methods.base.run_method`."""
    return run_method(get_method(name), task, cfg, seed, state, on_iteration)
