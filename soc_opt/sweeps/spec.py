"""Sweeps: a grid of trials (tasks x settings x methods x seeds) from one strict TOML file.

This module is the pure part of ``soc-opt sweep`` (docs/sweeps.md): reading and validating a
sweep file and expanding it into :class:`TrialSpec` objects; one trial runs in its own run directory
(:func:`soc_opt.sweeps.trial.run_trial`, called inside a Ray worker by :mod:`soc_opt.sweeps.runner`, but
an ordinary function).  Nothing here imports Ray.

A sweep file (every key optional except ``tasks``, ``methods`` and ``seeds``)::

    name = "linear2d_small"          # label of the report (default: the file's stem)
    tasks = ["linear2d"]             # built-in names, task TOML paths (relative to this file), gym:<EnvId>
    methods = ["lqr-flm", "dpsoc-em"]
    seeds = [0, 1]                   # a list, or N for 0..N-1
    config = "algo.toml"             # algorithm TOML replacing each task's default file
    paper = false                    # paper scale first (14 iterations, 20 samples, switch at 4)
    eval_samples = 10                # rollouts evaluating each final policy (default: samples)

    [common]                         # overrides for every trial: algorithm layout + [common.task]
    i_switch = 1
    baseline = { iterations = 3, samples = 5 }
    task = { T = 20 }

    [grid]                           # cartesian product; each leaf is the list of values
    task.rho2 = [0.1, 0.01]
    em.y_mode = ["model", "measured"]

    [[settings]]                     # explicit settings, crossed with the grid
    name = "entropy-floor"
    em = { entropy_floor = true }

Override keys follow the algorithm TOML (``i_switch``, ``[baseline]``, ``[baseline.fit]``,
``[baseline.kl]``, ``[em]``; docs/configuration.md) plus ``task`` for the task config's keys
(docs/tasks.md).  Precedence: the task's default algorithm file (or ``config``), ``paper``,
``[common]``, then the setting (``[[settings]]`` entry and grid values; the two may not set the
same key).  Every trial's task and configuration is built, and so validated, by
:func:`load_sweep` before anything runs; an unknown key, value or task raises
:class:`SweepError` naming it.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import files
from ..config import MAX_INT, ConfigError, read_toml, show
from ..methods.config import MAX_SAMPLES, DPSOCConfig, check_scale
from ..methods.registry import check_config, sample_based, sections_of

__all__ = [
    "SweepError",
    "TrialDiverged",
    "Setting",
    "TrialSpec",
    "SweepSpec",
    "load_sweep",
    "sweep_from_dict",
    "read_json",
    "as_json",
    "write_json",
]

def __getattr__(name: str):
    """``METHODS``: the methods a sweep can run, the registry's sample-based ones, read when asked."""
    if name == "METHODS":
        return sample_based()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
TOP_KEYS = ("name", "tasks", "methods", "seeds", "config", "paper", "eval_samples", "common", "grid", "settings")
OVERRIDE_KEYS = ("i_switch", "baseline", "em", "task")
#: Most settings (``[[settings]]`` entries times grid points) and trials of one sweep, checked before any is
#: built; a sweep's name and each trial folder's name are at most MAX_NAME characters (docs/security.md).
MAX_SETTINGS = 1000
MAX_TRIALS = 10_000
MAX_NAME = 100
_SWEEP_NAME = re.compile(r"[A-Za-z0-9_+=,-][A-Za-z0-9._+=,-]{0,%d}" % (MAX_NAME - 1))
RESULT = "result.json"
PROGRESS = "progress.json"
ERROR = "error.txt"
TRIAL = "trial.json"


class SweepError(ConfigError):
    """A sweep file is invalid; the message names the file and the bad key, value or task."""


class TrialDiverged(RuntimeError):
    """A trial's sampled costs became non-finite (a diverging simulation)."""


# --------------------------------------------------------------------------- small helpers


def write_json(path: Path, data, anchor: Path | None = None) -> None:
    """Write ``data`` as JSON atomically (a reader never sees a half-written file), following no link
    below ``anchor`` (:func:`soc_opt.files.write_bytes`)."""
    files.write_json(path, data, anchor=anchor, indent=1, default=_jsonable)


def as_json(data):
    """``data`` after a JSON round trip (tuples become lists, numpy scalars numbers)."""
    return json.loads(json.dumps(data, default=_jsonable))


def read_json(path: Path):
    """The JSON content of ``path``, or ``None`` when it is missing, unreadable, not a regular file, larger
    than :data:`soc_opt.files.MAX_JSON_BYTES` or nested deeper than :data:`soc_opt.config.MAX_DEPTH`."""
    try:
        return files.read_json_file(path)
    except (OSError, ConfigError):
        return None


#: The fields of a finished trial's ``result.json`` the report reads: required, and typed when present.
RESULT_REQUIRED = ("final_cost", "state_spread", "action_spread")
RESULT_TYPED = {"best_cost": float, "final_cost_mean_action": float, "rejected_steps": float, "final_vs_last_ratio": float,
                "final_vs_last_worse": float, "iterations": float, "wall_time": float, "attempt": float,
                "resumed_from": float, "metrics": dict, "metrics_mean_action": dict, "cost_per_iteration": list}


def _number(v) -> bool:
    return isinstance(v, (int, float))  # booleans included: final_vs_last_worse is one


def read_result(path: Path, *, finished: bool = True) -> dict | None:
    """A trial's ``result.json``, None when absent, unreadable or (``finished``) not marked ``"done"``;
    :class:`SweepError` naming the file when it lacks a field the report reads or holds one of the
    wrong type (a crafted or foreign file, never one a trial wrote)."""
    res = read_json(path)
    if not isinstance(res, dict) or (finished and res.get("status") != "done"):
        return None
    for key in (*RESULT_REQUIRED, *RESULT_TYPED):
        if key not in res and key not in RESULT_REQUIRED:
            continue
        v, typ = res.get(key), RESULT_TYPED.get(key, float)
        if typ is float:
            ok = _number(v)
        elif typ is dict:
            ok = isinstance(v, dict) and all(_number(x) for x in v.values())
        else:
            ok = isinstance(v, list) and all(_number(x) for x in v)
        if not ok:
            raise SweepError(f"{str(path)!r}: field {key!r} is {'missing' if key not in res else type(v).__name__}, "
                             f"expected {'a number' if typ is float else typ.__name__}; not a result soc_opt wrote: "
                             "delete it to run the trial again")
    return res


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


def _merge(base: dict, over: dict) -> dict:
    """``base`` with ``over`` merged in recursively (tables merge, other values replace)."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _nest(path: tuple[str, ...], value) -> dict:
    d = value
    for k in reversed(path):
        d = {k: d}
    return d


def _fmt_value(v) -> str:
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (list, tuple)):
        return "-".join(_fmt_value(x) for x in v)
    if isinstance(v, dict):
        return "+".join(f"{k}-{_fmt_value(x)}" for k, x in v.items())
    return str(v)


def _safe_name(text: str) -> str:
    """A directory-safe version of a setting name: one path component, not starting with a dot, at most
    :data:`MAX_NAME` characters (else :class:`ConfigError`)."""
    name = re.sub(r"^\.", "_", re.sub(r"[^A-Za-z0-9._=,+-]", "_", text)) or "_"
    if len(name) > MAX_NAME:
        raise ConfigError(f"the name {show(text)} is longer than a trial folder's name may be ({MAX_NAME} characters)")
    return name


# --------------------------------------------------------------------------- specs


@dataclass(frozen=True)
class Setting:
    """One point of the settings grid.

    name:      directory-safe label (``"default"`` when there are no settings).
    overrides: nested override table: algorithm keys (``i_switch``, ``baseline``, ``em``) and
               ``task`` (task config keys).
    group:     the ``[[settings]]`` entry it comes from (its name, ``""`` without entries).
    grid:      the grid values of this point, ``((label, value), ...)`` in grid order.
    """

    name: str
    overrides: dict
    group: str = ""
    grid: tuple = ()


@dataclass(frozen=True)
class TrialSpec:
    """One trial: one method on one task, setting and seed (an ordinary run directory).

    task:           built-in task name, or the absolute path of a task TOML file.
    task_label:     short task name used in paths and tables.
    task_overrides: top-level task config keys replacing the file's (tables already merged).
    config:         the full algorithm configuration of the run.
    eval_samples:   rollouts evaluating the final policy (evaluation seed ``10000 + seed``, as in
                    ``soc-opt compare``).
    """

    task: str
    task_label: str
    task_overrides: dict
    method: str
    seed: int
    setting: str
    config: DPSOCConfig
    eval_samples: int
    gym_modules: tuple[str, ...] = ()  # modules a gym:<module>:<EnvId> may import (--gym-module; not recorded)

    @property
    def id(self) -> str:
        return f"{self.task_label}/{self.setting}/{self.method}/seed_{self.seed}"

    @property
    def relpath(self) -> Path:
        """The trial's run directory relative to the sweep's output directory."""
        return Path("trials", self.task_label, self.setting, self.method, f"seed_{self.seed}")

    def to_dict(self) -> dict:
        return {"task": self.task, "task_label": self.task_label, "task_overrides": self.task_overrides,
                "method": self.method, "seed": self.seed, "setting": self.setting,
                "config": self.config.to_dict(), "eval_samples": self.eval_samples}


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep: ``trials`` is the full grid, in task, setting, method, seed order."""

    name: str
    source: str | None
    tasks: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...]
    settings: tuple[Setting, ...]
    trials: tuple[TrialSpec, ...]

    def to_dict(self) -> dict:
        return {"name": self.name, "source": self.source, "tasks": list(self.tasks),
                "methods": list(self.methods), "seeds": list(self.seeds),
                "settings": [{"name": s.name, "overrides": s.overrides} for s in self.settings],
                "trials": [t.id for t in self.trials]}


# --------------------------------------------------------------------------- parsing


def load_sweep(path: str | Path, *, gym_modules: tuple[str, ...] = ()) -> SweepSpec:
    """Read and validate a sweep file (module docstring); :class:`SweepError` names what is wrong.  ``gym_modules``:
    the modules its ``gym:<module>:<EnvId>`` tasks may import (``--gym-module``; none by default, docs/gym.md)."""
    path = Path(path)
    try:
        data = read_toml(path)
    except ConfigError as e:
        raise SweepError(str(e)) from e
    return sweep_from_dict(data, base_dir=path.parent, source=str(path), default_name=path.stem, gym_modules=gym_modules)


def sweep_from_dict(data: dict, *, base_dir: str | Path = ".", source: str | None = None,
                    default_name: str = "sweep", gym_modules: tuple[str, ...] = ()) -> SweepSpec:
    """Validate a sweep table and expand it into its trials (nothing is run)."""
    where = f"sweep file {source!r}" if source else "sweep"
    try:
        spec = _expand(data, Path(base_dir), default_name, tuple(gym_modules))
    except ConfigError as e:
        raise SweepError(f"{where}: {e}") from e
    return dataclasses.replace(spec, source=source)


def _check_keys(table: dict, allowed, what: str) -> None:
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ConfigError(f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
                          f"in {what}; allowed: {', '.join(allowed)}")


def _str_list(data: dict, key: str) -> list[str]:
    v = data.get(key)
    if not isinstance(v, list) or not v or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{key}: expected a non-empty list of strings, got {v!r}")
    if len(set(v)) != len(v):
        raise ConfigError(f"{key}: duplicate entries in {v!r}")
    return v


def _seeds(v) -> tuple[int, ...]:
    if isinstance(v, int) and not isinstance(v, bool):
        if not 1 <= v <= MAX_TRIALS:
            raise ConfigError(f"seeds: expected a count in [1, {MAX_TRIALS}], got {show(v)}")
        return tuple(range(v))
    if (not isinstance(v, list) or not v
            or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_INT for s in v)):
        raise ConfigError(f"seeds: expected a count or a non-empty list of integers in [0, {MAX_INT}], got {show(v)}")
    if len(set(v)) != len(v):
        raise ConfigError(f"seeds: duplicate entries in {v!r}")
    return tuple(v)


def _resolve_task(ref: str, base_dir: Path, i: int, gym_modules: tuple[str, ...] = ()) -> tuple[str, str, Path | None]:
    """``(task reference passed to workers, label, task TOML path or None for gym:<EnvId>)``."""
    from ..tasks.config import GYM_PREFIX
    from ..tasks.loading import BUILTIN_TASKS, problems_dir

    if ref.startswith(GYM_PREFIX):  # a Gymnasium environment (docs/gym.md); checked by load_task below
        from ..tasks.gym import check_gym_import

        check_gym_import(ref, gym_modules)  # a module named in a file only if the command line names it
        return ref, _safe_name(ref.replace(":", "-")), None
    if ref in BUILTIN_TASKS:
        return ref, ref, problems_dir() / BUILTIN_TASKS[ref]
    p = Path(ref)
    for cand in ([p] if p.is_absolute() else [base_dir / p, p]):
        if cand.is_file():
            return str(cand.resolve()), cand.stem, cand.resolve()
    raise ConfigError(f"tasks[{i}]: unknown task {ref!r}: not a built-in task ({', '.join(BUILTIN_TASKS)}), "
                      f"no task file {str(base_dir / p)!r} and not {GYM_PREFIX}<EnvId>")


def _check_overrides(table, what: str) -> dict:
    if not isinstance(table, dict):
        raise ConfigError(f"{what}: expected a table, got {table!r}")
    _check_keys(table, OVERRIDE_KEYS, what)
    if "task" in table and not isinstance(table["task"], dict):
        raise ConfigError(f"{what}.task: expected a table of task config keys, got {table['task']!r}")
    return table


def _grid_leaves(table: dict, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], list]]:
    leaves = []
    for k, v in table.items():
        path = prefix + (k,)
        if isinstance(v, dict):
            leaves += _grid_leaves(v, path)
        elif isinstance(v, list) and v:
            leaves.append((path, v))
        else:
            raise ConfigError(f"grid.{'.'.join(path)}: expected a non-empty list of values, got {v!r}")
    return leaves


def _settings(data: dict) -> tuple[Setting, ...]:
    """The explicit ``[[settings]]`` (or one empty setting) crossed with the grid."""
    entries = data.get("settings", [])
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ConfigError("settings: expected an array of tables ([[settings]])")
    explicit = []
    for i, e in enumerate(entries):
        e = dict(e)
        name = e.pop("name", None)
        if name is not None and (not isinstance(name, str) or not name):
            raise ConfigError(f"settings[{i}].name: expected a non-empty string, got {name!r}")
        explicit.append((name, _check_overrides(e, f"settings[{i}]"), i))
    explicit = explicit or [(None, {}, None)]
    grid = data.get("grid", {})
    _check_overrides(grid, "grid")
    leaves = _grid_leaves(grid)
    count = len(explicit) * math.prod(len(vals) for _, vals in leaves)  # before any is built
    if count > MAX_SETTINGS:
        raise ConfigError(f"grid: {len(explicit)} setting(s) x {' x '.join(str(len(v)) for _, v in leaves)} grid values "
                          f"= {count} settings, more than a sweep may have ({MAX_SETTINGS})")
    short = [p[-1] for p, _ in leaves]
    labels = [p[-1] if short.count(p[-1]) == 1 else ".".join(p) for p, _ in leaves]
    out = []
    for name, over, i in explicit:
        for combo in itertools.product(*[vals for _, vals in leaves]):
            merged = dict(over)
            for (path, _), value in zip(leaves, combo):
                if _lookup(over, path) is not _MISSING:
                    raise ConfigError(f"settings[{i}] and grid both set {'.'.join(path)}")
                merged = _merge(merged, _nest(path, value))
            parts = ([name or f"settings{i}"] if (name or len(explicit) > 1) else []) + [
                f"{lab}={_fmt_value(v)}" for lab, v in zip(labels, combo)]
            out.append(Setting(_safe_name(",".join(parts)) if parts else "default", merged,
                               group=name or (f"settings{i}" if len(explicit) > 1 else ""),
                               grid=tuple(zip(labels, combo))))
    dup = sorted(n for n, k in collections.Counter(s.name for s in out).items() if k > 1)
    if dup:
        raise ConfigError(f"settings: duplicate setting names {dup[:5]}{' and more' if len(dup) > 5 else ''}; give each "
                          "[[settings]] entry a distinct name")
    return tuple(out)


_MISSING = object()


def _lookup(table: dict, path: tuple[str, ...]):
    for k in path:
        if not isinstance(table, dict) or k not in table:
            return _MISSING
        table = table[k]
    return table


def _config(task_ref, cfg_file, paper, common, setting, method, task_init_var: float,
            sweep_sets_task_init_var: bool) -> DPSOCConfig:
    """The trial's configuration; ``baseline.init_var`` resolved (the task's unless set, see below).

    ``init_var`` precedence: the sweep's ``baseline.init_var``, else its ``task.init_var``, else the
    run configuration file's ``[baseline] init_var``, else the task file's ``init_var``.  The sweep
    may not set both.
    """
    from ..experiments.run import load_run_config as load_config

    base = load_config(task_ref, cfg_file, paper=paper, method="dpsoc-em").to_dict()
    ours = _merge(common, setting)
    if sweep_sets_task_init_var:
        if _lookup(ours, ("baseline", "init_var")) is not _MISSING:
            raise ConfigError("task.init_var and baseline.init_var both set the initial policy covariance; "
                              "set one of them")
        base.get("baseline", {}).pop("init_var", None)
    d = _merge(base, ours)
    if _lookup(d, ("baseline", "init_var")) is _MISSING:
        d = _merge(d, {"baseline": {"init_var": task_init_var}})
    if "i_switch" not in sections_of(method):  # the switch point is unused (as in `soc-opt run`)
        it = _lookup(d, ("baseline", "iterations"))
        if isinstance(d.get("i_switch"), int) and isinstance(it, int) and it >= 1:
            d["i_switch"] = min(d["i_switch"], it - 1)
    cfg = DPSOCConfig.from_dict(d)
    check_config(method, cfg)  # method-specific rules (i_switch < iterations for DPSOC-EM), before any trial
    return cfg


def _expand(data: dict, base_dir: Path, default_name: str, gym_modules: tuple[str, ...] = ()) -> SweepSpec:
    from ..tasks import load_task

    if not isinstance(data, dict):
        raise ConfigError("expected a table")
    _check_keys(data, TOP_KEYS, "the sweep file")
    for key in ("tasks", "methods", "seeds"):
        if key not in data:
            raise ConfigError(f"missing key {key!r}")
    name = data["name"] if "name" in data else _safe_name(default_name[:MAX_NAME])
    if not isinstance(name, str) or not _SWEEP_NAME.fullmatch(name):
        raise ConfigError(f"name: expected a name of letters, digits and . _ - + = , (at most {MAX_NAME} characters, "
                          f"not starting with a dot; it names the default output folder runs/sweep-NAME), got {show(name)}")
    methods = _str_list(data, "methods")
    runnable = sample_based()  # read now: a method registered from a script is among them
    for m in methods:
        if m not in runnable:
            raise ConfigError(f"methods: unknown method {m!r}; use {list(runnable)}")
    seeds = _seeds(data["seeds"])
    tasks = [_resolve_task(ref, base_dir, i, gym_modules) for i, ref in enumerate(_str_list(data, "tasks"))]
    labels = [lab for _, lab, _ in tasks]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"tasks: two tasks share a name {labels}; rename a task file")
    cfg_file = data.get("config")
    if cfg_file is not None:
        if not isinstance(cfg_file, str):
            raise ConfigError(f"config: expected a file path, got {cfg_file!r}")
        cfg_file = str(base_dir / cfg_file) if not Path(cfg_file).is_absolute() else cfg_file
    paper = data.get("paper", False)
    if not isinstance(paper, bool):
        raise ConfigError(f"paper: expected true/false, got {paper!r}")
    eval_samples = data.get("eval_samples")
    if eval_samples is not None and (isinstance(eval_samples, bool) or not isinstance(eval_samples, int)
                                     or not 1 <= eval_samples <= MAX_SAMPLES):
        raise ConfigError(f"eval_samples: expected an integer in [1, {MAX_SAMPLES}], got {show(eval_samples)}")
    common = dict(_check_overrides(data.get("common", {}), "common"))
    common_task = common.pop("task", {})
    settings = _settings(data)
    n_trials = len(tasks) * len(settings) * len(methods) * len(seeds)
    if n_trials > MAX_TRIALS:
        raise ConfigError(f"{len(tasks)} task(s) x {len(settings)} setting(s) x {len(methods)} method(s) x {len(seeds)} "
                          f"seed(s) = {n_trials} trials, more than a sweep may have ({MAX_TRIALS})")
    trials = []
    for ref, label, task_file in tasks:
        file_table = read_toml(task_file) if task_file is not None else {}
        for s in settings:
            over = dict(s.overrides)
            task_over = _merge(common_task, over.pop("task", {}))
            top = {k: _merge(file_table[k], v) if isinstance(v, dict) and isinstance(file_table.get(k), dict) else v
                   for k, v in task_over.items()}
            ctx = f"task {label!r}, setting {s.name!r}"
            try:
                task = load_task(ref, overrides=top, gym_modules=gym_modules)  # validates the task keys (and model)
            except ConfigError as e:
                raise ConfigError(f"{ctx}, task keys: {e}") from e
            try:
                cfgs = {m: _config(ref, cfg_file, paper, common, over, m, task.config.init_var, "init_var" in top)
                        for m in methods}
            except ConfigError as e:
                raise ConfigError(f"{ctx}, algorithm keys: {e}") from e
            for m in methods:
                cfg = cfgs[m]
                check_scale(cfg.replace(evaluation=cfg.evaluation.replace(samples=eval_samples)), task)  # largest batch
                for seed in seeds:
                    trials.append(TrialSpec(ref, label, top, m, seed, s.name, cfg,
                                            eval_samples or cfg.baseline.samples, gym_modules))
    return SweepSpec(name, None, tuple(labels), tuple(methods), seeds, settings, tuple(trials))


def describe(spec: SweepSpec) -> str:
    """One line: the grid's shape."""
    return (f"{len(spec.trials)} trials = {len(spec.tasks)} task(s) x {len(spec.settings)} setting(s) x "
            f"{len(spec.methods)} method(s) x {len(spec.seeds)} seed(s)")


def setting_table(spec: SweepSpec) -> list[tuple[str, str]]:
    """``(setting name, its overrides as dotted key = value)`` for the report."""
    rows = []
    for s in spec.settings:
        flat = _flatten(s.overrides)
        rows.append((s.name, ", ".join(f"{k} = {_fmt_value(v)}" for k, v in flat.items()) or "(none)"))
    return rows


def _flatten(table: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in table.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out
