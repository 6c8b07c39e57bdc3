"""Rendering of the verification rows (docs/math.md §9): a plain-text table and a JSON-safe dict."""

from __future__ import annotations

import math
from dataclasses import asdict

import numpy as np

from .common import ClaimResult

__all__ = ["format_table", "to_json"]


def _fmt_margin(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    return f"{x:.3e}"


def format_table(results: list[ClaimResult]) -> str:
    """Plain-text table: one line per row, then the margin meanings and notes."""
    headers = ("claim", "held", "worst margin", "counterexample")
    rows = []
    for r in results:
        rows.append(
            (
                r.claim,
                f"{r.held}/{r.instances}",
                _fmt_margin(r.worst_margin),
                "yes" if r.counterexample is not None else "-",
            )
        )
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(headers)]
    def line(cells):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))
    out = [line(headers), "  ".join("-" * w for w in widths)]
    out += [line(row) for row in rows]
    out.append("")
    for r in results:
        out.append(f"[{r.claim}] {r.description}")
        out.append(f"    margin: {r.margin_meaning}")
        if r.notes:
            out.append(f"    notes: {r.notes}")
    return "\n".join(out)


def json_safe(x):
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def to_json(results: list[ClaimResult]) -> dict:
    """JSON-serialisable dict ``{"results": [row, ...]}`` (non-finite floats become ``null``)."""
    return {"results": [json_safe(asdict(r)) for r in results]}
