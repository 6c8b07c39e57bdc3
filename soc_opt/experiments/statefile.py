"""Run states as data: a checkpoint file that holds arrays and JSON, never code.

A checkpoint (``checkpoint.npz``, ``checkpoint.prev.npz``, ``fork_state.npz``) is a zip file
(numpy ``.npz``) with

- ``a0``, ``a1``, ...: the numeric arrays of the state (bool, integer, float or complex dtypes
  only; read with ``allow_pickle=False``, so an object array is refused);
- ``__tree__``: UTF-8 JSON (as a ``uint8`` array) describing the structure: JSON numbers,
  strings, ``null`` and booleans as they are, and ``{"$": kind, ...}`` nodes for tuples,
  lists, dicts with string keys, arrays (a reference to ``aN`` plus its layout) and the
  objects of an explicit schema (:func:`schema`: the core run state and the types it holds, plus
  the ``state_types`` every registered method and estimator declares, :mod:`soc_opt.plugins`);
- ``__sha256__``: the SHA-256 of the tree and of every array (name, dtype, shape, bytes).

Reading never imports or calls anything named by the file: the type names of object nodes are
looked up in :func:`schema` and anything else is refused, and objects are rebuilt field by field
(the fields of each type are fixed by its class).  The checksum detects truncated or damaged
files; it is **not** a security measure (whoever writes the file can recompute it).  Security
comes from the format holding no code.

**Layout.**  Each array is stored with its memory layout (strides, offset in the smallest
buffer spanning it, writeable flag) and rebuilt with the same strides.  The numbers of a run
depend on it: the same product on a transposed view and on a C-ordered copy calls different BLAS
kernels (``gemv`` N vs T) and rounds differently, and the previous KL step's model
(``RunState.prev``) holds such views; a checkpoint that made them contiguous (as pickle does)
lets a resumed run drift from the uninterrupted one at the 1e-16 level from its first
step-size adaptation on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import types
import typing
import zipfile
import zlib
from typing import Any

import numpy as np

from .. import plugins
from ..config import ConfigError
from ..files import load_json

__all__ = ["StateFileError", "schema", "FORMAT", "VERSION", "encode_state", "decode_state", "peek_state", "RECORD_MARK"]

FORMAT = "soc_opt state"
VERSION = 2
_TREE, _SUM = "__tree__", "__sha256__"
_KINDS = "biufc"  # numeric and boolean dtypes only


class StateFileError(ValueError):
    """A state file is damaged, not a state file, or holds something outside the schema."""


def _core_types() -> list[type]:
    from .. import models
    from ..learning import mixture
    from ..lqg import problem
    from ..methods import state
    from ..noise import estimator

    return [state.RunState, state.IterationRecord, state.EMDiagnostics, state.BestPolicy, state.PreviousStep,
            state.AcceptedPolicy, models.LinearGaussianPolicy, models.LinearGaussianDynamics, models.QuadraticCost,
            models.Rollouts, estimator.FilteredPolicy, estimator.KalmanFilter, problem.LocalModel,
            mixture.MixturePrior, mixture.VBState]


def _schema() -> dict[str, type]:
    out: dict[str, type] = {}
    for cls in [*_core_types(), *plugins.METHODS.state_types(), *plugins.ESTIMATORS.state_types()]:
        known = out.setdefault(cls.__name__, cls)
        if known is not cls:
            raise StateFileError(f"two state types are named {cls.__name__!r} ({known.__module__}.{known.__qualname__} "
                                 f"and {cls.__module__}.{cls.__qualname__}); a state file names types by their class name")
    return out


_SCHEMA: dict[tuple[int, int], dict[str, type]] = {}


def schema() -> dict[str, type]:
    """The types a state file may hold, by name: the core run state and everything it contains, and the
    ``state_types`` of every registered method and estimator (rebuilt when a plug-in is registered)."""
    key = (plugins.METHODS.version, plugins.ESTIMATORS.version)
    if key not in _SCHEMA:
        plugins.load_all()
        key = (plugins.METHODS.version, plugins.ESTIMATORS.version)
        _SCHEMA.clear()
        _SCHEMA[key] = _schema()
    return _SCHEMA[key]


def _is_namedtuple(cls) -> bool:
    return issubclass(cls, tuple) and hasattr(cls, "_fields")


def _fields(cls) -> list[str]:
    if _is_namedtuple(cls):
        return list(cls._fields)
    return [f.name for f in dataclasses.fields(cls)]


# ----------------------------------------------------------------------------- encoding


def _span(shape, strides, itemsize) -> int:
    """Bytes from the first to past the last element of a layout with non-negative strides."""
    if 0 in shape:
        return 0
    return sum((n - 1) * s for n, s in zip(shape, strides)) + itemsize


def _array_node(a: np.ndarray, arrays: dict, where: str) -> dict:
    if a.dtype.kind not in _KINDS:
        raise TypeError(f"{where}: arrays of dtype {a.dtype} cannot be stored in a state file")
    a_ = a
    if a.dtype.byteorder not in "=|" or any(s < 0 for s in a.strides) or any(s % a.itemsize for s in a.strides):
        a_ = np.ascontiguousarray(a).astype(a.dtype.newbyteorder("="), copy=False)
    n_bytes = _span(a_.shape, a_.strides, a_.itemsize)
    buf = np.zeros(n_bytes // a_.itemsize, a_.dtype)
    if buf.size:
        np.lib.stride_tricks.as_strided(buf, a_.shape, a_.strides)[...] = a_
    key = f"a{len(arrays)}"
    arrays[key] = buf
    return {"$": "array", "key": key, "shape": list(a_.shape), "strides": list(a_.strides),
            "writeable": bool(a.flags.writeable)}


def _encode(v: Any, arrays: dict, where: str):
    if v is None or type(v) in (bool, int, float, str):
        return v
    if isinstance(v, np.ndarray):
        return _array_node(v, arrays, where)
    if isinstance(v, np.generic):
        if v.dtype.kind not in _KINDS:
            raise TypeError(f"{where}: numpy scalar of dtype {v.dtype} cannot be stored in a state file")
        node = _array_node(np.asarray(v), arrays, where)
        return {**node, "$": "scalar"}
    cls = type(v)
    if schema().get(cls.__name__) is cls:
        values = list(v) if _is_namedtuple(cls) else [getattr(v, f) for f in _fields(cls)]
        return {"$": "object", "type": cls.__name__,
                "fields": {f: _encode(x, arrays, f"{where}.{f}") for f, x in zip(_fields(cls), values)}}
    if cls in (tuple, list):
        return {"$": cls.__name__, "items": [_encode(x, arrays, f"{where}[{i}]") for i, x in enumerate(v)]}
    if cls is dict:
        bad = [k for k in v if not isinstance(k, str)]
        if bad:
            raise TypeError(f"{where}: dict keys must be strings, got {bad[0]!r}")
        return {"$": "dict", "items": {k: _encode(x, arrays, f"{where}.{k}") for k, x in v.items()}}
    raise TypeError(f"{where}: a {cls.__module__}.{cls.__qualname__} cannot be stored in a state file "
                    "(not in the state file's schema: declare its class in the state_types of the method or estimator "
                    "that saves it, soc_opt.plugins)")


def _digest(tree: bytes, arrays: dict) -> str:
    h = hashlib.sha256(tree)
    for key in sorted(arrays, key=lambda k: int(k[1:])):
        a = arrays[key]
        h.update(f"\n{key} {a.dtype.str} {a.shape}\n".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def encode_state(state: Any) -> bytes:
    """The bytes of a state file holding ``state`` (module docstring)."""
    arrays: dict[str, np.ndarray] = {}
    body = _encode(state, arrays, "state")
    tree = json.dumps({"format": FORMAT, "version": VERSION, "state": body}).encode()  # insertion order: dicts read back in their order
    buf = io.BytesIO()
    np.savez(buf, **arrays, **{_TREE: np.frombuffer(tree, np.uint8),
                               _SUM: np.frombuffer(_digest(tree, arrays).encode(), np.uint8)})
    return buf.getvalue()


# ----------------------------------------------------------------------------- decoding


#: Largest state read back: its arrays' buffers and its arrays as views (each budget separately), 1 GiB.
MAX_STATE_BYTES = 1 << 30
#: Largest structure (``__tree__``) read back: 64 MiB.
MAX_TREE_BYTES = 64 << 20
#: Largest dimension or stride accepted in a layout (far beyond any array that fits in memory).
_MAX_INT = 1 << 48
_NPY_HEADER = 4096  # bytes allowed for a member's .npy header


def _member_bytes(zf: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int, name: str, what: str) -> tuple[np.dtype, int, bytes]:
    """``(dtype, length, data bytes)`` of one ``.npy`` member, refused before inflating it when the
    archive declares more than ``limit`` bytes of data (inflation stops at the declared size)."""
    if info.file_size > limit + _NPY_HEADER:
        raise StateFileError(f"{name}: entry {info.filename!r} declares {info.file_size} bytes, more than {what} "
                             f"needs ({limit} bytes); not a state file soc_opt wrote")
    with zf.open(info) as f:
        raw = f.read(info.file_size + 1)
    f = io.BytesIO(raw)
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"npy format version {version}")
    except ValueError as e:
        raise StateFileError(f"{name}: entry {info.filename!r} is not a numpy array ({e})") from None
    if dtype.hasobject or dtype.kind not in _KINDS or len(shape) != 1 or fortran:
        raise StateFileError(f"{name}: unexpected entry {info.filename!r} (dtype {dtype}, shape {shape})")
    data = raw[f.tell():]
    if len(data) != shape[0] * dtype.itemsize:
        raise StateFileError(f"{name}: entry {info.filename!r} is truncated or damaged ({len(data)} bytes for "
                             f"{shape[0]} values of {dtype})")
    return dtype, shape[0], data


def _needs(node, name: str) -> tuple[dict[str, int], dict[str, int]]:
    """For every array reference of the tree, by key: the bytes its buffer must hold, and the elements of
    all views of it; layouts are checked to be lists of bounded non-negative integers.  Walked without
    recursion (the tree's depth is bounded when it is parsed)."""
    needs: dict[str, int] = {}
    elements: dict[str, int] = {}
    total = 0
    stack = [node]
    while stack:
        v = stack.pop()
        if isinstance(v, list):
            stack.extend(v)
            continue
        if not isinstance(v, dict):
            continue
        if v.get("$") in ("array", "scalar") and isinstance(v.get("key"), str):
            key, shape, strides = v["key"], v.get("shape"), v.get("strides")
            for what, lst in (("shape", shape), ("strides", strides)):
                if not isinstance(lst, list) or len(lst) > 32 or not all(type(x) is int and 0 <= x < _MAX_INT for x in lst):
                    raise StateFileError(f"{name}: array {key!r} has an invalid {what} {str(lst)[:60]}")
            size = math.prod(shape)
            span = 0 if size == 0 else sum((n - 1) * s for n, s in zip(shape, strides))
            needs[key] = max(needs.get(key, 0), span)
            elements[key] = elements.get(key, 0) + size
            total += size
            if total > MAX_STATE_BYTES:  # counted in elements here; in bytes once the dtypes are known
                raise StateFileError(f"{name}: its arrays hold more than {MAX_STATE_BYTES} elements; not a state "
                                     "file soc_opt wrote")
            continue
        stack.extend(v.values())
    return needs, elements


def _read(data: bytes, name: str) -> tuple[dict, dict]:
    """Verified ``(tree, arrays)`` of a state file's bytes.

    Bounded: the structure is read first (at most :data:`MAX_TREE_BYTES`, nesting at most
    :data:`soc_opt.config.MAX_DEPTH`); each array member is inflated only after its declared size is
    checked against what the structure's views need (and the whole against :data:`MAX_STATE_BYTES`),
    and the checksum is verified before any view is built.
    """
    if not data:
        raise StateFileError(f"{name} is empty")
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
        infos = zf.infolist()
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as e:
        raise StateFileError(f"{name} is truncated or damaged ({type(e).__name__}: {e})") from None
    with zf:
        by_key = {}
        for info in infos:
            key = info.filename[:-4] if info.filename.endswith(".npy") else None
            ok = key in (_TREE, _SUM) or (key is not None and key[:1] == "a" and key[1:].isdigit() and len(key) < 12)
            if not ok or key in by_key:
                raise StateFileError(f"{name}: unexpected entry {info.filename!r}" + (" (twice)" if ok else ""))
            by_key[key] = info
        if _TREE not in by_key or _SUM not in by_key:
            raise StateFileError(f"{name} is not a soc_opt state file (no {_TREE} / {_SUM} entry)")
        try:
            dt_t, _, tree_b = _member_bytes(zf, by_key.pop(_TREE), MAX_TREE_BYTES, name, "a structure")
            dt_s, _, sum_b = _member_bytes(zf, by_key.pop(_SUM), 64, name, "a checksum")
            if dt_t != np.uint8 or dt_s != np.uint8:
                raise StateFileError(f"{name}: {_TREE} and {_SUM} must be uint8 byte strings")
            try:
                tree = load_json(tree_b, f"{name} ({_TREE})")
            except ConfigError as e:
                raise StateFileError(str(e)) from None
            needs, elements = _needs(tree, name)
            members, total = {}, 0
            for key, info in sorted(by_key.items(), key=lambda kv: int(kv[0][1:])):
                dtype, length, raw = _member_bytes(zf, info, min(needs.get(key, 0) + 16, MAX_STATE_BYTES), name,
                                                   "the arrays referring to it")
                total += len(raw)
                if total > MAX_STATE_BYTES:
                    raise StateFileError(f"{name}: its arrays hold more than {MAX_STATE_BYTES} bytes")
                members[key] = np.frombuffer(bytearray(raw), dtype)
        except (zipfile.BadZipFile, EOFError, OSError, zlib.error, NotImplementedError) as e:
            raise StateFileError(f"{name} is truncated or damaged ({type(e).__name__}: {e})") from None
    view_bytes = sum(size * members[key].itemsize for key, size in elements.items() if key in members)
    if view_bytes > MAX_STATE_BYTES:  # e.g. a zero-stride view expanding a small buffer
        raise StateFileError(f"{name}: its arrays span {view_bytes} bytes as views, more than {MAX_STATE_BYTES}; "
                             "not a state file soc_opt wrote")
    if _digest(tree_b, members).encode() != sum_b:
        raise StateFileError(f"{name} is truncated or damaged (checksum mismatch)")
    if not isinstance(tree, dict) or tree.get("format") != FORMAT or "state" not in tree:
        raise StateFileError(f"{name} is not a soc_opt state file")
    if tree.get("version") != VERSION:
        raise StateFileError(f"{name} has state file version {tree.get('version')!r}; this soc_opt reads "
                             f"version {VERSION}")
    return tree, members


def _bad(where: str, what: str):
    return StateFileError(f"unexpected content at {where}: {what}")


def _int_list(v, where: str) -> list[int]:
    if not isinstance(v, list) or not all(type(x) is int and x >= 0 for x in v):
        raise _bad(where, f"expected a list of non-negative integers, got {str(v)[:60]}")
    return v


def _decode_array(node: dict, arrays: dict, where: str) -> np.ndarray:
    key = node.get("key")
    if not isinstance(key, str) or key not in arrays:
        raise _bad(where, f"array reference {key!r} names no array in the file")
    buf = arrays[key]
    shape, strides = _int_list(node.get("shape"), where), _int_list(node.get("strides"), where)
    if len(shape) != len(strides) or any(s % buf.itemsize for s in strides):
        raise _bad(where, f"array layout shape {shape} strides {strides} does not fit dtype {buf.dtype}")
    if _span(shape, strides, buf.itemsize) > buf.nbytes:  # the view must stay inside its buffer
        raise _bad(where, f"array layout shape {shape} strides {strides} exceeds its {buf.nbytes}-byte buffer")
    a = np.lib.stride_tricks.as_strided(buf, tuple(shape), tuple(strides), writeable=True)
    if node.get("writeable") is False:
        a.flags.writeable = False
    return a


def _decode(v: Any, arrays: dict, where: str):
    if v is None or type(v) in (bool, int, float, str):
        return v
    if not isinstance(v, dict) or not isinstance(v.get("$"), str):
        raise _bad(where, f"a JSON {type(v).__name__} where a value node was expected")
    kind = v["$"]
    if kind in ("array", "scalar"):
        a = _decode_array(v, arrays, where)
        return a[()] if kind == "scalar" and a.ndim == 0 else a
    if kind in ("tuple", "list"):
        items = v.get("items")
        if not isinstance(items, list):
            raise _bad(where, f"{kind} without an item list")
        out = [_decode(x, arrays, f"{where}[{i}]") for i, x in enumerate(items)]
        return tuple(out) if kind == "tuple" else out
    if kind == "dict":
        items = v.get("items")
        if not isinstance(items, dict):
            raise _bad(where, "dict without an item table")
        return {k: _decode(x, arrays, f"{where}.{k}") for k, x in items.items()}
    if kind == "object":
        return _decode_object(v, arrays, where)
    raise _bad(where, f"unknown node kind {kind!r}")


def _decode_object(v: dict, arrays: dict, where: str):
    name, fields = v.get("type"), v.get("fields")
    cls = schema().get(name) if isinstance(name, str) else None
    if cls is None:
        raise _bad(where, f"type {name!r} is not part of the run state schema (the method or estimator that "
                   "declares it in its state_types is not registered)")
    if not isinstance(fields, dict):
        raise _bad(where, f"{name} without a field table")
    names = _fields(cls)
    unknown = sorted(set(fields) - set(names))
    if unknown:
        raise _bad(where, f"{name} has no field {unknown[0]!r}")
    values = {f: _decode(x, arrays, f"{where}.{f}") for f, x in fields.items()}
    if _is_namedtuple(cls):
        missing = [f for f in names if f not in values and f not in cls._field_defaults]
        if missing:
            raise _bad(where, f"{name} lacks field {missing[0]!r}")
        obj = cls(**values)
        _check_fields(obj, cls, where)
        return obj
    obj = object.__new__(cls)  # field by field, as stored: no validation that could copy or reorder arrays
    for f in dataclasses.fields(cls):
        if f.name in values:
            val = values[f.name]
        elif f.default is not dataclasses.MISSING:
            val = f.default
        elif f.default_factory is not dataclasses.MISSING:
            val = f.default_factory()
        else:
            raise _bad(where, f"{name} lacks field {f.name!r}")
        object.__setattr__(obj, f.name, val)
    _check_fields(obj, cls, where)
    return obj


_HINTS: dict[type, dict] = {}
#: A class attribute: ``True`` on a state type whose float fields are records of what happened (they may be NaN
#: or infinite, e.g. ``IterationRecord``); elsewhere floats are finite.
RECORD_MARK = "nonfinite_floats"


def _hints(cls) -> dict:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls, localns=dict(schema()))
    return _HINTS[cls]


def _conforms(value, hint, finite: bool) -> bool:
    """Whether a decoded ``value`` is of the annotated type ``hint`` (floats finite when ``finite``)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is typing.Any:
        return True
    if hint is type(None):
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(_conforms(value, a, finite) for a in args)
    if origin is typing.Literal:
        return type(value) is str and value in args
    if hint is bool:
        return isinstance(value, (bool, np.bool_))
    if hint is int:
        return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if hint is float:
        ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
        return ok and (not finite or bool(np.isfinite(value)))
    if hint is str:
        return type(value) is str
    if hint is np.ndarray:
        return isinstance(value, np.ndarray)
    if origin is tuple or hint is tuple:
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_conforms(v, args[0], finite) for v in value)
        return not args or (len(args) == len(value) and all(_conforms(v, a, finite) for v, a in zip(value, args)))
    if origin is dict or hint is dict:
        return isinstance(value, dict) and (not args or all(
            type(k) is str and _conforms(v, args[1], finite) for k, v in value.items()))
    if isinstance(hint, type):
        return isinstance(value, hint)
    return True  # a type this check does not know: left to the class


def _check_fields(obj, cls, where: str) -> None:
    """Every field of a decoded object of schema type ``cls`` against its annotation (docs/security.md)."""
    finite = not getattr(cls, RECORD_MARK, False)
    for f, hint in _hints(cls).items():
        if f.startswith("_") or f not in _fields(cls):
            continue
        v = getattr(obj, f)
        if not _conforms(v, hint, finite):
            shown = type(v).__name__ if not isinstance(v, (int, float, str)) else repr(v)[:40]
            raise _bad(f"{where}.{f}", f"{shown} is not a valid {getattr(hint, '__name__', str(hint))}"
                       + (" (finite)" if finite and "float" in str(hint) else ""))


def decode_state(data: bytes, name: str = "state file"):
    """The state in the bytes of a state file; :class:`StateFileError` saying what is wrong."""
    tree, arrays = _read(data, name)
    try:
        return _decode(tree["state"], arrays, "state")
    except StateFileError as e:
        raise StateFileError(f"{name}: {e}") from None
    except (TypeError, ValueError) as e:  # a field the class rejects (e.g. a bad RNG state)
        raise StateFileError(f"{name}: unexpected content ({type(e).__name__}: {e})") from None


def peek_state(data: bytes, name: str = "state file") -> dict:
    """The top-level scalar fields of the state in a verified state file, without rebuilding it
    (e.g. ``{"iteration": 3, ...}``); :class:`StateFileError` if the file is damaged."""
    tree, _ = _read(data, name)
    node = tree["state"]
    fields = node.get("fields") if isinstance(node, dict) else None
    if not isinstance(fields, dict):
        raise StateFileError(f"{name}: unexpected content at state: not a run state")
    return {k: x for k, x in fields.items() if x is None or type(x) in (bool, int, float, str)}
