"""Run states as data: a checkpoint file that holds arrays and JSON, never code.

A checkpoint (``checkpoint.npz``, ``checkpoint.prev.npz``, ``fork_state.npz``) is a zip file
(numpy ``.npz``) with

- ``a0``, ``a1``, ...: the numeric arrays of the state (bool, integer, float or complex dtypes
  only; read with ``allow_pickle=False``, so an object array is refused);
- ``__tree__``: UTF-8 JSON (as a ``uint8`` array) describing the structure: JSON numbers,
  strings, ``null`` and booleans as they are, and ``{"$": kind, ...}`` nodes for tuples,
  lists, dicts with string keys, arrays (a reference to ``aN`` plus its layout) and the
  objects of an explicit schema (:func:`schema`: the run state and the types it holds);
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
let a resumed run drift from the uninterrupted one at the 1e-16 level from its first
step-size adaptation on (issue 18).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import zipfile
from typing import Any

import numpy as np

__all__ = ["StateFileError", "schema", "FORMAT", "VERSION", "encode_state", "decode_state", "peek_state"]

FORMAT = "soc_opt state"
VERSION = 2
_TREE, _SUM = "__tree__", "__sha256__"
_KINDS = "biufc"  # numeric and boolean dtypes only


class StateFileError(ValueError):
    """A state file is damaged, not a state file, or holds something outside the schema."""


def _schema() -> dict[str, type]:
    from .. import models
    from ..learning import mixture
    from ..lqg import step_size
    from ..methods import ilqg
    from ..methods import state as algorithms
    from ..noise import estimator
    from ..noise.kinematic import filter as kinematic

    classes = [algorithms.RunState, algorithms.IterationRecord, algorithms.EMDiagnostics, algorithms.BestPolicy,
               algorithms.PreviousStep, algorithms.AcceptedPolicy, models.LinearGaussianPolicy, models.LinearGaussianDynamics,
               models.QuadraticCost, models.Rollouts, estimator.FilteredPolicy, estimator.KalmanFilter,
               step_size.LocalModel, mixture.MixturePrior, mixture.VBState, ilqg.ILQGState, ilqg.ILQGRecord,
               kinematic.KinematicFilter, kinematic.KinematicFilteredPolicy]
    return {c.__name__: c for c in classes}


_SCHEMA: dict[str, type] = {}


def schema() -> dict[str, type]:
    """The types a state file may hold, by name: the run states and everything they contain
    (built on first use: the modules defining them import this one indirectly)."""
    if not _SCHEMA:
        _SCHEMA.update(_schema())
    return _SCHEMA


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
                    "(add its class to soc_opt.experiments.statefile's schema)")


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


def _read(data: bytes, name: str) -> tuple[dict, dict]:
    """Verified ``(tree, arrays)`` of a state file's bytes."""
    if not data:
        raise StateFileError(f"{name} is empty")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as f:
            members = {k: f[k] for k in f.files}
    except (zipfile.BadZipFile, EOFError, OSError) as e:
        raise StateFileError(f"{name} is truncated or damaged ({type(e).__name__}: {e})") from None
    except ValueError as e:  # allow_pickle=False refusing an object array, or a bad .npy header
        raise StateFileError(f"{name} holds something other than numeric arrays ({e})") from None
    except Exception as e:
        raise StateFileError(f"{name} is not a state file ({type(e).__name__}: {e})") from None
    if _TREE not in members or _SUM not in members:
        raise StateFileError(f"{name} is not a soc_opt state file (no {_TREE} / {_SUM} entry)")
    tree_a, sum_a = members.pop(_TREE), members.pop(_SUM)
    for k, a in members.items():
        if not (k[:1] == "a" and k[1:].isdigit()) or a.dtype.kind not in _KINDS or a.ndim != 1:
            raise StateFileError(f"{name}: unexpected entry {k!r} (dtype {a.dtype}, shape {a.shape})")
    if tree_a.dtype != np.uint8 or sum_a.dtype != np.uint8 or tree_a.ndim != 1:
        raise StateFileError(f"{name}: {_TREE} and {_SUM} must be uint8 byte strings")
    tree_b = tree_a.tobytes()
    if _digest(tree_b, members).encode() != sum_a.tobytes():
        raise StateFileError(f"{name} is truncated or damaged (checksum mismatch)")
    try:
        tree = json.loads(tree_b.decode())
    except (UnicodeDecodeError, ValueError) as e:
        raise StateFileError(f"{name}: its structure is not valid JSON ({e})") from None
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
        raise _bad(where, f"type {name!r} is not part of the run state schema")
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
        return cls(**values)
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
    return obj


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
