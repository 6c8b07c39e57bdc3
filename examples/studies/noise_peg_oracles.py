"""Where noise-aware LQR-FLM loses on peg (or door) at rho^2 = 0.1: the estimator or the fit? (issue 9)

Three runs per seed of noise-aware LQR-FLM (the task's experiment configuration at the paper's
scale with ``[baseline.noise] estimator = "kalman", fit_correction = "ssm_em", time_window = 5``;
for peg that is ``docs/results/noise/peg_noise_aware.toml``), each scored on 20 fresh rollouts of
its final policy (evaluation seed ``10000 + seed``):

* ``noise-aware``: as configured (SSM-EM fit from the measured states, Kalman filter in the loop).
* ``oracle fit``: the learner is handed the *true* states of its rollouts (prior, fit and cost
  expansion on ``x``; the paper's fit, no correction), while the policy still acts on the Kalman
  filter of that model run on the noisy measurements.  It isolates the estimator in the loop.
* ``oracle state``: the policy acts on the *true* state (rollouts on a ``rho^2 = 0`` twin of the
  task), while the learner sees only ``s = x + eps`` (the SSM-EM fit, no filter).  It isolates the fit.

Both oracles are diagnostics, not methods: they use information a real controller does not have.
BLAS runs on one thread (as in a sweep's Ray workers): 14 sampled iterations amplify last-digit
rounding differences, so threaded BLAS gives other, equally valid, numbers.

Usage:
    python examples/studies/noise_peg_oracles.py --seeds 0 1 2 --out runs/noise_peg_oracles.md
    python examples/studies/noise_peg_oracles.py --task door --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.noise.aware import NoiseConfig
from soc_opt.tasks import load_task

NOISE_AWARE = NoiseConfig(estimator="kalman", fit_correction="ssm_em", time_window=5)


class _Wrapped:
    """A task whose ``rollouts`` are changed for the learner; everything else is the task's."""

    def __init__(self, task, rollouts):
        self.wrapped, self.learner_rollouts = task, rollouts

    def __getattr__(self, name):
        return getattr(self.wrapped, name)

    def rollouts(self, policy, M, rng, noise=True, workers=1, x0=None):
        return self.learner_rollouts(policy, M, rng, noise, workers, x0)


def _with_states(task, ro, s):
    cost = task.cost(s, ro.a)
    return dataclasses.replace(ro, s=s, cost=cost, y=np.exp(-task.y_scale * cost))


def oracle_fit_task(task):
    """The learner sees the true states; the rollouts themselves ran on the noisy measurements."""
    return _Wrapped(task, lambda p, M, rng, noise, w, x0: (lambda ro: _with_states(task, ro, ro.x))(
        task.rollouts(p, M, rng, noise, w, x0)))


def oracle_state_task(task, rho2):
    """The policy acts on the true state; the learner sees ``x + eps``, ``eps ~ N(0, rho2 I)``."""
    twin = load_task(task.name, overrides={"rho2": 0.0})

    def rollouts(p, M, rng, noise, w, x0):
        ro = twin.rollouts(p, M, rng, noise, w, x0)
        return _with_states(task, ro, ro.x + np.sqrt(rho2) * rng.standard_normal(ro.x.shape))

    return _Wrapped(task, rollouts), twin


def run_one(task_name: str, variant: str, seed: int, rho2: float) -> dict:
    task = load_task(task_name, overrides={"rho2": rho2})
    cfg = load_run_config(task_name, paper=True, method="lqr-flm")
    cfg = cfg.replace(baseline=cfg.baseline.replace(noise=NOISE_AWARE))
    eval_task, learner = task, task
    if variant == "oracle fit":
        learner = oracle_fit_task(task)
        cfg = cfg.replace(baseline=cfg.baseline.replace(noise=cfg.baseline.noise.replace(
            fit_correction="none", time_window=0)))
    elif variant == "oracle state":
        learner, eval_task = oracle_state_task(task, rho2)
        cfg = cfg.replace(baseline=cfg.baseline.replace(noise=cfg.baseline.noise.replace(estimator="none")))
    t0 = time.perf_counter()
    st = run_experiment(learner, "lqr-flm", cfg, seed, None)
    ro = eval_task.rollouts(st.policy, 20, np.random.default_rng(10000 + seed))
    m = task.metrics(ro)
    return {"task": task_name, "variant": variant, "seed": seed, **m, "wall_time": time.perf_counter() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="peg", help="built-in task: peg or door")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--variants", nargs="+", default=["noise-aware", "oracle fit", "oracle state"])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    rows = []
    for v in a.variants:
        for s in a.seeds:
            rows.append(run_one(a.task, v, s, a.rho2))
            print(json.dumps(rows[-1]), flush=True)
    key = "success_rate" if "success_rate" in rows[0] else next(k for k in rows[0] if k.startswith("min_") and
                                                                   not k.endswith("_best"))
    lines = [f"# {a.task}, rho^2 = {a.rho2}: estimator vs fit (seeds {a.seeds})", "",
             f"| variant | {key} | per seed | final cost |", "|---|---|---|---|"]
    for v in a.variants:
        r = [x for x in rows if x["variant"] == v]
        val = np.array([x[key] for x in r])
        c = np.array([x["cost"] for x in r])
        lines.append(f"| {v} | {val.mean():.3g} ± {val.std():.2g} | {', '.join(f'{x:.3g}' for x in val)} | "
                     f"{c.mean():.1f} ± {c.std():.1f} |")
    report = "\n".join(lines) + "\n"
    print(report)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(report)
        a.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
