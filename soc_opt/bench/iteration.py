"""Wall time per iteration of each method, split into phases (issue: DPSOC-EM end to end).

Runs a short DPSOC-EM (EM phase after the first iteration) on a task at paper scale
(20 samples) and reports the mean time of each phase over the baseline iterations and the EM
recursions: rollouts, fitting, E-step, M-step, LQG step.
"""

from __future__ import annotations

import time

import numpy as np


def run(task: str = "peg", iterations: int = 3, samples: int = 20, seed: int = 0) -> list[dict]:
    from ..algorithms import run_algorithm
    from ..experiment import load_run_config
    from ..tasks import load_task

    t = load_task(task)
    cfg = load_run_config(task, overrides={"iterations": iterations, "samples": samples, "i_switch": 1})
    t0 = time.perf_counter()
    state = run_algorithm(t, "dpsoc-em", cfg, seed=seed)
    total = time.perf_counter() - t0
    rows = []
    base = [r for r in state.history if r.phase == "baseline"]
    em = [r.em for r in state.history if r.em is not None]
    em_rollouts = [r.timings["rollouts"] for r in state.history if r.em is not None]
    for phase in ("rollouts", "fit", "lqg"):
        rows.append({"method": "lqr-flm iteration", "phase": phase,
                     "mean_s": float(np.mean([r.timings.get(phase, np.nan) for r in base]))})
    rows.append({"method": "lqr-flm iteration", "phase": "total",
                 "mean_s": float(np.mean([sum(r.timings.values()) for r in base]))})
    for phase, vals in (("rollouts", em_rollouts), ("fit augmented", [d.time_fit_augmented for d in em]),
                        ("E-step", [d.time_estep for d in em]), ("M-step", [d.time_mstep for d in em])):
        rows.append({"method": "EM recursion", "phase": phase, "mean_s": float(np.mean(vals))})
    rows.append({"method": f"whole run ({task}, {iterations} it, {samples} samples)", "phase": "total",
                 "mean_s": total})
    return rows


if __name__ == "__main__":
    for r in run():
        print(r)
