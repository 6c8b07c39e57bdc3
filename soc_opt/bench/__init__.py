"""Benchmarks and solver comparisons (``soc-opt solvers``, ``soc-opt bench``).

Each submodule exposes ``run(...) -> list[dict]`` (one row per measured case) and ``QUICK``, the
keyword arguments of ``run`` for tiny sizes (``soc-opt bench --quick``: every code path in seconds,
the numbers are not meaningful).  :data:`PARTS` lists the parts ``soc-opt bench --only`` accepts,
:data:`DEFAULT_PARTS` those ``soc-opt bench`` runs without ``--only``.  Nothing here imports the
command line.
"""

from __future__ import annotations

import importlib

from ..config import ConfigError

__all__ = ["PARTS", "DEFAULT_PARTS", "SUPPORT", "parse_parts", "run_part"]

#: Every benchmark part, in the order ``soc-opt bench`` runs them.
PARTS = ("rollouts", "fit", "estep", "mstep", "lqg", "iteration", "compiled", "noisefit", "gym_envs", "env_steps")
#: The parts of a plain ``soc-opt bench`` (``noisefit``: ~3 CPU minutes, ``gym_envs``: minutes per
#: environment; both only on request, as is ``env_steps``, the soc_opt Gymnasium environments' steps/s).
#: ``compiled``: the numba kernels against the numpy path, and their compile and cache-load times.
DEFAULT_PARTS = ("rollouts", "fit", "estep", "mstep", "lqg", "iteration", "compiled")
#: Modules of this package that are not ``bench`` parts: the solver benchmark of ``soc-opt solvers``
#: (``qp_bench``, its report and qpbenchmark export ``qp_bench_report``; the earlier ``solvers`` and
#: ``solvers_report``, ``--legacy``), the fatrop build-time study (``fatrop_scale``) and the guarded worker
#: that runs every solver call of ``soc-opt solvers`` with its limits (``guard``).
SUPPORT = ("qp_bench", "qp_bench_report", "solvers", "solvers_report", "fatrop_scale", "guard")


def parse_parts(only: str | None) -> tuple[str, ...]:
    """The parts named by ``--only`` (comma-separated; ``None``: :data:`DEFAULT_PARTS`).

    An unknown or empty name raises :class:`ConfigError` naming it and the valid parts.
    """
    if only is None:
        return DEFAULT_PARTS
    names = tuple(n.strip() for n in only.split(","))
    bad = [n for n in names if n not in PARTS]
    if bad:
        raise ConfigError(f"--only: unknown benchmark part {bad[0]!r}; valid parts: {', '.join(PARTS)}")
    return tuple(dict.fromkeys(names))


def run_part(name: str, *, quick: bool = False) -> list[dict]:
    """The rows of benchmark part ``name`` (:data:`PARTS`); ``quick``: its ``QUICK`` sizes."""
    if name not in PARTS:
        raise ConfigError(f"unknown benchmark part {name!r}; valid parts: {', '.join(PARTS)}")
    mod = importlib.import_module(f"{__name__}.{name}")
    return mod.run(**(mod.QUICK if quick else {}))
