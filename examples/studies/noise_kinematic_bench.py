"""CPU time of the kinematic estimator on one paper-scale batch (20 rollouts x 100 steps of peg),
by part: the MuJoCo measurement map with its Jacobian, the smoother passes, the M-steps, the
filter's gains, and the whole `loop.learn` call.  Process (CPU) time, single-threaded BLAS, best of
``--repeat``: on a shared machine wall time mostly measures the other jobs.

Usage:
    python examples/studies/noise_kinematic_bench.py runs/peg_kinematic/seed_0/lqr-flm/samples/iter_010.npz
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from soc_opt.models import Rollouts
from soc_opt.noise.kinematic import em, loop
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.noise.kinematic.filter import build_filter
from soc_opt.noise.kinematic.model import KinematicModel
from soc_opt.noise.kinematic.smoother import smooth
from soc_opt.tasks import load_task


def _best(f, repeat):
    out, best = None, np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        out = f()
        best = min(best, time.process_time() - t0)
    return out, best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("samples")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    task = load_task(a.task)
    with np.load(a.samples, allow_pickle=False) as d:
        ro = Rollouts(**{k: d[k] for k in ("x", "s", "a", "cost", "y")})
    km, cfg = KinematicModel(task), KinematicConfig()
    R = task.rho2 * np.eye(km.n)
    z = km.z_of(ro.x)
    rows = {}
    _, rows["h and Jacobian, all M (T+1) states"] = _best(lambda: km.measure(z), a.repeat)
    acc = em.initial_map(km, ro.s, task.rho2, cfg.s_floor)
    lg = em.z_model(km, acc, cfg)
    sm0, rows["smoother, EKF pass (h per step)"] = _best(lambda: smooth(km, lg, ro.s, ro.a, R), a.repeat)
    sm1, rows["smoother, Gauss-Newton pass (h at the mean)"] = _best(lambda: smooth(km, lg, ro.s, ro.a, R, sm0.mean), a.repeat)
    _, rows["smoother, fixed linearisation (EM E-step)"] = _best(
        lambda: smooth(km, lg, ro.s, ro.a, R, sm1.z_lin, sm1.lin), a.repeat)
    acc2, rows["M-step"] = _best(lambda: em.mstep(sm1, ro.a, km.dt, km.nq, cfg.segments, cfg.prior_strength,
                                                  cfg.s_floor), a.repeat)
    _, rows["filter gains (build_filter)"] = _best(
        lambda: build_filter(km, acc2, em.z_model(km, acc2, cfg), sm1.mean.mean(0), task.rho2), a.repeat)
    _, rows["whole loop.learn (defaults)"] = _best(lambda: loop.learn(task, ro, None, cfg), a.repeat)
    print(f"| part ({a.task}, M = {ro.M}, T = {ro.T}) | CPU time (s) |\n|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {v:.3f} |")


if __name__ == "__main__":
    main()
