"""Side-by-side comparison of LQR-FLM and DPSOC-EM on the same seeds (docs/math.md §9.5).

For each seed the baseline runs first; DPSOC-EM starts from a copy of the baseline's state at
``i_switch`` (same policy, prior and RNG state), so both methods share their first
``i_switch`` iterations exactly and differ only from the EM phase on.  Each method's final
policy is then evaluated on ``evaluation.samples`` fresh rollouts drawn with the same evaluation
seed for both methods (:func:`evaluate_policy`, :class:`~soc_opt.methods.config.EvalConfig`).
Everything is written under ``out/``; a rerun with the same ``out`` resumes.
``out`` is locked while the comparison runs (:func:`soc_opt.experiments.rundir.lock_directory`), and each
method's run directory checks its contract (:mod:`soc_opt.experiments.rundir`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from .. import files, plugins
from ..config import ConfigError
from ..methods.config import DPSOCConfig, EvalConfig, check_scale, with_task_init_var
from ..methods.lqr_flm.acceptance import rank_worse
from ..methods.state import RunState
from ..models import LinearGaussianPolicy, Rollouts
from ..noise.aware import mean_action
from . import report
from .progress import Progress, as_progress
from .run import fork_state, run_experiment
from .rundir import (
    CheckpointError,
    RunDirectoryError,
    decode_checkpoint,
    encode_checkpoint,
    lock_directory,
    npz_bytes,
    refuse_foreign,
    refuse_legacy,
    run_record,
    unowned_entries,
)

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["compare", "evaluate_policy", "spreads", "point_names", "point_targets", "action_names", "final_vs_last",
           "worse_than_batch", "WORSE_MARGIN", "WORSE_ALPHA"]

#: The compared pair: the baseline and the method forked from its state at ``i_switch`` (registry names,
#: looked up in :data:`soc_opt.plugins.METHODS`).
BASELINE, FORKED = "lqr-flm", "dpsoc-em"
METHODS = (BASELINE, FORKED)


def point_names(task) -> list[str] | None:
    """Names of the end-effector points drawn in the figures (the task's state sites)."""
    sites = list(getattr(getattr(task.config, "state", None), "sites", ()) or ())
    return sites or None


def action_names(task) -> list[str]:
    """Names of the actions in the figures: the task's actuators (MuJoCo), else ``action i``."""
    names = list(getattr(task, "actuated", None) or ())
    return names if len(names) == task.m else [f"action {i}" for i in range(task.m)]


def point_targets(task) -> np.ndarray | None:
    """``(P, 3)`` targets of the drawn points, from the task's point cost (or its metric target)."""
    sites = point_names(task)
    cfg = task.config
    if sites:
        for term in getattr(cfg, "cost", ()):
            tgt = getattr(term, "target", None)
            if tuple(getattr(term, "sites", ()) or ()) == tuple(sites) and tgt and len(tgt) == 3 * len(sites):
                return np.asarray(tgt, float).reshape(len(sites), 3)
        return None
    tgt = tuple(getattr(getattr(cfg, "metric", None), "target", ()) or ())
    if 0 < len(tgt) <= 3:
        return np.pad(np.asarray(tgt, float), (0, 3 - len(tgt)))[None]
    return None


def evaluate_policy(task: Task, policy: LinearGaussianPolicy, samples: int, seed: int, workers: int = 1,
                    evaluation: EvalConfig = EvalConfig()) -> Rollouts:
    """``samples`` fresh rollouts of ``policy`` from the evaluation stream of ``seed``.

    The generator is seeded with ``evaluation.seed_offset + seed``, so that every method is
    evaluated on the same noise, distinct from its training samples (docs/math.md §9.5).
    """
    rng = np.random.default_rng(evaluation.seed_offset + seed)
    return task.rollouts(policy, samples, rng, workers=workers)


def spreads(task: Task, ro: Rollouts) -> dict[str, float]:
    """Final-policy statistics of the claims table (:func:`soc_opt.experiments.report.claims_table`).

    ``cost``: mean true-state total cost; ``state_spread``: mean over time and points of the std
    over samples of the end-effector points; ``action_spread``: the same for the actions.
    """
    pts = np.asarray(task.ee_points(ro.x))  # (S, T+1, P, 3)
    return {
        "cost": float(np.mean(task.true_cost(ro).sum(-1))),
        "state_spread": float(np.mean(pts.std(axis=0))),
        "action_spread": float(np.mean(ro.a.std(axis=0))),
    }


def compare(
    task: Task,
    cfg: DPSOCConfig,
    seeds: list[int],
    out: str | Path,
    *,
    task_name: str | None = None,
    eval_samples: int | None = None,
    progress: Progress | Callable[[str], None] | None = None,
    restart: bool = False,
) -> dict:
    """Run both methods on ``seeds``, write figures and ``report.md`` under ``out``; return a summary.

    ``eval_samples`` (optional) overrides ``cfg.evaluation.samples`` for the final evaluation;
    ``restart`` discards the runs already in ``out``.
    ``progress``: a :class:`soc_opt.experiments.progress.Progress` (a bar over the seeds above each run's
    bar over its iterations, or plain lines), a callable printing lines, or ``None``.
    """
    plugins.METHODS.lookup(FORKED).check_config(cfg)
    if not 1 <= len(seeds) <= MAX_SEEDS:
        raise ConfigError(f"compare runs 1 to {MAX_SEEDS} seeds, got {len(seeds)}")
    check_scale(cfg, task)
    if eval_samples is not None:
        check_scale(cfg.replace(evaluation=cfg.evaluation.replace(samples=eval_samples)), task)
    cfg = with_task_init_var(cfg, task)  # the task's init_var unless the configuration sets one
    progress = as_progress(progress)
    out = Path(out)
    check_compare_dir(out)  # before the lock file is created
    with lock_directory(out, what="compare directory"):
        check_compare_dir(out)
        files.write_json(out / COMPARE_FILE, {"format": COMPARE_FORMAT, "task": task_name or task.name,
                                              "seeds": list(seeds)}, anchor=out, indent=1)
        return _compare_locked(task, cfg, seeds, out, task_name, eval_samples, progress, restart)


#: Most seeds one comparison runs (each is two runs).
MAX_SEEDS = 1000
#: ``compare.json``: what marks a folder as a compare directory.
COMPARE_FILE, COMPARE_FORMAT = "compare.json", "soc_opt compare"
_SEED_DIR = re.compile(r"seed_\d+")


def check_compare_dir(out: Path) -> None:
    """Refuse (:class:`~soc_opt.experiments.rundir.RunDirectoryError`) an ``out`` that is neither new, empty
    nor a compare directory (its ``compare.json``; one written before it: ``seed_N`` folders holding run
    directories): a comparison writes into no folder of the user's, and ``--restart`` removes only its files."""
    if os.path.lexists(out) and not out.is_dir():
        raise RunDirectoryError(f"--out {str(out)!r} exists and is not a folder; use another --out")
    try:
        rec = files.read_json_file(out / COMPARE_FILE) if os.path.lexists(out / COMPARE_FILE) else None
    except (OSError, ConfigError):
        rec = None
    if isinstance(rec, dict) and rec.get("format") == COMPARE_FORMAT:
        return
    foreign = unowned_entries(out)
    seeds = [n for n in foreign if _SEED_DIR.fullmatch(n) and (out / n).is_dir() and not (out / n).is_symlink()]
    runs = [run_record(out / n / m) for n in seeds for m in METHODS if (out / n / m).exists()]
    if runs and all(r is not None for r in runs):
        return  # a compare directory from before compare.json: seed_N folders holding run directories only
    refuse_foreign(out, foreign, "a compare directory", "compare.json")


def _compare_locked(task, cfg, seeds, out, task_name, eval_samples, progress, restart) -> dict:
    eval_samples = eval_samples or cfg.evaluation.samples or cfg.baseline.samples
    workers = cfg.baseline.workers
    per_seed = {m: {"cost": [], "state_spread": [], "action_spread": []} for m in METHODS}
    histories = {m: [] for m in METHODS}
    eval_ro = {m: [] for m in METHODS}
    eval_mean = {m: [] for m in METHODS}
    seeds_bar = progress.bar(len(seeds), "seeds") if progress else None
    try:
        for seed in seeds:
            _compare_seed(task, cfg, seed, out, task_name, eval_samples, workers, progress,
                          per_seed, histories, eval_ro, eval_mean, restart)
            if seeds_bar is not None:
                final = {m: float(np.mean(per_seed[m]["cost"][-1])) for m in METHODS}
                seeds_bar.advance(f"seed {seed}: final cost LQR-FLM {final[BASELINE]:.4g}, "
                                  f"DPSOC-EM {final[FORKED]:.4g}",
                                  **{f"cost {m}": v for m, v in final.items()})
    finally:
        if seeds_bar is not None:
            seeds_bar.close()
    return _write_report(task, cfg, seeds, out, per_seed, histories, eval_ro, eval_mean, task_name or task.name)


def _compare_seed(task, cfg, seed, out, task_name, eval_samples, workers, progress, per_seed, histories, eval_ro,
                  eval_mean, restart):
    """Both methods on one seed (see :func:`compare`); appends to the per-method accumulators."""
    level = 1 if progress is not None and progress.mode == "bar" else 0
    sdir = out / f"seed_{seed}"
    files.make_dirs(sdir, anchor=out)
    fork_path = sdir / "fork_state.npz"  # a checkpoint (soc_opt.experiments.statefile): data only
    if restart:
        for p in (fork_path, sdir / "fork_state.pkl"):
            files.remove(p, anchor=out)
    refuse_legacy(sdir, ("fork_state.pkl",))

    def keep_fork(st: RunState, _p=fork_path):
        if st.iteration == cfg.i_switch and not os.path.lexists(_p):
            files.write_bytes(_p, encode_checkpoint(st), anchor=out)

    # Baseline, with a copy of its state kept at i_switch for DPSOC-EM to start from.
    base = run_experiment(task, BASELINE, cfg, seed, sdir / BASELINE, task_name=task_name,
                          progress=progress, on_iteration=keep_fork, bar_level=level, restart=restart, anchor=out)
    try:
        fork = decode_checkpoint(fork_path) if os.path.lexists(fork_path) else None
    except CheckpointError:
        fork = None  # damaged: it is recomputed below
    if fork is None or fork.iteration != cfg.i_switch:
        # i_switch == 0, a baseline resumed past i_switch without its fork, or a damaged fork:
        # replay the deterministic baseline prefix in memory.
        baseline = plugins.METHODS.lookup(BASELINE)
        st = baseline.initial_state(task, cfg, seed)
        while st.iteration < cfg.i_switch:
            st = baseline.iterate(task, cfg, st)
        files.write_bytes(fork_path, encode_checkpoint(st), anchor=out)
        fork = st
    em = run_experiment(
        task, FORKED, cfg, seed, sdir / FORKED, task_name=task_name, progress=progress,
        start_state=fork_state(fork), bar_level=level, restart=restart, anchor=out,
    )
    for meth, st in ((BASELINE, base), (FORKED, em)):
        policy = plugins.METHODS.lookup(meth).final_policy(cfg, st)
        ro = evaluate_policy(task, policy, eval_samples, seed, workers, cfg.evaluation)
        ro_mean = evaluate_policy(task, mean_action(policy), eval_samples, seed, workers, cfg.evaluation)
        eval_ro[meth].append(ro)
        eval_mean[meth].append(ro_mean)
        for k, v in spreads(task, ro).items():
            per_seed[meth][k].append(v)
        histories[meth].append(st.history)
        files.write_bytes(sdir / meth / "final_eval.npz", npz_bytes(**ro.to_dict()), anchor=out)
        files.write_bytes(sdir / meth / "final_eval_mean_action.npz", npz_bytes(**ro_mean.to_dict()), anchor=out)


#: what each state estimator does (docs/math.md §10, §11); the paper's method is "none"
ESTIMATOR_TEXT = {
    "none": "none: the paper's method (the policy acts on the measured state, the learner fits on it)",
    "kalman": "kalman (docs/math.md §10.2, beyond the paper): the policy acts on a Kalman filter of the fitted model",
    "kinematic": "kinematic (docs/math.md §11, beyond the paper): the learner fits on a structured smoother that knows "
                 "the robot's kinematics, the policy acts on its online filter",
}


def noise_text(noise) -> str:
    """The run's ``[baseline.noise]`` settings for the report: the estimator, and every option that differs
    from its default (docs/configuration.md)."""
    text = ESTIMATOR_TEXT.get(noise.estimator, f"{noise.estimator} (a registered plug-in estimator)")
    ours, default = noise.to_dict(), type(noise)().to_dict()
    changed = {k: v for k, v in ours.items() if k != "estimator" and default.get(k) != v}
    return text + ("; [baseline.noise] " + ", ".join(f"{k} = {v}" for k, v in changed.items()) if changed
                   else "; other [baseline.noise] options at their defaults")


def _acceptance_text(acc) -> str:
    if not acc.enabled:
        return "off (the paper as written: every step taken, the last KL step's policy returned)"
    return (f"on (docs/math.md §12: kappa {acc.kappa:g}, eps {acc.eps:g}, shrink {acc.shrink:g}, ceiling {acc.ceiling:g}, "
            f"{acc.cost} cost; the last accepted policy returned)")



#: "worse" needs a mean rise of more than this fraction of ``|C_last|`` (docs/math.md §12.3)
WORSE_MARGIN = 0.1
#: and one of the two one-sided tests below this level, each at half of it (Bonferroni)
WORSE_ALPHA = 0.05


def worse_than_batch(c_last, c_fin, alpha: float = WORSE_ALPHA, margin: float = WORSE_MARGIN) -> dict:
    """Is a policy's fresh evaluation ``c_fin (m,)`` worse than the batch ``c_last (n,)`` it is compared with?
    (docs/math.md §12.3): :func:`soc_opt.methods.lqr_flm.acceptance.rank_worse` at ``alpha`` and ``margin``,
    a material rise of the mean confirmed by one of two one-sided rank tests.

    Returns ``{"ratio", "rise", "p_rank", "p_tail", "exceed", "worse"}``.
    """
    return rank_worse(c_last, c_fin, alpha, margin)


def final_vs_last(task, history, ro: Rollouts, acceptance=None) -> dict:
    """The final policy's evaluation against the run's last sampled batch (true-state total costs).

    ``worse``: :func:`worse_than_batch` of the final policy's fresh rollouts against the last sampled batch
    (a material rise confirmed by a rank test; docs/math.md §12.3).  ``acceptance`` is not used (the step
    acceptance test of §12.1 compares means through standard errors, which the heavy tails of a fresh
    evaluation widen until a 4x rise passes); kept for callers that pass it.
    """
    last = [r for r in history if r.phase == "baseline"][-1]
    c_last = np.asarray(last.cost, float)
    c_fin = np.asarray(task.true_cost(ro).sum(-1), float)
    w = worse_than_batch(c_last, c_fin)
    return {"last_iteration": int(last.iteration), "last_sampled_cost": float(c_last.mean()),
            "final_cost": float(c_fin.mean()), "ratio": w["ratio"], "p_rank": w["p_rank"], "p_tail": w["p_tail"],
            "worse": w["worse"]}


def _by_metric(final_metrics: dict, kind: str, keys) -> dict:
    """``{method: {metric: [value per seed]}}`` of one kind ("sampled" or "mean") of final evaluation."""
    return {m: {k: [float(r[k]) for r in final_metrics[m, kind]] for k in keys} for m in METHODS}


def _write_report(task, cfg, seeds, out, per_seed, histories, eval_ro, eval_mean, name) -> dict:
    # Cost per iteration: the baseline-phase records (one per iteration), samples pooled over seeds.
    costs = {}
    metric_hist = {}
    for meth in METHODS:
        n_it = cfg.baseline.iterations
        per_it = [[] for _ in range(n_it)]
        met = []
        for hist in histories[meth]:
            rows = [r for r in hist if r.phase == "baseline"]
            for r in rows:
                per_it[r.iteration].extend(np.asarray(r.cost).tolist())
            met.append([r.metrics for r in rows])
        costs[meth] = [np.asarray(c) for c in per_it]
        metric_hist[meth] = met
    figs = {}
    figs["Expected cost per iteration (box plots over samples and seeds)"] = report.plot_costs(
        costs, out / "cost_per_iteration.png", f"{name}: total cost per iteration", i_switch=cfg.i_switch)
    pts = {m: np.concatenate([np.asarray(task.ee_points(ro.x)) for ro in eval_ro[m]]) for m in METHODS}
    figs["End-effector trajectories of the final policies"] = report.plot_ee(
        pts, task.dt, out / "ee_trajectories.png", f"{name}: end-effector points",
        point_names=point_names(task), targets=point_targets(task))
    acts = {m: np.concatenate([ro.a for ro in eval_ro[m]]) for m in METHODS}
    figs["Actions per actuator of the final policies (over samples and time)"] = report.plot_actions(
        acts, out / "actions.png", f"{name}: actions per actuator", names=action_names(task))
    first_metrics = metric_hist[BASELINE][0][0] if metric_hist[BASELINE] and metric_hist[BASELINE][0] else {}
    extra_tables = {}
    for key in first_metrics:
        vals = {m: np.array([[row[key] for row in seed_rows] for seed_rows in metric_hist[m]]) for m in METHODS}
        if key == "min_hinge":
            figs["Minimum hinge angle per iteration (lower is better; mean ± std over seeds)"] = report.plot_metric(
                vals, out / "min_hinge.png", f"{name}: minimum hinge angle of the sampled batch",
                "min hinge angle over the rollout [rad]", i_switch=cfg.i_switch)
        elif key in ("min_distance",):
            figs["Minimum distance to the target per iteration (lower is better; mean ± std over seeds)"] = \
                report.plot_metric(vals, out / f"{key}.png", f"{name}: minimum distance to the target of the sampled batch",
                                   "min distance over the rollout [m]", i_switch=cfg.i_switch)
    # the final policies' task metrics (and true cost), sampled and with the mean action, computed once
    final_metrics = {(m, kind): [{**task.metrics(ro), "cost": float(np.mean(task.true_cost(ro).sum(-1)))} for ro in ros]
                     for m in METHODS for kind, ros in (("sampled", eval_ro[m]), ("mean", eval_mean[m]))}
    metric_rows = []
    for key in ["cost", *[k for k in first_metrics if k != "cost"]]:
        metric_rows.append([key] + [report.mean_std([r[key] for r in final_metrics[m, kind]])
                                    for m in METHODS for kind in ("sampled", "mean")])
    extra_tables[f"Task metrics of the final policies, sampled and mean action ({report.over_seeds(len(seeds))})"] = (
        ["metric", "LQR-FLM sampled", "LQR-FLM mean action", "DPSOC-EM sampled", "DPSOC-EM mean action"], metric_rows)
    fvl = {m: [final_vs_last(task, h, ro, cfg.baseline.acceptance) for h, ro in zip(histories[m], eval_ro[m])]
           for m in METHODS}
    extra_tables["Final policy against the run's last sampled iteration (true-state cost)"] = (
        ["seed"] + [f"{m} {c}" for m in ("LQR-FLM", "DPSOC-EM") for c in ("last sampled", "final", "ratio")],
        [[seed] + [x for m in METHODS for x in (f"{fvl[m][i]['last_sampled_cost']:.4g}", f"{fvl[m][i]['final_cost']:.4g}",
                                                 f"{fvl[m][i]['ratio']:.3g}" + (" **worse**" if fvl[m][i]["worse"] else ""))]
         for i, seed in enumerate(seeds)])
    em_rows = []
    for seed, hist in zip(seeds, histories[FORKED]):
        for r in hist:
            if r.em is not None:
                e = r.em
                em_rows.append([seed, e.recursion, f"{np.mean(r.cost):.4g}", f"{e.surrogate_old:.5g}",
                                f"{e.surrogate_new:.5g}", f"{e.loglik_old:.5g}", f"{e.loglik_new:.5g}"])
    extra_tables["EM phase diagnostics"] = (
        ["seed", "recursion", "cost of sampled policy", "surrogate before", "surrogate after",
         "log p(Y) before", "log p(Y) after"], em_rows)
    claims = report.claims_table(per_seed)
    setup = {
        "task": name,
        "seeds": ", ".join(map(str, seeds)),
        "iterations": cfg.baseline.iterations,
        "samples per iteration": cfg.baseline.samples,
        "EM phase at": report.em_switch_text(cfg.i_switch),
        "EM recursions": cfg.em.n_em,
        "Y mode": cfg.em.y_mode,
        "M-step": f"{cfg.em.method}, {cfg.em.variant}, objective {cfg.em.objective}, "
                  + ("entropy floor" if cfg.em.entropy_floor else f"covariance floor {cfg.em.cov_floor_scale} x current"),
        "sensor noise rho^2": getattr(task, "rho2", "n/a"),
        "state estimator": noise_text(cfg.baseline.noise),
        "step acceptance": _acceptance_text(cfg.baseline.acceptance),
        "final policies worse than their last sampled iteration": ", ".join(
            f"{m} {sum(r['worse'] for r in fvl[m])}/{len(seeds)}" for m in METHODS),
    }
    notes = [
        "Costs are evaluated on the true simulator states; the controllers only see measured states.",
        "Both methods share their first i_switch iterations exactly (same seed, same RNG stream); "
        "final policies are evaluated on fresh rollouts with the same evaluation seed for both methods.",
        "A claim 'held' when the 95% paired bootstrap interval of DPSOC-EM minus LQR-FLM over seeds lies below 0 "
        "and the one-sided signed-rank test agrees at 5% (p shown); 'reversed' when the interval lies wholly above "
        "0; 'untestable with N seeds' below 5 seeds, where the signed-rank test cannot reach 5% (docs/math.md §12.3).",
        f"A final policy is 'worse' than its run's last sampled batch when its fresh rollouts' mean cost is more than "
        f"{WORSE_MARGIN:.0%} above the batch's and a one-sided rank test confirms it at {WORSE_ALPHA / 2:.1%}: "
        "Mann-Whitney U (the bulk) or Rosenbaum's exceedance test (fresh rollouts above the batch's largest) "
        "(docs/math.md §12.3).",
        "The final policy is the method's returned policy (with step acceptance: its last accepted policy); it is "
        "evaluated sampled (with its exploration covariance) and with its mean action K s + k on the same evaluation seed.",
    ]
    md = report.write_markdown(out / "report.md", title=f"DPSOC-EM vs LQR-FLM on {name}", setup=setup,
                               claims=claims, figures=figs, extra_tables=extra_tables, notes=notes)
    summary = {"task": name, "seeds": list(seeds), "claims": claims, "per_seed": per_seed,
               "metrics_sampled": _by_metric(final_metrics, "sampled", first_metrics),
               "metrics_mean_action": _by_metric(final_metrics, "mean", first_metrics),
               "final_vs_last": fvl,
               "report": str(md), "config": cfg.to_dict()}
    files.write_json(out / "summary.json", summary, anchor=out, indent=1, default=float)
    return summary
