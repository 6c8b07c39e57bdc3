"""One trial of a sweep (docs/sweeps.md): an ordinary run directory plus the sweep's records, run or resumed
by :func:`run_trial`, which :mod:`soc_opt.sweeps.runner` calls in a worker (a plain function: nothing here
imports Ray)."""

from __future__ import annotations

import math
import os
import socket
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

from .. import files
from ..methods.state import RunState
from .spec import ERROR, PROGRESS, RESULT, TRIAL, TrialDiverged, TrialSpec, read_json, write_json

__all__ = ["run_trial", "check_finite", "TRIAL_FILES"]


def check_finite(state: RunState) -> None:
    """Raise :class:`TrialDiverged` when the last iteration's sampled costs are not all finite."""
    rec = state.history[-1] if state.history else None
    if rec is not None and not np.all(np.isfinite(np.asarray(rec.cost, float))):
        raise TrialDiverged(f"diverging simulation: non-finite sampled cost at iteration {rec.iteration + 1} "
                            f"({rec.phase} phase)")


def _result(spec: TrialSpec, task, state: RunState, trial_dir: Path, anchor: Path) -> dict:
    from ..experiments.compare import evaluate_policy as _evaluate
    from ..experiments.compare import final_vs_last as _final_vs_last
    from ..experiments.compare import spreads as _spreads
    from ..methods.registry import get_method
    from ..noise.aware import mean_action

    policy = get_method(spec.method).final_policy(spec.config, state)
    ro = _evaluate(task, policy, spec.eval_samples, spec.seed, spec.config.baseline.workers)
    ro_mean = _evaluate(task, mean_action(policy), spec.eval_samples, spec.seed, spec.config.baseline.workers)
    from ..experiments.rundir import npz_bytes

    files.write_bytes(trial_dir / "final_eval.npz", npz_bytes(**ro.to_dict()), anchor=anchor)
    files.write_bytes(trial_dir / "final_eval_mean_action.npz", npz_bytes(**ro_mean.to_dict()), anchor=anchor)
    final = _spreads(task, ro)
    if not math.isfinite(final["cost"]):
        raise TrialDiverged("diverging simulation: non-finite cost of the final policy")
    base = [r for r in state.history if r.phase == "baseline"]
    return {
        "final_cost": final["cost"],
        "state_spread": final["state_spread"],
        "action_spread": final["action_spread"],
        "metrics": {k: float(v) for k, v in task.metrics(ro).items()},
        "final_cost_mean_action": float(np.mean(task.true_cost(ro_mean).sum(-1))),
        "metrics_mean_action": {k: float(v) for k, v in task.metrics(ro_mean).items()},
        "rejected_steps": int(sum(1 for r in state.history if r.extra.get("accepted") == 0.0)),
        **{f"final_vs_last_{k}": v for k, v in
           _final_vs_last(task, state.history, ro, spec.config.baseline.acceptance).items()},
        "best_cost": float(state.best[0]) if state.best else float("nan"),
        "best_iteration": int(state.best[2]) if state.best else -1,
        "iterations": state.iteration,
        "cost_per_iteration": [float(np.mean(r.cost)) for r in base],
    }


#: Files a sweep puts in a trial's run directory besides the run's own.
TRIAL_FILES = (TRIAL, PROGRESS, ERROR, RESULT, "final_eval.npz", "final_eval_mean_action.npz")


def run_trial(spec: TrialSpec, trial_dir: str | Path,
              on_iteration: Callable[[str, RunState, Path], None] | None = None, anchor: str | Path | None = None) -> dict:
    """Run (or resume) one trial in ``trial_dir``; return its status record.

    An ordinary run directory (soc_opt.experiments.run) plus ``trial.json`` (the spec),
    ``progress.json`` (state, attempt, iteration, pid), ``final_eval.npz`` and ``result.json``
    (written last: its presence marks the trial finished), or ``error.txt`` (the traceback) when
    the trial failed.  Exceptions of the trial (including :class:`TrialDiverged`) are recorded,
    not raised.  ``on_iteration(trial_id, state, trial_dir)`` runs after each checkpoint.  ``anchor``: the
    sweep's directory, below which no link is followed (:mod:`soc_opt.files`; default ``trial_dir``).
    """
    from ..experiments.run import run_experiment
    from ..tasks import load_task

    d = Path(trial_dir)
    anchor = d if anchor is None else Path(anchor)
    files.make_dirs(d, anchor=anchor)
    files.remove(d / ERROR, anchor=anchor)
    prev = read_json(d / PROGRESS)
    prev_attempt = prev.get("attempt", 0) if isinstance(prev, dict) else 0
    attempt = (prev_attempt if type(prev_attempt) is int and 0 <= prev_attempt < 10**6 else 0) + 1
    t0 = time.time()
    prog = {"state": "running", "attempt": attempt, "pid": os.getpid(), "host": socket.gethostname(),
            "iteration": None, "iterations": spec.config.baseline.iterations, "started": t0}
    write_json(d / PROGRESS, prog, anchor)
    ran = [0]

    def cb(st: RunState):
        ran[0] += 1
        check_finite(st)
        write_json(d / PROGRESS, {**prog, "iteration": st.iteration}, anchor)
        if on_iteration is not None:
            on_iteration(spec.id, st, d)

    try:
        task = load_task(spec.task, overrides=spec.task_overrides, gym_modules=spec.gym_modules)
        state = run_experiment(task, spec.method, spec.config, spec.seed, d, task_name=spec.task_label,
                               on_iteration=cb, anchor=anchor, owned=TRIAL_FILES)
        res = {"trial": spec.id, "status": "done", **_result(spec, task, state, d, anchor),
               "attempt": attempt, "resumed_from": state.iteration - ran[0], "wall_time": time.time() - t0}
        write_json(d / RESULT, res, anchor)
        write_json(d / PROGRESS, {**prog, "state": "done", "iteration": state.iteration}, anchor)
        return res
    except Exception as e:  # noqa: BLE001 - a failed trial is recorded, the sweep goes on
        msg = f"{type(e).__name__}: {e}"
        files.write_text(d / ERROR, f"{spec.id} (attempt {attempt})\n{traceback.format_exc()}", anchor=anchor)
        write_json(d / PROGRESS, {**prog, "state": "failed", "error": msg}, anchor)
        return {"trial": spec.id, "status": "failed", "error": msg, "attempt": attempt,
                "wall_time": time.time() - t0}
