"""Where the kinematic estimator loses in closed loop (issue 19): its fit or its filter?

Runs of LQR-FLM with ``[baseline.noise] estimator = "kinematic"`` at the paper's scale (the task's
experiment configuration with ``--paper``), each final policy scored on 20 fresh rollouts
(evaluation seed ``10000 + seed``):

* ``kinematic``: as configured (learn from the structured smoother's states, act on its filter);
* ``oracle fit``: the learner's rollouts carry the *true* states (prior, fit, cost expansion on
  ``x``), the policy still acts on the kinematic filter (fitted on the noisy measurements);
  it isolates the filter in the loop;
* ``oracle state``: the policy acts on the *true* state (rollouts of a ``rho^2 = 0`` twin with the
  policy's gains only), the learner still sees ``x + eps`` through the kinematic smoother;
  it isolates the fit.

Both oracles are diagnostics, not methods.  The estimator uses the robot's kinematics (not its
masses, inertia or damping), which the paper's learner does not assume.

Usage:
    python examples/studies/noise_kinematic_oracles_loop.py --task door --seeds 0 1 --out runs/door_kin_oracles.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.methods.registry import get_method
from soc_opt.noise.aware import NoiseConfig, gains
from soc_opt.noise.kinematic import loop
from soc_opt.tasks import load_task

_learn = loop.learn


def _true_state_learn(task, rollouts, sampler, cfg, previous=None):
    smoothed, filt, diag = _learn(task, rollouts, sampler, cfg, previous)
    cost = np.asarray(task.cost(rollouts.x, rollouts.a))
    return dataclasses.replace(rollouts, s=rollouts.x, cost=cost, y=np.exp(-task.y_scale * cost)), filt, diag


class _TrueStateActor:
    """The task, except that rollouts run the policy's gains on the true state of a noise-free twin
    and then add the measurement noise for the learner."""

    def __init__(self, task, twin):
        self.wrapped, self.twin = task, twin

    def __getattr__(self, name):
        return getattr(self.wrapped, name)

    def rollouts(self, policy, M, rng, noise=True, workers=1, x0=None):
        ro = self.twin.rollouts(gains(policy), M, rng, noise, workers, x0)
        s = ro.x + np.sqrt(self.wrapped.rho2) * rng.standard_normal(ro.x.shape)
        cost = np.asarray(self.wrapped.cost(s, ro.a))
        return dataclasses.replace(ro, s=s, cost=cost, y=np.exp(-self.wrapped.y_scale * cost))


def run_one(task_name: str, variant: str, seed: int, rho2: float) -> dict:
    task = load_task(task_name, overrides={"rho2": rho2})
    cfg = load_run_config(task_name, paper=True, method="lqr-flm")
    cfg = cfg.replace(baseline=cfg.baseline.replace(noise=NoiseConfig(estimator="kinematic")))
    learner, eval_task = task, task
    loop.learn = _true_state_learn if variant == "oracle fit" else _learn
    if variant == "oracle state":
        twin = load_task(task_name, overrides={"rho2": 0.0})
        learner = _TrueStateActor(task, twin)
    t0 = time.perf_counter()
    try:
        st = run_experiment(learner, "lqr-flm", cfg, seed, None)
    finally:
        loop.learn = _learn
    final = get_method("lqr-flm").final_policy(cfg, st)  # the returned policy (docs/math.md §12.3)
    pol = gains(final) if variant == "oracle state" else final
    ro = (twin if variant == "oracle state" else eval_task).rollouts(pol, 20, np.random.default_rng(10000 + seed))
    return {"task": task_name, "variant": variant, "seed": seed, **task.metrics(ro), "wall_time": time.perf_counter() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="door")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--variants", nargs="+", default=["oracle fit", "oracle state"])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    rows = []
    for v in a.variants:
        for s in a.seeds:
            rows.append(run_one(a.task, v, s, a.rho2))
            print(json.dumps(rows[-1]), flush=True)
            if a.out:
                a.out.parent.mkdir(parents=True, exist_ok=True)
                a.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
