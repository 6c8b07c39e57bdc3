"""Experiments on disk: run directories, checkpoints, resume, and method comparisons.

A run directory holds

- ``config.toml``-equivalent ``config.json`` (the configuration used, with task, method, seed);
- ``metrics.csv`` and ``metrics.json``: one row per sampling round (``IterationRecord.summary``);
- ``policies/iter_XXX.npz``: the policy after each iteration (``K, k, cov``);
- ``samples/iter_XXX.npz``: the rollouts of each iteration (``x, s, a, cost, y``);
- ``checkpoint.pkl``: the full :class:`~soc_opt.algorithms.RunState` after the last finished
  iteration.  Starting again with the same directory resumes from it; because the RNG state
  is part of the checkpoint, the resumed run ends with the same results as an uninterrupted one.

:func:`load_run_config` builds the run configuration the way ``soc-opt run|compare`` does (the
task's default file, a TOML file, the paper scale, single-key overrides).
"""

from __future__ import annotations

import csv
import json
import os
import pickle
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from . import algorithms
from .algorithms import DPSOCConfig, RunState
from .config import ConfigError
from .progress import Progress, as_progress

if TYPE_CHECKING:
    from .tasks import Task

__all__ = ["EXPERIMENTS", "load_run_config", "RunDirectory", "run_experiment", "fork_state", "headline_metric"]

CHECKPOINT = "checkpoint.pkl"
#: Default run configurations of the built-in tasks: ``EXPERIMENTS / "<task>.toml"``.
EXPERIMENTS = Path(__file__).resolve().parent.parent / "problems" / "experiments"
#: Keys of ``load_run_config(overrides=...)`` that set a top-level field; the others set ``baseline``'s.
_TOP_LEVEL = {"i_switch"}


def load_run_config(task_name: str, config_file: str | Path | None = None, *, paper: bool = False,
                    overrides: dict | None = None, method: str = "dpsoc-em") -> DPSOCConfig:
    """The run configuration of ``task_name``: default file, then ``config_file``, then the rest.

    Precedence: ``config_file`` if given, else the task's default ``EXPERIMENTS/<stem>.toml`` (if
    any), else the defaults; then the paper scale (``paper``: :data:`soc_opt.algorithms.PAPER`);
    then ``overrides`` (``i_switch`` or any ``baseline`` field; ``None`` values are skipped).
    For ``method = "lqr-flm"`` the switch point is unused; it is clamped into the run so that a
    short baseline run is not rejected for it.  Invalid values raise :class:`ConfigError`.
    """
    if config_file is not None:
        cfg = DPSOCConfig.from_toml(config_file)
    else:
        default = EXPERIMENTS / f"{Path(task_name).stem}.toml"
        cfg = DPSOCConfig.from_toml(default) if default.is_file() else DPSOCConfig()
    set_values = {k: v for k, v in (overrides or {}).items() if v is not None}
    try:
        if paper:
            cfg = algorithms.with_paper_scale(cfg)
        base_changes = {k: v for k, v in set_values.items() if k not in _TOP_LEVEL}
        top_changes = {k: v for k, v in set_values.items() if k in _TOP_LEVEL}
        base = cfg.baseline.replace(**base_changes) if base_changes else cfg.baseline
        if method == "lqr-flm":
            top_changes["i_switch"] = min(top_changes.get("i_switch", cfg.i_switch), base.iterations - 1)
        return cfg.replace(baseline=base, **top_changes)
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e)) from e


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".")
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def _same_settings(old, new) -> bool:
    """Every setting recorded in ``old`` has the same value in ``new``.

    Keys only in ``new`` are options added by a later version of soc_opt after the run was
    started; they do not make the run a different one.
    """
    if isinstance(old, dict) and isinstance(new, dict):
        return all(k in new and _same_settings(v, new[k]) for k, v in old.items())
    return old == new


@dataclass(frozen=True)
class RunDirectory:
    """Files of one run (see module docstring)."""

    path: Path

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))

    def prepare(self, meta: dict) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / "policies").mkdir(exist_ok=True)
        (self.path / "samples").mkdir(exist_ok=True)
        meta_path = self.path / "config.json"
        if meta_path.exists():
            old = json.loads(meta_path.read_text())
            if not _same_settings(old, json.loads(json.dumps(meta))):
                raise ValueError(
                    f"run directory {str(self.path)!r} holds a run with a different configuration; "
                    "use another --out or delete it"
                )
        else:
            meta_path.write_text(json.dumps(meta, indent=2, sort_keys=True))

    def load_checkpoint(self) -> RunState | None:
        p = self.path / CHECKPOINT
        if not p.exists():
            return None
        with open(p, "rb") as f:
            return pickle.load(f)

    def save(self, state: RunState) -> None:
        """Write the iteration's files, then the checkpoint (atomically, last)."""
        it = state.iteration
        np.savez_compressed(self.path / "policies" / f"iter_{it:03d}.npz", **state.policy.to_dict())
        if state.last_rollouts is not None:
            np.savez_compressed(self.path / "samples" / f"iter_{it - 1:03d}.npz", **state.last_rollouts.to_dict())
        rows = [r.summary() for r in state.history]
        (self.path / "metrics.json").write_text(json.dumps([{k: _jsonable(v) for k, v in r.items()} for r in rows], indent=1))
        keys = []
        for r in rows:
            keys += [k for k in r if k not in keys]
        with open(self.path / "metrics.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows(rows)
        costs = np.array([r.cost for r in state.history], dtype=object)
        np.savez_compressed(
            self.path / "costs.npz",
            iteration=np.array([r.iteration for r in state.history]),
            phase=np.array([r.phase for r in state.history]),
            **{f"cost_{i:03d}": np.asarray(c, float) for i, c in enumerate(costs)},
        )
        if state.best is not None:
            np.savez_compressed(self.path / "best_policy.npz", **state.best.policy.to_dict(),
                                mean_cost=state.best.mean_cost, iteration=state.best.iteration)
        _atomic_write_bytes(self.path / CHECKPOINT, pickle.dumps(state))


def fork_state(state: RunState) -> RunState:
    """A copy of a baseline state to continue with another method (same RNG state)."""
    return pickle.loads(pickle.dumps(state))


def run_experiment(
    task: Task,
    method: str,
    cfg: DPSOCConfig,
    seed: int,
    out: str | Path | None,
    *,
    task_name: str | None = None,
    progress: Progress | Callable[[str], None] | None = None,
    start_state: RunState | None = None,
    on_iteration: Callable[[RunState], None] | None = None,
    bar_level: int = 0,
) -> RunState:
    """Run one method on one task and seed, writing every iteration to ``out`` (resumable).

    ``progress``: a :class:`soc_opt.progress.Progress` (a bar over the iterations, showing the
    mean cost, the KL and the task's headline metric, or plain lines), a callable printing
    one line per iteration, or ``None`` (silent).  ``bar_level``: nesting of the bar (compare).
    """
    prog = as_progress(progress)
    rd = RunDirectory(out) if out is not None else None
    state = start_state
    if rd is not None:
        rd.prepare({"task": task_name or task.name, "method": method, "seed": seed, "config": cfg.to_dict()})
        saved = rd.load_checkpoint()
        if saved is not None:
            state = saved
            if prog:
                prog.message(f"resuming {method} from iteration {state.iteration} in {rd.path}")
    if state is None:
        state = algorithms.initial_state(task, cfg.baseline, seed)
    t_last = [time.perf_counter()]
    bar = prog.bar(cfg.baseline.iterations, f"{method} seed {seed}", initial=state.iteration,
                   level=bar_level) if prog else None

    user_callback = on_iteration

    def on_iteration(st: RunState):
        if rd is not None:
            rd.save(st)
        if user_callback is not None:
            user_callback(st)
        if bar is not None:
            rec = st.history[-1]
            dt = time.perf_counter() - t_last[0]
            t_last[0] = time.perf_counter()
            metrics = " ".join(f"{k}={v:.4g}" for k, v in rec.metrics.items())
            em = [r for r in st.history if r.em is not None and r.iteration == rec.iteration]
            em_txt = ""
            if em:
                e = em[-1].em
                em_txt = (f" | EM: cost {np.mean(em[-1].cost):.4g}, surrogate {e.surrogate_old:.4g}->{e.surrogate_new:.4g},"
                          f" logp(Y) {e.loglik_old:.4g}->{e.loglik_new:.4g}")
            line = (
                f"[{method} seed {seed}] iter {rec.iteration + 1:2d}/{cfg.baseline.iterations}"
                f" cost {np.mean(rec.cost):10.4g} ± {np.std(rec.cost):.3g}  KL {rec.kl:.3g}/{rec.nu:.3g}"
                f"  {metrics}  {dt:.1f}s{em_txt}"
            )
            bar.advance(line, cost=float(np.mean(rec.cost)), KL=float(rec.kl), **headline_metric(rec.metrics))

    try:
        return algorithms.run_algorithm(task, method, cfg, seed=seed, state=state, on_iteration=on_iteration)
    finally:
        if bar is not None:
            bar.close()


def headline_metric(metrics: dict) -> dict:
    """The task's first metric other than the cost (e.g. ``min_distance``, ``min_hinge``,
    ``return``) as ``{name: value}``, or ``{}``: what progress bars show next to the cost."""
    for k, v in metrics.items():
        if k != "cost":
            return {k: float(v)}
    return {}
