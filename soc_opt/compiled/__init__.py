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

Compiled functions are cached on disk under the user's cache directory, ``$SOC_OPT_CACHE_DIR`` or
``$XDG_CACHE_HOME/soc_opt/numba`` (default ``~/.cache/soc_opt/numba``), never in the source tree, keyed by
the content of this package's source (:func:`source_hash`), not by where the checkout is: the first
process on a machine compiles a version of the kernels (tens of seconds), every later one, in any clone
of the same code, loads them (:func:`jit`).  Importing this module does not import numba; the kernel
modules do, on first use.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
from pathlib import Path

__all__ = ["ENV", "backend", "available", "describe", "cache_dir", "jit"]

#: The environment variable that selects the path: ``numpy`` or ``numba`` (unset: numba when installed).
ENV = "SOC_OPT_KERNELS"
_CHOICES = ("numpy", "numba")


@functools.lru_cache(maxsize=1)
def available() -> bool:
    """Whether numba can be imported (without importing it; looked up once per process)."""
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


@functools.lru_cache(maxsize=1)
def source_hash() -> str:
    """SHA-256 of the kernels' source (every module of this package, in name order): the key of their cache."""
    h = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def _cache_class():
    """numba's function cache with a locator of our own: one directory per version of the kernels' source
    under :func:`cache_dir`, found by the source's content (:func:`source_hash`), not by the path of the
    checkout, so that another clone of the same code loads what this one compiled, and a change to any
    module of this package (a kernel or a helper it calls) compiles anew."""
    from numba.core.caching import CompileResultCacheImpl, FunctionCache, UserProvidedCacheLocator

    class Locator(UserProvidedCacheLocator):  # every method of the locator protocol overridden
        def __init__(self, py_func, py_file):
            self._lineno = py_func.__code__.co_firstlineno
            self._path = str(cache_dir() / f"kernels-{source_hash()[:20]}")

        def get_cache_path(self):
            return self._path

        def get_source_stamp(self):
            return source_hash()

        def get_disambiguator(self):
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file):
            loc = cls(py_func, py_file)
            loc.ensure_cache_path()
            return loc

    class Impl(CompileResultCacheImpl):
        _locator_classes = [Locator]

    class Cache(FunctionCache):
        _impl_class = Impl

    return Cache


def jit(fn):
    """``numba.njit`` with the project's options: cached on disk under :func:`cache_dir` (module docstring),
    GIL released (the rollouts' threads), multiply-adds fused (``fastmath={"contract"}``: no reassociation,
    so a kernel's rounding is fixed by its code and the CPU), no bounds checks.  Where the cache directory
    cannot be written the kernels are compiled in each process (never cached in the source tree)."""
    import numba

    disp = numba.njit(nogil=True, fastmath={"contract"}, boundscheck=False)(fn)
    try:
        disp._cache = _cache_class()(disp.py_func)  # what numba's own cache=True does, with our locator
    except (OSError, RuntimeError, ImportError, AttributeError):
        pass
    return disp
