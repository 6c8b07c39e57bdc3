"""What would lift a final kinematic-estimator policy on peg (issue 19, sixth round): its filter or its exploration?

Each final policy of a sweep setting (``METHOD/seed_N/``, with ``checkpoint.npz``-era ``policies/`` and
``samples/``) is scored on 20 rollouts (evaluation seed ``10000 + seed``, as the sweep scores it) with
one part changed at a time, the gains ``K, k`` kept:

* ``--em JSON ...``: the filter rebuilt from the last batch by ``kinematic.loop.learn`` with these
  :class:`~soc_opt.noise.kinematic.config.KinematicConfig` fields (``{}`` rebuilds the filter the
  run made, which the script checks), optionally from the last ``--pool`` batches together;
* ``--update-iters N ...``: the online update iterated ``N`` times (Gauss-Newton on the update's
  MAP, relinearising ``h`` at the new estimate; ``1`` is the filter as run);
* ``--cov-scales C ...``: the policy's exploration covariance times ``C`` (``1``: as learned; the
  same noise draws, their effect scaled by ``sqrt(C)``).

Diagnostics, not methods: every variant changes the final policy after learning.  The estimator
uses the robot's kinematics (not its masses, inertia or damping).

Usage:
    python examples/studies/noise_kinematic_final_variants.py "runs/sweep-noise_peg10/trials/peg/kinematic,rho2=0.1" \\
        --em '{}' '{"em_iters": 6}' --pool 1 2 --update-iters 1 3 --cov-scales 1 0.5 0.1
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np

from soc_opt.models import LinearGaussianPolicy, Rollouts
from soc_opt.noise.kinematic import loop
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import KinematicFilteredPolicy
from soc_opt.tasks import load_task


@dataclasses.dataclass(frozen=True)
class IteratedUpdatePolicy(KinematicFilteredPolicy):
    """The policy acting on its filter with the online update iterated ``iters`` times: from the
    prediction ``z^-``, ``z <- z^- + (Lm + H^T H / rho^2)^{-1} H^T (s - h(z) - H (z^- - z)) / rho^2``
    with ``H = dh/dz(z)`` (one iteration is the filter's own update)."""

    iters: int = 1

    def estimate(self, k, s_k, xhat_prev=None, a_prev=None):
        f = self.filter
        if self.iters == 1 or not np.any(f.R):
            return f.step(k, s_k, xhat_prev, a_prev)
        s_k = np.asarray(s_k, dtype=float)
        if k == 0:
            pred = np.broadcast_to(f.z0, s_k.shape[:-1] + f.z0.shape)
        else:
            zp = np.asarray(xhat_prev, dtype=float)[..., f.zidx]
            pred = zp @ f.A[k - 1].T + np.asarray(a_prev, dtype=float) @ f.Bz[k - 1].T + f.cz[k - 1]
        km, r2, z = f.__dict__["_km"], f.R[0, 0], pred
        for _ in range(self.iters):
            hx, H = km.measure(z)
            Ht = np.swapaxes(H, -1, -2)
            g = np.einsum("...ij,...j->...i", Ht, s_k - hx - np.einsum("...ij,...j->...i", H, pred - z)) / r2
            z = pred + np.linalg.solve(f.Lm[k] + Ht @ H / r2, g[..., None])[..., 0]
        return km.measure(z, False)


def _score(task, policy, seed: int) -> float:
    m = task.metrics(task.rollouts(policy, 20, np.random.default_rng(10000 + seed)))
    return round(float(m["success_rate"] if "success_rate" in m else m["min_hinge"]), 4)


def _batch(trial: Path, it: int) -> Rollouts:
    with np.load(trial / "samples" / f"iter_{it:03d}.npz") as d:
        return Rollouts(**{k: d[k] for k in ("x", "s", "a", "cost", "y")})


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("setting_dir", type=Path, help="a sweep setting's directory (holding METHOD/seed_N/)")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--method", default="lqr-flm")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--em", nargs="*", default=[], help="KinematicConfig fields as JSON, one filter per value")
    ap.add_argument("--pool", type=int, nargs="+", default=[1], help="batches the --em filters learn from")
    ap.add_argument("--update-iters", type=int, nargs="*", default=[])
    ap.add_argument("--cov-scales", type=float, nargs="*", default=[])
    a = ap.parse_args(argv)
    task = load_task(a.task, overrides={"rho2": a.rho2})
    for seed in a.seeds:
        trial = a.setting_dir / a.method / f"seed_{seed}"
        last = max(int(p.stem.split("_")[1]) for p in (trial / "samples").glob("iter_*.npz"))
        with np.load(trial / "policies" / f"iter_{last:03d}.npz") as d:
            sampler = KinematicFilteredPolicy.from_dict(d, task)
        with np.load(trial / "policies" / f"iter_{last + 1:03d}.npz") as d:
            final = KinematicFilteredPolicy.from_dict(d, task)
        row: dict = {"seed": seed, "method": a.method}
        for fields, pool in itertools.product(a.em, a.pool):
            batches = [_batch(trial, last - j) for j in range(pool)]
            ro = Rollouts(**{k: np.concatenate([getattr(b, k) for b in batches]) for k in ("x", "s", "a", "cost", "y")})
            _, filt, _ = loop.learn(task, ro, sampler, KinematicConfig(**json.loads(fields)))
            if json.loads(fields) == {} and pool == 1:
                row["rebuilt filter is the run's"] = bool(np.array_equal(filt.accel_B, final.filter.accel_B))
            row[f"em {fields} pool {pool}"] = _score(task, KinematicFilteredPolicy(final.policy, filt), seed)
        for n in a.update_iters:
            row[f"update iters {n}"] = _score(task, IteratedUpdatePolicy(final.policy, final.filter, n), seed)
        for c in a.cov_scales:
            p = final.policy
            scaled = p if c == 1.0 else LinearGaussianPolicy(p.K, p.k, c * p.cov)  # Cholesky: the same draws, scaled
            row[f"cov x {c:g}"] = _score(task, dataclasses.replace(final, policy=scaled), seed)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
