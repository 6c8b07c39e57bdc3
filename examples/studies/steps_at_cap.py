"""How often a KL step taken at the multiplier's cap makes the policy worse (issue 30, docs/math.md §12).

    python examples/studies/steps_at_cap.py RUN_ROOT [RUN_ROOT ...] [--cap MULT]

Reads every ``metrics.json`` under the roots (run, compare or sweep directories).  Step ``i`` is the KL
step taken in iteration ``i`` with multiplier ``mult_i``; it produced the policy sampled in iteration
``i + 1`` (baseline rows only); the cap is the run's ``step_size.mult_max`` (its ``config.json``).  The step
*degraded* the policy when that sample fails the acceptance
test of docs/math.md §12.1 against the batch of iteration ``i`` (``kappa = 2, eps = 0.02`` on the
recorded true-state costs; for runs with acceptance the recorded verdict is used instead).  Steps are
counted at the cap (``mult >= 0.999 cap``) and below it, per task and setting (the path components
between the root and the method directory).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def _costs(run: Path) -> dict[int, np.ndarray]:
    """Per baseline iteration, the true-state total costs of its batch (``costs.npz``)."""
    with np.load(run / "costs.npz") as f:
        it, phase = f["iteration"], f["phase"]
        return {int(i): f[f"cost_{j:03d}"] for j, (i, p) in enumerate(zip(it, phase)) if p == "baseline"}


def run_cap(run: Path, default: float | None) -> float:
    """The run's ``step_size.mult_max`` from its ``config.json`` (``default`` if given; a run recorded before
    ``[baseline.step_size]`` existed holds it in ``kl``)."""
    if default is not None:
        return default
    base = json.loads((run / "config.json").read_text())["config"]["baseline"]
    return float(base["step_size"]["mult_max"] if "step_size" in base else base["kl"]["mult_max"])


def degraded_steps(run: Path, cap: float, kappa: float = 2.0, eps: float = 0.02) -> list[tuple[bool, bool]]:
    """``(at_cap, degraded)`` for every step of one run whose successor was sampled."""
    rows = [r for r in json.loads((run / "metrics.json").read_text()) if r["phase"] == "baseline"]
    costs = _costs(run)
    out = []
    for a, b in zip(rows, rows[1:]):
        at_cap = a["mult"] >= 0.999 * cap
        if "accepted" in b:
            bad = b["accepted"] == 0.0
        else:
            ca, cb = costs[a["iteration"]], costs[b["iteration"]]
            se = np.hypot(ca.std(ddof=1) / np.sqrt(ca.size), cb.std(ddof=1) / np.sqrt(cb.size))
            bad = cb.mean() > ca.mean() + kappa * se + eps * abs(ca.mean())
        out.append((bool(at_cap), bool(bad)))
    return out


def table(roots: list[str], cap: float | None = None) -> list[dict]:
    count = defaultdict(lambda: np.zeros(4, int))  # cap steps, cap degraded, other steps, other degraded
    for root in map(Path, roots):
        for m in sorted(root.rglob("metrics.json")):
            run = m.parent
            key = "/".join(run.relative_to(root).parts[:-2]) or root.name
            for at_cap, bad in degraded_steps(run, run_cap(run, cap)):
                count[key] += [at_cap, at_cap and bad, not at_cap, (not at_cap) and bad]
    return [{"group": k, "steps at cap": int(c[0]), "degraded at cap": int(c[1]),
             "rate at cap": c[1] / max(c[0], 1), "steps below cap": int(c[2]), "degraded below cap": int(c[3]),
             "rate below cap": c[3] / max(c[2], 1)} for k, c in sorted(count.items())]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--cap", type=float, help="the multiplier's cap (default: each run's step_size.mult_max)")
    a = ap.parse_args(argv)
    rows = table(a.roots, a.cap)
    keys = list(rows[0]) if rows else []
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
