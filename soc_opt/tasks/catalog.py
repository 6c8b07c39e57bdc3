"""Every task soc_opt ships (``soc-opt tasks``; docs/tasks.md): the built-in names and the task files under
``problems/``."""

from __future__ import annotations

import os
from pathlib import Path

from .loading import BUILTIN_TASKS, problems_dir

__all__ = ["shipped_tasks"]


def shipped_tasks() -> list[tuple[str, str]]:
    """``(name to pass as TASK, where it is)`` of every task soc_opt ships: the built-in names, then every task
    TOML under ``problems/`` (not the algorithm files of ``problems/experiments`` nor the sweep files)."""
    root = problems_dir()
    builtin = {(root / rel).resolve() for rel in BUILTIN_TASKS.values()}
    out = [(name, str(Path("problems") / rel)) for name, rel in BUILTIN_TASKS.items()]
    for path in sorted(root.glob("*/*.toml")):
        if path.parent.name in ("experiments", "sweeps") or path.resolve() in builtin:
            continue
        shown = os.path.relpath(path) if Path.cwd() in path.resolve().parents else str(path)
        out.append((shown, str(Path("problems") / path.relative_to(root))))
    return out
