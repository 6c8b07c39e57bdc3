"""``--set key=value`` overrides of a run, a comparison or a sweep (docs/interface.md, "Overrides").

A key is a dotted path: ``task.<key>`` sets a key of the task (``task.rho2``, ``task.T``, ``task.linear.x0``;
docs/tasks.md), any other key one of the run configuration (``baseline.iterations``, ``em.n_em``,
``baseline.noise.estimator``, ``i_switch``; docs/configuration.md).  The value is read as a TOML value
(``0.1``, ``true``, ``[1, 2]``, ``"text"``); what is not one is taken as a bare string
(``baseline.noise.estimator=kinematic``).  The overridden configuration is checked exactly as a TOML
file is (types, finiteness, ranges, the method's own rules), and an error names the ``--set`` item.
"""

from __future__ import annotations

import tomllib
from typing import Iterable

from ..config import ConfigError

__all__ = ["parse_set", "split_sets", "nested", "merge", "apply_config_sets"]


def parse_set(item: str) -> tuple[str, object]:
    """``"baseline.iterations=5"`` -> ``("baseline.iterations", 5)``; :class:`ConfigError` for a malformed item."""
    key, sep, text = item.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not sep or not key or not all(p.strip() and p == p.strip() for p in parts):
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE with a dotted KEY (e.g. baseline.iterations=5, "
                          "task.rho2=0.1)")
    try:
        value = tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    return key, value


def split_sets(items: Iterable[str] | dict) -> tuple[dict, dict]:
    """``(task_overrides, config_sets)`` from ``--set`` items (or a ``{key: value}`` mapping of Python values):
    the ``task.`` keys as a nested table for :func:`soc_opt.tasks.load_task`, the others as ``{dotted key:
    value}``.  A key given twice is an error naming it."""
    pairs = list(items.items()) if isinstance(items, dict) else [parse_set(i) for i in items]
    seen: set[str] = set()
    task: dict = {}
    sets: dict = {}
    for key, value in pairs:
        if key in seen:
            raise ConfigError(f"--set {key}: given twice")
        seen.add(key)
        if key == "task":
            raise ConfigError("--set task: name a task key, e.g. task.rho2=0.1")
        if key.startswith("task."):
            _put(task, key[len("task."):].split("."), value, key)
        else:
            sets[key] = value
    return task, sets


def nested(sets: dict) -> dict:
    """``{"a.b": 1, "a.c": 2}`` -> ``{"a": {"b": 1, "c": 2}}``."""
    out: dict = {}
    for key, value in sets.items():
        _put(out, key.split("."), value, key)
    return out


def _put(table: dict, path: list[str], value, key: str) -> None:
    for p in path[:-1]:
        nxt = table.setdefault(p, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"--set {key}: {p!r} is a value, not a table")
        table = nxt
    table[path[-1]] = value


def merge(base: dict, extra: dict) -> dict:
    """``base`` with ``extra`` laid over it, tables merged key by key (``base`` is not changed)."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def apply_config_sets(cfg, sets: dict, method: str):
    """``cfg`` (a :class:`~soc_opt.methods.config.DPSOCConfig`) with ``sets`` applied and checked as a TOML file
    is, then by ``method``'s own rules; :class:`ConfigError` names the ``--set`` item at fault."""
    if not sets:
        return cfg
    from ..plugins import METHODS

    data = merge(cfg.to_dict(), nested(sets))
    items = ", ".join(f"{k}={v!r}" for k, v in sets.items())
    try:
        new = type(cfg).from_dict(data)
        METHODS.lookup(method).check_config(new)
    except ConfigError as e:
        raise ConfigError(f"--set ({items}): {e}") from e
    return new
