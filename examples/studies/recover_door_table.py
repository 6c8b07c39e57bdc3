"""Step sizes that recover (issue 47 item 2, docs/math.md §12.2): the noise-free door with step acceptance
as it is beside the same with ``[baseline.acceptance] recover = true``.

    soc-opt sweep problems/sweeps/recover_door.toml --workers 2 --out runs/recover_door
    python examples/studies/recover_door_table.py runs/recover_door --trace 608

Per (setting, method): the final policies' min hinge over the seeds, sampled and with the mean action (mean
and 95% Student-t interval), the seeds at min hinge <= -0.95 (the issue's goal) and the final policies flagged
worse than their last batch (docs/math.md §12.3), then the seeds that miss the goal.  With two settings: the
paired difference over seeds and the seeds where the two differ by more than 0.05 rad.  Any door sweep's
folder will do (door_search.toml and the tuning sweeps beside it, docs/results/door_search.md).  And, for
each ``--trace`` seed, every iteration's multiplier, predicted and actual improvement and verdict in both
settings (read from the trials' ``metrics.csv``).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
from noise_kernels_table import interval  # the same 95% Student-t interval (a study beside this one)

GOAL = -0.95


def trials(root: Path) -> dict[tuple[str, str, int], Path]:
    """``{(setting, method, seed): trial folder}`` of the finished door trials under ``root``."""
    out = {}
    for res in sorted((root / "trials" / "door").glob("*/*/seed_*/result.json")):
        r = json.loads(res.read_text())
        if r.get("status") != "done":
            continue
        folder = res.parent
        setting = folder.parent.parent.name.split(",")[0]
        out[(setting, folder.parent.name, int(folder.name.split("_")[1]))] = folder
    return out


def final(folder: Path) -> tuple[float, float, bool]:
    """Sampled and mean-action min hinge of the final policy, and its worse-than-last-batch flag."""
    r = json.loads((folder / "result.json").read_text())
    return (float(r["metrics"]["min_hinge"]), float(r["metrics_mean_action"]["min_hinge"]),
            bool(r.get("final_vs_last_worse", False)))


def trace(folder: Path) -> list[dict]:
    """The rows of ``metrics.csv`` (one per iteration)."""
    with open(folder / "metrics.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _num(row: dict, key: str) -> str:
    v = row.get(key, "")
    try:
        return f"{float(v):.3g}"
    except ValueError:
        return v or "-"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path, help="the sweep's output folder")
    ap.add_argument("--trace", type=int, nargs="*", default=[], help="seeds whose iterations to print")
    args = ap.parse_args(argv)
    found = trials(args.sweep)
    if not found:
        raise SystemExit(f"{args.sweep}: no finished door trials")
    settings = sorted({k[0] for k in found})
    methods = sorted({k[1] for k in found})
    print("| setting | method | seeds | sampled (95% CI) | mean action (95% CI) | <= -0.95 sampled | worse finals |")
    print("|---|---|---|---|---|---|---|")
    for s in settings:
        for m in methods:
            seeds = sorted(k[2] for k in found if k[:2] == (s, m))
            vals = np.array([final(found[(s, m, x)]) for x in seeds], dtype=float)
            if not len(vals):
                continue
            a, b = interval(vals[:, 0]), interval(vals[:, 1])
            print(f"| {s} | {m} | {len(seeds)} | {a[0]:.3f} [{a[1]:.3f}, {a[2]:.3f}] | {b[0]:.3f} [{b[1]:.3f}, {b[2]:.3f}] "
                  f"| {int((vals[:, 0] <= GOAL).sum())} / {len(seeds)} | {int(vals[:, 2].sum())} |")
    print("\nseeds above -0.95 sampled (sampled / mean action):")
    for s in settings:
        for m in methods:
            miss = [(x, *final(found[(s, m, x)])[:2]) for x in sorted(k[2] for k in found if k[:2] == (s, m))]
            miss = [f"{x} ({a:.3f} / {b:.3f})" for x, a, b in miss if a > GOAL]
            print(f"  {s}, {m}: {', '.join(miss) or 'none'}")
    if len(settings) == 2:
        s0, s1 = settings
        print(f"\npaired over seeds, {s1} minus {s0} (min hinge, mean and 95% Student-t interval):")
        for m in methods:
            both = sorted(x for x in {k[2] for k in found} if (s0, m, x) in found and (s1, m, x) in found)
            for i, kind in ((0, "sampled"), (1, "mean action")):
                d = interval(np.array([final(found[(s1, m, x)])[i] - final(found[(s0, m, x)])[i] for x in both]))
                print(f"  {m}, {kind}: {d[0]:+.3f} [{d[1]:+.3f}, {d[2]:+.3f}] over {len(both)} seeds")
        print(f"\nseeds where {s1} and {s0} differ by more than 0.05 rad (sampled):")
        for m in methods:
            for x in sorted({k[2] for k in found}):
                if (s0, m, x) in found and (s1, m, x) in found:
                    v0, v1 = final(found[(s0, m, x)])[0], final(found[(s1, m, x)])[0]
                    if abs(v1 - v0) > 0.05:
                        print(f"  {m} seed {x}: {s0} {v0:.3f} -> {s1} {v1:.3f}")
    for x in args.trace:
        for m in methods:
            for s in settings:
                if (s, m, x) not in found:
                    continue
                print(f"\n{m} seed {x}, {s}: iteration, multiplier, predicted / actual improvement, accepted")
                for row in trace(found[(s, m, x)]):
                    print(f"  {row['iteration']:>2} {row['phase']:<8} mult {_num(row, 'mult'):>8}  "
                          f"predicted {_num(row, 'predicted_improvement'):>9}  actual {_num(row, 'actual_improvement'):>9}  "
                          f"accepted {row.get('accepted', '-') or '-'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
