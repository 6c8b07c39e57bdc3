"""The noise sweep's table against rho^2 with per-seed numbers and 95% intervals (issue 19).

Reads a sweep's ``trials.csv`` (``soc-opt sweep problems/sweeps/noise_peg.toml`` or
``noise_door.toml``) and prints one markdown row per (variant, rho^2, method): the task's metric
(peg: success rate; door: mean over rollouts of the minimum hinge angle), mean ± std over seeds
(``ddof = 1``), the 95% t-interval of the mean, the seeds and the per-seed values, and the final
cost.  The ``kinematic`` variant uses the robot's kinematics (not its masses, inertia or damping),
which the paper's learner does not assume.

With ``--claims VARIANT RHO2``: the paper's claims (docs/math.md §9.5) for DPSOC-EM against
LQR-FLM in that cell, per seed: final cost, state spread and action spread, mean ± std per method
and the seeds on which DPSOC-EM is lower.

Usage:
    python examples/studies/noise_sweep_table.py runs/sweep-noise_peg/trials.csv
    python examples/studies/noise_sweep_table.py runs/sweep-noise_peg/trials.csv --claims kinematic 0.1
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict

import numpy as np
from scipy import stats

METRIC = {"peg": "metric_success_rate", "door": "metric_min_hinge"}


def rows(path: str) -> list[dict]:
    with open(path, newline="") as f:
        return [r for r in csv.DictReader(f) if r["state"] == "done"]


def table(trials: list[dict]) -> str:
    groups: dict = defaultdict(list)
    for r in trials:
        variant, _, rho = r["setting"].partition(",rho2=")
        groups[(r["task"], variant, float(rho), r["method"])].append(r)
    out = ["| variant | rho^2 | method | metric | mean ± std | 95% t-interval | seeds | per seed | final cost |",
           "|---|---|---|---|---|---|---|---|---|"]
    order = {"paper": 0, "noise-aware": 1, "kinematic": 2}
    for key in sorted(groups, key=lambda k: (k[0], order.get(k[1], 9), k[2], k[3] != "lqr-flm")):
        task, variant, rho, method = key
        rs = sorted(groups[key], key=lambda r: int(r["seed"]))
        col = METRIC[task]
        v = np.array([float(r[col]) for r in rs])
        c = np.array([float(r["final_cost"]) for r in rs])
        n = v.size
        sd = v.std(ddof=1) if n > 1 else 0.0
        half = stats.t.ppf(0.975, n - 1) * sd / np.sqrt(n) if n > 1 else float("nan")
        seeds = [int(r["seed"]) for r in rs]
        span = f"{seeds[0]}–{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) else ",".join(map(str, seeds))
        out.append(f"| {variant} | {rho:g} | {method} | {col.removeprefix('metric_')} | {v.mean():.3f} ± {sd:.3f} | "
                   f"[{v.mean() - half:.3f}, {v.mean() + half:.3f}] | {n} ({span}) | "
                   f"{', '.join(f'{x:.2f}' for x in v)} | {c.mean():.1f} ± {c.std(ddof=1) if n > 1 else 0:.1f} |")
    return "\n".join(out) + "\n"


CLAIMS = (("final_cost", "DPSOC-EM lowers the final expected cost"),
          ("state_spread", "DPSOC-EM lowers the spread of the state (end-effector) trajectories"),
          ("action_spread", "DPSOC-EM lowers the spread of the actions"))


def claims(trials: list[dict], variant: str, rho2: float) -> str:
    """The claims table of ``variant`` at ``rho2``, one per task in ``trials`` (a ``### task`` heading
    before each when there are several: seeds are compared within a task)."""
    cell = [r for r in trials if r["setting"] == f"{variant},rho2={rho2:g}"]
    tasks = sorted({r["task"] for r in cell})
    out = []
    for task in tasks:
        rows_t = [r for r in cell if r["task"] == task]
        by = {m: {int(r["seed"]): r for r in rows_t if r["method"] == m} for m in ("lqr-flm", "dpsoc-em")}
        seeds = sorted(set(by["lqr-flm"]) & set(by["dpsoc-em"]))
        if len(tasks) > 1:
            out += [f"### {task}", ""]
        out += ["| claim | LQR-FLM | DPSOC-EM | seeds where DPSOC-EM lower | held (mean) |", "|---|---|---|---|---|"]
        for col, text in CLAIMS:
            a = np.array([float(by["lqr-flm"][s][col]) for s in seeds])
            b = np.array([float(by["dpsoc-em"][s][col]) for s in seeds])
            out.append(f"| {text} | {a.mean():.4g} ± {a.std(ddof=1):.3g} | {b.mean():.4g} ± {b.std(ddof=1):.3g} | "
                       f"{int((b < a).sum())}/{len(seeds)} | {'yes' if b.mean() < a.mean() else 'no'} |")
        if len(tasks) > 1:
            out.append("")
    return "\n".join(out).rstrip("\n") + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", help="a sweep's trials.csv")
    ap.add_argument("--claims", nargs=2, metavar=("VARIANT", "RHO2"), default=None)
    a = ap.parse_args(argv)
    if a.claims:
        print(claims(rows(a.trials), a.claims[0], float(a.claims[1])), end="")
    else:
        print(table(rows(a.trials)), end="")


if __name__ == "__main__":
    main()
