"""Configuration objects: frozen dataclasses loadable from TOML with strict checking.

Every algorithm keeps its solver choice, tolerances and hyperparameters in one
frozen dataclass deriving from :class:`Config`.  ``Config.from_dict`` rejects
unknown keys and wrong types with a message naming the key, before any work
starts; nested configs are nested TOML tables.

Every ``Config`` checks itself when it is constructed, whether from TOML or in Python, in one
declared style (as scikit-learn's ``_parameter_constraints``):

1. NaN and infinite numbers are rejected in float fields (and lists of floats) (:func:`check_finite`);
2. every field's value must match its annotation (types, ``Literal`` choices, ``X | None``);
3. every field named in the class's ``_constraints`` table must satisfy one of its constraints:
   :class:`Interval` (a range of numbers), :class:`Options` (a set of names, possibly read from a
   solver or estimator table when the class is checked) or ``None`` (the value ``None``);
4. the subclass's own ``__post_init__`` runs last, for the rules between fields.

Every failure is one :class:`ConfigError` whose message starts with the key and names the value
(``from_dict`` prefixes the table path, ``from_toml`` the file).

**Plug-in tables.**  A config whose class names a plug-in table in ``_plugins`` (a
:class:`soc_opt.plugins.Registry`) also holds, beside its fields, one table per registered plug-in
that declares ``settings``, named after the plug-in (the run configuration's ``[ilqg]``, the noise
table's ``[baseline.noise.kinematic]``).  They are read as attributes (``cfg.ilqg``) or with
:meth:`Config.section`, given as keyword arguments (``NoiseConfig(kinematic=KinematicConfig(...))``,
``cfg.replace(ilqg=...)``), loaded from and written to TOML/JSON like nested configs, and kept in the
field :data:`PLUGIN_TABLES` (only the tables that differ from their defaults, so that equal settings
compare equal whatever is registered).
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from .reading import RefusedFile, read_regular

__all__ = ["Config", "ConfigError", "Interval", "Options", "config_error", "read_toml", "read_toml_file", "parse_toml",
           "check_finite", "IMPLIED_WHEN_ABSENT", "check_depth", "MAX_DEPTH", "MAX_TOML_BYTES", "MAX_TOML_ITEMS", "MAX_INT",
           "MAX_MESSAGE", "PLUGIN_TABLES", "plugin_settings", "shorten", "show"]

C = TypeVar("C", bound="Config")


#: Longest message of a :class:`ConfigError` (characters): a longer one is cut in its middle, keeping the
#: file and key it starts with and the advice it ends with.
MAX_MESSAGE = 2000
#: Longest key or value shown in a message (characters), cut in its middle likewise.
MAX_SHOWN = 100


def shorten(text: str, limit: int = MAX_SHOWN) -> str:
    """``text`` if it has at most ``limit`` characters, else its start and end around the count left out."""
    if len(text) <= limit:
        return text
    keep = max(limit // 2 - 10, 1)
    return f"{text[:keep]}...[{len(text) - 2 * keep} characters]...{text[-keep:]}"


def show(value: Any) -> str:
    """``repr(value)`` for a message, at most about :data:`MAX_SHOWN` characters (:func:`shorten`)."""
    return shorten(repr(value))


class ConfigError(ValueError):
    """A configuration value or key is invalid; the message names it (at most :data:`MAX_MESSAGE` characters)."""

    def __init__(self, *args):
        if len(args) == 1 and isinstance(args[0], str) and len(args[0]) > MAX_MESSAGE:
            args = (shorten(args[0], MAX_MESSAGE),)
        super().__init__(*args)


def config_error(key: str, message: str) -> ConfigError:
    """A :class:`ConfigError` ``"key: message"`` that :meth:`Config.from_dict` prefixes with the table path."""
    err = ConfigError(f"{key}: {message}")
    err.key = key
    return err


@dataclasses.dataclass(frozen=True)
class Interval:
    """A number in ``[lo, hi]`` (``None``: unbounded); ``closed`` says which ends are included."""

    lo: float | None = None
    hi: float | None = None
    closed: typing.Literal["both", "left", "right", "neither"] = "both"

    def holds(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        lo_ok = self.lo is None or (value >= self.lo if self.closed in ("both", "left") else value > self.lo)
        hi_ok = self.hi is None or (value <= self.hi if self.closed in ("both", "right") else value < self.hi)
        return lo_ok and hi_ok

    def __str__(self) -> str:
        if self.lo is not None and self.hi is None:
            return f"{'>=' if self.closed in ('both', 'left') else '>'} {self.lo:g}"
        if self.hi is not None and self.lo is None:
            return f"{'<=' if self.closed in ('both', 'right') else '<'} {self.hi:g}"
        left = "[" if self.closed in ("both", "left") else "("
        right = "]" if self.closed in ("both", "right") else ")"
        return f"in {left}{self.lo:g}, {self.hi:g}{right}"


@dataclasses.dataclass(frozen=True)
class Options:
    """One of a set of names: a tuple, or a callable returning the current names of a table
    (e.g. the KL-step solvers), so that a registered entry is accepted without editing the config."""

    values: tuple | typing.Callable[[], typing.Iterable]

    def names(self) -> tuple:
        return tuple(self.values() if callable(self.values) else self.values)

    def holds(self, value) -> bool:
        return isinstance(value, str) and value in self.names()

    def __str__(self) -> str:
        return f"one of {list(self.names())}"


def _satisfies(value, constraint) -> bool:
    return value is None if constraint is None else constraint.holds(value)


def check_constraints(cfg: "Config") -> None:
    """Types (annotations) and the ``_constraints`` table of ``cfg``'s class (module docstring)."""
    cls = type(cfg)
    hints = _hints(cls)
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.name in hints:
            _check_value(f.name, value, hints[f.name])
        big = _big_int(value)
        if big is not None:
            raise config_error(f.name, f"{show(big)} is beyond {MAX_INT} (every integer setting of soc_opt is at most "
                                       "that; the sizes and counts have smaller bounds, docs/security.md)")
        allowed = cls._constraints.get(f.name)
        if allowed is not None and not any(_satisfies(value, c) for c in allowed):
            wanted = " or ".join("None" if c is None else str(c) for c in allowed)
            raise config_error(f.name, f"must be {wanted}, got {show(value)}")


#: Largest magnitude of any integer in a configuration (a C ``int``: what MuJoCo, numpy sizes and the
#: solvers take); counts and sizes that cost memory or time have smaller bounds in their ``_constraints``.
MAX_INT = 2**31 - 1


def _big_int(value: Any):
    """The first integer of ``value`` (an integer or nested lists of them) beyond :data:`MAX_INT`, or None."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value if abs(value) > MAX_INT else None
    if isinstance(value, (tuple, list)):
        for v in value:
            big = _big_int(v)
            if big is not None:
                return big
    return None


_HINTS: dict[type, dict] = {}


def _hints(cls) -> dict:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _check_value(key: str, value: Any, tp: Any) -> None:
    """Raise a :class:`ConfigError` if ``value`` does not match the annotation ``tp`` (no conversion)."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            try:
                _check_value(key, value, arg)
                return
            except ConfigError:
                continue
        raise config_error(key, f"{show(value)} does not match {tp}")
    if tp is type(None):
        if value is not None:
            raise config_error(key, f"expected None, got {show(value)}")
        return
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise config_error(key, f"{show(value)} is not one of {list(typing.get_args(tp))}")
        return
    if origin in (tuple, list):
        if type(value).__name__ == "ndarray":  # an array given in Python: its owner converts it
            return
        if not isinstance(value, (list, tuple)):
            raise config_error(key, f"expected a list, got {type(value).__name__} {show(value)}")
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        if origin is tuple and typing.get_args(tp) and typing.get_args(tp)[-1] is not Ellipsis:
            if len(args) != len(value):
                raise config_error(key, f"expected {len(args)} entries, got {len(value)}")
            for v, a in zip(value, args):
                _check_value(key, v, a)
        elif args:
            for v in value:
                _check_value(key, v, args[0])
        return
    if origin is dict:
        if not isinstance(value, (dict, Config)):  # a table, or the config its owner built from it
            raise config_error(key, f"expected a table, got {type(value).__name__}")
        return
    checks = {
        float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
        int: lambda v: isinstance(v, int) and not isinstance(v, bool),
        bool: lambda v: isinstance(v, bool),
        str: lambda v: isinstance(v, str),
    }
    if tp in checks:
        if not checks[tp](value):
            raise config_error(key, f"expected {tp.__name__}, got {type(value).__name__} {show(value)}")
    elif isinstance(tp, type) and not isinstance(value, tp):
        raise config_error(key, f"expected {tp.__name__}, got {type(value).__name__} {show(value)}")


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
            err = ConfigError(f"{bad}: must be a finite number, got {show(_first_nonfinite(value))}")
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
        raise ConfigError(f"{path}: value {show(value)} does not match {tp}")
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ConfigError(f"{path}: {show(value)} is not one of {list(allowed)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {type(value).__name__} {show(value)}")
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
            raise ConfigError(f"{path}: expected a table, got {type(value).__name__} {show(value)}")
        return tp.from_dict(value, _path=path)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {type(value).__name__} {show(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {type(value).__name__} {show(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true/false, got {type(value).__name__} {show(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {type(value).__name__} {show(value)}")
        return value
    return value


def read_toml(path: str | Path) -> dict:
    """The table of a TOML file; a missing, unreadable, oversized or invalid file raises :class:`ConfigError`
    naming it (:func:`read_toml_file`)."""
    return read_toml_file(path)[0]


def read_toml_file(path: str | Path, what: str = "config file") -> tuple[dict, bytes]:
    """``(table, raw bytes)`` of the TOML file ``path`` (a link at its name is followed: the user named it).

    Read by :func:`soc_opt.reading.read_regular` (a regular file, never blocking, at most
    :data:`MAX_TOML_BYTES`), then :func:`parse_toml`.  Every refusal is a :class:`ConfigError` naming
    ``what`` and the file.
    """
    path = Path(path)
    name = f"{what} {str(path)!r}"
    try:
        raw = read_regular(path, MAX_TOML_BYTES, what="TOML file", follow=True)
    except FileNotFoundError:
        raise ConfigError(f"{name} does not exist") from None
    except RefusedFile as e:
        raise ConfigError(f"{what} {e}") from None
    except OSError as e:
        raise ConfigError(f"{name} cannot be read: {e.strerror or e}") from None
    return parse_toml(raw, name), raw


#: Largest TOML file read (a configuration, task or sweep file): 16 MiB.
MAX_TOML_BYTES = 16 << 20
#: Most characters ``= , [ { .`` a TOML file may hold (counted anywhere, strings and comments included): a
#: bound on the keys, values, tables and dotted-key parts the parser builds before anything is checked.
MAX_TOML_ITEMS = 50_000
#: Deepest nesting of lists and tables accepted in a JSON or TOML file soc_opt reads.
MAX_DEPTH = 64

_KEY_PART = r"""(?:[A-Za-z0-9_-]+|"(?:[^"\\\n]|\\.)*"|'[^'\n]*')"""
#: A dotted key (or table header) of more than MAX_DEPTH parts, starting at the first part.
_DEEP_KEY = re.compile(rf"""(?<![A-Za-z0-9_.'"-]){_KEY_PART}(?:[ \t]*\.[ \t]*{_KEY_PART}){{{MAX_DEPTH},}}""")


def _prescan_toml(text: str, name: str) -> None:
    """Refuse, before parsing, TOML text whose parse would build more than the bounds allow: more than
    :data:`MAX_TOML_ITEMS` structural characters, or a dotted key longer than :data:`MAX_DEPTH` parts
    (the standard library's parser spends memory quadratic in a dotted key's length)."""
    items = sum(text.count(c) for c in "=,[{.")
    if items > MAX_TOML_ITEMS:
        raise ConfigError(f"{name} holds {items} of the characters = , [ {{ . (keys, values, tables, dotted keys), "
                          f"more than a TOML file soc_opt reads may ({MAX_TOML_ITEMS})")
    if text.count(".") >= MAX_DEPTH and _DEEP_KEY.search(text):
        raise ConfigError(f"{name}: a dotted key or table name has more than {MAX_DEPTH} parts; nested more than "
                          f"{MAX_DEPTH} levels deep")


def parse_toml(raw: bytes | str, name: str) -> dict:
    """The table of TOML text ``raw`` (UTF-8 bytes or text), after the pre-scan bounds (:func:`_prescan_toml`)
    and checked to nest at most :data:`MAX_DEPTH` deep; :class:`ConfigError` starting with ``name`` otherwise."""
    try:
        text = raw.decode() if isinstance(raw, (bytes, bytearray)) else raw
    except UnicodeDecodeError as e:
        raise ConfigError(f"{name} is not UTF-8 text: {e}") from None
    _prescan_toml(text, name)
    try:
        return check_depth(tomllib.loads(text), name)
    except RecursionError:
        raise ConfigError(f"{name}: nested more than {MAX_DEPTH} levels deep") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{name} is not valid TOML: {e}") from None
    except ValueError as e:  # an integer of more digits than Python converts
        raise ConfigError(f"{name} is not a TOML file soc_opt reads: {shorten(str(e))}") from None


def check_depth(value: Any, name: str, limit: int = MAX_DEPTH) -> Any:
    """``value`` (parsed JSON or TOML) if its lists and tables nest at most ``limit`` deep, else a
    :class:`ConfigError` naming ``name`` (walked without recursion)."""
    stack = [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            items = v.values()
        elif isinstance(v, list):
            items = v
        else:
            continue
        if d > limit:
            raise ConfigError(f"{name}: nested more than {limit} levels deep; not a file soc_opt reads")
        stack.extend((x, d + 1) for x in items)
    return value


#: The field of a config with plug-in tables that holds them: ``((name, config), ...)`` sorted by name.
PLUGIN_TABLES = "plugin_tables"


def plugin_settings(cls) -> dict[str, type]:
    """``name -> Config class`` of the plug-in tables of config class ``cls`` in registration order (``{}`` for a
    class without plug-in tables)."""
    table = getattr(cls, "_plugins", None)
    if table is None:
        return {}
    out = table.settings()
    clash = sorted(set(out) & {f.name for f in dataclasses.fields(cls)})
    if clash:
        raise ConfigError(f"{table.kind} {clash[0]!r}: its settings table would hide the field {clash[0]!r} of {cls.__name__}")
    return out


def _canonical_plugin_tables(cls, given) -> tuple:
    """``given`` (pairs or a mapping of plug-in name to its config or table) as stored: checked against the
    registered plug-ins, converted from tables, defaults dropped, sorted by name."""
    settings = plugin_settings(cls)
    items = dict(given.items() if isinstance(given, dict) else given)
    out = []
    for name, value in items.items():
        if name not in settings:
            raise config_error(name, f"no registered plug-in of {cls.__name__} has settings named {name!r}; "
                               f"known: {', '.join(sorted(settings)) or 'none'}")
        tp = settings[name]
        if isinstance(value, dict):
            value = tp.from_dict(value, _path=name)
        if not isinstance(value, tp):
            raise config_error(name, f"expected {tp.__name__}, got {type(value).__name__} {show(value)}")
        if value != tp():
            out.append((name, value))
    return tuple(sorted(out, key=lambda kv: kv[0]))


class _ConfigMeta(type):
    """Lets a config with plug-in tables take them as keyword arguments (``NoiseConfig(kinematic=...)``,
    ``dataclasses.replace(cfg, ilqg=...)``): they are gathered into its :data:`PLUGIN_TABLES` field."""

    def __call__(cls, *args, **kwargs):
        settings = plugin_settings(cls) if kwargs else {}
        given = {k: kwargs.pop(k) for k in list(kwargs) if k in settings}
        if given:
            kwargs[PLUGIN_TABLES] = {**dict(kwargs.get(PLUGIN_TABLES, ())), **given}
        return super().__call__(*args, **kwargs)


def _resolve_plugin_tables(cfg) -> None:
    if PLUGIN_TABLES in cfg.__dataclass_fields__:
        object.__setattr__(cfg, PLUGIN_TABLES, _canonical_plugin_tables(type(cfg), getattr(cfg, PLUGIN_TABLES)))


#: Dotted key suffix -> ``(value, when)``: the value implied by the key's absence from a recorded
#: configuration (a run directory's ``config.json``, a sweep's ``trial.json``) when the table holding the
#: key's section has the entries ``when`` (the section is in use), declared by each class's
#: ``_implied_when_absent``.  A key
#: missing from an old record normally means an option added later whose default reproduces what the
#: run did; these are the exceptions, so resuming compares them (:func:`soc_opt.experiments.rundir.differences`).
IMPLIED_WHEN_ABSENT: dict[str, tuple[Any, dict]] = {}


@dataclasses.dataclass(frozen=True)
class Config(metaclass=_ConfigMeta):
    """Base class: a frozen dataclass with strict ``from_dict`` / ``from_toml`` / ``to_dict``.

    ``_constraints`` (a class attribute, ``{field: [Interval | Options | None, ...]}``) declares
    the allowed values of each field; subclasses may define ``__post_init__`` for the rules
    between fields; it runs after :func:`check_finite` and :func:`check_constraints` (installed by
    ``__init_subclass__``), so it never sees NaN, a wrong type or an out-of-range value.
    """

    _constraints: typing.ClassVar[dict[str, list]] = {}
    #: ``{"section.field": (value, when)}``: a field added after runs were recorded whose default changes
    #: what such a run did; a record without the field ran with ``value`` if the table holding ``section``
    #: has the entries ``when`` (:data:`IMPLIED_WHEN_ABSENT`).
    _implied_when_absent: typing.ClassVar[dict[str, tuple[Any, dict]]] = {}
    #: A :class:`soc_opt.plugins.Registry` whose plug-ins' ``settings`` are tables of this config (module
    #: docstring, "Plug-in tables"); such a class declares the field :data:`PLUGIN_TABLES`.
    _plugins: typing.ClassVar[Any] = None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        IMPLIED_WHEN_ABSENT.update(cls.__dict__.get("_implied_when_absent", {}))
        own = cls.__dict__.get("__post_init__")
        if own is not None and not getattr(own, "_checks_finite", False):
            def __post_init__(self, _own=own):
                _resolve_plugin_tables(self)
                check_finite(self)
                check_constraints(self)
                _own(self)

            __post_init__._checks_finite = True
            __post_init__.__doc__ = own.__doc__
            cls.__post_init__ = __post_init__

    def __post_init__(self):
        _resolve_plugin_tables(self)
        check_finite(self)
        check_constraints(self)

    def __getattr__(self, name: str):
        """A plug-in table read as an attribute (``cfg.ilqg``): :meth:`section`."""
        if name.startswith("_") or name == PLUGIN_TABLES:
            raise AttributeError(name)
        if name in plugin_settings(type(self)):
            return self.section(name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @classmethod
    def plugin_registry(cls):
        """The :class:`soc_opt.plugins.Registry` whose plug-ins' settings are tables of this class, or None."""
        return cls._plugins

    def section(self, name: str) -> "Config":
        """The plug-in table ``name`` (its defaults when not set); ``KeyError`` for an unregistered name."""
        settings = plugin_settings(type(self))
        if name not in settings:
            raise KeyError(f"{type(self).__name__} has no plug-in table {name!r}; registered: {', '.join(settings)}")
        return dict(getattr(self, PLUGIN_TABLES, ())).get(name) or settings[name]()

    @classmethod
    def from_dict(cls: type[C], data: dict, _path: str = "") -> C:
        if not isinstance(data, dict):
            raise ConfigError(f"{_path or cls.__name__}: expected a table, got {type(data).__name__}")
        hints = typing.get_type_hints(cls)
        tables = plugin_settings(cls)
        fields = {f.name: f for f in dataclasses.fields(cls) if f.init and f.name != PLUGIN_TABLES}
        fields.update(dict.fromkeys(tables))
        unknown = sorted(set(data) - set(fields))
        if unknown:
            where = f" in [{_path}]" if _path else ""
            shown = ", ".join(show(k) for k in unknown[:5]) + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else "")
            raise ConfigError(
                f"unknown config key{'s' if len(unknown) > 1 else ''} {shown}{where} "
                f"for {cls.__name__}; allowed: {', '.join(sorted(fields))}"
            )
        kwargs = {}
        for name, value in data.items():
            path = f"{_path}.{name}" if _path else name
            kwargs[name] = _check_type(path, value, tables.get(name) or hints[name])
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
        try:
            return cls.from_dict(data)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from e

    def to_dict(self) -> dict:
        """The TOML/JSON table: every field, then every registered plug-in table (``None`` values left out)."""
        out = {}
        for f in dataclasses.fields(self):
            if f.name == PLUGIN_TABLES:
                continue
            v = getattr(self, f.name)
            if isinstance(v, Config):
                v = v.to_dict()
            elif isinstance(v, tuple):
                v = list(v)
            if v is None:
                continue
            out[f.name] = v
        for name in plugin_settings(type(self)):
            out[name] = self.section(name).to_dict()
        return out

    def replace(self: C, **changes) -> C:
        return dataclasses.replace(self, **changes)
