"""Side by side with the peers users would pick instead (docs/results/peers/README.md).

``soc-opt bench --only peers`` runs every part; ``--only peers.smoothers``, ``peers.lqr`` or
``peers.rl`` one of them.  Each part's ``run()`` returns one row per measured case and needs the
optional extra ``pip install -e '.[peers]'`` (a part whose peer is missing gives one row saying
so instead of failing).  ``python -m soc_opt.bench.peers.report --out docs/results/peers`` writes
the report's JSON, tables and figures.
"""

from __future__ import annotations

__all__ = ["run", "PARTS"]

PARTS = ("smoothers", "lqr", "rl")


def run(parts=PARTS) -> list[dict]:
    """Every part's rows, each with its ``part`` name first."""
    import importlib

    rows = []
    for p in parts:
        mod = importlib.import_module(f"{__name__}.{p}")
        rows += [{"part": p, **r} for r in mod.run()]
    return rows
