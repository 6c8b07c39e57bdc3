"""Experiments on disk: run configurations, resumable runs, and forks for method comparisons.

:func:`run_experiment` runs one method (``lqr-flm``, ``dpsoc-em`` or ``ilqg``) on one task and
seed in a run directory (:mod:`soc_opt.experiments.rundir`: files, contract, lock, verified checkpoints).
Starting again with the same directory resumes from its checkpoint; because the RNG state and
the memory layout of every array are part of the checkpoint (:mod:`soc_opt.experiments.statefile`), the
resumed run ends with the same results as an uninterrupted one, also in a new process.
Reopening a finished run only reads the directory (no lock, nothing written).
With ``tensorboardX`` installed the directory also gets ``events.out.tfevents.*`` files with the
per-iteration scalars (:mod:`soc_opt.experiments.tblog`).

:func:`load_run_config` builds and validates the run configuration the way ``soc-opt run|compare``
does (the task's default file, a TOML file, the paper scale, single-key overrides), before
anything is simulated or written.
"""

from __future__ import annotations

import json
import os
import stat
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from .. import files
from ..config import MAX_INT, ConfigError, read_toml, show
from ..errors import resumable
from ..methods.base import apply_overrides, run_method
from ..methods.config import DPSOCConfig, check_scale, with_task_init_var
from ..methods.state import RunState
from ..plugins import METHODS
from ..tasks.loading import problems_dir
from .environment import environment, environment_differences
from .progress import Progress, as_progress
from .rundir import CHECKPOINT, CheckpointError, RunDirectory, RunDirectoryError, differences, lock_directory
from .statefile import decode_state, encode_state
from .tblog import MISSING_MESSAGE, RunLog

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["EXPERIMENTS", "load_run_config", "RunDirectory", "RunDirectoryError", "CheckpointError",
           "run_experiment", "finished_run", "fork_state", "lock_directory", "headline_metric", "CHECKPOINT"]

#: Default run configurations of the built-in tasks: ``EXPERIMENTS / "<task>.toml"``.
EXPERIMENTS = problems_dir() / "experiments"


def get_method(name: str):
    """The registered method ``name`` (:data:`soc_opt.plugins.METHODS`); ``ConfigError`` naming the known ones."""
    return METHODS.lookup(name)


def _read_run_config(path: Path, method: str) -> DPSOCConfig:
    """A run configuration file; an iLQG file in the old top-level layout gets a hint."""
    data = read_toml(path)
    get_method(method).check_file(data, path)
    try:
        return DPSOCConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e


def load_run_config(task_name: str, config_file: str | Path | None = None, *, paper: bool = False,
                    overrides: dict | None = None, method: str = "dpsoc-em") -> DPSOCConfig:
    """The validated run configuration of ``task_name`` for ``method``.

    Precedence: ``config_file`` if given, else the task's default ``EXPERIMENTS/<stem>.toml`` (if
    any), else the defaults; then the paper scale (``paper``: :data:`soc_opt.methods.config.PAPER`)
    and ``overrides`` as the method applies them (``Method.apply_overrides``: for the sample-based
    methods ``i_switch`` or any ``baseline`` field; for iLQG only ``iterations``, which sets
    ``ilqg.iterations``; ``None`` values are skipped).  Every value is checked (types, finiteness,
    ranges) and then the method's own requirements (``Method.check_config``: ``i_switch`` matters
    for DPSOC-EM only).  Invalid values raise :class:`ConfigError` naming the key.
    """
    meth = get_method(method)
    if config_file is not None:
        cfg = _read_run_config(Path(config_file), method)
    else:
        default = EXPERIMENTS / f"{Path(task_name).stem}.toml"
        cfg = _read_run_config(default, method) if default.is_file() else DPSOCConfig()
    set_values = {k: v for k, v in (overrides or {}).items() if v is not None}
    try:
        cfg = apply_overrides(meth, cfg, set_values, paper)  # a flag the method does not read: refused
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e)) from e
    meth.check_config(cfg)
    return cfg


def same_settings(old, new) -> bool:
    """Every setting recorded in ``old`` has the same value in ``new`` (keys only in ``new`` are
    ignored): no :func:`soc_opt.experiments.rundir.differences`.  Kept for ``soc_opt.sweeps.runner``."""
    return not differences(old, new)


def fork_state(state: RunState) -> RunState:
    """A copy of a baseline state to continue with another method (same RNG state), made through
    the checkpoint format (:mod:`soc_opt.experiments.statefile`: same values and array layouts)."""
    return decode_state(encode_state(state))



def _contract(meta: dict) -> dict:
    """What of a ``config.json`` a resumed run must match: method, seed (not for the deterministic
    iLQG) and the configuration sections the method reads (``Method.sections``)."""
    method = meta.get("method")
    meth = METHODS.get(method)
    sections = meth.sections if meth is not None else tuple(meta.get("config", {}))
    out = {"method": method, "config": {k: v for k, v in meta.get("config", {}).items() if k in sections}}
    if meth is None or meth.seeded:
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
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_INT:
        raise ConfigError(f"seed must be an integer in [0, {MAX_INT}], got {show(seed)}")
    meth = get_method(method)
    meth.check_config(cfg)
    meth.check_task(task, cfg)
    check_scale(cfg, task)


def _progress_line(method: str, seed: int, total: int, st, dt: float, elapsed: float) -> str:
    """One console line per iteration; iterations numbered from 0 as in ``metrics.csv``."""
    rec = st.history[-1]
    metrics = " ".join(f"{k}={v:.4g}" for k, v in rec.metrics.items())
    times = f"time {dt:.1f}s (total {elapsed:.0f}s)"
    where = f"iter {rec.iteration:2d} ({rec.iteration + 1}/{total})"
    return get_method(method).progress_line(seed, where, st, metrics, times)


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
    anchor: str | Path | None = None,
    owned: tuple[str, ...] = (),
    finish: Callable[[object, RunLog | None], None] | None = None,
):
    """Run one method on one task and seed, writing every iteration to ``out`` (resumable).

    ``method``: a name in :data:`soc_opt.methods.registry.METHODS` (``"lqr-flm"``, ``"dpsoc-em"``:
    returns a :class:`~soc_opt.methods.state.RunState`; ``"ilqg"``: reads ``cfg.ilqg``, returns an
    :class:`~soc_opt.methods.ilqg.ILQGState`).  Everything is
    validated before ``out`` is touched.  With ``out``, the run holds the directory's lock, checks
    its contract and resumes from its checkpoint (:mod:`soc_opt.experiments.rundir`); ``restart`` discards a
    previous run's files first; ``previous_checkpoint`` resumes from the checkpoint before the last
    (after a damaged one).  ``out`` must be new, empty or a run directory (:meth:`RunDirectory.check_owned`;
    ``owned``: other names the caller put there, e.g. a sweep's ``trial.json``); ``anchor``: the folder above
    ``out`` the caller owns (a compare or sweep directory), below which no link is followed
    (:mod:`soc_opt.files`).  ``start_state`` (no checkpoint yet) starts from a given state, e.g. a
    fork of the baseline.  An exception during an iteration leaves the finished iterations saved;
    the run directory's path is added to it as a note.

    ``finish(state, log)``: the run's final phase (``soc-opt run``: figures, filmstrip, ``final_policy.npz``,
    ``final_eval*.npz``), called with the final state and the directory's TensorBoard log (or ``None``) while
    the lock is still held.  It must write its files from ``state`` alone, deterministically: a run counts as
    finished (:func:`finished_run` with ``final=True``) only once ``finish`` has returned and ``final.json``
    records it; a kill, Ctrl-C or failed write before that leaves the run to be finished by the same command,
    which runs ``finish`` again from the checkpoint and so writes the same files.

    ``progress``: a :class:`soc_opt.experiments.progress.Progress` (a bar over the iterations, showing the
    mean cost, the KL and the task's headline metric, or plain lines), a callable printing
    one line per iteration, or ``None`` (silent).  ``bar_level``: nesting of the bar (compare).
    """
    _check_inputs(task, method, cfg, seed)
    cfg = with_task_init_var(cfg, task)  # recorded in config.json: the value the run uses
    prog = as_progress(progress)
    if out is None:
        return _run(task, method, cfg, seed, None, start_state, on_iteration, prog, bar_level, None)
    if not restart and not previous_checkpoint:
        finished = finished_run(task, method, cfg, seed, out, task_name=task_name, anchor=anchor,
                                final=finish is not None)
        if finished is not None:  # read only: no lock, no file written
            if prog:
                prog.message(f"{method} run in {out} already finished ({finished.iteration} iterations)")
            return finished
    rd, meta, done = RunDirectory(out, anchor=anchor), _meta(task, method, cfg, seed, task_name), _done(method, cfg)
    rd.check_owned(owned)  # before the lock file is created
    with rd.lock():
        rd.check_owned(owned)
        if restart:
            rd.clear()
        rd.prepare(meta, _task_record(task, task_name), contract=_contract)
        saved = rd.load_checkpoint(previous=previous_checkpoint)
        if saved is not None:
            check_state(saved, task, method, cfg, str(rd.path / ("checkpoint.prev.npz" if previous_checkpoint else CHECKPOINT)))
        state = start_state
        if saved is None:
            state = _initial_state(task, method, cfg, seed) if state is None else state
            rd.save_policy(state.iteration, state.policy)  # the policy sampled first (policies/iter_000.npz)
        else:
            state = saved
            if prog and done(state):
                prog.message(f"{method} run in {rd.path} already finished ({state.iteration} iterations)"
                             + ("; writing its final files" if finish is not None else ""))
            elif prog:
                prog.message(f"resuming {method} in {rd.path}: {state.iteration} iterations done "
                             f"(next: iteration {state.iteration})")
            changed = environment_differences(rd.recorded_meta().get("environment"), meta["environment"])
            if changed and prog and not done(state):
                prog.message("note: this run was started in another environment (" + "; ".join(changed[:6])
                             + "): the iterations from here on may differ in the last digits from the "
                             "same run continued there (docs/reproducibility.md)")
        tb = RunLog.open(rd.path, purge_step=state.iteration if saved is not None else None, anchor=rd.anchor)
        if tb is None and prog:
            prog.message(MISSING_MESSAGE)
        if tb is not None and saved is None and state is not None:  # a fresh run from a fork
            for rec in state.history:  # log the iterations it shares
                tb.iteration(rec)
        try:
            try:
                state = _run(task, method, cfg, seed, rd, state, on_iteration, prog, bar_level, tb)
            except Exception as e:
                try:
                    done = rd.load_checkpoint()
                except CheckpointError:
                    done = None
                n = 0 if done is None else done.iteration
                kept = f"run directory {str(rd.path)!r} keeps {n} finished iteration{'s' if n != 1 else ''}"
                e.add_note(f"{kept}; running the same command again resumes after them" if resumable(e) else
                           f"{kept}; the error comes from the computation, so running the same command again "
                           "would repeat it (a resumed run is bit-identical, docs/reproducibility.md)")
                raise
            if finish is not None:
                _final_phase(rd, state, finish, tb)
            return state
        finally:
            if tb is not None:
                tb.close()


#: Written last by a run's final phase (``soc-opt run``): its iteration count and the final files it wrote.
FINAL_MARK = "final.json"
#: The files a final phase may write (each method writes some of them).
FINAL_FILES = ("cost_per_iteration.png", "ee_trajectories.png", "filmstrip.png", "policy.npz", "final_policy.npz",
               "final_eval.npz", "final_eval_mean_action.npz", "final_eval_filtered.npz",
               "final_eval_filtered_mean_action.npz", "final_eval_open_loop.npz")


def _final_phase(rd: RunDirectory, state, finish, tb) -> None:
    """``finish(state, tb)`` between removing and writing ``final.json`` (see :func:`run_experiment`)."""
    files.remove(rd.path / FINAL_MARK, anchor=rd.anchor)
    try:
        finish(state, tb)
    except Exception as e:
        e.add_note(f"run directory {str(rd.path)!r} keeps its {state.iteration} iterations; its final files are not "
                   "all written: running the same command again writes them")
        raise
    written = [n for n in FINAL_FILES if stat.S_ISREG(_lstat_mode(rd.path / n))]
    rd.write_file(FINAL_MARK, json.dumps({"iteration": state.iteration, "files": written}, indent=1).encode())


def _lstat_mode(path: Path) -> int:
    try:
        return os.lstat(path).st_mode
    except OSError:
        return 0


def final_done(out: str | Path, iteration: int) -> bool:
    """Whether the final phase of the run in ``out`` completed after ``iteration`` iterations: ``final.json``
    records that count, and every final file it lists is a regular file of the directory."""
    try:
        mark = files.read_json_file(Path(out) / FINAL_MARK, limit=1 << 16)
    except (OSError, ConfigError):
        return False
    if not isinstance(mark, dict) or mark.get("iteration") != iteration or not isinstance(mark.get("files"), list):
        return False
    return all(name in FINAL_FILES and stat.S_ISREG(_lstat_mode(Path(out) / name)) for name in mark["files"])


def _meta(task, method: str, cfg: DPSOCConfig, seed: int, task_name) -> dict:
    """The content of ``config.json`` (the environment is recorded, not part of the contract)."""
    return {"task": str(task_name or task.name), "method": method, "seed": seed, "config": cfg.to_dict(),
            "environment": environment()}


def _done(method: str, cfg: DPSOCConfig) -> Callable[[object], bool]:
    meth = get_method(method)
    return lambda st: meth.finished(cfg, st)


def finished_run(task: Task, method: str, cfg: DPSOCConfig, seed: int, out: str | Path, *,
                 task_name: str | None = None, anchor: str | Path | None = None, final: bool = False):
    """The final state of the finished run of this method, task, seed and configuration in ``out``,
    or None (no such directory, not finished, or a damaged last checkpoint; with ``final``: also when its
    final phase has not completed, :func:`final_done`).  Reads only: no lock,
    nothing written (works on a read-only file system); a different run in ``out`` raises
    :class:`RunDirectoryError` as :func:`run_experiment` would."""
    if not Path(out).is_dir():
        return None
    cfg = with_task_init_var(cfg, task)  # compared as run_experiment records it
    rd = RunDirectory(out, anchor=anchor)
    state = rd.finished(_meta(task, method, cfg, seed, task_name), _task_record(task, task_name), _contract,
                        _done(method, cfg))
    if state is None or final and not final_done(out, state.iteration):
        return None
    return check_state(state, task, method, cfg, str(Path(out) / CHECKPOINT))


def _initial_state(task: Task, method: str, cfg: DPSOCConfig, seed: int):
    """The state a fresh run starts from (the method's own ``initial_state``)."""
    return get_method(method).initial_state(task, cfg, seed)


def check_state(state, task: Task, method: str, cfg: DPSOCConfig, where: str):
    """A state read from a checkpoint checked against the run it is to continue: its iteration count within
    ``0 .. total_iterations``, its RNG state one numpy accepts, its policy's arrays finite and shaped for the task;
    :class:`CheckpointError` naming ``where`` otherwise.  Returns ``state``."""
    total = get_method(method).total_iterations(cfg)
    it = getattr(state, "iteration", None)
    if type(it) is not int or not 0 <= it <= total:
        raise CheckpointError(f"{where}: iteration {it!r} is outside 0..{total} (the configured iterations); "
                              "not a checkpoint of this run: rerun with --restart")
    rng_state = getattr(state, "rng_state", None)
    if rng_state is not None:
        try:
            np.random.default_rng().bit_generator.state = rng_state
        except (TypeError, ValueError, KeyError) as e:
            raise CheckpointError(f"{where}: rng_state is not a numpy generator state ({e}); rerun with --restart") from None
    policy = getattr(state, "policy", None)
    lin = getattr(policy, "policy", policy)
    T, m = getattr(task, "T", None), getattr(task, "m", None)
    for name, shape in (("K", (T, m)), ("k", (T, m)), ("cov", (T, m, m))):
        a = getattr(lin, name, None)
        if not isinstance(a, np.ndarray) or a.dtype.kind != "f" or tuple(a.shape[:len(shape)]) != shape \
                or not np.all(np.isfinite(a)):
            got = f"shape {a.shape}, dtype {a.dtype}" if isinstance(a, np.ndarray) else type(a).__name__
            raise CheckpointError(f"{where}: policy.{name} ({got}) is not a finite float array of the task's "
                                  f"shape {shape + ('...',) if name == 'K' else shape}; rerun with --restart")
    return state


def _run(task, method, cfg, seed, rd: RunDirectory | None, state, user_callback, prog, bar_level, tb):
    meth = get_method(method)
    total = meth.total_iterations(cfg)
    t_start = t_last = time.perf_counter()
    logged = len(state.history) if state is not None else 0
    desc = f"{method} seed {seed}" if meth.seeded else method
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
            shown = meth.progress_fields(rec)
            bar.advance(_progress_line(method, seed, total, st, now - t_last, now - t_start),
                        cost=float(np.mean(rec.cost)), **shown, **headline_metric(rec.metrics))
            t_last = now

    try:
        return run_method(meth, task, cfg, seed, state, on_iteration)
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
