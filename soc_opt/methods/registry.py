"""The methods, one registry line each: the CLI, experiments, ``soc-opt compare`` and sweeps read them.

Importing this module fills :data:`soc_opt.plugins.METHODS` (the core reads that table and never
this module; the table imports it on first use).  A new method is one module defining a
:class:`~soc_opt.methods.base.Method` (usually a subclass of :class:`~soc_opt.methods.base.MethodBase`;
its own settings as ``settings``, the ``[NAME]`` table of the run configuration, and the classes of
its saved state as ``state_types``) plus one line here; tests and scripts can also call :func:`register`.
"""

from __future__ import annotations

from typing import Callable

from ..plugins import METHODS
from .base import Method, run_method
from .dpsoc_em import DPSOC_EM
from .ilqg import ILQG_METHOD
from .lqr_flm import LQR_FLM

__all__ = ["METHODS", "get_method", "register", "check_config", "sections_of", "sample_based", "run"]

# Every method by name (the order is the CLI's).
METHODS.register(DPSOC_EM)
METHODS.register(LQR_FLM)
METHODS.register(ILQG_METHOD)


def get_method(name: str) -> Method:
    """The registered method ``name``; :class:`ConfigError` listing the known ones otherwise."""
    return METHODS.lookup(name)


def register(method: Method, *, replace: bool = False) -> Method:
    """Add ``method`` to :data:`METHODS` (``replace`` to overwrite a name); returns it."""
    if not isinstance(method, Method):
        raise TypeError(f"{method!r} does not implement the Method protocol (soc_opt.methods.base.Method)")
    return METHODS.register(method, replace=replace)


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
