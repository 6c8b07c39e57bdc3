"""What every plug-in must do: :func:`check_method` and :func:`check_estimator`, after scikit-learn's
``check_estimator``.

A plug-in that passes runs through the drivers like a built-in: its settings table loads, the
command-line flags it does not read are refused naming the flag, its iterations are pure (the state
holds the RNG), a checkpoint of its state resumes to the same numbers, its history rows make
``metrics.csv`` rows, and its final evaluation and console lines are what the CLI prints.  Both checks
take the plug-in as registered in :data:`soc_opt.plugins.METHODS` / :data:`soc_opt.plugins.ESTIMATORS`
(the tables its settings and saved state are read through) and run it on a short task (default:
``linear2d`` with 8 steps).  A failure raises ``AssertionError`` saying what the plug-in got wrong.
The built-in plug-ins and the toy ones of ``tests/`` pass (``tests/test_conformance.py``).
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from . import plugins
from .config import Config, ConfigError
from .experiments.statefile import decode_state, encode_state
from .methods.base import FLAGS, FinalEvaluation, apply_overrides, check_protocol
from .methods.config import DPSOCConfig
from .noise.strategy import check_strategy, resolve

__all__ = ["check_method", "check_estimator", "short_task"]

#: The values :func:`check_method` gives the command-line flags: the shortest run they allow.
_FLAG_VALUES = {"iterations": 2, "samples": 4, "workers": 1, "i_switch": 1, "as_written": True}


def short_task():
    """The task the checks run on by default: ``linear2d`` with a horizon of 8 steps."""
    from .tasks import load_task

    return load_task("linear2d", overrides={"T": 8})


def _fail(plugin: str, what: str) -> AssertionError:
    return AssertionError(f"{plugin}: {what}")


def _rows(state) -> list[dict]:
    """The history's ``metrics.csv`` rows without their wall times."""
    return [{k: v for k, v in r.summary().items() if not k.startswith("time_")} for r in state.history]


def _same(a: dict, b: dict) -> bool:
    if a.keys() != b.keys():
        return False
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y):
            continue
        if x != y:
            return False
    return True


def _policy_arrays(policy) -> dict:
    gains = getattr(policy, "policy", policy)  # a policy acting on a filter: its gains
    return {k: np.asarray(v) for k, v in gains.to_dict().items()}


def _check_state(who: str, state, iteration: int) -> None:
    for attr in ("iteration", "policy", "history", "best", "last_rollouts"):
        if not hasattr(state, attr):
            raise _fail(who, f"its state has no {attr!r} (the run directory reads it)")
    if state.iteration != iteration:
        raise _fail(who, f"state.iteration is {state.iteration} after {iteration} iterations")
    if not isinstance(state.history, tuple):
        raise _fail(who, "state.history must be a tuple of records")


def _check_rows(who: str, state) -> None:
    for rec in state.history:
        row = rec.summary()
        for key in ("iteration", "phase", "cost_mean"):
            if key not in row:
                raise _fail(who, f"a history row has no {key!r} column: {sorted(row)}")
        bad = [k for k, v in row.items() if v is None]
        if bad:
            raise _fail(who, f"a history row has empty columns {bad} (leave a column out rather than None)")


def _resumes(who: str, iterate, task, cfg, s1, s2) -> None:
    """A checkpoint of ``s1`` (the state file format) iterated once equals ``s2``, and ``s1`` was not changed."""
    before = encode_state(s1)
    again = iterate(task, cfg, decode_state(before))
    if encode_state(s1) != before:
        raise _fail(who, "iterate changed the state it was given (iterations must be pure)")
    ra, rb = _rows(again), _rows(s2)
    if len(ra) != len(rb) or not all(_same(a, b) for a, b in zip(ra, rb)):
        raise _fail(who, "an iteration from a checkpoint of its state gives other history rows (is the RNG in the state?)")
    pa, pb = _policy_arrays(again.policy), _policy_arrays(s2.policy)
    if any(not np.array_equal(pa[k], pb[k]) for k in pa):
        raise _fail(who, "an iteration from a checkpoint of its state gives another policy")


def check_method(method: Any, task=None, cfg: DPSOCConfig | None = None) -> None:
    """``AssertionError`` unless ``method`` (registered in :data:`soc_opt.plugins.METHODS`) behaves as the
    drivers need (module docstring).  ``cfg``: the run configuration to start from (default: the defaults
    with the shortest run ``method.flags`` allow); ``task``: default :func:`short_task`."""
    try:
        check_protocol(method)
    except TypeError as e:
        raise AssertionError(str(e)) from None
    who = f"method {method.name!r}"
    if plugins.METHODS.get(method.name) is not method:
        raise _fail(who, "is not registered (soc_opt.plugins.METHODS.register(...)): its table and state are read there")
    if method.settings is not None:
        if not (isinstance(method.settings, type) and issubclass(method.settings, Config)):
            raise _fail(who, "settings must be a soc_opt.config.Config subclass")
        table = DPSOCConfig.from_dict({method.name: {}}).section(method.name)
        if table != method.settings() or DPSOCConfig.from_dict(DPSOCConfig().to_dict()).section(method.name) != table:
            raise _fail(who, f"its [{method.name}] table does not load with the settings' defaults")

    base = DPSOCConfig() if cfg is None else cfg
    for flag in FLAGS:
        if flag in method.flags:
            continue
        values, paper = ({}, True) if flag == "paper" else ({flag: _FLAG_VALUES[flag]}, False)
        try:
            apply_overrides(method, base, values, paper)
        except ConfigError as e:
            if f"--{flag.replace('_', '-')}" not in str(e):
                raise _fail(who, f"refuses --{flag} without naming it: {e}") from None
        else:
            raise _fail(who, f"accepts --{flag.replace('_', '-')}, which it does not declare in flags")
    if cfg is None:
        cfg = apply_overrides(method, base, {k: v for k, v in _FLAG_VALUES.items()
                                             if k in method.flags and k not in ("as_written", "workers")})
    method.check_config(cfg)
    task = short_task() if task is None else task
    method.check_task(task, cfg)
    total = method.total_iterations(cfg)
    if not isinstance(total, int) or total < 1:
        raise _fail(who, f"total_iterations must be a positive int, got {total!r}")

    s0 = method.initial_state(task, cfg, 3)
    _check_state(who, s0, 0)
    before = encode_state(s0)
    s1 = method.iterate(task, cfg, s0)
    if encode_state(s0) != before:
        raise _fail(who, "iterate changed the state it was given (iterations must be pure)")
    _check_state(who, s1, 1)
    s2 = s1 if method.finished(cfg, s1) else method.iterate(task, cfg, s1)
    for st in (s1, s2):
        _check_rows(who, st)
    if not isinstance(method.finished(cfg, s2), bool):
        raise _fail(who, "finished must return True or False")
    if s2 is not s1:
        _resumes(who, method.iterate, task, cfg, s1, s2)
    if not any(r.phase == method.cost_phase for r in s2.history):
        raise _fail(who, f"no history row has its cost_phase {method.cost_phase!r} (the cost figure would be empty)")

    fields = method.progress_fields(s2.history[-1])
    if not isinstance(fields, dict) or not all(isinstance(v, float) for v in fields.values()):
        raise _fail(who, f"progress_fields must map names to floats, got {fields!r}")
    if not isinstance(method.progress_line(3, "iter 1", s2, "", ""), str):
        raise _fail(who, "progress_line must return a string")
    ev = method.evaluate_final(task, cfg, 3, s2, lambda ro: f"cost {float(np.mean(ro.total_cost())):.4g}")
    if not isinstance(ev, FinalEvaluation) or not {"final_eval", "final_eval_mean_action"} <= set(ev.rollouts):
        raise _fail(who, "evaluate_final must return a FinalEvaluation with final_eval and final_eval_mean_action")
    if not isinstance(ev.line, str) or not hasattr(ev.policy, "to_dict"):
        raise _fail(who, "evaluate_final's line must be a string and its policy writable (to_dict)")
    with tempfile.TemporaryDirectory() as out:
        if not isinstance(method.finish(s2, Path(out)), str):
            raise _fail(who, "finish must return the closing console line")


def check_estimator(cls: Any, task=None, options: Config | None = None) -> None:
    """``AssertionError`` unless the estimator class ``cls`` (registered in :data:`soc_opt.plugins.ESTIMATORS`)
    drives two LQR-FLM iterations whose checkpoint resumes to the same numbers (module docstring).
    ``options``: its ``[baseline.noise.NAME]`` table (default: its settings' defaults); ``task``: default
    :func:`short_task` (an estimator for another kind of task is given one)."""
    try:
        check_strategy(cls)
    except TypeError as e:
        raise AssertionError(str(e)) from None
    who = f"estimator {cls.name!r}"
    if plugins.ESTIMATORS.get(cls.name) is not cls:
        raise _fail(who, "is not registered (soc_opt.plugins.ESTIMATORS.register(...))")
    lqr_flm = plugins.METHODS.lookup("lqr-flm")
    tables = {} if options is None else {cls.name: options}
    cfg = DPSOCConfig()
    cfg = cfg.replace(baseline=cfg.baseline.replace(iterations=2, samples=6,
                                                    noise=cfg.baseline.noise.replace(estimator=cls.name, **tables)))
    task = short_task() if task is None else task
    lqr_flm.check_task(task, cfg)
    if not isinstance(resolve(task, cfg.baseline.noise), cls):
        raise _fail(who, "is not what [baseline.noise] estimator = its name resolves to")
    s1 = lqr_flm.iterate(task, cfg, lqr_flm.initial_state(task, cfg, 3))
    s2 = lqr_flm.iterate(task, cfg, s1)
    _check_rows(who, s2)
    _resumes(who, lqr_flm.iterate, task, cfg, s1, s2)
