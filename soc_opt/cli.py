"""The ``soc-opt`` command line.

Subcommands::

    soc-opt [--debug] run TASK [--method dpsoc-em|lqr-flm|ilqg] [--config FILE] [--seed N] [--out DIR] [--paper]
                                [--iterations N] [--i-switch N] [--set KEY=VALUE ...] [--restart | --previous-checkpoint]
    soc-opt compare TASK [--seeds N] [--config FILE] [--out DIR] [--paper] [--set KEY=VALUE ...] [--restart]
    soc-opt verify [--json] [--seed N] [--instances N] [--full] [--replay FILE..] [--write-certificates DIR] [--rows]
    soc-opt solvers [--json] [--quick] [--sizes NxM[xT],..] [--instances N] [--repeats N] [--kl-T N] [--sqp] [--legacy] [--T N]
                    [--out DIR] [--no-kl]
    soc-opt bench [--json] [--only NAMES] [--quick]
    soc-opt tasks
    soc-opt sweep SWEEP.toml [--out DIR] [--address ADDR] [--workers N] [--set KEY=VALUE ...] [--dry-run]
    soc-opt config-doc [--out FILE]
    soc-opt convert-checkpoint --trust DIR

``TASK`` is a built-in name (``linear2d``, ``peg``, ``door``), the path of a task TOML file, or ``gym:<EnvId>``
(docs/gym.md); ``soc-opt tasks`` lists every shipped task.  ``--set KEY=VALUE`` overrides one setting
(:mod:`soc_opt.experiments.overrides`).
Configurations are validated before any simulation starts and before anything is written to
``--out``; they are built by :func:`soc_opt.experiments.run.load_run_config` (the same loader is
public for scripts).  Every method writes a resumable run directory (:mod:`soc_opt.experiments.rundir`).

Every error ends the command with one line ``soc-opt: error: ...`` on standard error and exit
status 2 (``--debug``: the traceback before that line, same exit status).  Iterations are numbered from 0 on the console
as in ``metrics.csv``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from .config import MAX_INT, MAX_MESSAGE, ConfigError, shorten

__all__ = ["main", "build_parser"]


def _print(line: str) -> None:
    print(line, flush=True)


def _table(rows: list[dict]) -> str:
    from .experiments.report import format_table

    return format_table(rows)


def _progress(args):
    """Progress of ``run``/``compare``: a bar on a terminal, plain lines otherwise (``--progress``)."""
    from .experiments.progress import Progress

    return Progress(getattr(args, "progress", "auto"), print_line=_print)


def _log_to_tensorboard(out: Path, *, figures=(), step: int = 0, scalars: dict | None = None) -> None:
    """Figures (PNG paths) and scalar series into ``out``'s TensorBoard events (if tensorboardX is installed)."""
    from .experiments.tblog import RunLog

    log = RunLog.open(out)
    if log is None:
        return
    try:
        for tag, values in (scalars or {}).items():
            log.series(tag, values)
        n = log.figures(figures, step)
    finally:
        log.close()
    if figures:
        _print(f"TensorBoard: {n} figures in {out} (tensorboard --logdir {out})")


def _cmd_tasks(args) -> int:
    from .tasks import load_task
    from .tasks.catalog import shipped_tasks

    tasks = shipped_tasks()
    w = max(len("TASK"), *(len(name) for name, _ in tasks))
    _print(f"{'TASK':{w}s} {'n':>3s} {'m':>3s} {'T':>4s} {'dt':>6s} {'rho2':>6s}  shipped as")
    for name, where in tasks:
        try:
            t = load_task(name)
        except Exception as e:  # noqa: BLE001 -- one broken file does not hide the others
            _print(f"{name:{w}s} cannot be loaded: {_one_line(e, hint=False)}")
            continue
        _print(f"{name:{w}s} {t.n:3d} {t.m:3d} {t.T:4d} {t.dt:6g} {t.rho2:6g}  {where}")
    _print("\nAlso: any task TOML file (docs/tasks.md), and gym:<EnvId> for a Gymnasium MuJoCo environment "
           "(e.g. gym:Reacher-v5, gym:Swimmer-v5; docs/gym.md).")
    return 0


def _run_method(args, task, out: Path) -> int:
    """One registered method in a resumable run directory; its final phase (figures, filmstrip, final policy and
    evaluations) inside the run's lock, resumed by the same command when interrupted (``run_experiment(finish=)``)."""
    from .experiments.run import finished_run, run_experiment

    cfg = _load_run_config(args, args.method)
    if not args.restart and not args.previous_checkpoint:
        done = finished_run(task, args.method, cfg, args.seed, out, task_name=args.task, final=True)
        if done is not None:  # reopening a finished run reads only: no figure, event file or lock written
            _print(f"{args.method} run in {out} already finished ({done.iteration} iterations); nothing to do "
                   "(--restart to run it again)")
            return 0
    if cfg.baseline.noise.estimator == "kinematic":  # the estimator whose smoother and filter have compiled kernels
        from .compiled import describe

        _print(f"kernels: {describe()} (recorded in config.json; docs/architecture.md, \"Compiled kernels\")")

    def finish(state, log):
        _final_phase(task, args.method, cfg, args.seed, state, out, log)

    run_experiment(task, args.method, cfg, args.seed, out, task_name=args.task, progress=_progress(args),
                   restart=args.restart, previous_checkpoint=args.previous_checkpoint, finish=finish)
    return 0


def _final_phase(task, method: str, cfg, seed: int, state, out: Path, log) -> None:
    """The files a finished run adds, from its final state alone (so that a rerun after an interruption writes
    the same ones): figures, the filmstrip, the method's own files, the final policy and its evaluations."""
    from .methods.registry import get_method

    _write_run_figures(task, method, state, out)
    if state.last_rollouts is not None:
        from .tasks import render_filmstrip

        res = render_filmstrip(task, state.last_rollouts, out / "filmstrip.png")
        _print(f"filmstrip of the last iteration's first sample: {res.path} ({res.backend}"
               + (f"; {res.message}" if res.message else "") + ")")
    if log is not None:
        n = log.figures(sorted(out.glob("*.png")), max(state.iteration - 1, 0))
        _print(f"TensorBoard: {n} figures in {out} (tensorboard --logdir {out})")
    _print(get_method(method).finish(state, out))
    _print(_final_evaluation(task, method, cfg, seed, state, out))


def _final_evaluation(task, method: str, cfg, seed: int, state, out: Path) -> str:
    """The method's final evaluation (``Method.evaluate_final``, docs/math.md §12.3): ``final_policy.npz`` and
    each batch of fresh rollouts as ``<stem>.npz`` in ``out``; one line saying what was evaluated."""
    from .experiments.run import headline_metric
    from .experiments.rundir import atomic_write_bytes, npz_bytes
    from .plugins import METHODS

    def score(r):
        m = headline_metric(task.metrics(r))
        txt = ", ".join(f"{k} {v:.4g}" for k, v in m.items())
        return f"cost {float(np.mean(task.true_cost(r).sum(-1))):.4g}" + (f", {txt}" if txt else "")

    ev = METHODS.lookup(method).evaluate_final(task, cfg, seed, state, score)
    atomic_write_bytes(out / "final_policy.npz", npz_bytes(**ev.policy.to_dict()))
    for stem, ro in ev.rollouts.items():
        atomic_write_bytes(out / f"{stem}.npz", npz_bytes(**ro.to_dict()))
    return ev.line


def _load_run_config(args, method: str):
    """The run configuration of ``run``/``compare``; a bad ``i_switch`` gets a hint naming its
    source and ``--i-switch``."""
    from .experiments.overrides import apply_config_sets, split_sets
    from .experiments.run import EXPERIMENTS, load_run_config

    try:
        cfg = load_run_config(args.task, args.config, paper=args.paper, method=method,
                              overrides={"iterations": args.iterations, "samples": args.samples,
                                         "workers": args.workers, "i_switch": args.i_switch,
                                         "as_written": True if args.as_written else None})
        return apply_config_sets(cfg, split_sets(args.set or [])[1], method)
    except ConfigError as e:
        if str(e).startswith("i_switch"):
            default = EXPERIMENTS / f"{Path(args.task).stem}.toml"
            source = ("--i-switch" if args.i_switch is not None else "--paper" if args.paper
                      else args.config or (str(default) if default.is_file() else "the default (DPSOCConfig)"))
            e.add_note(f"i_switch comes from {source}; choose the EM switch with --i-switch N "
                       "(0 <= N < --iterations), raise --iterations, or use --method lqr-flm")
        raise


def _cmd_run(args) -> int:

    if not 0 <= args.seed <= MAX_INT:
        raise ConfigError(f"--seed must be in [0, {MAX_INT}], got {args.seed}")
    if args.restart and args.previous_checkpoint:
        raise ConfigError("--restart and --previous-checkpoint exclude each other: choose one")
    task = _load_task(args)
    out = Path(args.out or f"runs/{Path(args.task).stem}-{args.method}-seed{args.seed}")
    return _run_method(args, task, out)


def _load_task(args):
    """The task of ``run``/``compare`` with its ``--set task.KEY=VALUE`` overrides (docs/interface.md)."""
    from .experiments.overrides import split_sets
    from .tasks import load_task

    task_sets = split_sets(args.set or [])[0]
    try:
        return load_task(args.task, overrides=task_sets or None, gym_modules=tuple(args.gym_module or ()))
    except ConfigError as e:
        if task_sets:
            e.add_note("from --set " + ", ".join(f"task.{k}" for k in task_sets))
        raise


def _write_run_figures(task, method: str, state, out: Path) -> None:
    from .experiments import report
    from .experiments.compare import point_names, point_targets
    from .methods.registry import get_method

    phase = get_method(method).cost_phase
    costs = {method: [np.asarray(r.cost) for r in state.history if r.phase == phase]}
    if costs[method]:
        report.plot_costs(costs, out / "cost_per_iteration.png", f"{task.name}: total cost per iteration")
    if state.last_rollouts is not None:
        report.plot_ee({method: np.asarray(task.ee_points(state.last_rollouts.x))}, task.dt,
                       out / "ee_trajectories.png", f"{task.name}: end-effector points (last iteration)",
                       point_names=point_names(task), targets=point_targets(task))


def _cmd_compare(args) -> int:
    from .experiments.compare import MAX_SEEDS, compare
    from .experiments.report import em_switch_text

    if not 0 <= args.seed <= MAX_INT or not 1 <= args.seeds <= MAX_SEEDS:
        raise ConfigError(f"--seed must be in [0, {MAX_INT}] and --seeds in [1, {MAX_SEEDS}], got {args.seed} and {args.seeds}")
    task = _load_task(args)
    cfg = _load_run_config(args, "dpsoc-em")
    out = Path(args.out or f"runs/compare-{Path(args.task).stem}")
    seeds = list(range(args.seed, args.seed + args.seeds))
    _print(f"comparing LQR-FLM and DPSOC-EM on {args.task}: seeds {seeds}, {cfg.baseline.iterations} iterations, "
           f"{cfg.baseline.samples} samples, EM phase at {em_switch_text(cfg.i_switch)}; output {out}")
    t0 = time.perf_counter()
    summary = compare(task, cfg, seeds, out, task_name=Path(args.task).stem, progress=_progress(args),
                      restart=args.restart)
    _print("")
    _print(_table([{k: r[k] for k in ("claim", "baseline_mean", "dpsoc_mean", "diff_mean", "ci_low", "ci_high",
                                      "seeds_lower", "verdict", "held")}
                   for r in summary["claims"]]))
    worse = {m: sum(r["worse"] for r in rows) for m, rows in summary["final_vs_last"].items()}
    _print("final policies worse than their run's last sampled iteration: "
           + ", ".join(f"{m} {n}/{len(seeds)}" for m, n in worse.items()))
    _log_to_tensorboard(out, figures=sorted(out.glob("*.png")), step=cfg.baseline.iterations - 1)
    _print(f"\nreport: {summary['report']}  (total time {time.perf_counter() - t0:.0f}s)")
    return 0


def _cmd_verify(args) -> int:
    """Claims table (exit 1 when a verdict differs from the expected one), ``--replay`` of certificates
    (exit 1 when one does not reproduce), ``--write-certificates`` (the counterexample searches) or the
    older per-row table (``--rows``)."""
    from . import verification
    from .verification import registry

    if args.replay:
        from .verification.replay import replay_file

        ok_all = True
        for path in args.replay:
            ok, lines = replay_file(path)
            ok_all &= ok
            _print("\n".join(lines))
        return 0 if ok_all else 1
    if args.write_certificates:
        from .verification.certificates import write_certificates

        for p in write_certificates(args.write_certificates):
            _print(f"wrote {p}")
        return 0
    if args.instances is not None and args.instances < 1:
        raise ConfigError(f"--instances must be >= 1, got {args.instances}")
    if args.rows:
        results = verification.run_all(seed=args.seed, instances=args.instances or 20)
        _print(json.dumps(verification.to_json(results), indent=1) if args.json else verification.format_table(results))
        return 0
    t0 = time.perf_counter()
    only = None
    if args.only:
        only = tuple(k.strip() for k in args.only.split(","))
        known = [c.key for c in registry.CLAIMS]
        bad = [k for k in only if k not in known]
        if bad:
            raise ConfigError(f"--only: unknown claim key(s) {bad}; known: {known}")
    res = registry.run_claims(args.seed, full=args.full, instances=args.instances, only=only)
    doc = registry.verdicts_json(res)
    if args.full:  # rerun the counterexample searches and replay what they find
        from .verification.certificates import SEARCHES
        from .verification.replay import replay

        doc["searches"] = []
        for name, search in SEARCHES.items():
            cert = search()
            ok, _ = replay(json.loads(json.dumps(cert)))
            doc["searches"].append({"certificate": name, "n": cert["n"], "m": cert["m"], "T": cert["T"],
                                    "replay_ok": ok})
            doc["ok"] = doc["ok"] and ok
    doc["seconds"] = round(time.perf_counter() - t0, 2)
    if args.json:
        _print(json.dumps(doc, indent=1))
    else:
        _print(registry.format_verdicts(res))
        for srch in doc.get("searches", []):
            _print(f"search {srch['certificate']}: found at (n, m, T) = ({srch['n']}, {srch['m']}, {srch['T']}), "
                   f"replay {'ok' if srch['replay_ok'] else 'FAILED'}")
        _print(f"\n{'all verdicts as expected' if doc['ok'] else 'VERDICT DIFFERS FROM EXPECTED'} "
               f"({doc['seconds']:.1f} s)")
    return 0 if doc["ok"] else 1


def _parse_sizes(text: str, allow_T: bool = False) -> tuple[tuple[int, ...], ...]:
    """``"2x1,4x2"`` -> ``((2, 1), (4, 2))`` (with ``allow_T`` also ``NxMxT``); a clear error names a bad entry."""
    out = []
    for part in text.split(","):
        try:
            vals = tuple(int(x) for x in part.lower().split("x"))
        except ValueError:
            vals = ()
        if len(vals) not in ((2, 3) if allow_T else (2,)):
            raise ConfigError(f"--sizes: {part!r} is not NxM{' or NxMxT' if allow_T else ''} (e.g. 26x7)")
        if min(vals) < 1:
            raise ConfigError(f"--sizes: {part!r} needs n >= 1, m >= 1 (and T >= 1)")
        out.append(vals)
    return tuple(out)


def _cmd_solvers(args) -> int:
    """M-step solver benchmark (``soc_opt.bench.qp_bench``: families x accuracy levels, files and
    the qpbenchmark test set in ``--out``; ``--legacy``: the earlier ``soc_opt.bench.solvers``) and
    the KL-step comparison (closed form vs CasADi IPOPT, fatrop, sqpmethod) at the same sizes
    (``NxMxT``; ``NxM`` uses ``T = --kl-T``) unless ``--no-kl``."""
    from .bench import lqg as bench_lqg
    from .bench import qp_bench, solvers_report
    from .bench import solvers as bench_solvers

    given = _parse_sizes(args.sizes, allow_T=True) if args.sizes else None
    sizes = tuple(s[:2] for s in given) if given else (((2, 1), (4, 2)) if args.quick else bench_solvers.SIZES)
    kl_T = args.kl_T or (20 if args.quick else 100)
    kl_sizes = tuple((s[0], s[1], s[2] if len(s) == 3 else kl_T) for s in given) if given else \
        (((4, 2, 20),) if args.quick else ((4, 2, 20), (26, 7, 100)))
    instances = args.instances or (2 if args.quick else (10 if args.legacy else 6))
    T = args.T or (2 if args.quick else 3)
    if instances < 1 or T < 1 or kl_T < 1:
        raise ConfigError(f"--instances, --T and --kl-T must be >= 1, got {instances}, {T} and {kl_T}")
    from .bench.guard import Guard

    t0, c0 = time.perf_counter(), time.process_time()

    def line(text: str) -> None:  # progress, on standard error (standard output holds the tables or the JSON)
        print(f"[{time.perf_counter() - t0:6.1f} s] {text}", file=sys.stderr, flush=True)

    repeats = args.repeats or (1 if args.quick else 3)
    line(f"every solver call runs in a guarded worker: M-step calls stop at {qp_bench.call_limit_s(repeats):g} s "
         f"({repeats} solves of at most {qp_bench.TIME_LIMIT_S:g} s each plus {qp_bench.CALL_GRACE_S:g} s), KL-step calls "
         f"at {bench_lqg.KL_TIME_LIMIT_S:g} s, any call after more than {Guard().nan_limit} NaN reports; Ctrl-C stops")
    with solvers_report.quiet_stdout(), Guard() as guard:
        if args.legacy:
            progress = (lambda rs: solvers_report.write_rows(rs, args.out)) if args.out else None
            rows = bench_solvers.run(sizes=sizes, T=T, instances=instances, seed=args.seed, on_progress=progress)
            warm = [w for n, m in sizes[-2:] for w in bench_solvers.warm_vs_cold(n, m, seed=args.seed)]
        else:
            problems = qp_bench.make_problems(sizes, instances, args.seed)
            rows = qp_bench.run(problems=problems, repeats=repeats, call=guard.call, progress=line)
        l_rows = [] if args.no_kl else bench_lqg.run(sizes=kl_sizes, repeats=1 if args.quick else 5, sqp=args.sqp,
                                                     call=guard.call, progress=line)
    meta = {"sizes": sizes, "kl_sizes": kl_sizes, "instances": instances, "seed": args.seed,
            "wall_s": round(time.perf_counter() - t0, 1), "cpu_s": round(time.process_time() - c0, 1)}
    return _report_solvers(args, rows, l_rows, meta, warm if args.legacy else None, None if args.legacy else problems)


def _report_solvers(args, rows, l_rows, meta, warm, problems) -> int:
    from .bench import qp_bench, qp_bench_report, solvers_report

    legacy = warm is not None
    summary = solvers_report.summarize(rows) if legacy else qp_bench.summarize(rows)
    if args.out:
        if legacy:
            paths = solvers_report.write(rows, warm, args.out, dict(meta, T=args.T))
        else:
            paths = qp_bench_report.write(rows, args.out, meta)
            paths += qp_bench_report.export_qpbenchmark(problems, Path(args.out, "qpbenchmark"))[-1:]
        for p in paths:
            print(f"wrote {p}", file=sys.stderr if args.json else sys.stdout, flush=True)
        if l_rows:
            Path(args.out, "kl_step.json").write_text(json.dumps(l_rows, indent=1, default=float))
    if args.json:
        _print(json.dumps({"meta": meta, "mstep": summary, "warm_vs_cold": warm, "kl_step": l_rows}, indent=1,
                          default=float))
        return 0
    text = solvers_report.markdown(summary, warm) if legacy else qp_bench_report.markdown(summary)
    _print("M-step: every family, accuracy level and solver against an independent reference\n" + text)
    if l_rows:
        _print("\nKL-constrained LQG step: closed form vs CasADi IPOPT, fatrop and sqpmethod\n" + _table(l_rows))
    return 0


def _cmd_bench(args) -> int:
    from .bench import parse_parts, run_part

    out = {}
    for name in parse_parts(args.only):
        rows = run_part(name, quick=args.quick)
        out[name] = rows
        if not args.json:
            _print(f"\n== {name}\n" + _table(rows))
    if args.json:
        _print(json.dumps(out, indent=1, default=float))
    return 0


def _cmd_sweep(args) -> int:
    from .sweeps.sets import load_sweep_with_sets
    from .sweeps.spec import describe, load_sweep

    gym_modules = tuple(args.gym_module or ())  # every trial validated before anything starts
    spec = (load_sweep_with_sets(args.file, args.set, gym_modules=gym_modules) if args.set
            else load_sweep(args.file, gym_modules=gym_modules))
    out = Path(args.out or f"runs/sweep-{spec.name}")
    _print(f"sweep {spec.name}: {describe(spec)}; output {out}")
    if args.dry_run:
        _print("\n".join(t.id for t in spec.trials))
        return 0
    from .sweeps.runner import run_sweep

    res = run_sweep(spec, out, address=args.address, workers=args.workers, max_retries=args.max_retries)
    c = res["counts"]
    _print(f"{c['done']} done, {c['failed']} failed; report: {res['report']}  (trial states: {out / 'status.json'})")
    return 1 if c["failed"] else 0

def _cmd_config_doc(args) -> int:
    from .config_doc import render

    text = render()
    if args.out:
        Path(args.out).write_text(text)
        _print(f"wrote {args.out}")
    else:
        print(text, end="")
    return 0


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default, except for flags and options without one."""

    def _get_help_string(self, action):
        if action.default is None or isinstance(action.default, bool) or action.default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    from .methods.registry import METHODS

    p = argparse.ArgumentParser(
        prog="soc-opt", description="EM-based stochastic optimal control (DPSOC-EM).", formatter_class=_HelpFormatter,
        epilog="TASK is a built-in name (linear2d, peg, door), a task TOML file, or gym:<EnvId> for a Gymnasium "
               "MuJoCo environment (docs/gym.md); 'soc-opt tasks' lists every shipped task.  Output goes under "
               "runs/ unless --out says otherwise: runs/TASK-METHOD-seedSEED (run), runs/compare-TASK (compare), "
               "runs/sweep-NAME (sweep); a rerun with the same --out resumes.  --set KEY=VALUE overrides one "
               "setting (task.rho2=0.1, baseline.iterations=5).  Docs: docs/interface.md.")
    p.add_argument("--debug", action="store_true", help="show the traceback of an error (exit status still 2)")
    sub = p.add_subparsers(dest="command", required=True)

    def add(name: str, **kw) -> argparse.ArgumentParser:
        return sub.add_parser(name, formatter_class=_HelpFormatter, **kw)

    def common_algo(sp, default_out: str):
        sp.add_argument("task", help="a built-in task (linear2d, peg, door; 'soc-opt tasks' lists every shipped "
                                     "task), a task TOML file, or gym:<EnvId> for a Gymnasium MuJoCo environment "
                                     "(e.g. gym:Reacher-v5; docs/gym.md)")
        sp.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="override one setting, repeatable: task.KEY for the task (task.rho2=0.1), any other "
                             "dotted key for the run configuration (baseline.iterations=5, em.n_em=2); the value is "
                             "TOML and is checked like the TOML files' (applied after --config and the flags)")
        sp.add_argument("--config", help="algorithm configuration TOML (see docs/configuration.md)")
        sp.add_argument("--paper", action="store_true",
                        help="the paper's scale: its iterations, samples and EM switch (soc_opt.methods.config.PAPER)")
        sp.add_argument("--iterations", type=int, help="override baseline.iterations")
        sp.add_argument("--samples", type=int, help="override baseline.samples")
        sp.add_argument("--workers", type=int, help="parallel rollout workers")
        sp.add_argument("--i-switch", dest="i_switch", type=int,
                        help="override i_switch: the DPSOC-EM iteration after which the EM phase runs")
        sp.add_argument("--as-written", dest="as_written", action="store_true",
                        help="the paper's methods as written: no step acceptance, the last KL step's policy returned "
                             "(docs/math.md §12; [baseline.acceptance] enabled = false)")
        sp.add_argument("--out", help=f"output folder (default {default_out}); a rerun with the same --out resumes")
        sp.add_argument("--restart", action="store_true",
                        help="discard the run(s) already in --out and start from scratch")
        sp.add_argument("--progress", choices=["auto", "bar", "lines"], default="auto",
                        help="progress bar (auto: on a terminal) or plain lines")
        gym_module(sp)

    def gym_module(sp):
        sp.add_argument("--gym-module", dest="gym_module", action="append", metavar="MODULE",
                        help="let a task or sweep file's model = 'gym:MODULE:<EnvId>' import this Python module "
                             "(runs its code; repeatable; docs/gym.md)")

    r = add("run", help="run one method on a task, writing a resumable run directory")
    common_algo(r, "runs/TASK-METHOD-seedSEED")
    r.add_argument("--method", choices=list(METHODS), default="dpsoc-em", help="the method to run")
    r.add_argument("--seed", type=int, default=0, help="random seed of the run")
    r.add_argument("--previous-checkpoint", dest="previous_checkpoint", action="store_true",
                   help="resume from the checkpoint before the last (when the last one is damaged)")
    r.set_defaults(func=_cmd_run)

    c = add("compare", help="LQR-FLM vs DPSOC-EM on the same seeds, with a Markdown report")
    common_algo(c, "runs/compare-TASK")
    c.add_argument("--seeds", type=int, default=3, help="number of seeds")
    c.add_argument("--seed", type=int, default=0, help="first seed")
    c.set_defaults(func=_cmd_compare)

    v = add("verify", help="check the paper's claims (docs/math.md §9) numerically; exit 1 if a "
                           "verdict differs from the expected one")
    v.add_argument("--json", action="store_true")
    v.add_argument("--seed", type=int, default=0)
    v.add_argument("--instances", type=int, help="instances per claim (default 20; --full 100)")
    v.add_argument("--full", action="store_true", help="more instances and the literal CVXPY sweep")
    v.add_argument("--replay", nargs="+", metavar="FILE", help="re-check certificate files in exact rational and interval arithmetic")
    v.add_argument("--write-certificates", dest="write_certificates", metavar="DIR",
                   help="run the counterexample searches and write their certificates to DIR")
    v.add_argument("--only", help="comma-separated claim keys (uniqueness, uniqueness_sigma, ltv, dpsoc, "
                                  "em_lemma, cost_decrease, free_energy, hessian_impl, ecm, smoother, kl_step)")
    v.add_argument("--rows", action="store_true", help="the older per-row table (claims 1-4, rows 1a..4e)")
    v.set_defaults(func=_cmd_verify)

    s = add("solvers", help="M-step solver benchmark (every constraint set and solver) and the KL step "
                                       "(closed form vs CasADi/IPOPT and fatrop)")
    s.add_argument("--json", action="store_true")
    s.add_argument("--quick", action="store_true", help="tiny sizes only")
    s.add_argument("--sizes", help="sizes NxM or NxMxT, comma-separated, for the M-step (n, m) and the KL step "
                                   "(n, m, T; T = --kl-T if omitted); default 2x1,4x2,8x3,16x5,26x7 and KL 4x2x20,26x7x100")
    s.add_argument("--instances", type=int, help="random instances per size and family (default 6; --legacy 10)")
    s.add_argument("--repeats", type=int, help="timed calls per solve, median reported (default 3)")
    s.add_argument("--T", type=int, help="--legacy: steps per instance, each one problem (default 3)")
    s.add_argument("--kl-T", dest="kl_T", type=int, help="horizon of the KL-step sizes given as NxM (default 100)")
    s.add_argument("--sqp", action="store_true", help="KL step: also CasADi sqpmethod on the structured NLP")
    s.add_argument("--legacy", action="store_true", help="the earlier benchmark (soc_opt.bench.solvers)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", help="write the table (md/CSV/JSON), profiles and plots into this directory")
    s.add_argument("--no-kl", dest="no_kl", action="store_true", help="skip the KL-step comparison")
    s.set_defaults(func=_cmd_solvers)

    from .bench import DEFAULT_PARTS as bench_default
    from .bench import PARTS as bench_parts

    b = add("bench", help="benchmarks: rollouts, fitting, E-step, M-step, LQG, full iterations")
    b.add_argument("--json", action="store_true")
    b.add_argument("--only", help="comma-separated subset of: " + ", ".join(bench_parts) + " (default: "
                   + ",".join(bench_default) + ")")
    b.add_argument("--quick", action="store_true", help="tiny sizes: checks every code path in seconds")
    b.set_defaults(func=_cmd_bench)

    t = add("tasks", help="list every task shipped with soc_opt (and how to name gym: tasks)")
    t.set_defaults(func=_cmd_tasks)

    w = add("sweep", help="a grid of trials (tasks x settings x methods x seeds) on Ray (docs/sweeps.md)")
    w.add_argument("file", help="sweep TOML file")
    w.add_argument("--out", help="output directory (default runs/sweep-NAME); a rerun skips finished trials")
    w.add_argument("--address", help="join this Ray cluster (default: start a local Ray on this machine's cores; "
                   "token authentication: docs/sweeps.md)")
    w.add_argument("--workers", type=int, help="at most this many trials at once (default: all cores)")
    w.add_argument("--max-retries", dest="max_retries", type=int, default=3,
                   help="re-executions of a trial whose worker process died (resumes from its checkpoint)")
    w.add_argument("--dry-run", dest="dry_run", action="store_true", help="validate and list the trials only")
    gym_module(w)
    w.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting of every trial, repeatable: merged into the sweep file's [common] "
                        "(task.T=20, baseline.iterations=5), so a [grid] or [[settings]] key still wins")
    w.set_defaults(func=_cmd_sweep)

    d = add("config-doc", help="write the configuration reference (docs/configuration.md)")
    d.add_argument("--out", help="write to this file instead of standard output")
    d.set_defaults(func=_cmd_config_doc)

    k = add("convert-checkpoint",
                       help="convert the old pickle checkpoints under DIR (only for a directory you trust)")
    k.add_argument("dir", help="run, compare or sweep directory")
    k.add_argument("--trust", action="store_true",
                   help="required: reading a pickle runs the code it holds; give it only for files you trust")
    k.set_defaults(func=_cmd_convert_checkpoint)
    return p


def _cmd_convert_checkpoint(args) -> int:
    from .experiments.convert_checkpoint import convert_directory

    done = convert_directory(args.dir, trust=args.trust)
    for old, new in done:
        _print(f"converted {old} -> {new.name}")
    _print(f"{len(done)} checkpoint{'s' if len(done) != 1 else ''} converted under {args.dir}")
    return 0


def _one_line(e: BaseException, *, hint: bool = True) -> str:
    """The error as one line: its message (type name too when it is not one of ours) and notes."""
    from .errors import FlatCostError, SolverError
    from .tasks import SimulationError

    ours = (ConfigError, FileNotFoundError, SimulationError, SolverError, FlatCostError)
    text = str(e) if isinstance(e, ours) else f"{type(e).__name__}: {e}"
    parts = [shorten(text, MAX_MESSAGE)] + list(getattr(e, "__notes__", ()))
    if hint and not isinstance(e, ours):
        parts.append("rerun with --debug for the traceback")
    return " ".join("; ".join(p.strip() for p in parts if p.strip()).split())


def main(argv: list[str] | None = None) -> int:
    argv_is_process = argv is None  # the console script, not a caller in Python
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    args = build_parser().parse_args([a for a in argv if a != "--debug"])
    try:
        return args.func(args)
    except KeyboardInterrupt:
        resumes = args.command in ("run", "compare", "sweep")
        print("\nsoc-opt: interrupted" + ("; rerun the same command to resume from the last finished iteration"
                                         if resumes else ""), file=sys.stderr)
        if args.command == "solvers" and argv_is_process:  # nothing to save: skip the interpreter's ~1 s teardown
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(130)
        return 130
    except BrokenPipeError:  # the reader of the output went away (`soc-opt ... | head`): stop as a pipe stage does
        try:  # no second error when the interpreter flushes standard output at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141
    except Exception as e:
        if debug:
            traceback.print_exc()
        print(f"soc-opt: error: {_one_line(e, hint=not debug)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
