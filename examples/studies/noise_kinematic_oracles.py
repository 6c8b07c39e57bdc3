"""Offline estimator table on a saved peg (or door) policy at rho^2 = 0.1 (issue 19, acceptance (a)).

Runs ``--rollouts`` rollouts of a saved kinematic policy (``iter_XXX.npz`` of a run with
``[baseline.noise] estimator = "kinematic"``; its filter is re-attached to the task's MuJoCo model),
then estimates the true joint angles and point positions of those rollouts with

* ``raw``: the measurement ``s = x + eps`` itself;
* ``§10 filter``: the Kalman filter of the noise-aware fit of these rollouts (mixture prior, SSM-EM,
  ``time_window = 5``: ``docs/results/noise/peg_noise_aware.toml``);
* ``kinematic smoother`` / ``kinematic filter``: the structured model of ``docs/math.md §11``
  (EM from ``B = D = c = 0``, then the smoother's ``h(E[z | s, a])`` and the online filter of the
  fitted map), which uses the robot's kinematics (not masses, inertia or damping);
* ``true-state fit's filter`` (oracle): the Kalman filter of the paper's fit on the *true* states.

Every estimator is fitted on the same rollouts it is scored on.  RMS errors against the true state.

Usage:
    python examples/studies/noise_kinematic_oracles.py runs/peg_kinematic/seed_0/lqr-flm/policies/iter_014.npz \
        --out docs/results/noise/peg_kinematic_offline.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from soc_opt.learning import fit
from soc_opt.noise import aware as noise_aware
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.estimator import filter_states
from soc_opt.noise.kinematic import loop
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import load_task

SECTION10 = NoiseConfig(estimator="kalman", fit_correction="ssm_em", time_window=5)


def _rms(est, x, idx):
    return float(np.sqrt(np.mean((est[..., idx] - x[..., idx]) ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("policy", type=Path)
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--rollouts", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    task = load_task(a.task, overrides={"rho2": a.rho2})
    with np.load(a.policy, allow_pickle=False) as d:
        pol = KinematicFilteredPolicy.from_dict(d, task)
    rng = np.random.default_rng(a.seed)
    ro = task.rollouts(pol, a.rollouts, rng)
    km = KinematicModel(task)
    q = km.zidx[: km.nq]
    p = np.arange(task.n)[task.layout["site_pos"]]
    fcfg = fit.FitConfig()
    nm = noise_aware.noise_model(task)
    est, times = {"raw": ro.s}, {}

    t0 = time.perf_counter()
    prior = fit.update_prior(None, ro, fcfg, np.random.default_rng(1))
    dyn = noise_aware.fit_local(ro, fcfg, prior, SECTION10, nm, pol.policy)
    est["§10 filter"] = filter_states(noise_aware.loop_filter(dyn, nm, SECTION10), ro.s, ro.a)
    times["§10 filter"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    smoothed, kf, diag = loop.learn(task, ro, pol.policy, KinematicConfig())
    est["kinematic smoother"] = smoothed.s
    times["kinematic smoother"] = time.perf_counter() - t0
    est["kinematic filter"] = kf.states(ro.s, ro.a)
    nominal = loop.learn(task, ro, pol.policy, KinematicConfig(gains="nominal"))[1]
    est["kinematic filter, nominal gains (first round)"] = nominal.states(ro.s, ro.a)
    est["kinematic filter (saved, of the policy)"] = pol.filter.states(ro.s, ro.a)

    xro = dataclasses.replace(ro, s=ro.x)
    xprior = fit.update_prior(None, xro, fcfg, np.random.default_rng(1))
    xdyn = fit.fit_dynamics(xro, fcfg, xprior)
    est["true-state fit's filter (oracle)"] = filter_states(noise_aware.loop_filter(xdyn, nm, SECTION10), ro.s, ro.a)

    rows = [{"estimator": k, "joint_rms_rad": _rms(v, ro.x, q), "point_rms_m": _rms(v, ro.x, p),
             "fit_time_s": times.get(k)} for k, v in est.items()]
    lines = [f"# {a.task}, rho^2 = {a.rho2}: estimation error on {a.rollouts} rollouts of `{a.policy}` "
             f"(seed {a.seed})", "",
             "| estimator | joint angles RMS (rad) | point positions RMS (m) |", "|---|---|---|"]
    lines += [f"| {r['estimator']} | {r['joint_rms_rad']:.4f} | {r['point_rms_m']:.4f} |" for r in rows]
    lines += ["", "The kinematic estimator uses the robot's kinematics (not its masses, inertia or damping), "
              "which the paper's learner does not assume."]
    report = "\n".join(lines) + "\n"
    print(report)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(report)
        a.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
