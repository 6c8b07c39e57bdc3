"""Where the kinematic smoother's states are biased, and by which EM start (issue 19, fourth round).

For each seed of a sweep setting, the samples of one iteration (``samples/iter_NNN.npz``) are smoothed
again, EM started two ways: from the batch's own initial map (``warm_start = false``, the default
since the fourth round) and from the acceleration map of the filter of the policy that drew them
(``policies/iter_NNN.npz``; ``warm_start = true``, the third round).  Per start: EM's final
``log p(s | a)`` (the linearisation held fixed: higher is the better fit of the same batch), the bias
and RMS error of the smoothed peg-bottom position over the last steps, and the batch's mean cost on
the smoothed states (what the learner sees) beside its cost on the true states.  Diagnostics, not a
method.  The estimator uses the robot's kinematics (not its masses, inertia or damping).

Usage:
    python examples/studies/noise_kinematic_bias.py "runs/sweep-noise_peg10/trials/peg/kinematic-warm,rho2=0.1" \\
        --method lqr-flm --iteration 13 --em-iters 2 10
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soc_opt.models import Rollouts
from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import load_task


def batch_bias(task, run_dir: Path, iteration: int, site: str, start: int, cfg: KinematicConfig) -> dict:
    """``{start: {loglik, bias_xyz, bias_norm, rms, smoothed_cost}}`` for the two EM starts on one batch,
    plus the batch's ``true_cost`` and the site's mean true height ``true_z`` over steps ``start..T``."""
    z = np.load(run_dir / "samples" / f"iter_{iteration:03d}.npz")
    ro = Rollouts(**{k: z[k] for k in ("x", "s", "a", "cost", "y")})
    sampler = KinematicFilteredPolicy.from_dict(dict(np.load(run_dir / "policies" / f"iter_{iteration:03d}.npz")))
    km = KinematicModel(task)
    idx = [task.state_labels.index(f"{site}.{c}") for c in "xyz"]
    out = {"true_cost": round(float(task.true_cost(ro).sum(-1).mean()), 2),
           "true_z": round(float(ro.x[:, start:, idx[2]].mean()), 3)}
    for name, init in (("cold", None), ("warm", sampler.filter.accel())):
        res = em.fit(km, ro.s, ro.a, float(task.rho2), cfg, init)
        xs = km.measure(res.smoothed.mean, False)
        err = xs[:, start:, idx] - ro.x[:, start:, idx]
        cost = np.asarray(task.cost(xs, ro.a)).sum(-1).mean()
        out[name] = {"loglik": round(float(res.loglik[-1]), 1),
                     "bias_xyz": np.round(err.mean(axis=(0, 1)), 4).tolist(),
                     "bias_norm": round(float(np.linalg.norm(err.mean(axis=(0, 1)))), 4),
                     "rms": round(float(np.sqrt((err ** 2).sum(-1).mean())), 4),
                     "smoothed_cost": round(float(cost), 2)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting_dir", type=Path, help="a sweep setting's directory (holding METHOD/seed_N/)")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--iteration", type=int, default=13)
    ap.add_argument("--em-iters", type=int, nargs="+", default=[2], help="EM iterations (default 2, the loop's)")
    ap.add_argument("--site", default="peg_bottom")
    ap.add_argument("--start", type=int, default=60, help="first step of the window (default 60 of 100)")
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    for seed in a.seeds:
        for iters in a.em_iters:
            row = batch_bias(task, a.setting_dir / a.method / f"seed_{seed}", a.iteration, a.site, a.start,
                             KinematicConfig(em_iters=iters))
            print(json.dumps({"seed": seed, "method": a.method, "iteration": a.iteration, "em_iters": iters, **row}),
                  flush=True)


if __name__ == "__main__":
    main()
