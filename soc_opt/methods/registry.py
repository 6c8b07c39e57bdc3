"""The methods, one registry line each: the CLI, experiments, ``soc-opt compare`` and sweeps read them
from :data:`soc_opt.plugins.METHODS` when they run.

Importing this module fills that table (the core reads the table and never this module; the table
imports it on first use) and installs its check, :func:`~soc_opt.methods.base.check_protocol`,
which every registration passes, here or ``soc_opt.plugins.METHODS.register(...)`` from a script.  A
new method is one folder (or module) defining a :class:`~soc_opt.methods.base.Method` (usually a
subclass of :class:`~soc_opt.methods.base.MethodBase`) plus one line here.
"""

from __future__ import annotations

from typing import Callable

from ..plugins import METHODS
from .base import check_protocol, run_method
from .dpsoc_em.method import DPSOC_EM
from .ilqg.method import ILQG_METHOD
from .lqr_flm.method import LQR_FLM

__all__ = ["METHODS", "get_method", "register", "check_config", "sections_of", "sample_based", "run"]

METHODS.check = check_protocol

# Every method by name (the order is the CLI's).
METHODS.register(DPSOC_EM)
METHODS.register(LQR_FLM)
METHODS.register(ILQG_METHOD)

#: The one lookup and the one registration, under the names scripts used before (:data:`METHODS`'s own).
get_method = METHODS.lookup
register = METHODS.register


def check_config(name: str, cfg) -> None:
    """The method-specific checks of ``cfg`` for method ``name`` (``ConfigError`` naming the key)."""
    METHODS.lookup(name).check_config(cfg)


def sections_of(name: str) -> tuple[str, ...]:
    """The top-level keys of the run configuration that method ``name`` reads."""
    return METHODS.lookup(name).sections


def sample_based() -> tuple[str, ...]:
    """The names of the registered methods that learn from samples (``soc-opt compare`` and sweeps), read
    when called: a method registered later from a script is among them."""
    return tuple(name for name, m in METHODS.items() if m.sample_based)


def run(task, name: str, cfg, seed: int = 0, state=None, on_iteration: Callable | None = None):
    """Run method ``name`` to the end from ``state`` (or a fresh start); :func:`~soc_opt.methods.base.run_method`."""
    return run_method(METHODS.lookup(name), task, cfg, seed, state, on_iteration)
