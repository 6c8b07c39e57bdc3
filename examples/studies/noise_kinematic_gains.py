"""Nominal against online gains of the kinematic filter, on the batches of a run (issue 19).

For each saved batch ``samples/iter_K.npz`` of a run directory (a peg or door run at ``rho^2 > 0``),
the kinematic estimator is learned on the batch (no warm start) and the batch is filtered with
both updates of docs/math.md §11.3: gains fixed along the mean smoothed trajectory
(``gains = "nominal"``) and the update relinearised at each rollout's prediction
(``gains = "online"``).  Prints the RMS error against the true states (joint angles in rad, point
positions in m) beside the smoother's, and the spread of the batch's joint angles (the filters
differ where the rollouts spread far from the nominal).  In sample: filter and smoother are fitted
on the batch they are scored on.  The estimator uses the robot's kinematics (not its masses,
inertia or damping), which the paper's learner does not assume.

Usage (the weak seed of docs/results/noise/kinematic.md (b)):
    soc-opt run peg --paper --seed 3 --method lqr-flm \\
        --config docs/results/noise/peg_kinematic_nominal.toml --out runs/peg_kin_s3
    python examples/studies/noise_kinematic_gains.py runs/peg_kin_s3 --iterations 6 9 12
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soc_opt.models import Rollouts
from soc_opt.noise.kinematic import loop
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import load_task


def _rms(est, x, idx) -> float:
    return float(np.sqrt(np.mean((est[..., idx] - x[..., idx]) ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a run directory (with samples/ and task.json)")
    ap.add_argument("--iterations", type=int, nargs="+", default=[6, 9, 12])
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    rec = json.loads((a.run / "task.json").read_text())
    task = load_task(rec.get("task_argument", rec["name"]), overrides={"rho2": rec["config"]["rho2"]})
    km = KinematicModel(task)
    q = km.zidx[: km.nq]
    p = np.arange(task.n)[task.layout["site_pos"]]
    print("| iteration | joint spread (rad) | smoother | nominal gains | online gains |")
    print("|---|---|---|---|---|")
    for k in a.iterations:
        with np.load(a.run / "samples" / f"iter_{k:03d}.npz", allow_pickle=False) as d:
            ro = Rollouts(d["x"], d["s"], d["a"], d["cost"], d["y"])
        cells = []
        for gains in ("nominal", "online"):
            smoothed, filt, _ = loop.learn(task, ro, None, KinematicConfig(gains=gains))
            xf = filt.states(ro.s, ro.a)
            cells.append(f"{_rms(xf, ro.x, q):.4f} / {_rms(xf, ro.x, p):.4f}")
        sm = f"{_rms(smoothed.s, ro.x, q):.4f} / {_rms(smoothed.s, ro.x, p):.4f}"
        print(f"| {k} | {ro.x[..., q].std(axis=0).mean():.3f} | {sm} | {cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
