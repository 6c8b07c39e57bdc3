"""The plug-in tables: methods and noise estimators by name, one idiom for both.

A plug-in is an object (a method instance, an estimator class) with

- ``name``: its name (``soc-opt run --method NAME``, ``[baseline.noise] estimator = "NAME"``);
- ``settings``: its own configuration, a :class:`~soc_opt.config.Config` subclass (or ``None``),
  the TOML table named after the plug-in: ``[NAME]`` of the run configuration for a method,
  ``[baseline.noise.NAME]`` for an estimator;
- ``state_types``: the classes of its saved state beyond the core run state (frozen dataclasses or
  named tuples), which the state file's schema then accepts.

It is registered by one line in its registry module (:mod:`soc_opt.methods.registry`,
:mod:`soc_opt.noise.registry`) or, from a script, by :meth:`Registry.register`: the one registration
API, which checks the plug-in (:func:`check_plugin`, then the table's ``check``: the method protocol,
an estimator class) whichever way it is added; :meth:`Registry.lookup` is the one lookup.  The core
(run configuration, state files, run directories) reads the tables :data:`METHODS` and
:data:`ESTIMATORS` and never imports a plug-in module: a table fills itself on first use by importing
its registry module (``loader``), the one place that names the built-in plug-ins and installs the
table's ``check``.  That import is made at run time, from this floor up to the methods' and the
estimators' floors; ``tests/test_layers.py`` checks that it names exactly these two registry modules.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Iterator, MutableMapping
from typing import Any

from .config import Config, ConfigError

__all__ = ["Registry", "METHODS", "ESTIMATORS", "check_plugin", "load_all"]


def check_plugin(plugin: Any, kind: str) -> None:
    """``TypeError`` unless ``plugin`` declares a name, its ``settings`` (a Config subclass or None) and its
    ``state_types`` (dataclasses or named tuples)."""
    name = getattr(plugin, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"a {kind} needs a non-empty string name, got {name!r}")
    settings = getattr(plugin, "settings", None)
    if settings is not None and not (isinstance(settings, type) and issubclass(settings, Config)):
        raise TypeError(f"{kind} {name!r}: settings must be a soc_opt.config.Config subclass or None, got {settings!r}")
    types_ = getattr(plugin, "state_types", ())
    if not isinstance(types_, tuple):
        raise TypeError(f"{kind} {name!r}: state_types must be a tuple of classes, got {types_!r}")
    for cls in types_:
        ok = isinstance(cls, type) and (dataclasses.is_dataclass(cls) or (issubclass(cls, tuple) and hasattr(cls, "_fields")))
        if not ok:
            raise TypeError(f"{kind} {name!r}: state type {cls!r} is not a dataclass or a named tuple")


class Registry(MutableMapping):
    """``name -> plug-in`` in registration order (the order the CLI lists them).

    ``kind`` names the plug-ins in messages; ``loader`` is the module whose import registers the
    built-in ones, imported on first read; ``selector``: the key that picks one of them in the table
    holding their settings tables (``estimator`` in ``[baseline.noise]``; ``None``: picked elsewhere, as
    a method is by ``--method``).  ``check(plugin)``: the table's own test of a plug-in, raising
    ``TypeError`` (installed by the loader).  :attr:`version` counts the changes (caches of the
    assembled schema key on it).
    """

    def __init__(self, kind: str, loader: str, selector: str | None = None):
        self.kind = kind
        self.loader = loader
        self.selector = selector
        self.check = None
        self.version = 0
        self._entries: dict[str, Any] = {}
        self._loaded = False

    def _load(self) -> None:
        if not self._loaded:
            self._loaded = True  # set first: the loader's own registrations read the table
            try:
                importlib.import_module(self.loader)
            except BaseException:
                self._loaded = False
                raise

    def __getitem__(self, name: str):
        self._load()
        return self._entries[name]

    def __setitem__(self, name: str, plugin) -> None:
        self._load()
        check_plugin(plugin, self.kind)
        if self.check is not None:
            self.check(plugin)
        if plugin.name != name:
            raise ValueError(f"{self.kind} {plugin.name!r} registered under another name {name!r}")
        self._entries[name] = plugin
        self.version += 1

    def __delitem__(self, name: str) -> None:
        self._load()
        del self._entries[name]
        self.version += 1

    def __iter__(self) -> Iterator[str]:
        self._load()
        return iter(list(self._entries))

    def __len__(self) -> int:
        self._load()
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {list(self._entries)!r})"

    def register(self, plugin, *, replace: bool = False):
        """Add ``plugin`` under its ``name`` (``replace`` to overwrite) once it passes the checks; returns it."""
        self._load()
        name = getattr(plugin, "name", None)
        if name in self._entries and not replace:
            raise ValueError(f"a {self.kind} named {name!r} is already registered")
        self[name] = plugin
        return plugin

    def lookup(self, name: str):
        """The plug-in ``name``; :class:`ConfigError` listing the registered ones otherwise."""
        plugin = self.get(name)
        if plugin is None:
            raise ConfigError(f"unknown {self.kind} {name!r}; use one of {', '.join(map(repr, self))}")
        return plugin

    def settings(self) -> dict[str, type[Config]]:
        """``name -> settings class`` of the plug-ins that declare their own settings."""
        return {name: p.settings for name, p in self.items() if getattr(p, "settings", None) is not None}

    def state_types(self) -> tuple[type, ...]:
        """The state types every registered plug-in declares (in registration order)."""
        return tuple(cls for p in self.values() for cls in getattr(p, "state_types", ()))


#: Every method by name (a :class:`soc_opt.methods.base.Method` instance), filled by :mod:`soc_opt.methods.registry`.
METHODS = Registry("method", "soc_opt.methods.registry")
#: Every noise estimator by name (a :class:`soc_opt.noise.strategy.NoiseStrategy` subclass), filled by
#: :mod:`soc_opt.noise.registry`.
ESTIMATORS = Registry("estimator", "soc_opt.noise.registry", selector="estimator")


def load_all() -> None:
    """Register the built-in plug-ins of both tables (what reading either table does on first use)."""
    for table in (METHODS, ESTIMATORS):
        table._load()
