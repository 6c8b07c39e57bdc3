"""Where the peg comes down under sensor noise, and how far off the policy's estimate is there (issue 46).

For each trial of a peg sweep under noise (kinematic estimator), the filter of the policy the run returns is run
again on the measurements and actions of its ``final_eval.npz``. At the first step where the true peg bottom is
within ``--above`` of the table top, the script takes the horizontal error of the estimate and the true
horizontal offset from the hole's centre. It prints their medians for the rollouts that end in the hole, that
count as successes, and that fail. Per seed it separates where the plan comes down (the mean landing point's
offset from the hole, true and as the policy estimates it) from the scatter of the rollouts around it, and the
estimate's common error (bias) from its scatter, and it correlates a seed's success with its plan's offset.
It compares the true distance to the target with the filter's estimate of it (and, with ``--smoother``, the
learner's smoothed one) over a window of steps, for successful and failed rollouts.
Diagnostics, not a method.

    python examples/studies/noise_peg_landing.py "runs/n46/trials/peg/kinematic,rho2=0.1/lqr-flm"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from soc_opt.experiments.rundir import decode_checkpoint
from soc_opt.methods.config import DPSOCConfig
from soc_opt.methods.registry import get_method
from soc_opt.models import Rollouts
from soc_opt.noise.kinematic.loop import learn
from soc_opt.tasks import load_task

TARGET = np.array([0.0, 0.3, -0.5])  # the peg bottom's target, the floor of the hole (docs/math.md §8)
TABLE_Z = -0.4  # the table top


def landing(x: np.ndarray, xhat: np.ndarray, z_below: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per rollout of true and estimated peg-bottom positions ``x, xhat (M, T+1, 3)``: the first step where the
    true height is at or below ``z_below`` (the lowest step if never), the horizontal estimate error there and
    the true horizontal offset from the target there."""
    k, e, o = landing_vectors(x, xhat, z_below)
    return k, np.linalg.norm(e, axis=-1), np.linalg.norm(o, axis=-1)


def landing_vectors(x: np.ndarray, xhat: np.ndarray, z_below: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`landing` with the horizontal estimate errors and true offsets as vectors ``(M, 2)``."""
    below = x[..., 2] <= z_below
    k = np.where(below.any(axis=1), below.argmax(axis=1), x[..., 2].argmin(axis=1))
    r = np.arange(x.shape[0])
    return k, xhat[r, k, :2] - x[r, k, :2], x[r, k, :2] - TARGET[:2]


def per_seed(err: np.ndarray, off: np.ndarray) -> dict:
    """One seed's rollouts from :func:`landing_vectors` (``err, off (M, 2)``): where its plan comes down (the norm
    of the mean true offset, and of the mean estimated offset ``off + err``), how far the rollouts scatter
    around that point (RMS), and the estimate's common error (the norm of the mean error vector, the bias all
    its rollouts share) against its scatter around that bias (RMS)."""
    def rms(v):
        return float(np.sqrt(((v - v.mean(0)) ** 2).sum(-1).mean()))

    return {"plan_offset": float(np.linalg.norm(off.mean(0))), "plan_offset_estimated": float(np.linalg.norm((off + err).mean(0))),
            "scatter": rms(off), "estimate_bias": float(np.linalg.norm(err.mean(0))), "estimate_scatter": rms(err)}


def trial_policy(d: Path, task):
    """``(trial, config, policy)`` of the sweep trial in ``d``: its ``trial.json``, its configuration and the policy its
    method returns (``final_policy`` of the last checkpoint), bound to ``task``."""
    trial = json.loads((d / "trial.json").read_text())
    cfg = DPSOCConfig.from_dict(trial["config"])
    return trial, cfg, get_method(trial["method"]).final_policy(cfg, decode_checkpoint(d / "checkpoint.npz")).for_task(task)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a method's directory of a peg sweep: seed_*/ below it")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--above", type=float, default=0.02, help="height above the table top that counts as landing (m)")
    ap.add_argument("--json", type=Path, help="write the per-seed rows here")
    ap.add_argument("--eval", default="final_eval", help="the evaluation file: final_eval (sampled) or final_eval_mean_action")
    ap.add_argument("--window", type=int, nargs=2, default=[10, 60], help="steps over which the distances to the target are averaged")
    ap.add_argument("--smoother", action="store_true",
                    help="also the learner's smoothed states of each batch (the kinematic estimator run on it, as in learning)")
    args = ap.parse_args(argv)
    task = load_task("peg", overrides={"rho2": args.rho2})
    ib = [task.state_labels.index(f"peg_bottom.{c}") for c in "xyz"]
    success = task.config.metric.success
    end, err, off, seeds = [], [], [], []
    dist: dict[str, list] = {"true": [], "filtered": [], "smoothed": []}
    w = slice(*args.window)
    for d in sorted(args.root.glob("seed_*")):
        z = np.load(d / f"{args.eval}.npz")
        if args.rho2 > 0:
            _, cfg, policy = trial_policy(d, task)
            xhat = policy.filter.states(z["s"], z["a"])
        else:  # without sensor noise the policy acts on the measured state, the state itself
            xhat = z["s"]
        pb, pbh = z["x"][..., ib], xhat[..., ib]
        end.append(np.linalg.norm(pb - TARGET, axis=-1).min(axis=1))
        dist["true"].append(np.linalg.norm(pb[:, w] - TARGET, axis=-1).mean(axis=1))
        dist["filtered"].append(np.linalg.norm(pbh[:, w] - TARGET, axis=-1).mean(axis=1))
        if args.smoother and args.rho2 > 0:
            batch = Rollouts(z["x"], z["s"], z["a"], z["cost"], z["y"])
            smoothed = learn(task, batch, policy, cfg.baseline.noise.kinematic)[0].s
            dist["smoothed"].append(np.linalg.norm(smoothed[:, w][..., ib] - TARGET, axis=-1).mean(axis=1))
        k, e, o = landing_vectors(pb, pbh, TABLE_Z + args.above)
        err.append(np.linalg.norm(e, axis=-1))
        off.append(np.linalg.norm(o, axis=-1))
        seeds.append({"seed": d.name, "success": float((end[-1] < success).mean()), "landing_step": float(np.median(k)),
                      **per_seed(e, o)})
    end, err, off = (np.concatenate(v) for v in (end, err, off))
    for name, mask in (("in the hole (< 0.03 m)", end < 0.03), (f"success (< {success:g} m)", end < success),
                       ("failed", end >= success)):
        if mask.any():
            print(f"{name:24s} {int(mask.sum()):5d} rollouts: estimate error {100 * np.median(err[mask]):.2f} cm "
                  f"(90%: {100 * np.quantile(err[mask], 0.9):.2f}), true offset from the hole {100 * np.median(off[mask]):.2f} cm")
    print(f"distance to the target, mean over steps {args.window[0]}-{args.window[1] - 1}, median over rollouts (m):")
    for name, mask in (("success", end < success), ("failed", end >= success)):
        if mask.any():
            print(f"  {name:8s} " + ", ".join(f"{k} {np.median(np.concatenate(v)[mask]):.4f}" for k, v in dist.items() if v))
    print(f"all {end.size} rollouts: estimate error median {100 * np.median(err):.2f} cm, RMS {100 * np.sqrt(np.mean(err ** 2)):.2f} cm")
    print("per seed (cm): seed, success, landing step, plan offset (true / estimated), scatter, estimate bias / scatter")
    for r in seeds:
        print(f"  {r['seed']}: {r['success']:.2f}, {r['landing_step']:.0f}, {100 * r['plan_offset']:.1f} / "
              f"{100 * r['plan_offset_estimated']:.1f}, {100 * r['scatter']:.1f}, {100 * r['estimate_bias']:.1f} / "
              f"{100 * r['estimate_scatter']:.1f}")
    mean = {k: float(np.mean([r[k] for r in seeds])) for k in seeds[0] if k != "seed"}
    print("mean over seeds: " + ", ".join(f"{k} {v:.3f}" for k, v in mean.items()))
    if len(seeds) > 2:
        rho = spearmanr([r["plan_offset"] for r in seeds], [r["success"] for r in seeds])
        print(f"Spearman correlation of a seed's success with its plan offset: {rho.statistic:.2f} (p = {rho.pvalue:.2g})")
    if args.json:
        args.json.write_text(json.dumps(seeds, indent=1))


if __name__ == "__main__":
    main()
