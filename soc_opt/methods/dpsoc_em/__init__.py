"""DPSOC-EM (paper Algorithm 1; docs/math.md §3–§5, §7), one folder: :mod:`.config` its own settings
(``[em]``; it reads ``i_switch`` and LQR-FLM's ``[baseline]`` too), :mod:`.em` the EM phase it plugs
into the LQR-FLM iteration (``em_update``, ``em_phase``), :mod:`.method` the
:class:`~soc_opt.methods.base.Method` (``DPSOC_EM``).

The names of those modules are read from here as well; they are imported when first read, so that the
core may import the settings module without the method.
"""

import importlib

_MODULES = ("em", "config", "method")


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
