"""Experiments on disk: run configurations, resumable runs, and forks for method comparisons.

:func:`run_experiment` runs one method (``lqr-flm``, ``dpsoc-em`` or ``ilqg``) on one task and
seed in a run directory (:mod:`soc_opt.rundir`: files, contract, lock, verified checkpoints).
Starting again with the same directory resumes from its checkpoint; because the RNG state and
the memory layout of every array are part of the checkpoint (:mod:`soc_opt.statefile`), the
resumed run ends with the same results as an uninterrupted one, also in a new process.
Reopening a finished run only reads the directory (no lock, nothing written).
With ``tensorboardX`` installed the directory also gets ``events.out.tfevents.*`` files with the
per-iteration scalars (:mod:`soc_opt.tblog`).

:func:`load_run_config` builds and validates the run configuration the way ``soc-opt run|compare``
does (the task's default file, a TOML file, the paper scale, single-key overrides), before
anything is simulated or written.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from . import algorithms
from . import ilqg as ilqg_mod
from .algorithms import DPSOCConfig, RunState
from .config import ConfigError, read_toml
from .progress import Progress, as_progress
from .rundir import CHECKPOINT, CheckpointError, RunDirectory, RunDirectoryError, differences, lock_directory
from .statefile import decode_state, encode_state
from .tblog import MISSING_MESSAGE, RunLog

if TYPE_CHECKING:
    from .tasks import Task

__all__ = ["EXPERIMENTS", "load_run_config", "RunDirectory", "RunDirectoryError", "CheckpointError",
           "run_experiment", "finished_run", "fork_state", "lock_directory", "headline_metric", "CHECKPOINT"]

#: Default run configurations of the built-in tasks: ``EXPERIMENTS / "<task>.toml"``.
EXPERIMENTS = Path(__file__).resolve().parent.parent / "problems" / "experiments"
#: Keys of ``load_run_config(overrides=...)`` that set a top-level field; the others set ``baseline``'s
#: (for ``method = "ilqg"``: ``iterations`` sets ``ilqg.iterations``).
_TOP_LEVEL = {"i_switch"}


def _read_run_config(path: Path, method: str) -> DPSOCConfig:
    """A run configuration file; an iLQG file in the old top-level layout gets a hint."""
    data = read_toml(path)
    if method == "ilqg":
        misplaced = sorted(set(data) & set(ilqg_mod.ILQGConfig.__dataclass_fields__)
                           - set(DPSOCConfig.__dataclass_fields__))
        if misplaced:
            raise ConfigError(f"{path}: iLQG settings {', '.join(map(repr, misplaced))} belong in an [ilqg] "
                              "table of the run configuration (docs/configuration.md)")
    try:
        return DPSOCConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e


def load_run_config(task_name: str, config_file: str | Path | None = None, *, paper: bool = False,
                    overrides: dict | None = None, method: str = "dpsoc-em") -> DPSOCConfig:
    """The validated run configuration of ``task_name`` for ``method``.

    Precedence: ``config_file`` if given, else the task's default ``EXPERIMENTS/<stem>.toml`` (if
    any), else the defaults; then the paper scale (``paper``: :data:`soc_opt.algorithms.PAPER`);
    then ``overrides`` (``i_switch`` or any ``baseline`` field; ``None`` values are skipped; for
    ``method = "ilqg"`` only ``iterations``, which sets ``ilqg.iterations``).  Every value is
    checked (types, finiteness, ranges) and then the method's own requirements
    (:meth:`DPSOCConfig.check_for`: ``i_switch`` matters for DPSOC-EM only).  Invalid values raise
    :class:`ConfigError` naming the key.
    """
    if config_file is not None:
        cfg = _read_run_config(Path(config_file), method)
    else:
        default = EXPERIMENTS / f"{Path(task_name).stem}.toml"
        cfg = _read_run_config(default, method) if default.is_file() else DPSOCConfig()
    set_values = {k: v for k, v in (overrides or {}).items() if v is not None}
    try:
        if method == "ilqg":
            cfg = _ilqg_overrides(cfg, set_values, paper)
        else:
            if paper:
                cfg = algorithms.with_paper_scale(cfg)
            base_changes = {k: v for k, v in set_values.items() if k not in _TOP_LEVEL}
            top_changes = {k: v for k, v in set_values.items() if k in _TOP_LEVEL}
            base = cfg.baseline.replace(**base_changes) if base_changes else cfg.baseline
            cfg = cfg.replace(baseline=base, **top_changes)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e)) from e
    cfg.check_for(method)
    return cfg


def _ilqg_overrides(cfg: DPSOCConfig, values: dict, paper: bool) -> DPSOCConfig:
    unused = sorted(k for k in values if k != "iterations") + (["paper"] if paper else [])
    if unused:
        raise ConfigError(f"--{unused[0].replace('_', '-')} does not apply to --method ilqg "
                          "(it sets the sample-based methods); iLQG reads the [ilqg] table and --iterations")
    if "iterations" in values:
        cfg = cfg.replace(ilqg=cfg.ilqg.replace(iterations=values["iterations"]))
    return cfg


def same_settings(old, new) -> bool:
    """Every setting recorded in ``old`` has the same value in ``new`` (keys only in ``new`` are
    ignored): no :func:`soc_opt.rundir.differences`.  Kept for ``soc_opt.sweep_runner``."""
    return not differences(old, new)


def fork_state(state: RunState) -> RunState:
    """A copy of a baseline state to continue with another method (same RNG state), made through
    the checkpoint format (:mod:`soc_opt.statefile`: same values and array layouts)."""
    return decode_state(encode_state(state))



def _contract(meta: dict) -> dict:
    """What of a ``config.json`` a resumed run must match: method, seed (not for the deterministic
    iLQG) and the configuration sections the method reads (:data:`~soc_opt.algorithms.RUN_SECTIONS`)."""
    method = meta.get("method")
    sections = algorithms.RUN_SECTIONS.get(method, tuple(meta.get("config", {})))
    out = {"method": method, "config": {k: v for k, v in meta.get("config", {}).items() if k in sections}}
    if method != "ilqg":
        out["seed"] = meta.get("seed")
    return out


def _task_record(task: Task, task_name: str | None) -> dict | None:
    """``task.json``: the task's provenance (``soc_opt.tasks.loading``) or its configuration."""
    rec = getattr(task, "provenance", None)
    if rec is None and getattr(task, "config", None) is not None and hasattr(task.config, "to_dict"):
        rec = {"name": task.name, "config": task.config.to_dict(), "model_files": {}}
    if rec is not None and task_name is not None:
        rec = {**rec, "task_argument": str(task_name)}
    return rec


def _check_inputs(task: Task, method: str, cfg: DPSOCConfig, seed: int) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {seed!r}")
    cfg.check_for(method)
    if method == "ilqg":
        ilqg_mod.check_task(task)


def _progress_line(method: str, seed: int, total: int, st, dt: float, elapsed: float) -> str:
    """One console line per iteration; iterations numbered from 0 as in ``metrics.csv``."""
    rec = st.history[-1]
    metrics = " ".join(f"{k}={v:.4g}" for k, v in rec.metrics.items())
    times = f"time {dt:.1f}s (total {elapsed:.0f}s)"
    where = f"iter {rec.iteration:2d} ({rec.iteration + 1}/{total})"
    if method == "ilqg":
        step = f"step {rec.alpha:g}" if rec.accepted else "no descent step"
        return f"[ilqg] {where} cost {np.mean(rec.cost):.6g}  {step}  mu {rec.mu:.1e}  {metrics}  {times}"
    em = [r for r in st.history if r.em is not None and r.iteration == rec.iteration]
    em_txt = ""
    if em:
        e = em[-1].em
        em_txt = (f" | EM: cost {np.mean(em[-1].cost):.4g}, surrogate {e.surrogate_old:.4g}->{e.surrogate_new:.4g},"
                  f" logp(Y) {e.loglik_old:.4g}->{e.loglik_new:.4g}")
    return (f"[{method} seed {seed}] {where} cost {np.mean(rec.cost):10.4g} ± {np.std(rec.cost):.3g}"
            f"  KL {rec.kl:.3g}/{rec.nu:.3g}  {metrics}  {times}{em_txt}")


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
    restart: bool = False,
    previous_checkpoint: bool = False,
):
    """Run one method on one task and seed, writing every iteration to ``out`` (resumable).

    ``method``: ``"lqr-flm"``, ``"dpsoc-em"`` (returns a :class:`~soc_opt.algorithms.RunState`) or
    ``"ilqg"`` (reads ``cfg.ilqg``; returns an :class:`~soc_opt.ilqg.ILQGState`).  Everything is
    validated before ``out`` is touched.  With ``out``, the run holds the directory's lock, checks
    its contract and resumes from its checkpoint (:mod:`soc_opt.rundir`); ``restart`` discards a
    previous run's files first; ``previous_checkpoint`` resumes from the checkpoint before the last
    (after a damaged one).  ``start_state`` (no checkpoint yet) starts from a given state, e.g. a
    fork of the baseline.  An exception during an iteration leaves the finished iterations saved;
    the run directory's path is added to it as a note.

    ``progress``: a :class:`soc_opt.progress.Progress` (a bar over the iterations, showing the
    mean cost, the KL and the task's headline metric, or plain lines), a callable printing
    one line per iteration, or ``None`` (silent).  ``bar_level``: nesting of the bar (compare).
    """
    _check_inputs(task, method, cfg, seed)
    cfg = algorithms.with_task_init_var(cfg, task)  # recorded in config.json: the value the run uses
    prog = as_progress(progress)
    if out is None:
        return _run(task, method, cfg, seed, None, start_state, on_iteration, prog, bar_level, None)
    if not restart and not previous_checkpoint:
        finished = finished_run(task, method, cfg, seed, out, task_name=task_name)
        if finished is not None:  # read only: no lock, no file written
            if prog:
                prog.message(f"{method} run in {out} already finished ({finished.iteration} iterations)")
            return finished
    rd, meta, done = RunDirectory(out), _meta(task, method, cfg, seed, task_name), _done(method, cfg)
    with rd.lock():
        if restart:
            rd.clear()
        rd.prepare(meta, _task_record(task, task_name), contract=_contract)
        saved = rd.load_checkpoint(previous=previous_checkpoint)
        state = start_state
        if saved is None:
            state = _initial_state(task, method, cfg, seed) if state is None else state
            rd.save_policy(state.iteration, state.policy)  # the policy sampled first (policies/iter_000.npz)
        else:
            state = saved
            if prog and done(state):
                prog.message(f"{method} run in {rd.path} already finished ({state.iteration} iterations)")
            elif prog:
                prog.message(f"resuming {method} in {rd.path}: {state.iteration} iterations done "
                             f"(next: iteration {state.iteration})")
        tb = RunLog.open(rd.path, purge_step=state.iteration if saved is not None else None)
        if tb is None and prog:
            prog.message(MISSING_MESSAGE)
        if tb is not None and saved is None and state is not None:  # a fresh run from a fork
            for rec in state.history:  # log the iterations it shares
                tb.iteration(rec)
        try:
            return _run(task, method, cfg, seed, rd, state, on_iteration, prog, bar_level, tb)
        except Exception as e:
            try:
                done = rd.load_checkpoint()
            except CheckpointError:
                done = None
            n = 0 if done is None else done.iteration
            e.add_note(f"run directory {str(rd.path)!r} keeps {n} finished iteration{'s' if n != 1 else ''}; "
                       "running the same command again resumes after them")
            raise
        finally:
            if tb is not None:
                tb.close()


def _meta(task, method: str, cfg: DPSOCConfig, seed: int, task_name) -> dict:
    """The content of ``config.json``."""
    return {"task": str(task_name or task.name), "method": method, "seed": seed, "config": cfg.to_dict()}


def _done(method: str, cfg: DPSOCConfig) -> Callable[[object], bool]:
    total = cfg.ilqg.iterations if method == "ilqg" else cfg.baseline.iterations
    return lambda st: st.iteration >= total or getattr(st, "status", "running") != "running"


def finished_run(task: Task, method: str, cfg: DPSOCConfig, seed: int, out: str | Path, *,
                 task_name: str | None = None):
    """The final state of the finished run of this method, task, seed and configuration in ``out``,
    or None (no such directory, not finished, or a damaged last checkpoint).  Reads only: no lock,
    nothing written (works on a read-only file system); a different run in ``out`` raises
    :class:`RunDirectoryError` as :func:`run_experiment` would."""
    if not Path(out).is_dir():
        return None
    cfg = algorithms.with_task_init_var(cfg, task)  # compared as run_experiment records it
    return RunDirectory(out).finished(_meta(task, method, cfg, seed, task_name), _task_record(task, task_name),
                                      _contract, _done(method, cfg))


def _initial_state(task: Task, method: str, cfg: DPSOCConfig, seed: int):
    """The state a fresh run starts from (what ``run_algorithm`` / ``run_ilqg`` build)."""
    if method == "ilqg":
        return ilqg_mod.initial_ilqg_state(task, cfg.ilqg)
    return algorithms.initial_state(task, cfg.baseline, seed)


def _run(task, method, cfg, seed, rd: RunDirectory | None, state, user_callback, prog, bar_level, tb):
    total = cfg.ilqg.iterations if method == "ilqg" else cfg.baseline.iterations
    t_start = t_last = time.perf_counter()
    logged = len(state.history) if state is not None else 0
    desc = "ilqg" if method == "ilqg" else f"{method} seed {seed}"
    bar = prog.bar(total, desc, initial=state.iteration if state is not None else 0, level=bar_level) if prog else None

    def on_iteration(st):
        nonlocal t_last, logged
        if rd is not None:
            rd.save(st)
        if tb is not None:
            for rec in st.history[logged:]:
                tb.iteration(rec)
            logged = len(st.history)
        if user_callback is not None:
            user_callback(st)
        if bar is not None:
            now = time.perf_counter()
            rec = st.history[-1]
            shown = {"mu": float(rec.mu)} if method == "ilqg" else {"KL": float(rec.kl)}
            bar.advance(_progress_line(method, seed, total, st, now - t_last, now - t_start),
                        cost=float(np.mean(rec.cost)), **shown, **headline_metric(rec.metrics))
            t_last = now

    try:
        if method == "ilqg":
            return ilqg_mod.run_ilqg(task, cfg.ilqg, state=state, on_iteration=on_iteration)
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
