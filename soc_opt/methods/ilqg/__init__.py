"""Model-based iLQG on a known model (docs/math.md §7), one folder: :mod:`.config` its settings
(``[ilqg]``), :mod:`.state` its saved state and history rows, :mod:`.algorithm` the iteration,
:mod:`.method` the :class:`~soc_opt.methods.base.Method` (``ILQG_METHOD``) with its final evaluation.

The names of those modules are read from here as well (``from soc_opt.methods.ilqg import ilqg``); they
are imported when first read.
"""

import importlib

_MODULES = ("algorithm", "config", "state", "method")


def __getattr__(name: str):
    for module in _MODULES:
        mod = importlib.import_module(f"{__name__}.{module}")
        if module == name:
            return mod
        if hasattr(mod, name):
            return getattr(mod, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted({n for m in _MODULES for n in getattr(importlib.import_module(f"{__name__}.{m}"), "__all__", ())}
                  | set(_MODULES))
