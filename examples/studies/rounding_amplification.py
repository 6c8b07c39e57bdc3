"""How far one run carries a rounding difference (issue 46: results that depend on the BLAS kernel).

Two runs of the same method, task, seed and code, in one process, differ only in a relative
perturbation ``--eps`` (default 1e-12, a few thousand ulps) of the initial policy's offsets ``k`` (``k + eps (1 + |k|)``): what a
different BLAS kernel or CPU does to the first iteration's arithmetic.  Printed per iteration: the
relative difference of the two runs' policy gains ``K`` and their batches' true mean costs; then, for
one iteration ``--split`` run twice from the same state (offsets perturbed by ``--eps``), the
relative difference after each phase of that iteration (rollouts, the kinematic smoother, the fit,
the KL step).  The phase where the difference jumps is where a run decides its fate by rounding.

Usage:
    python examples/studies/rounding_amplification.py --task peg --seed 100 --split 1
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from soc_opt import lqg
from soc_opt.experiments.run import load_run_config
from soc_opt.learning import fit as fit_module
from soc_opt.methods.lqr_flm import iteration as lqr_flm  # the module whose globals the iteration calls
from soc_opt.methods.registry import get_method
from soc_opt.models import LinearGaussianPolicy
from soc_opt.noise import kinematic_strategy
from soc_opt.noise.aware import NoiseConfig, gains, with_gains
from soc_opt.tasks import load_task


def relative(a, b) -> float:
    """``max |a - b| / max |b|``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def perturbed(state, eps: float):
    g = gains(state.policy)
    return dataclasses.replace(state, policy=with_gains(state.policy, LinearGaussianPolicy(g.K, g.k + eps * (1.0 + np.abs(g.k)), g.cov)))


class Capture:
    """Records the outputs of the phases of one iteration (wrapping the module functions it calls)."""

    def __init__(self):
        self.values: dict[str, np.ndarray] = {}
        self.saved = []

    def wrap(self, module, name: str, pick):
        original = getattr(module, name)

        def wrapped(*args, **kwargs):
            out = original(*args, **kwargs)
            for key, value in pick(args, out).items():
                self.values[key] = np.array(value, dtype=float)
            return out

        self.saved.append((module, name, original))
        setattr(module, name, wrapped)

    def restore(self):
        for module, name, original in reversed(self.saved):
            setattr(module, name, original)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="peg")
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--estimator", default="kinematic")
    ap.add_argument("--eps", type=float, default=1e-12)
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--split", type=int, default=1, help="the iteration whose phases are compared")
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    cfg = load_run_config(a.task, paper=True, method=a.method)
    cfg = cfg.replace(baseline=cfg.baseline.replace(noise=NoiseConfig(estimator=a.estimator)))
    method = get_method(a.method)
    runs = [method.initial_state(task, cfg, a.seed), perturbed(method.initial_state(task, cfg, a.seed), a.eps)]
    for it in range(a.iterations):
        runs = [method.iterate(task, cfg, s) for s in runs]
        k0, k1 = (gains(s.policy).K for s in runs)
        c0, c1 = (float(np.mean(s.history[-1].cost)) for s in runs)
        print(json.dumps({"iteration": it, "K relative difference": relative(k1, k0), "cost": [c0, c1]}), flush=True)

    state = method.initial_state(task, cfg, a.seed)
    for _ in range(a.split):
        state = method.iterate(task, cfg, state)
    phases = []
    for eps in (0.0, a.eps):
        cap = Capture()
        cap.wrap(lqr_flm, "sample", lambda args, out: {"rollouts x": out[0].x})
        cap.wrap(kinematic_strategy.kinematic_loop, "learn", lambda args, out: {"smoothed states": out[0].s})
        cap.wrap(fit_module, "update_prior", lambda args, out: {"mixture prior weights": out.weights if hasattr(out, "weights") else [0.0]})
        cap.wrap(fit_module, "fit_dynamics", lambda args, out: {"fitted B": out.B, "fitted A": out.A})
        cap.wrap(lqg, "kl_step_local", lambda args, out: {"KL-step eta": out.eta, "KL-step K": out.policy.K})
        saved = lqr_flm.lqg.kl_step_local
        lqr_flm.lqg.kl_step_local = lqg.kl_step_local
        try:
            method.iterate(task, cfg, perturbed(state, eps))
        finally:
            lqr_flm.lqg.kl_step_local = saved
            cap.restore()
        phases.append(cap.values)
    print(json.dumps({"split iteration": a.split, "perturbation": a.eps,
                      **{k: relative(phases[1][k], phases[0][k]) for k in phases[0] if k in phases[1]}}))


if __name__ == "__main__":
    main()
