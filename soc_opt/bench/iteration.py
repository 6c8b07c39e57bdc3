"""Wall time per iteration of each method at the paper's scale, split into phases.

Runs LQR-FLM and DPSOC-EM on a task with the paper's settings (:data:`soc_opt.methods.config.PAPER`:
14 iterations x 20 samples, EM phase after iteration 4) and reports, per phase, the median and
the range over the iterations: rollouts, fitting (mixture prior refit + local model), LQG step,
and the wall time of the whole iteration (measured between two ``on_iteration`` calls, so it
includes the cost expansion and the step adaptation), and for DPSOC-EM's EM recursions the
augmented fit, E-step and M-step, and the wall time of the outer iteration that holds the EM
phase (EM recursions, then the LQR-FLM step from the EM policy).  The first iteration (prior fitted from scratch) is reported
separately from the median over the others (warm-started prior).
"""

from __future__ import annotations

import time

import numpy as np


def _timed_run(task, method: str, cfg, seed: int):
    from ..methods import registry

    stamps = [time.perf_counter()]
    state = registry.run(task, method, cfg, seed=seed, on_iteration=lambda _s: stamps.append(time.perf_counter()))
    return state, np.diff(stamps)


def _row(method: str, phase: str, vals) -> dict:
    vals = np.asarray(vals, float)
    later = vals[1:] if vals.size > 1 else vals
    return {"method": method, "phase": phase, "median_s": float(np.median(later)),
            "min_s": float(later.min()), "max_s": float(later.max()), "first_s": float(vals[0]), "n": int(vals.size)}


def run(task: str = "peg", seed: int = 0, iterations: int | None = None, samples: int | None = None) -> list[dict]:
    """Rows ``{method, phase, median_s, min_s, max_s, first_s, n}``: ``median/min/max`` over
    iterations 2..n, ``first_s`` the first iteration.  ``iterations``/``samples`` override the
    paper's (for a quick check)."""
    from ..experiments.run import load_run_config
    from ..linalg import single_thread_blas
    from ..methods.config import PAPER
    from ..tasks import load_task

    t = load_task(task)
    i_switch = PAPER.i_switch if iterations is None else min(PAPER.i_switch, iterations - 1)
    cfg = load_run_config(task, paper=True, overrides={"iterations": iterations, "samples": samples,
                                                       "i_switch": i_switch})
    rows = []
    with single_thread_blas():  # as `soc-opt run` does
        for method in ("lqr-flm", "dpsoc-em"):
            state, wall = _timed_run(t, method, cfg, seed)
            base = [r for r in state.history if r.phase == "baseline"]
            label = f"{method} ({task}, {cfg.baseline.iterations} it x {cfg.baseline.samples} samples)"
            em = [r for r in state.history if r.em is not None]
            if not em:  # the baseline: no EM phase
                for phase in ("rollouts", "fit", "lqg"):
                    rows.append(_row(label, phase, [r.timings.get(phase, np.nan) for r in base]))
                rows.append(_row(label, "iteration (wall)", wall))
                continue
            if em:
                for phase, vals in (("rollouts", [r.timings["rollouts"] for r in em]),
                                    ("fit augmented", [r.em.time_fit_augmented for r in em]),
                                    ("E-step", [r.em.time_estep for r in em]),
                                    ("M-step", [r.em.time_mstep for r in em])):
                    rows.append(_row(label, f"EM recursion: {phase}", vals))
                rows.append(_row(label, "iteration with the EM phase (wall)", [wall[cfg.i_switch]]))
            rows.append({"method": label, "phase": "whole run", "median_s": float(wall.sum()), "min_s": None,
                         "max_s": None, "first_s": None, "n": int(wall.size)})
    return rows


#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"task": "linear2d", "iterations": 2, "samples": 4}


if __name__ == "__main__":
    for r in run():
        print(r)
