"""A sweep file with ``--set KEY=VALUE`` overrides (docs/sweeps.md; :mod:`soc_opt.experiments.overrides`)."""

from __future__ import annotations

from pathlib import Path

from ..config import ConfigError, read_toml
from ..experiments.overrides import merge, nested, split_sets
from .spec import SweepError, SweepSpec, sweep_from_dict

__all__ = ["load_sweep_with_sets"]


def load_sweep_with_sets(path: str | Path, items: list[str], *, gym_modules: tuple[str, ...] = ()) -> SweepSpec:
    """The sweep file with ``--set`` items merged into its ``[common]`` table (after the file's own), then
    validated as :func:`soc_opt.sweeps.spec.load_sweep` validates a file (``gym_modules`` as there)."""
    task_sets, sets = split_sets(items)
    p = Path(path)
    try:
        data = read_toml(p)
    except ConfigError as e:
        raise SweepError(str(e)) from e
    extra = nested(sets)
    if task_sets:
        extra["task"] = task_sets
    common = merge(data.get("common", {}), extra)
    try:
        return sweep_from_dict({**data, "common": common}, base_dir=p.parent, source=str(p), default_name=p.stem,
                               gym_modules=gym_modules)
    except SweepError as e:
        e.add_note("with --set " + ", ".join(items))
        raise
