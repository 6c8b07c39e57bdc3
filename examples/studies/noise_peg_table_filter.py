"""The peg policy's online filter told that the peg cannot be inside the table (issue 46). Diagnostics, not a method.

The kinematic filter knows the robot's kinematics but not the scene: a peg resting on the table top beside the
hole is estimated 1.6 cm below the table top (median of the failed rollouts), as if it had begun to enter. This
study rescores each final policy of a peg sweep on 20 fresh rollouts (evaluation seed ``10000 + seed``, as the
sweep scores it) with its filter changed after each update: where the estimated peg bottom lies below the table
top and its horizontal offset from the hole's centre exceeds ``OUTSIDE`` in either direction (so that the peg
cannot be in the opening), one pseudo-measurement ``peg_bottom.z = table top`` with variance ``--r`` is applied
(:func:`project`), relinearised and repeated once.  ``None`` scores the filter as learned (it reproduces the
recorded ``final_eval.npz``).  The policy's gains were learned with the filter as it was.

    python examples/studies/noise_peg_table_filter.py "runs/n46/trials/peg/kinematic,rho2=0.1/lqr-flm" \\
        --outside None 0.01 0.02 0.03 0.05
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from noise_kernels_table import interval  # the same 95% Student-t interval (a study beside this one)
from noise_peg_landing import TABLE_Z, TARGET, trial_policy

from soc_opt.noise.kinematic.filter import KinematicFilter
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.tasks import load_task


def inside_table(pb: np.ndarray, outside: float) -> np.ndarray:
    """Which peg-bottom positions ``pb (B, 3)`` lie below the table top more than ``outside`` (m) from the hole's
    centre in x or y, where the peg cannot be (``(B,)`` booleans)."""
    return (pb[:, 2] < TABLE_Z) & (np.abs(pb[:, :2] - TARGET[:2]).max(axis=1) > outside)


def project(z: np.ndarray, measure, prior_info: np.ndarray, r2: float, ib: list[int], outside: float, r: float,
            passes: int = 2) -> np.ndarray:
    """Latent estimates ``z (B, nz)`` moved so that no peg bottom lies below the table top outside the opening.

    ``measure(z) -> (h (B, n), H (B, n, nz))`` at the estimates of the update just made; its information matrix
    is ``info = prior_info + H^T H / r2`` (the filter's predicted information ``(nz, nz)`` and ``rho^2``), from
    the first pass's ``H``; ``ib`` the peg bottom's rows in ``h``.  Each violating row gets the scalar update
    ``z += P h_z (TABLE_Z - h_z(z)) / (h_z P h_z^T + r)`` with ``P = info^{-1}``, relinearised ``passes`` times."""
    z = np.array(z, dtype=float)
    info = None
    for _ in range(passes):
        hx, H = measure(z)
        if info is None:  # the update's information, at the estimates it made
            info = prior_info + np.swapaxes(H, -1, -2) @ H / r2
        pb = hx[:, ib]
        bad = np.flatnonzero(inside_table(pb, outside))
        if bad.size == 0:
            break
        for i in bad:
            hz = H[i, ib[2]]
            Ph = np.linalg.solve(info[i], hz)
            z[i] += Ph * (TABLE_Z - pb[i, 2]) / (hz @ Ph + r)
    return z


def patched_step(original, km, outside: float | None, r: float, ib: list[int]):
    """``original`` (:meth:`KinematicFilter.step` as the library defines it) followed by :func:`project` (``km`` the task's
    :class:`~soc_opt.noise.kinematic.model.KinematicModel`); ``outside = None``: the step as it is.  The
    estimate's joint coordinates are the filter's latent ``z`` exactly (:mod:`soc_opt.noise.kinematic.filter`)."""
    def step(self, k, s_k, xhat_prev=None, a_prev=None):
        x = original(self, k, s_k, xhat_prev, a_prev)
        if outside is None or k == 0:
            return x
        z = np.atleast_2d(x)[:, self.zidx]
        return km.measure(project(z, km.measure, self.Lm[k], self.R[0, 0], ib, outside, r), False).reshape(np.shape(x))

    return step


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="a method's directory of a peg sweep under noise: seed_*/ below it")
    ap.add_argument("--outside", type=lambda v: None if v == "None" else float(v), nargs="+", default=[None, 0.02])
    ap.add_argument("--r", type=float, default=1e-4, help="variance of the pseudo-measurement (m^2)")
    ap.add_argument("--rho2", type=float, default=0.1)
    args = ap.parse_args(argv)
    task = load_task("peg", overrides={"rho2": args.rho2})
    ib = [task.state_labels.index(f"peg_bottom.{c}") for c in "xyz"]
    km = KinematicModel(task)
    original = KinematicFilter.step
    scores: dict[str, list[float]] = {str(o): [] for o in args.outside}
    try:
        for d in sorted(args.root.glob("seed_*")):
            trial, _, policy = trial_policy(d, task)
            row = {}
            for o in args.outside:
                KinematicFilter.step = patched_step(original, km, o, args.r, ib)
                m = task.metrics(task.rollouts(policy, 20, np.random.default_rng(10000 + int(trial["seed"]))))
                row[str(o)] = float(m["success_rate"])
                scores[str(o)].append(row[str(o)])
            print(json.dumps({"seed": d.name, "success_by_outside": row}), flush=True)
    finally:
        KinematicFilter.step = original
    base = np.asarray(scores[str(None)]) if None in args.outside else None
    for o, v in scores.items():
        m, lo, hi = interval(v)
        line = f"outside {o}: success {m:.3f} [{lo:.3f}, {hi:.3f}] over {len(v)} seeds"
        if base is not None and o != str(None):
            d, dlo, dhi = interval(np.asarray(v) - base)
            line += f"; paired change against the filter as learned {d:+.3f} [{dlo:+.3f}, {dhi:+.3f}]"
        print(line)


if __name__ == "__main__":
    main()
