"""Whether the final kinematic filter's noise level is what a peg policy loses (issue 19, fifth round).

Each final policy of a sweep setting (``checkpoint.npz``) is scored on 20 rollouts (evaluation seed
``10000 + seed``, as the sweep scores it) with its filter rebuilt around the acceleration noise ``S``
scaled by each factor given (``1``: the filter as learned).  A smaller ``S`` makes the filter trust
its model more, a larger one the measurements.  Diagnostics, not a method.  The estimator uses the
robot's kinematics (not its masses, inertia or damping).

Usage:
    python examples/studies/noise_kinematic_filter_noise.py "runs/sweep-noise_peg10/trials/peg/kinematic,rho2=0.1" \\
        --scales 1 0.5 0.25 2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from soc_opt.experiments.rundir import decode_checkpoint
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.model import KinematicModel, transition
from soc_opt.tasks import load_task


def scaled(policy, km: KinematicModel, factor: float, q_noise: float):
    """``policy`` with its filter's ``S`` times ``factor`` (transition noise and gains recomputed)."""
    f = policy.filter
    accel = dataclasses.replace(f.accel(), S=f.accel_S * factor)
    Q = transition(accel, km.dt, km.c2, q_noise ** 2)[3]
    return dataclasses.replace(policy, filter=dataclasses.replace(f, Q=Q, accel_S=accel.S).attach(km))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting_dir", type=Path, help="a sweep setting's directory (holding METHOD/seed_N/)")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.5, 0.25, 2.0])
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    km = KinematicModel(task)
    q_noise = KinematicConfig().q_noise
    for seed in a.seeds:
        pol = decode_checkpoint(a.setting_dir / a.method / f"seed_{seed}" / "checkpoint.npz").policy
        row = {}
        for s in a.scales:
            m = task.metrics(task.rollouts(scaled(pol, km, s, q_noise), 20, np.random.default_rng(10000 + seed)))
            row[str(s)] = round(float(m["success_rate"] if "success_rate" in m else m["min_hinge"]), 4)
        print(json.dumps({"seed": seed, "method": a.method, "metric_by_scale": row}), flush=True)


if __name__ == "__main__":
    main()
