"""The learner's local model under sensor noise, before and after errors in variables (issue 46, docs/math.md §13.1).

Replays the batches of a finished kinematic-estimator run (``samples/iter_XXX.npz`` and the policies that
sampled them, the mixture prior rebuilt batch by batch as the run did) and, at the iterations given, fits
the local dynamics of docs/math.md §2 four ways:

* ``oracle``: on the true states (with a mixture prior of true-state tuples): what no controller has;
* ``paper``: on the measured states (the paper's learner);
* ``kinematic``: the kinematic estimator's fit on its smoothed states and their posterior moments (§11.3);
* ``kinematic + eiv``: that fit refitted on the measured batch with the states latent (§13.1,
  ``fit_correction = "eiv"``).

Printed per fit, as Markdown rows: the relative error of ``B_k`` against the oracle fit and against the
finite-difference linearisation of the simulator along the batch's mean true trajectory
(``task.linearize``; all rows, and the joint-velocity rows), the same for ``A_k`` against the oracle,
``tr W_k`` (mean over steps; the plant has no process noise), and the KL step each model leads to from the
sampling policy at the base budget: the mean ``||K_k||_F`` of its gains, their relative difference from the
gains designed on the oracle model, and the model's predicted cost.

Usage:
    python examples/studies/noise_eiv_fit.py "runs/n46-skx/trials/peg/kinematic,rho2=0.1/lqr-flm/seed_400" \\
        --iterations 1 6
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from soc_opt import lqg
from soc_opt.learning import fit
from soc_opt.lqg import LocalModel
from soc_opt.methods.config import DPSOCConfig
from soc_opt.models import LinearGaussianPolicy, Rollouts
from soc_opt.noise.aware import NoiseConfig, gains
from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
from soc_opt.noise.strategy import resolve
from soc_opt.tasks import load_task


def batch(trial: Path, it: int) -> Rollouts:
    with np.load(trial / "samples" / f"iter_{it:03d}.npz") as d:
        return Rollouts(**{k: d[k] for k in ("x", "s", "a", "cost", "y")})


def sampler(trial: Path, it: int, task):
    with np.load(trial / "policies" / f"iter_{it:03d}.npz") as d:
        if any(k.startswith("kfilter") for k in d.files):
            return KinematicFilteredPolicy.from_dict(d, task)
        return LinearGaussianPolicy(d["K"], d["k"], d["cov"])


def relative(X: np.ndarray, Y: np.ndarray, rows=slice(None)) -> float:
    """Mean over steps of ``||X_k[rows] - Y_k[rows]||_F / ||Y_k[rows]||_F``."""
    num = np.linalg.norm((X - Y)[:, rows].reshape(len(X), -1), axis=1)
    den = np.linalg.norm(Y[:, rows].reshape(len(Y), -1), axis=1)
    return float(np.mean(num / np.maximum(den, 1e-300)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trial", type=Path, help="a finished run directory of the kinematic estimator")
    ap.add_argument("--iterations", type=int, nargs="+", default=[1, 6])
    a = ap.parse_args(argv)
    cj = json.loads((a.trial / "config.json").read_text())
    cfg = DPSOCConfig.from_dict(cj["config"])
    base = cfg.baseline
    task = load_task(cj["task"], overrides={"rho2": 0.1})
    fc = base.fit
    kin = resolve(task, base.noise)
    kin_eiv = resolve(task, base.noise.replace(fit_correction="eiv"))
    paper = resolve(task, NoiseConfig())
    qd = [i for i, label in enumerate(task.state_labels) if label.startswith("qd:")]
    priors = {"kin": None, "paper": None, "true": None}
    previous = None
    print("| iteration | fit | B vs oracle | B vs FD | B vs FD, joint-velocity rows | A vs oracle | tr W | mean ||K|| "
          "| K vs oracle's | predicted cost |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for it in range(max(a.iterations) + 1):
        ro, pol = batch(a.trial, it), sampler(a.trial, it, task)
        est = kin.estimate(priors["kin"], ro, fc, pol, np.random.default_rng(it), previous=previous)
        est_p = paper.estimate(priors["paper"], ro, fc, pol, np.random.default_rng(it))
        true = dataclasses.replace(ro, s=ro.x)
        priors["true"] = fit.update_prior(priors["true"], true, fc, np.random.default_rng(it))
        if it in a.iterations:
            models = {
                "oracle (true states)": fit.fit_dynamics(true, fc, priors["true"]),
                "paper (measured states)": paper.fit(ro, fc, est_p, pol),
                "kinematic (smoothed + posterior)": kin.fit(est.data(ro), fc, est, pol),
                "kinematic + eiv": kin_eiv.fit(est.data(ro), fc, est, pol),
            }
            fd = task.linearize(ro.x.mean(axis=0), ro.a.mean(axis=0))
            cost = task.cost_expansion(est.data(ro).s.mean(axis=0), ro.a.mean(axis=0))
            ref = gains(pol)
            oracle_K = None
            for name, dyn in models.items():
                try:
                    res = lqg.kl_step_local(LocalModel(dyn, cost, kin.noise.mu0, kin.noise.P0), ref,
                                            base.kl_budget * task.T, method=base.kl_method, config=base.kl)
                    K, pred = res.policy.K, float(res.expected_cost)
                except (lqg.SolverError, np.linalg.LinAlgError, ValueError) as e:
                    K, pred = None, f"KL step fails: {str(e)[:40]}"
                if oracle_K is None:
                    oracle_K = K
                k_txt = "" if K is None else f"{np.mean(np.linalg.norm(K, axis=(1, 2))):.1f}"
                kd_txt = "" if K is None or oracle_K is None else f"{relative(K, oracle_K):.3f}"
                pred_txt = pred if isinstance(pred, str) else f"{pred:.2f}"
                print(f"| {it} | {name} | {relative(dyn.B, models['oracle (true states)'].B):.3f} | {relative(dyn.B, fd.B):.3f} "
                      f"| {relative(dyn.B, fd.B, qd):.3f} | {relative(dyn.A, models['oracle (true states)'].A):.3f} "
                      f"| {np.mean(np.trace(dyn.cov, axis1=1, axis2=2)):.4g} | {k_txt} | {kd_txt} | {pred_txt} |", flush=True)
        priors["kin"], priors["paper"], previous = est.prior, est_p.prior, ro


if __name__ == "__main__":
    main()
