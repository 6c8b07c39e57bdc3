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
from pathlib import Path

__all__ = ["environment", "environment_differences", "PACKAGES"]

# the packages whose arithmetic a run's numbers depend on
PACKAGES = ("soc_opt", "numpy", "scipy", "mujoco", "scikit-learn", "casadi", "cvxpy", "clarabel", "scs", "numba")


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _blas() -> list[str]:
    """``"<library> <version> <kernel>"`` of the BLAS that numpy and scipy call (the kernel OpenBLAS picked for
    this CPU).  Only theirs: a BLAS that another package bundles (SCS's, loaded with cvxpy) is in the process
    only once that package is imported, so a list of every loaded one would differ between two processes of
    one run by what else they had imported.  Where numpy's and scipy's BLAS do not live in their own package
    directories (a system BLAS), every loaded BLAS is listed."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:  # pragma: no cover - a declared dependency
        return []
    import numpy
    import scipy.linalg  # loads scipy's BLAS

    homes = [Path(mod.__file__).resolve().parent for mod in (numpy, scipy)]
    homes += [h.with_name(h.name + ".libs") for h in homes]  # where the wheels keep their shared libraries
    found = [lib for lib in threadpool_info() if lib.get("user_api") == "blas"]
    own = [lib for lib in found if any(h in Path(str(lib.get("filepath", ""))).resolve().parents for h in homes)]
    return sorted({" ".join(str(lib.get(k)) for k in ("internal_api", "version", "architecture") if lib.get(k))
                   for lib in own or found})


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
