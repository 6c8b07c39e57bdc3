"""One run of LQR-FLM or DPSOC-EM with the kinematic estimator at the paper's scale, scored on 20
evaluation rollouts (seed ``10000 + seed``, as `soc-opt compare` does); one JSON line.

The second argument after the seed is a JSON table of ``[baseline.noise.kinematic]`` keys.  BLAS on
one thread.  The estimator uses the robot's kinematics (not masses, inertia or damping).

Usage:
    python examples/studies/noise_kinematic_run.py peg lqr-flm 3 '{"kl_model": "innovation"}'
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.kinematic.config import KinematicConfig
from soc_opt.tasks import load_task


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    task_name, method, seed = argv[0], argv[1], int(argv[2])
    kw = json.loads(argv[3]) if len(argv) > 3 else {}
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    task = load_task(task_name, overrides={"rho2": 0.1})
    cfg = load_run_config(task_name, paper=True, method=method)
    noise = NoiseConfig(estimator="kinematic", kinematic=KinematicConfig(**kw))
    cfg = cfg.replace(baseline=cfg.baseline.replace(noise=noise))
    t0 = time.perf_counter()
    st = run_experiment(task, method, cfg, seed, None)
    ro = task.rollouts(st.policy, 20, np.random.default_rng(10000 + seed))
    hist = [r.metrics.get("success_rate") for r in st.history if r.phase != "em"]
    print(json.dumps({"task": task_name, "method": method, "seed": seed, "kinematic": kw, **task.metrics(ro),
                      "wall": time.perf_counter() - t0, "metric_per_iteration": hist}), flush=True)


if __name__ == "__main__":
    main()
