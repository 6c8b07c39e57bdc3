"""The step-acceptance results table of issue 30 (docs/results/acceptance.md) from sweep directories.

    python examples/studies/acceptance_table.py runs/sweep-acceptance_free runs/sweep-acceptance_noise

One row per (task, setting, method) over the finished seeds: the final policy's task metric sampled and
with its mean action (docs/math.md §12.3; mean ± std over seeds), its true-state cost, the rejected
steps, and two counts of final policies worse than what the run had seen: than its last sampled
iteration, and than its best sampled iteration (the acceptance test of docs/math.md §12.1 with
``kappa = 2, eps = 0.02`` on the final evaluation against that batch's true-state costs).  For the door
also the seeds whose final policy moved the hinge by more than 0.1 rad (engaged the handle).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

METRIC = {"door": "min_hinge", "peg": "success_rate"}


def _worse(c_final: np.ndarray, c_ref: np.ndarray, kappa: float = 2.0, eps: float = 0.02) -> bool:
    se = np.hypot(c_final.std(ddof=1) / np.sqrt(c_final.size), c_ref.std(ddof=1) / np.sqrt(c_ref.size))
    return bool(c_final.mean() > c_ref.mean() + kappa * se + eps * abs(c_ref.mean()))


def trial_row(d: Path, task) -> dict | None:
    """The numbers of one finished trial directory."""
    if not (d / "result.json").exists():
        return None
    res = json.loads((d / "result.json").read_text())
    with np.load(d / "costs.npz") as f:
        base = [f[f"cost_{j:03d}"] for j, p in enumerate(f["phase"]) if p == "baseline"]
    with np.load(d / "final_eval.npz") as f:
        ro = {k: f[k] for k in f.files}
    from soc_opt.models import Rollouts

    c_final = np.asarray(task.true_cost(Rollouts(**{k: ro[k] for k in ("x", "s", "a", "cost", "y")})).sum(-1))
    best = min(base, key=lambda c: c.mean())
    return {"metric": res["metrics"][METRIC[task.name]], "metric_mean": res["metrics_mean_action"][METRIC[task.name]],
            "cost": res["final_cost"], "cost_mean": res["final_cost_mean_action"],
            "rejected": res.get("rejected_steps", 0), "worse_last": _worse(c_final, base[-1]),
            "worse_best": _worse(c_final, best)}


def rows(roots: list[str]) -> list[dict]:
    from soc_opt.tasks import load_task

    out = []
    for root in map(Path, roots):
        for task_dir in sorted((root / "trials").glob("*")):
            task = load_task(task_dir.name)
            for setting in sorted(p.name for p in task_dir.iterdir()):
                for method in ("lqr-flm", "dpsoc-em"):
                    trials = [trial_row(d, task) for d in sorted((task_dir / setting / method).glob("seed_*"))]
                    trials = [t for t in trials if t is not None]
                    if not trials:
                        continue
                    col = {k: np.array([t[k] for t in trials], float) for k in trials[0]}
                    row = {"task": task.name, "setting": setting, "method": method, "seeds": len(trials),
                           "metric sampled": f"{col['metric'].mean():.3f} ± {col['metric'].std():.3f}",
                           "metric mean action": f"{col['metric_mean'].mean():.3f} ± {col['metric_mean'].std():.3f}",
                           "cost sampled": f"{col['cost'].mean():.3g}", "cost mean action": f"{col['cost_mean'].mean():.3g}",
                           "rejected steps": int(col["rejected"].sum()),
                           "final worse than last sampled": int(col["worse_last"].sum()),
                           "final worse than best sampled": int(col["worse_best"].sum())}
                    if task.name == "door":
                        row["seeds engaged (< -0.1 rad)"] = int((col["metric"] < -0.1).sum())
                        row["seeds <= -0.95 (sampled / mean action)"] = (f"{int((col['metric'] <= -0.95).sum())} / "
                                                                          f"{int((col['metric_mean'] <= -0.95).sum())}")
                    out.append(row)
    return out


def markdown(table: list[dict]) -> str:
    keys = list(dict.fromkeys(k for r in table for k in r))
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(str(r.get(k, "")) for k in keys) + " |" for r in table]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+", help="sweep output directories")
    a = ap.parse_args(argv)
    print(markdown(rows(a.roots)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
