"""Why does DPSOC-EM help?  Ablations on top of a finished `soc-opt compare` directory.

For each seed, start from the baseline's state at the EM switch (``seed_S/fork_state.pkl``)
and run the rest of the schedule with one change, then evaluate the final policy exactly as
`soc-opt compare` does (same evaluation seed):

- ``em-sigma-kept``: DPSOC-EM with the covariance floor at the current covariance
  (``cov_floor_scale = 1``), so the EM step changes only the gains and offsets ``[K k]``;
- ``halve-sigma``: no EM at all; the policy's covariance is halved at the switch (what the
  default covariance floor does to ``Sigma``), then LQR-FLM continues.

Usage: .venv/bin/python examples/studies/ablation_em.py runs/paper-peg peg --seeds 0 1 2
Writes ``ablation.json`` and ``ablation.md`` into the compare directory.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
from pathlib import Path

import numpy as np

from soc_opt.experiments.compare import evaluate_policy, spreads
from soc_opt.methods import registry
from soc_opt.methods.config import DPSOCConfig
from soc_opt.tasks import load_task


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("compare_dir")
    ap.add_argument("task")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    out = Path(args.compare_dir)
    summary = json.loads((out / "summary.json").read_text())
    cfg = DPSOCConfig.from_dict(summary["config"])
    task = load_task(args.task)
    idx = {s: i for i, s in enumerate(summary["seeds"])}
    samples = cfg.evaluation.samples or cfg.baseline.samples

    def evaluate(policy, seed):
        return evaluate_policy(task, policy, samples, seed, workers=1, evaluation=cfg.evaluation)

    rows = {"lqr-flm": [], "dpsoc-em": [], "em-sigma-kept": [], "halve-sigma": []}
    for seed in args.seeds:
        for meth in ("lqr-flm", "dpsoc-em"):
            rows[meth].append({k: summary["per_seed"][meth][k][idx[seed]] for k in ("cost", "state_spread", "action_spread")})
        fork = pickle.loads((out / f"seed_{seed}" / "fork_state.pkl").read_bytes())
        kept = cfg.replace(em=cfg.em.replace(cov_floor_scale=1.0))
        st = registry.run(task, "dpsoc-em", kept, seed=seed, state=fork)
        rows["em-sigma-kept"].append(spreads(task, evaluate(st.policy, seed)))
        halved = dataclasses.replace(fork, policy=fork.policy.with_cov(0.5 * np.asarray(fork.policy.cov)))
        st = registry.run(task, "lqr-flm", cfg, seed=seed, state=halved)
        rows["halve-sigma"].append(spreads(task, evaluate(st.policy, seed)))
        print(f"seed {seed}: " + ", ".join(f"{m} cost {rows[m][-1]['cost']:.4g}" for m in rows), flush=True)
    (out / "ablation.json").write_text(json.dumps({"seeds": args.seeds, "rows": rows}, indent=1))
    lines = [f"# Ablation of the EM step on {args.task} (seeds {args.seeds})", "",
             "| variant | final cost | state spread | action spread |", "|---|---|---|---|"]
    for m, r in rows.items():
        cells = [f"{np.mean([x[k] for x in r]):.4g} ± {np.std([x[k] for x in r]):.3g}"
                 for k in ("cost", "state_spread", "action_spread")]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    (out / "ablation.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
