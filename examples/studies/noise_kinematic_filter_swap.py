"""Which part of a kinematic-estimator update breaks the closed loop: the gains or the filter (issue 19, fifth round).

For one batch ``i`` of a sweep trial (``samples/iter_NNN.npz``, drawn by ``policies/iter_NNN.npz``) and
the policy learned from it (``policies/iter_NNN+1.npz``):

* the four pairings of old/new gains with old/new filter, each scored on 20 rollouts of the task
  (evaluation seed ``10000 + seed``): which of the two changes the cost follows;
* the batch's two EM runs (from the sampler's map, ``warm``; from the batch's own map, ``data``),
  plus EM from the batch's own map with other settings (``--extra``, JSON of
  ``[baseline.noise.kinematic]`` keys): final ``log p(s | a)``, its likelihood of the previous
  batch (``heldout``, :func:`soc_opt.noise.kinematic.em.loglik`), mean acceleration noise
  ``sqrt(diag S)``, the filter built from each acting with the new gains (true cost, RMS action
  against the batch's), and each filter's RMS error of the joint angles and velocities on the batch
  itself, offline (same actions).

Diagnostics, not a method.  The estimator uses the robot's kinematics (not its masses, inertia or
damping).

Usage:
    python examples/studies/noise_kinematic_filter_swap.py "runs/sweep-noise_door10/trials/door/kinematic-r4,rho2=0.1" \\
        --task door --method lqr-flm --cases 3:1 8:2 --extra '{"prior_strength": 60}' '{"segments": 25}'
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from soc_opt.models import Rollouts
from soc_opt.noise.kinematic import em
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy, build_filter
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import load_task


def _score(task, policy, seed: int) -> dict:
    r = task.rollouts(policy, 20, np.random.default_rng(10000 + seed))
    m = task.metrics(r)
    key = "success_rate" if "success_rate" in m else "min_hinge"
    return {"cost": round(float(task.true_cost(r).sum(-1).mean()), 1), key: round(float(m[key]), 3),
            "action_rms": round(float(np.sqrt((r.a ** 2).mean())), 2)}


def swap(task, run_dir: Path, seed: int, i: int, cfg: KinematicConfig, extra=()) -> dict:
    """The pairings and the EM runs' filters of batch ``i`` (module docstring); ``extra``: dicts of
    :class:`KinematicConfig` overrides for more runs from the batch's own map."""
    z = np.load(run_dir / "samples" / f"iter_{i:03d}.npz")
    ro = Rollouts(**{k: z[k] for k in ("x", "s", "a", "cost", "y")})
    old = KinematicFilteredPolicy.from_dict(dict(np.load(run_dir / "policies" / f"iter_{i:03d}.npz")), task)
    new = KinematicFilteredPolicy.from_dict(dict(np.load(run_dir / "policies" / f"iter_{i + 1:03d}.npz")), task)
    out = {"seed": seed, "batch": i, "batch_action_rms": round(float(np.sqrt((ro.a ** 2).mean())), 2),
           "pairings": {f"gains {gi}, filter {fi}": _score(task, dataclasses.replace(g, filter=f.filter), seed)
                        for gi, g in ((i, old), (i + 1, new)) for fi, f in ((i, old), (i + 1, new))}}
    km = KinematicModel(task)
    rho2 = float(task.rho2)
    runs = {"warm": (cfg, em.fit(km, ro.s, ro.a, rho2, cfg, old.filter.accel())),
            "data": (cfg, em.fit(km, ro.s, ro.a, rho2, cfg))}
    for kw in extra:
        c = dataclasses.replace(cfg, **kw)
        runs[f"data {json.dumps(kw, sort_keys=True)}"] = (c, em.fit(km, ro.s, ro.a, rho2, c))
    prev = np.load(run_dir / "samples" / f"iter_{i - 1:03d}.npz") if i > 0 else None
    nq = km.nq
    for name, (c, res) in runs.items():
        f = build_filter(km, res.accel, em.z_model(km, res.accel, c), res.smoothed.mean.mean(axis=0), rho2,
                         online=c.gains == "online").attach(km)
        err = km.z_of(f.states(ro.s, ro.a)) - km.z_of(ro.x)
        out[name] = {"loglik": round(float(res.loglik[-1]), 1),
                     "heldout": None if prev is None else round(em.loglik(km, res.accel, prev["s"], prev["a"], rho2, c), 1),
                     "S_sd": round(float(np.sqrt(np.diagonal(res.accel.S, axis1=1, axis2=2)).mean()), 2),
                     "filter_rms_q": round(float(np.sqrt((err[..., :nq] ** 2).mean())), 3),
                     "filter_rms_qd": round(float(np.sqrt((err[..., nq:] ** 2).mean())), 3),
                     "new_gains": _score(task, dataclasses.replace(new, filter=f), seed)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting_dir", type=Path, help="a sweep setting's directory (holding METHOD/seed_N/)")
    ap.add_argument("--task", default="door")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--cases", nargs="+", default=["3:1"], help="SEED:BATCH pairs")
    ap.add_argument("--extra", nargs="*", default=[], help="JSON objects of [baseline.noise.kinematic] keys")
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    for case in a.cases:
        seed, i = map(int, case.split(":"))
        row = swap(task, a.setting_dir / a.method / f"seed_{seed}", seed, i, KinematicConfig(),
                   [json.loads(e) for e in a.extra])
        print(json.dumps({"task": a.task, "method": a.method, **row}), flush=True)


if __name__ == "__main__":
    main()
