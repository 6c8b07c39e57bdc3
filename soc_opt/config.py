"""Configuration objects: frozen dataclasses loadable from TOML with strict checking.

Every algorithm keeps its solver choice, tolerances and hyperparameters in one
frozen dataclass deriving from :class:`Config`.  ``Config.from_dict`` rejects
unknown keys and wrong types with a message naming the key, before any work
starts; nested configs are nested TOML tables.

Every ``Config`` also rejects NaN and infinite numbers in any of its float fields (and in
lists of floats), whether built from TOML or in Python: :meth:`Config.__post_init__` checks them
before a subclass's own ``__post_init__`` range checks run (:func:`check_finite`).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

__all__ = ["Config", "ConfigError", "read_toml", "check_finite"]

C = TypeVar("C", bound="Config")


class ConfigError(ValueError):
    """A configuration value or key is invalid; the message names it."""


def _nonfinite(name: str, value: Any) -> str | None:
    """The path of the first NaN/inf float in ``value`` (a float or nested lists of floats), or None."""
    if isinstance(value, float):
        return None if math.isfinite(value) else name
    if isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            bad = _nonfinite(f"{name}[{i}]", v)
            if bad is not None:
                return bad
    return None


def check_finite(cfg: "Config") -> None:
    """Raise :class:`ConfigError` naming the first field of ``cfg`` holding NaN or inf.

    Floats and (nested) lists of floats are checked; nested configs check themselves when they
    are built, and tables (``dict`` fields) are left to their owner.  The error's ``key`` attribute
    is the field name, so that :meth:`Config.from_dict` can prefix the table path.
    """
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        bad = _nonfinite(f.name, value)
        if bad is not None:
            err = ConfigError(f"{bad}: must be a finite number, got {_first_nonfinite(value)!r}")
            err.key = f.name
            raise err


def _first_nonfinite(value: Any) -> float:
    if isinstance(value, float):
        return value
    return next(_first_nonfinite(v) for v in value if _nonfinite("", v) is not None)


def _check_type(path: str, value: Any, tp: Any) -> Any:
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arg in typing.get_args(tp):
            if arg is type(None):
                if value is None:
                    return None
                continue
            try:
                return _check_type(path, value, arg)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{path}: value {value!r} does not match {tp}")
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ConfigError(f"{path}: {value!r} is not one of {list(allowed)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {type(value).__name__} {value!r}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{path}: expected {len(args)} entries, got {len(value)}")
            return tuple(_check_type(f"{path}[{i}]", v, a) for i, (v, a) in enumerate(zip(value, args)))
        elem = args[0] if args else Any
        out = [_check_type(f"{path}[{i}]", v, elem) for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a table, got {type(value).__name__}")
        return dict(value)
    if isinstance(tp, type) and issubclass(tp, Config):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a table, got {type(value).__name__} {value!r}")
        return tp.from_dict(value, _path=path)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true/false, got {type(value).__name__} {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {type(value).__name__} {value!r}")
        return value
    return value


def read_toml(path: str | Path) -> dict:
    """The table of a TOML file; a missing or invalid file raises :class:`ConfigError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {str(path)!r} is not valid TOML: {e}") from e


@dataclasses.dataclass(frozen=True)
class Config:
    """Base class: a frozen dataclass with strict ``from_dict`` / ``from_toml`` / ``to_dict``.

    Subclasses may define ``__post_init__`` for their range checks; it runs after
    :func:`check_finite` (installed by ``__init_subclass__``), so a range check never sees NaN.
    """

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        own = cls.__dict__.get("__post_init__")
        if own is not None and not getattr(own, "_checks_finite", False):
            def __post_init__(self, _own=own):
                check_finite(self)
                _own(self)

            __post_init__._checks_finite = True
            __post_init__.__doc__ = own.__doc__
            cls.__post_init__ = __post_init__

    def __post_init__(self):
        check_finite(self)

    @classmethod
    def from_dict(cls: type[C], data: dict, _path: str = "") -> C:
        if not isinstance(data, dict):
            raise ConfigError(f"{_path or cls.__name__}: expected a table, got {type(data).__name__}")
        hints = typing.get_type_hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
        unknown = sorted(set(data) - set(fields))
        if unknown:
            where = f" in [{_path}]" if _path else ""
            raise ConfigError(
                f"unknown config key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}{where} "
                f"for {cls.__name__}; allowed: {', '.join(sorted(fields))}"
            )
        kwargs = {}
        for name, value in data.items():
            path = f"{_path}.{name}" if _path else name
            kwargs[name] = _check_type(path, value, hints[name])
        try:
            return cls(**kwargs)
        except ConfigError as e:
            if _path and getattr(e, "key", None):
                raise ConfigError(f"{_path}.{e}") from e
            raise
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{_path or cls.__name__}: {e}") from e

    @classmethod
    def from_toml(cls: type[C], path: str | Path, table: str | None = None) -> C:
        data = read_toml(path)
        if table is not None:
            data = data.get(table, {})
        return cls.from_dict(data)

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Config):
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            if v is None:
                continue
            out[f.name] = v
        return out

    def replace(self: C, **changes) -> C:
        return dataclasses.replace(self, **changes)
