"""What a final kinematic-estimator policy loses to its exploration noise and to its estimate (issue 19).

Each final policy of a sweep's trials (``checkpoint.npz``) is scored on 20 rollouts (evaluation seed
``10000 + seed``, as the sweep scores it) four ways: acting on its filter's estimate or on the true
state (a ``rho^2 = 0`` twin of the task running the policy's gains), with its covariance (the
stochastic policy, what the success rate is measured on) or with its mean action only.  With
``--oracle-map`` a fifth way: acting on the estimate of a filter whose acceleration map is fitted on
the *true* states of the trial's last batch (the M-step on exact states, same segments and prior),
i.e. the filter this model class would give if learning the map were perfect; it tells the map's
learning apart from what the measurements and the model class allow.  Diagnostics, not methods.
The estimator uses the robot's kinematics (not its masses, inertia or damping).

Usage:
    python examples/studies/noise_kinematic_final_modes.py "runs/sweep-noise_peg10/trials/peg/kinematic,rho2=0.1" \\
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
from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import build_filter
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.noise.kinematic.smoother import smooth
from soc_opt.tasks import load_task


def oracle_map_policy(task, policy, trial_dir: Path, cfg: KinematicConfig = KinematicConfig()):
    """``policy`` acting on the filter of the acceleration map fitted on the true states ``x`` of the
    trial's last batch (``samples/iter_XXX.npz``), linearised along their mean (module docstring)."""
    km = KinematicModel(task)
    last = max(int(p.stem.split("_")[1]) for p in (trial_dir / "samples").glob("iter_*.npz"))
    with np.load(trial_dir / "samples" / f"iter_{last:03d}.npz") as d:
        x, a = d["x"], d["a"]
    exact = smooth(km, em.z_model(km, policy.filter.accel(), cfg), x, a, np.zeros((km.n, km.n)))
    accel = em.mstep(exact, a, km.dt, km.nq, cfg.segments, cfg.prior_strength, cfg.s_floor)
    filt = build_filter(km, accel, em.z_model(km, accel, cfg), exact.mean.mean(axis=0), float(task.rho2),
                        online=cfg.gains == "online").attach(km)
    return dataclasses.replace(policy, filter=filt)


def modes(task, twin, policy, seed: int, samples: int = 20, trial_dir: Path | None = None) -> dict:
    """``{mode: task.metrics}`` for the four ways of running ``policy`` (module docstring), five with
    ``trial_dir`` (the oracle map)."""
    pol = policy.for_task(task) if hasattr(policy, "for_task") else policy
    g = gains(pol)
    mean = LinearGaussianPolicy(g.K, g.k, np.zeros_like(g.cov), allow_singular=True)
    on_filter = dataclasses.replace(pol, policy=mean) if pol is not g else mean
    runs = {"estimate, stochastic": (task, pol), "estimate, mean action": (task, on_filter),
            "true state, stochastic": (twin, g), "true state, mean action": (twin, mean)}
    if trial_dir is not None:
        runs["oracle-map estimate, stochastic"] = (task, oracle_map_policy(task, pol, trial_dir))
    return {name: t.metrics(t.rollouts(p, samples, np.random.default_rng(10000 + seed))) for name, (t, p) in runs.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting_dir", type=Path, help="a sweep setting's directory (holding METHOD/seed_N/)")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--oracle-map", action="store_true", help="also the filter of the map fitted on the true states")
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    twin = load_task(a.task, overrides={"rho2": 0.0})
    for seed in a.seeds:
        trial = a.setting_dir / a.method / f"seed_{seed}"
        st = decode_checkpoint(trial / "checkpoint.npz")
        out = modes(task, twin, st.policy, seed, trial_dir=trial if a.oracle_map else None)
        print(json.dumps({"seed": seed, "method": a.method,
                          **{k: {m: round(v, 4) for m, v in met.items() if m in ("success_rate", "min_hinge", "cost")}
                             for k, met in out.items()}}), flush=True)


if __name__ == "__main__":
    main()
