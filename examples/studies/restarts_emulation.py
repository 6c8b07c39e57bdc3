"""Two restarts within one sample budget, emulated from runs with half the samples (issue 47).

Reads a sweep of ``problems/sweeps/door_half_samples.toml``: each trial is one run with half the paper's
samples.  Seeds ``s`` and ``s + offset`` are taken as the two restarts of one run, which returns the restart
whose last sampled batch cost less (``final_vs_last_last_sampled_cost`` of ``result.json``: only the
training samples decide, so the budget is the paper's).  Prints, per method: one half-sample run alone (every
seed), the best of two so picked (sampled and mean action, seeds at the goal), and the best of two picked
by its evaluation (an oracle, which a run cannot know).

    python examples/studies/restarts_emulation.py runs/sweep-door_half_samples [--offset 20] [--goal -0.95]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def results(root: Path, method: str) -> dict[int, dict]:
    out = {}
    for f in root.glob(f"trials/*/*/{method}/seed_*/result.json"):
        out[int(f.parent.name.removeprefix("seed_"))] = json.loads(f.read_text())
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--offset", type=int, default=20)
    ap.add_argument("--goal", type=float, default=-0.95, help="min hinge at or below this meets the goal")
    args = ap.parse_args(argv)
    for method in ("lqr-flm", "dpsoc-em"):
        res = results(args.root, method)
        if not res:
            continue
        hinge = {s: r["metrics"]["min_hinge"] for s, r in res.items()}
        alone = np.array(list(hinge.values()))
        print(f"{method}: one half-sample run, {alone.size} seeds: mean {alone.mean():+.3f}, "
              f"{int((alone <= args.goal).sum())} / {alone.size} at the goal")
        firsts = sorted(s for s in res if s + args.offset in res)
        picked, mean_action, oracle = [], [], []
        for s in firsts:
            a, b = res[s], res[s + args.offset]
            r = a if a["final_vs_last_last_sampled_cost"] <= b["final_vs_last_last_sampled_cost"] else b
            picked.append(r["metrics"]["min_hinge"])
            mean_action.append(r["metrics_mean_action"]["min_hinge"])
            oracle.append(min(hinge[s], hinge[s + args.offset]))
        p, m, o = np.array(picked), np.array(mean_action), np.array(oracle)
        print(f"  best of two by the last batch's cost, {p.size} runs: sampled {p.mean():+.3f} "
              f"({int((p <= args.goal).sum())} / {p.size} at the goal), mean action {m.mean():+.3f} "
              f"({int((m <= args.goal).sum())} / {m.size}); picked by evaluation (oracle): "
              f"{int((o <= args.goal).sum())} / {o.size}")
        print("  per run (first seed " + str(firsts[0]) + "): " + " ".join(f"{x:+.2f}" for x in p))


if __name__ == "__main__":
    main()
