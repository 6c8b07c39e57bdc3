"""Compiled kernels (numba): which path runs, where the compiled code is cached, the ``jit`` decorator.

The numpy code of :mod:`soc_opt.lgssm` and :mod:`soc_opt.noise.kinematic` is the reference.  The
per-sequence recursions of the Gaussian core (docs/math.md §4, covariances per sequence: the §11.2
smoother) and the kinematic filter's measurement update (docs/math.md §11.3) also exist as compiled
loops (:mod:`.lgssm_kernels`, :mod:`.kinematic_kernels`), tested against the numpy path to rounding.
They agree with it to rounding, not to the bit (docs/reproducibility.md, "The compiled kernels").

Which path runs (:func:`backend`):

* ``"numba"`` when numba is installed (the optional extra ``soc_opt[fast]``) and the environment
  variable ``SOC_OPT_KERNELS`` is unset or ``numba``;
* ``"numpy"`` when numba is missing or ``SOC_OPT_KERNELS=numpy``.

``SOC_OPT_KERNELS=numba`` without numba is an error (:class:`ImportError` on first use).  Every run
records the path in its ``config.json`` (``environment.kernels``, :func:`describe`).

Compiled functions are cached on disk (``cache=True``) under the user's cache directory,
``$SOC_OPT_CACHE_DIR`` or ``$XDG_CACHE_HOME/soc_opt/numba`` (default ``~/.cache/soc_opt/numba``), never in
the source tree: a process pays the compilation once per kernel and machine, later ones load it
(``NUMBA_CACHE_DIR``, when the user has set it, is respected).  Importing this module does not import
numba; the kernel modules do, on first use.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

__all__ = ["ENV", "backend", "available", "describe", "cache_dir", "jit"]

#: The environment variable that selects the path: ``numpy`` or ``numba`` (unset: numba when installed).
ENV = "SOC_OPT_KERNELS"
_CHOICES = ("numpy", "numba")


def available() -> bool:
    """Whether numba can be imported (without importing it)."""
    return importlib.util.find_spec("numba") is not None


def backend(requested: str | None = None) -> str:
    """``"numba"`` or ``"numpy"``: ``requested`` if given, else ``$SOC_OPT_KERNELS``, else numba when installed.

    Raises :class:`ValueError` for another name and :class:`ImportError` when numba is requested but missing.
    """
    choice = requested if requested is not None else (os.environ.get(ENV) or None)
    if choice is None:
        return "numba" if available() else "numpy"
    if choice not in _CHOICES:
        raise ValueError(f"kernels: {choice!r} is not one of {', '.join(_CHOICES)} (set by {ENV} or an argument)")
    if choice == "numba" and not available():
        raise ImportError(f"kernels: numba requested ({ENV}=numba or an argument) but not installed; "
                          "pip install 'soc_opt[fast]'")
    return choice


def describe() -> str:
    """The path as recorded with a run: ``"numba <version>"`` or ``"numpy"`` (plus why, when numba is installed)."""
    try:
        b = backend()
    except (ValueError, ImportError) as e:
        return f"error: {e}"
    if b == "numpy":
        return "numpy" + (f" ({ENV}=numpy)" if available() else "")
    from importlib import metadata

    try:
        return f"numba {metadata.version('numba')}"
    except metadata.PackageNotFoundError:  # pragma: no cover - found by find_spec, not by metadata
        return "numba"


def cache_dir() -> Path:
    """Where compiled kernels are cached (module docstring)."""
    own = os.environ.get("SOC_OPT_CACHE_DIR")
    if own:
        return Path(own)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "soc_opt" / "numba"


def jit(fn):
    """``numba.njit`` with the project's options: cached on disk under :func:`cache_dir` (unless the user
    set ``NUMBA_CACHE_DIR``), GIL released (the rollouts' threads), multiply-adds fused
    (``fastmath={"contract"}``: no reassociation, so a kernel's rounding is fixed by its code and the CPU),
    no bounds checks."""
    import numba
    from numba.core import config

    # numba fixes a function's cache location when the function is decorated, from config.CACHE_DIR
    # (NUMBA_CACHE_DIR): ours is set for the decoration only, so numba's own default stays for others
    own = not config.CACHE_DIR
    if own:
        config.CACHE_DIR = str(cache_dir())
    try:
        return numba.njit(cache=True, nogil=True, fastmath={"contract"}, boundscheck=False)(fn)
    finally:
        if own:
            config.CACHE_DIR = ""
