"""LQR-FLM (docs/math.md §7, §12), one folder: :mod:`.config` its settings (``[baseline]``),
:mod:`.acceptance` step acceptance and the multiplier (``judge``, ``next_multiplier``), :mod:`.iteration`
the one iteration, :mod:`.method` the :class:`~soc_opt.methods.base.Method` (``LQR_FLM``).

The names of those modules are read from here as well (``from soc_opt.methods.lqr_flm import
lqr_flm_iteration``); they are imported when first read, so that the core may import the settings
module without the method.
"""

import importlib

_MODULES = ("iteration", "acceptance", "config", "method")


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
