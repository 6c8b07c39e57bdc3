"""Results over seeds on two BLAS kernels (issue 46): the same sweep run twice, ``OPENBLAS_CORETYPE`` changed.

    OPENBLAS_CORETYPE=SkylakeX soc-opt sweep problems/sweeps/noise_issue46.toml --workers 2 --out runs/n46-skx
    OPENBLAS_CORETYPE=Haswell  soc-opt sweep problems/sweeps/noise_issue46.toml --workers 2 --out runs/n46-hsw
    python examples/studies/noise_kernels_table.py runs/n46-skx runs/n46-hsw --labels SkylakeX Haswell

One row per (task, setting, method, kernel) over the finished seeds: the final policy's task metric sampled
and with its mean action (docs/math.md §12.3), each as the mean over seeds with its 95% interval (Student
t over the per-seed values), the seeds that reach the goal (peg: success >= 0.9; door: min hinge <= -0.8)
and, for the door, the seeds whose final policy engages the handle (min hinge below -0.1 rad).  Then per
(task, setting, method) whether the two kernels' sampled means lie within each other's intervals.
``--csv FILE`` also writes the per-seed values.  The kernel a trial ran on is read from its
``config.json`` (``environment``) and printed, so a mislabelled directory shows.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
from scipy import stats

METRIC = {"door": "min_hinge", "peg": "success_rate", "push": "min_distance"}
GOAL = {"door": lambda v: v <= -0.8, "peg": lambda v: v >= 0.9, "push": lambda v: v <= 0.05}


def interval(values: np.ndarray) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean and its 95% Student-t interval (``nan`` bounds below 2 values)."""
    v = np.asarray(values, dtype=float)
    m = float(v.mean())
    if v.size < 2:
        return m, float("nan"), float("nan")
    h = float(stats.t.ppf(0.975, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size))
    return m, m - h, m + h


def kernel_of(trial: Path) -> str:
    """The BLAS kernels recorded in the trial's ``config.json`` (``environment.blas``: ``"openblas VERSION KERNEL"``
    per loaded library), the distinct kernels joined by ``+``."""
    env = json.loads((trial / "config.json").read_text()).get("environment", {})
    blas = env.get("blas") or []
    blas = blas if isinstance(blas, list) else [blas]
    return "+".join(sorted({str(b).split()[-1] for b in blas})) or "?"


def collect(root: Path) -> dict:
    """``{(task, setting, method): [per-seed dict]}`` of the finished trials under ``root/trials``."""
    out: dict = {}
    for res in sorted(root.glob("trials/*/*/*/seed_*/result.json")):
        trial = res.parent
        task, setting, method = trial.parts[-4], trial.parts[-3], trial.parts[-2]
        r = json.loads(res.read_text())
        key = METRIC.get(task, next(iter(r["metrics"])))
        out.setdefault((task, setting, method), []).append({
            "seed": int(trial.name.split("_")[1]), "sampled": r["metrics"][key],
            "mean_action": r["metrics_mean_action"][key], "cost": r["final_cost"], "kernel": kernel_of(trial)})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+", type=Path)
    ap.add_argument("--labels", nargs="+", default=None)
    ap.add_argument("--csv", type=Path, default=None)
    a = ap.parse_args(argv)
    labels = a.labels or [r.name for r in a.roots]
    tables = [collect(r) for r in a.roots]
    print("| task | setting | method | kernel | seeds | sampled (95% CI) | mean action (95% CI) | at goal | engaged |")
    print("|---|---|---|---|---|---|---|---|---|")
    keys = sorted(set().union(*tables))
    rows = []
    for key in keys:
        task = key[0]
        for label, table in zip(labels, tables):
            per = sorted(table.get(key, []), key=lambda d: d["seed"])
            if not per:
                continue
            s = np.array([d["sampled"] for d in per])
            ma = np.array([d["mean_action"] for d in per])
            kernels = sorted({d["kernel"] for d in per})
            ms, lo, hi = interval(s)
            mm, lo2, hi2 = interval(ma)
            goal = GOAL.get(task, lambda v: False)
            engaged = f"{int(np.sum(s < -0.1))} / {int(np.sum(ma < -0.1))}" if task == "door" else ""
            print(f"| {task} | {key[1]} | {key[2]} | {label} ({'/'.join(kernels)}) | {len(per)} | {ms:.3f} [{lo:.3f}, {hi:.3f}] "
                  f"| {mm:.3f} [{lo2:.3f}, {hi2:.3f}] | {int(np.sum(goal(s)))} / {int(np.sum(goal(ma)))} | {engaged} |")
            rows += [{"task": task, "setting": key[1], "method": key[2], "kernel_label": label, **d} for d in per]
    if len(tables) == 2:
        print()
        print("| task | setting | method | sampled means within each other's 95% intervals |")
        print("|---|---|---|---|")
        for key in keys:
            vals = [np.array([d["sampled"] for d in t.get(key, [])]) for t in tables]
            if any(v.size < 2 for v in vals):
                continue
            (m0, l0, h0), (m1, l1, h1) = interval(vals[0]), interval(vals[1])
            ok = l1 <= m0 <= h1 and l0 <= m1 <= h0
            print(f"| {key[0]} | {key[1]} | {key[2]} | {'yes' if ok else 'no'} ({m0:.3f} vs {m1:.3f}) |")
    if a.csv:
        with a.csv.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
