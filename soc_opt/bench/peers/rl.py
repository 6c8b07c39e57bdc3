"""SAC, CrossQ and PPO at equal environment steps (``soc-opt bench --only peers.rl``).

Runs the plan ``algos x settings x tasks x rho2 x seeds`` at ``budget`` environment steps, one
JSON file per run in ``out`` (a run whose file exists is not run again, so an interrupted plan
resumes), ``workers`` processes at a time, and stops starting runs after ``time_box_s`` seconds
(runs not started are listed as such).  Off-policy runs (SAC, CrossQ) checkpoint model and replay
buffer every ``checkpoint_every`` episodes into ``<run file>.ckpt/`` and continue from there when
started again; ``stop_after_s``: a running off-policy run stops at its next checkpoint after that
many seconds (to be resumed by the next call).  Returns one summary row per finished run.

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
         seeds=(0, 1, 2), budget: int = PAPER_BUDGET, backend: str = "sb3") -> list[dict]:
    """The runs, cheapest first within each seed round (PPO before SAC); settings an algorithm does
    not have (CrossQ: defaults only) are left out; PPO runs on stable-baselines3, CrossQ on sbx-rl."""
    from ...peers.rl import SETTINGS

    order = sorted(algos, key=lambda a: a != "ppo")
    extra = {"eval_at": [PAPER_BUDGET]} if budget > PAPER_BUDGET else {}
    return [{"algo": a, "backend": {"ppo": "sb3", "crossq": "sbx"}.get(a, backend), "setting": s, "task": t, "rho2": r,
             "seed": sd, "budget": budget, **extra}
            for sd in seeds for a in order for s in settings if (a, s) in SETTINGS for t in tasks for r in rho2s]


def run_file(out: Path, spec: dict) -> Path:
    """``<algo>[-<backend>]-<setting>-<task>-rho2_<rho2>-seed<seed>-<budget>.json`` (backend named
    unless stable-baselines3, the earlier runs' names)."""
    backend = spec.get("backend", "sb3")
    algo = spec["algo"] if backend == "sb3" else f"{spec['algo']}-{backend}"
    return out / f"{algo}-{spec['setting']}-{spec['task']}-rho2_{spec['rho2']:g}-seed{spec['seed']}-{spec['budget']}.json"


def _one(spec: dict, path: str, checkpoint_every: int = 10, deadline: float | None = None) -> str | None:
    """One run into ``path``; None when it stopped at its deadline (resumable, nothing written but its
    checkpoint and partial log)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    from ...peers.rl import OFF_POLICY, train

    ckpt = {"checkpoint": path + ".ckpt", "checkpoint_every": checkpoint_every, "deadline": deadline} \
        if spec["algo"] in OFF_POLICY else {}
    res = train(**spec, partial=path + ".partial", **ckpt)
    if res.get("partial"):
        return None
    Path(path).write_text(json.dumps(res))
    return path


def _summary(res: dict) -> dict:
    row = {k: res.get(k, "sb3") for k in ("algo", "backend", "setting", "task", "rho2", "seed", "budget")}
    row.update(wall_s=round(res["wall_s"], 1), steps_per_s=round(res["steps_per_s"], 1))
    for tag, key in (("", "final"), ("_sampled", "final_sampled")):
        fin = res.get(key, {})
        for m in ("cost", "success_rate", "min_hinge"):
            if m in fin:
                row[f"final{tag}_{m}"] = fin[m]
    return row


def run(out: str | Path = "runs/peers-rl", specs: list[dict] | None = None, workers: int = 2,
        time_box_s: float = 3600.0, checkpoint_every: int = 10, stop_after_s: float | None = None) -> list[dict]:
    """Run (or resume) the plan; one summary row per finished run, then one per run not finished."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    specs = plan() if specs is None else specs
    todo = [s for s in specs if not run_file(out, s).exists()]
    t0 = time.monotonic()
    deadline = None if stop_after_s is None else time.time() + stop_after_s
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
                futures.append(pool.submit(_one, s, str(run_file(out, s)), checkpoint_every, deadline))
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
    rows += [{**s, "note": "stopped at a checkpoint (resumable)"} for s in todo
             if s not in skipped and not run_file(out, s).exists()]
    return rows


def main(argv=None) -> None:
    """``python -m soc_opt.bench.peers.rl [--budget N] [--algos ppo sac] ...``: run one plan."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m soc_opt.bench.peers.rl", description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--out", default="runs/peers-rl")
    ap.add_argument("--budget", type=int, default=PAPER_BUDGET,
                    help="environment steps per run; above the paper's budget the run is also scored there")
    ap.add_argument("--algos", nargs="+", default=["ppo", "sac"], help="ppo, sac, crossq")
    ap.add_argument("--backend", default="sb3", help="SAC / CrossQ implementation: sb3 or sbx (CrossQ: sbx only)")
    ap.add_argument("--checkpoint-every", type=int, default=10, help="episodes between checkpoints (SAC, CrossQ)")
    ap.add_argument("--stop-after", type=float, default=None,
                    help="seconds after which running SAC / CrossQ runs stop at their next checkpoint")
    ap.add_argument("--settings", nargs="+", default=["default", "tuned"])
    ap.add_argument("--tasks", nargs="+", default=["peg", "door"])
    ap.add_argument("--rho2", nargs="+", type=float, default=[0.0, 0.1])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--time-box", type=float, default=3600.0, help="seconds after which no run is started")
    a = ap.parse_args(argv)
    specs = plan(tuple(a.algos), tuple(a.settings), tuple(a.tasks), tuple(a.rho2), tuple(a.seeds), a.budget, a.backend)
    for r in run(a.out, specs, a.workers, a.time_box, a.checkpoint_every, a.stop_after):
        print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
