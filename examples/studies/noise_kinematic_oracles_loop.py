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

A variant name ending in `` @ true state`` (e.g. ``oracle fit @ true state``) learns as the variant
without the suffix (the policy acting on the kinematic filter while it learns) and scores the final
policy's gains on the true state of a noise-free twin: what the filter costs the *returned* policy,
apart from what it cost the batches it was learned from.  Every variant is scored sampled and with
its mean action ``K s + k``.

``oracle fit`` splits into the learner's parts (issue 30, item 3); each gives *one* part the true
states and leaves the rest on the smoothed ones:

* ``oracle dynamics``: the per-step regression ``(A_k, B_k, c_k, W_k)`` on the true states (no posterior
  moments), with the mixture prior fitted on the smoothed states;
* ``oracle prior``: the mixture prior on the true states' tuples;
* ``oracle expansion``: the cost expanded around the true states' mean trajectory;
* ``oracle mean dynamics`` / ``oracle dynamics noise``: ``oracle dynamics`` split once more: ``A_k, B_k,
  c_k`` from the true states with the smoothed fit's ``W_k``, or the smoothed fit's ``A_k, B_k, c_k``
  with the true states' ``W_k``;
* ``oracle object rows``: the smoothed fit with the rows of the states of the door (its hinge, its
  handle's position and velocity: the labels naming ``hinge`` or ``handle``) from the true states' fit.

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
from soc_opt.noise.aware import NoiseConfig, gains, mean_action
from soc_opt.noise.kinematic import loop
from soc_opt.noise.kinematic_strategy import KinematicEstimator
from soc_opt.noise.strategy import Estimates, NoiseStrategy
from soc_opt.tasks import load_task

_learn = loop.learn
_estimate, _fit, _expansion = KinematicEstimator.estimate, KinematicEstimator.fit, KinematicEstimator.expansion_point
_UNPATCHED = (_learn, _estimate, _fit, _expansion)


def _true(rollouts):
    return dataclasses.replace(rollouts, s=rollouts.x)


def _oracle_dynamics(self, rollouts, fit_cfg, estimates, sampler, *, include_y=False):
    return NoiseStrategy.fit(self, _true(rollouts), fit_cfg, estimates, sampler, include_y=include_y)


def _oracle_mean_dynamics(self, rollouts, fit_cfg, estimates, sampler, *, include_y=False):
    true = _oracle_dynamics(self, rollouts, fit_cfg, estimates, sampler)
    return dataclasses.replace(true, cov=_fit(self, rollouts, fit_cfg, estimates, sampler).cov)


def _oracle_dynamics_noise(self, rollouts, fit_cfg, estimates, sampler, *, include_y=False):
    smoothed = _fit(self, rollouts, fit_cfg, estimates, sampler)
    return dataclasses.replace(smoothed, cov=_oracle_dynamics(self, rollouts, fit_cfg, estimates, sampler).cov)


def _oracle_object_rows(self, rollouts, fit_cfg, estimates, sampler, *, include_y=False):
    smoothed = _fit(self, rollouts, fit_cfg, estimates, sampler)
    true = _oracle_dynamics(self, rollouts, fit_cfg, estimates, sampler)
    rows = np.array([("hinge" in label or "handle" in label) for label in self.task.state_labels])
    A, B, c, W = (np.array(getattr(smoothed, f)) for f in ("A", "B", "c", "cov"))
    A[:, rows], B[:, rows], c[:, rows] = true.A[:, rows], true.B[:, rows], true.c[:, rows]
    W[:, rows] = true.cov[:, rows]
    W[:, :, rows] = true.cov[:, :, rows]
    W[:, rows[:, None] != rows[None, :]] = 0.0  # no noise couplings between the two blocks
    return dataclasses.replace(smoothed, A=A, B=B, c=c, cov=W)


def _oracle_prior(self, prior, rollouts, fit_cfg, sampler, rng, previous=None):
    learn, filt, diag = loop.learn(self.task, rollouts, sampler, self.cfg.kinematic, previous)
    base = NoiseStrategy.estimate(self, prior, _true(learn), fit_cfg, sampler, rng)
    return Estimates(prior=base.prior, learn=learn, filter=filt, moments=diag.get("posterior"),
                     timings={"estimator": diag["kin_time"]})


def _oracle_expansion(self, rollouts, dynamics):
    return rollouts.x.mean(axis=0)


def _patches():
    """The parts of the learner each variant replaces: ``(learn, estimate, fit, expansion_point)``."""
    return {"oracle fit": (_true_state_learn, _estimate, _fit, _expansion),
            "oracle dynamics": (_learn, _estimate, _oracle_dynamics, _expansion),
            "oracle prior": (_learn, _oracle_prior, _fit, _expansion),
            "oracle expansion": (_learn, _estimate, _fit, _oracle_expansion),
            "oracle mean dynamics": (_learn, _estimate, _oracle_mean_dynamics, _expansion),
            "oracle dynamics noise": (_learn, _estimate, _oracle_dynamics_noise, _expansion),
            "oracle object rows": (_learn, _estimate, _oracle_object_rows, _expansion)}


def _install(parts):
    loop.learn = parts[0]
    KinematicEstimator.estimate, KinematicEstimator.fit, KinematicEstimator.expansion_point = parts[1:]


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


TRUE_STATE_EVAL = " @ true state"


def parse_variant(variant: str) -> tuple[str, bool]:
    """``(how it learns, scored on the true state?)`` of a variant name (module docstring)."""
    learned_as = variant.removesuffix(TRUE_STATE_EVAL)
    known = ("kinematic", "oracle state", *_patches())
    if learned_as not in known:
        raise ValueError(f"unknown variant {variant!r}: one of {', '.join(known)}, optionally with {TRUE_STATE_EVAL!r}")
    return learned_as, learned_as == "oracle state" or variant.endswith(TRUE_STATE_EVAL)


def run_one(task_name: str, variant: str, seed: int, rho2: float) -> dict:
    learned_as, on_true = parse_variant(variant)
    task = load_task(task_name, overrides={"rho2": rho2})
    cfg = load_run_config(task_name, paper=True, method="lqr-flm")
    cfg = cfg.replace(baseline=cfg.baseline.replace(noise=NoiseConfig(estimator="kinematic")))
    twin = load_task(task_name, overrides={"rho2": 0.0}) if on_true else None  # "oracle state" is on_true
    learner = _TrueStateActor(task, twin) if learned_as == "oracle state" else task
    _install(_patches().get(learned_as, _UNPATCHED))
    t0 = time.perf_counter()
    try:
        st = run_experiment(learner, "lqr-flm", cfg, seed, None)
    finally:
        _install(_UNPATCHED)
    final = get_method("lqr-flm").final_policy(cfg, st)  # the returned policy (docs/math.md §12.3)
    pol, scorer = (gains(final), twin) if on_true else (final, task)
    ro = scorer.rollouts(pol, 20, np.random.default_rng(10000 + seed))
    ro_mean = scorer.rollouts(mean_action(pol), 20, np.random.default_rng(10000 + seed))
    return {"task": task_name, "variant": variant, "seed": seed, **task.metrics(ro),
            **{f"{k}_mean_action": v for k, v in task.metrics(ro_mean).items()}, "wall_time": time.perf_counter() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="door")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--variants", nargs="+", default=["oracle fit", "oracle state"])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    for v in a.variants:
        parse_variant(v)  # a misspelt variant fails before any run, not after hours of the others
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
