"""SAC and PPO at equal environment steps (``soc-opt bench --only peers.rl``).

Runs the plan ``algos x settings x tasks x rho2 x seeds`` at ``budget`` environment steps, one
JSON file per run in ``out`` (a run whose file exists is not run again, so an interrupted plan
resumes), ``workers`` processes at a time, and stops starting runs after ``time_box_s`` seconds
(runs not started are listed as such).  Returns one summary row per finished run.

The paper's budget is 14 iterations x 20 rollouts x T = 100 = 28,000 steps.
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

__all__ = ["run", "plan", "PAPER_BUDGET"]

PAPER_BUDGET = 14 * 20 * 100


def plan(algos=("sac", "ppo"), settings=("default", "tuned"), tasks=("peg", "door"), rho2s=(0.0, 0.1),
         seeds=(0, 1, 2), budget: int = PAPER_BUDGET) -> list[dict]:
    """The runs, cheapest first within each seed round (PPO before SAC)."""
    order = sorted(algos, key=lambda a: a != "ppo")
    extra = {"eval_at": [PAPER_BUDGET]} if budget > PAPER_BUDGET else {}
    return [{"algo": a, "setting": s, "task": t, "rho2": r, "seed": sd, "budget": budget, **extra}
            for sd in seeds for a in order for s in settings for t in tasks for r in rho2s]


def run_file(out: Path, spec: dict) -> Path:
    return out / f"{spec['algo']}-{spec['setting']}-{spec['task']}-rho2_{spec['rho2']:g}-seed{spec['seed']}-{spec['budget']}.json"


def _one(spec: dict, path: str) -> str:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from ...peers.rl import train

    res = train(**spec, partial=path + ".partial")
    Path(path).write_text(json.dumps(res))
    return path


def _summary(res: dict) -> dict:
    fin = res["final"]
    row = {k: res[k] for k in ("algo", "setting", "task", "rho2", "seed", "budget")}
    row.update(wall_s=round(res["wall_s"], 1), steps_per_s=round(res["steps_per_s"], 1),
               final_cost=fin["cost"])
    if "success_rate" in fin:
        row["final_success"] = fin["success_rate"]
    if "min_hinge" in fin:
        row["final_min_hinge"] = fin["min_hinge"]
    return row


def run(out: str | Path = "runs/peers-rl", specs: list[dict] | None = None, workers: int = 2,
        time_box_s: float = 3600.0) -> list[dict]:
    """Run (or resume) the plan; one summary row per finished run, then one per run not started."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    specs = plan() if specs is None else specs
    todo = [s for s in specs if not run_file(out, s).exists()]
    t0 = time.monotonic()
    skipped = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = []
        pending = list(todo)
        while pending or futures:
            while pending and len(futures) < workers:
                if time.monotonic() - t0 > time_box_s:
                    skipped += pending
                    pending = []
                    break
                s = pending.pop(0)
                futures.append(pool.submit(_one, s, str(run_file(out, s))))
            if not futures:
                break
            done = [f for f in futures if f.done()]
            for f in done:
                f.result()
                futures.remove(f)
            if not done:
                time.sleep(1.0)
    rows = [_summary(json.loads(run_file(out, s).read_text())) for s in specs if run_file(out, s).exists()]
    rows += [{**s, "note": f"not run: time box of {time_box_s:.0f} s reached"} for s in skipped]
    return rows


def main(argv=None) -> None:
    """``python -m soc_opt.bench.peers.rl [--budget N] [--algos ppo sac] ...``: run one plan."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m soc_opt.bench.peers.rl", description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--out", default="runs/peers-rl")
    ap.add_argument("--budget", type=int, default=PAPER_BUDGET,
                    help="environment steps per run; above the paper's budget the run is also scored there")
    ap.add_argument("--algos", nargs="+", default=["ppo", "sac"])
    ap.add_argument("--settings", nargs="+", default=["default", "tuned"])
    ap.add_argument("--tasks", nargs="+", default=["peg", "door"])
    ap.add_argument("--rho2", nargs="+", type=float, default=[0.0, 0.1])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--time-box", type=float, default=3600.0, help="seconds after which no run is started")
    a = ap.parse_args(argv)
    specs = plan(tuple(a.algos), tuple(a.settings), tuple(a.tasks), tuple(a.rho2), tuple(a.seeds), a.budget)
    for r in run(a.out, specs, a.workers, a.time_box):
        print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
