"""The software and machine a run was made with, recorded in its ``config.json``.

A run is bit-for-bit repeatable in one environment (same package versions, same BLAS kernel and
CPU class): resumed or not, the same command gives the same numbers.  Across environments the
floating-point rounding of MuJoCo, numpy and the BLAS differs in the last digits, and a closed loop
under noise amplifies it, so single runs differ while statistics over seeds agree (docs/reproducibility.md).
The record lets a reader tell which case they are in; a run resumed in another environment says so.
"""

from __future__ import annotations

import platform
import sys
from importlib import metadata

__all__ = ["environment", "environment_differences", "PACKAGES"]

# the packages whose arithmetic a run's numbers depend on
PACKAGES = ("soc_opt", "numpy", "scipy", "mujoco", "scikit-learn", "casadi", "cvxpy", "clarabel", "scs", "numba")


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _blas() -> list[str]:
    """``"<library> <version> <kernel>"`` of every BLAS loaded (the kernel OpenBLAS picked for this CPU)."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:  # pragma: no cover - a declared dependency
        return []
    out = []
    for lib in threadpool_info():
        if lib.get("user_api") == "blas":
            out.append(" ".join(str(lib.get(k)) for k in ("internal_api", "version", "architecture") if lib.get(k)))
    return sorted(set(out))


def environment() -> dict:
    """``{"python", "machine", "blas", "kernels", "packages": {name: version}}`` of this process; ``kernels`` is
    the path of the compiled kernels (:func:`soc_opt.compiled.describe`: ``"numba <version>"`` or ``"numpy"``),
    which round differently from the numpy path (docs/reproducibility.md)."""
    from ..compiled import describe

    return {"python": platform.python_version(), "machine": f"{platform.system()} {platform.machine()}",
            "implementation": sys.implementation.name, "blas": _blas(), "kernels": describe(),
            "packages": {p: _version(p) for p in PACKAGES}}


def environment_differences(old: dict | None, new: dict) -> list[str]:
    """``"what: old -> new"`` for every recorded entry of ``old`` that differs in ``new`` (an empty list
    when ``old`` records nothing (a run recorded without it); entries of an unexpected type
    in a hand-edited record are reported as they read, never raised on)."""
    if not isinstance(old, dict):
        return []
    out = []
    for key in ("python", "machine", "implementation", "blas", "kernels"):
        if key in old and old[key] != new.get(key):
            out.append(f"{key}: {old[key]} -> {new.get(key)}")
    olds, news = old.get("packages"), new.get("packages") or {}
    if not isinstance(olds, dict):
        return out + ([f"packages: {olds!r} -> (versions)"] if "packages" in old else [])
    for name, ver in olds.items():
        if ver != news.get(name):
            out.append(f"{name}: {ver} -> {news.get(name)}")
    return out
