"""Where the peg comes down under sensor noise, and how far off the policy's estimate is there (issue 46).

For each trial of a peg sweep under noise (kinematic estimator), the filter of the policy the run returns is run
again on the measurements and actions of its ``final_eval.npz``. At the first step where the true peg bottom is
within ``--above`` of the table top, the script takes the horizontal error of the estimate and the true
horizontal offset from the hole's centre. It prints their medians for the rollouts that end in the hole, that
count as successes, and that fail. Diagnostics, not a method.

    python examples/studies/noise_peg_landing.py "runs/n46/trials/peg/kinematic,rho2=0.1/lqr-flm"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soc_opt.experiments.rundir import decode_checkpoint
from soc_opt.methods.config import DPSOCConfig
from soc_opt.methods.registry import get_method
from soc_opt.tasks import load_task

TARGET = np.array([0.0, 0.3, -0.5])  # the peg bottom's target, the floor of the hole (docs/math.md §8)
TABLE_Z = -0.4  # the table top


def landing(x: np.ndarray, xhat: np.ndarray, z_below: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per rollout of true and estimated peg-bottom positions ``x, xhat (M, T+1, 3)``: the first step where the
    true height is at or below ``z_below`` (the lowest step if never), the horizontal estimate error there and
    the true horizontal offset from the target there."""
    below = x[..., 2] <= z_below
    k = np.where(below.any(axis=1), below.argmax(axis=1), x[..., 2].argmin(axis=1))
    r = np.arange(x.shape[0])
    err = np.linalg.norm(xhat[r, k, :2] - x[r, k, :2], axis=-1)
    off = np.linalg.norm(x[r, k, :2] - TARGET[:2], axis=-1)
    return k, err, off


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a method's directory of a peg sweep: seed_*/ below it")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--above", type=float, default=0.02, help="height above the table top that counts as landing (m)")
    args = ap.parse_args(argv)
    task = load_task("peg", overrides={"rho2": args.rho2})
    ib = [task.state_labels.index(f"peg_bottom.{c}") for c in "xyz"]
    success = task.config.metric.success
    end, err, off = [], [], []
    for d in sorted(args.root.glob("seed_*")):
        trial = json.loads((d / "trial.json").read_text())
        state = decode_checkpoint(d / "checkpoint.npz")
        policy = get_method(trial["method"]).final_policy(DPSOCConfig.from_dict(trial["config"]), state).for_task(task)
        z = np.load(d / "final_eval.npz")
        xhat = policy.filter.states(z["s"], z["a"])
        pb, pbh = z["x"][..., ib], xhat[..., ib]
        end.append(np.linalg.norm(pb - TARGET, axis=-1).min(axis=1))
        _, e, o = landing(pb, pbh, TABLE_Z + args.above)
        err.append(e)
        off.append(o)
    end, err, off = (np.concatenate(v) for v in (end, err, off))
    for name, mask in (("in the hole (< 0.03 m)", end < 0.03), (f"success (< {success:g} m)", end < success),
                       ("failed", end >= success)):
        if mask.any():
            print(f"{name:24s} {int(mask.sum()):5d} rollouts: estimate error {100 * np.median(err[mask]):.2f} cm "
                  f"(90%: {100 * np.quantile(err[mask], 0.9):.2f}), true offset from the hole {100 * np.median(off[mask]):.2f} cm")
    print(f"all {end.size} rollouts: estimate error median {100 * np.median(err):.2f} cm, RMS {100 * np.sqrt(np.mean(err ** 2)):.2f} cm")


if __name__ == "__main__":
    main()
