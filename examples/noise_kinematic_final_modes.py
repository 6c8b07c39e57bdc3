"""What a final kinematic-estimator policy loses to its exploration noise and to its estimate (issue 19).

Each final policy of a sweep's trials (``checkpoint.npz``) is scored on 20 rollouts (evaluation seed
``10000 + seed``, as the sweep scores it) four ways: acting on its filter's estimate or on the true
state (a ``rho^2 = 0`` twin of the task running the policy's gains), with its covariance (the
stochastic policy, what the success rate is measured on) or with its mean action only.  Diagnostics,
not methods.  The estimator uses the robot's kinematics (not its masses, inertia or damping).

Usage:
    python examples/noise_kinematic_final_modes.py "runs/sweep-noise_peg10/trials/peg/kinematic,rho2=0.1" \\
        --method lqr-flm --seeds 0 3 6 8
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from soc_opt.experiments.rundir import decode_checkpoint
from soc_opt.models import LinearGaussianPolicy
from soc_opt.noise.aware import gains
from soc_opt.tasks import load_task


def modes(task, twin, policy, seed: int, samples: int = 20) -> dict:
    """``{mode: task.metrics}`` for the four ways of running ``policy`` (module docstring)."""
    pol = policy.for_task(task) if hasattr(policy, "for_task") else policy
    g = gains(pol)
    mean = LinearGaussianPolicy(g.K, g.k, np.zeros_like(g.cov), allow_singular=True)
    on_filter = dataclasses.replace(pol, policy=mean) if pol is not g else mean
    runs = {"estimate, stochastic": (task, pol), "estimate, mean action": (task, on_filter),
            "true state, stochastic": (twin, g), "true state, mean action": (twin, mean)}
    return {name: t.metrics(t.rollouts(p, samples, np.random.default_rng(10000 + seed))) for name, (t, p) in runs.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting_dir", type=Path, help="a sweep setting's directory (holding METHOD/seed_N/)")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    twin = load_task(a.task, overrides={"rho2": 0.0})
    for seed in a.seeds:
        st = decode_checkpoint(a.setting_dir / a.method / f"seed_{seed}" / "checkpoint.npz")
        out = modes(task, twin, st.policy, seed)
        print(json.dumps({"seed": seed, "method": a.method,
                          **{k: {m: round(v, 4) for m, v in met.items() if m in ("success_rate", "min_hinge", "cost")}
                             for k, met in out.items()}}), flush=True)


if __name__ == "__main__":
    main()
