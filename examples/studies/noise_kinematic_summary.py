"""Per-seed final-policy metrics of a `soc-opt compare` output directory, with mean, std and a
95% t-interval over seeds (issue 19: every noise result with per-seed numbers and a 95% interval).

Reads ``seed_*/<method>/final_eval.npz`` (the 20 evaluation rollouts of each final policy) and
scores them with the task's metric (peg: success rate; door: mean minimum hinge angle).

Usage:
    python examples/studies/noise_kinematic_summary.py runs/peg_kinematic --task peg --rho2 0.1
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
from scipy import stats

from soc_opt.models import Rollouts
from soc_opt.tasks import load_task


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    key = "success_rate" if a.task == "peg" else None
    lines = []
    for method in ("lqr-flm", "dpsoc-em"):
        files = sorted(a.root.glob(f"seed_*/{method}/final_eval.npz"), key=lambda p: int(re.findall(r"seed_(\d+)", str(p))[0]))
        if not files:
            continue
        vals, costs, seeds = [], [], []
        for f in files:
            with np.load(f, allow_pickle=False) as d:
                ro = Rollouts(**{k: d[k] for k in ("x", "s", "a", "cost", "y")})
            m = task.metrics(ro)
            k = key or next(k for k in m if k.startswith("min_") and not k.endswith("_best"))
            vals.append(m[k])
            costs.append(m["cost"])
            seeds.append(int(re.findall(r"seed_(\d+)", str(f))[0]))
        v = np.array(vals)
        n = len(v)
        half = stats.t.ppf(0.975, n - 1) * v.std(ddof=1) / np.sqrt(n) if n > 1 else float("nan")
        lines.append(f"| {method} | {k} | {v.mean():.3f} ± {v.std(ddof=1) if n > 1 else 0:.3f} | "
                     f"[{v.mean() - half:.3f}, {v.mean() + half:.3f}] | {n} | "
                     f"{', '.join(f'{x:.2f}' for x in v)} | {np.mean(costs):.2f} ± {np.std(costs):.2f} | "
                     f"{seeds[0]}–{seeds[-1]} |")
    print("| method | metric | mean ± std (seeds) | 95% t-interval | seeds | per seed | final cost | seed range |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
