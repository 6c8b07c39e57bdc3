"""One row per RL run of a plan, finished or not (``python -m soc_opt.bench.peers.runs DIR``).

Reads the run files of :mod:`.rl` in ``DIR``: a finished run's ``<run>.json``; otherwise its last
checkpoint's log (``<run>.json.ckpt/latest.json``) or, failing that, its partial log
(``<run>.json.partial``).  Prints a Markdown table: the method, task, rho^2, seed, steps reached
of the budget, training wall time and steps/s, the sessions a resumed run started from, the last
20 training episodes (task metric and true-state cost), the final policy with its mean action and
sampled (20 fresh episodes each), and the steps to 90% peg success over 20 training episodes.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from ...peers.rl import steps_to
from .report import METRIC, rl_label

__all__ = ["rows", "markdown"]


def _load(path: Path) -> dict:
    """The run of ``path`` (``<run>-<budget>.json``) as far as it got; ``status`` says how far.  A
    checkpoint copied from a finished shorter run to extend it carries that run's budget: the budget
    is the file name's."""
    if path.exists():
        return {**json.loads(path.read_text()), "status": "finished"}
    tail = path.name[:-len(".json")].rsplit("-", 1)[-1]
    named = int(tail) if tail.isdigit() else None
    ckpt = path.with_name(path.name + ".ckpt") / "latest.json"
    if ckpt.exists():
        state = json.loads(ckpt.read_text())
        budget = int(state["budget"]) if named is None else named
        status = "stopped (checkpoint)" if int(state["budget"]) == budget else \
            f"extension of a {int(state['budget']):,}-step run, not started"
        return {**state, "budget": budget, "status": status}
    part = json.loads(path.with_name(path.name + ".partial").read_text())
    return {**part, "budget": int(part["budget"]) if named is None else named, "status": "partial log"}


def rows(root: str | Path) -> list[dict]:
    """One dict per run in ``root`` (finished, checkpointed or partial), sorted by method, task, rho^2, seed."""
    root = Path(root)
    names = {p.name for p in root.glob("*.json")}
    names |= {p.name[:-len(".ckpt")] for p in root.glob("*.json.ckpt")}
    names |= {p.name[:-len(".partial")] for p in root.glob("*.json.partial")}
    out = []
    for name in sorted(names):
        r = _load(root / name)
        m = METRIC[r["task"]]
        ep = r.get("episodes", [])
        steps = int(r.get("steps", ep[-1]["steps"] if ep else 0))
        row = {"method": rl_label(r), "task": r["task"], "rho2": r["rho2"], "seed": r["seed"], "budget": r["budget"],
               "steps": steps, "status": r["status"], "wall_s": r.get("wall_s"),
               "steps_per_s": steps / r["wall_s"] if r.get("wall_s") else None,
               "resumed_at": r.get("resumed_at", []),
               "metric_last20": float(np.mean([e[m] for e in ep[-20:]])) if ep else None,
               "cost_last20": float(np.mean([e["cost"] for e in ep[-20:]])) if ep else None}
        for tag, key in (("mean_action", "final"), ("sampled", "final_sampled")):
            row[f"metric_{tag}"] = r[key][m] if key in r else None
            row[f"cost_{tag}"] = r[key]["cost"] if key in r else None
        row["steps_to_90"] = steps_to([e["steps"] for e in ep], [e["success_rate"] for e in ep]) if m == "success_rate" else None
        out.append(row)
    return sorted(out, key=lambda x: (x["method"], x["task"], x["rho2"], x["seed"]))


def _f(v, fmt=".2f") -> str:
    if v is None:
        return "–"
    return f"{v:{fmt}}"


def markdown(rs: list[dict]) -> str:
    """The table of :func:`rows`."""
    head = ("| method | task | rho^2 | seed | steps reached / budget | status | train wall s | steps/s | resumed at | "
            "last 20 training: metric (cost) | final, mean action: metric (cost) | final, sampled: metric (cost) | "
            "steps to 90% |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rs:
        s90 = "" if r["task"] != "peg" else (f"{r['steps_to_90']:,}" if r["steps_to_90"] else "not reached")
        resumed = ", ".join(f"{s:,}" for s in r["resumed_at"]) or "–"
        lines.append(
            f"| {r['method']} | {r['task']} | {r['rho2']:g} | {r['seed']} | {r['steps']:,} / {r['budget']:,} | {r['status']} "
            f"| {_f(r['wall_s'], '.0f')} | {_f(r['steps_per_s'], '.1f')} | {resumed} "
            f"| {_f(r['metric_last20'])} ({_f(r['cost_last20'], '.1f')}) "
            f"| {_f(r['metric_mean_action'])} ({_f(r['cost_mean_action'], '.1f')}) "
            f"| {_f(r['metric_sampled'])} ({_f(r['cost_sampled'], '.1f')}) "
            f"| {s90} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown(rows(sys.argv[1])), end="")
