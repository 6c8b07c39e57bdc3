"""The aggregated report of a sweep: tables (CSV + Markdown) and figures (PNG).

Written beside the trial directories in the sweep's output directory:

- ``trials.csv``: one row per trial (state, final-policy statistics, error);
- ``summary.csv``: one row per (task, setting, method): seeds finished/failed and, for each
  quantity, its mean and standard deviation over the finished seeds;
- ``report.md``: the setup, the settings, one table per task (mean ± std over seeds), the failed
  trials, and the figures;
- ``final_<task>.png``: final cost and task metrics per setting and method (bars: mean over seeds,
  error bars: std over seeds);
- ``cost_<task>.png``: mean sampled cost per iteration, mean ± std over seeds, one panel per setting;
- ``versus_<key>_<task>.png`` (when the grid has one key and its values are numbers, e.g.
  ``task.rho2``): final cost and task metrics against that key, one line per ``[[settings]]``
  entry and method (mean ± std over seeds).

Quantities are those of ``soc-opt compare``: ``final_cost`` (mean true total cost of the final
policy on ``eval_samples`` fresh rollouts, evaluation seed ``10000 + seed``), ``state_spread``,
``action_spread``, the task metrics of those rollouts (``metric_*``) and ``best_cost`` (the best
mean sampled cost of the run).  Standard deviations are over seeds with ``ddof = 0`` (as in
``soc-opt compare``).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from .. import files  # noqa: E402
from ..experiments.report import COLORS, LABELS, verdict_text  # noqa: E402
from .spec import RESULT, SweepSpec, describe, read_result, setting_table  # noqa: E402

__all__ = ["write_report", "aggregate", "claims_rows", "versus_key", "QUANTITIES"]

QUANTITIES = ("final_cost", "state_spread", "action_spread", "best_cost")


def _flat_result(res: dict) -> dict:
    row = {q: res.get(q) for q in QUANTITIES}
    row.update({f"metric_{k}": v for k, v in (res.get("metrics") or {}).items()})
    if "final_cost_mean_action" in res:  # the same final policy with its mean action (docs/math.md §12.3)
        row["final_cost_mean_action"] = res["final_cost_mean_action"]
        row.update({f"mean_action_{k}": v for k, v in (res.get("metrics_mean_action") or {}).items()})
    for k in ("rejected_steps", "final_vs_last_ratio", "final_vs_last_worse"):
        if k in res:
            row[k] = float(res[k])
    return row


def claims_rows(spec: SweepSpec, results: dict[str, dict]) -> list[dict]:
    """The paper's claims (DPSOC-EM against LQR-FLM, docs/math.md §9.5) per task and setting, paired
    over the seeds both methods finished (:func:`soc_opt.experiments.report.claims_table`)."""
    from ..experiments.report import claims_table

    rows = []
    if not {"lqr-flm", "dpsoc-em"} <= set(spec.methods):
        return rows
    for task in spec.tasks:
        for s in spec.settings:
            by = {m: {t.seed: results[t.id] for t in spec.trials
                      if (t.task_label, t.setting, t.method) == (task, s.name, m) and t.id in results}
                  for m in ("lqr-flm", "dpsoc-em")}
            seeds = sorted(set(by["lqr-flm"]) & set(by["dpsoc-em"]))
            if not seeds:
                continue
            per_seed = {m: {q: [by[m][sd][q] for sd in seeds] for q in ("final_cost", "state_spread", "action_spread")}
                        for m in by}
            per_seed = {m: {"cost": v["final_cost"], "state_spread": v["state_spread"],
                            "action_spread": v["action_spread"]} for m, v in per_seed.items()}
            for r in claims_table(per_seed):
                rows.append({"task": task, "setting": s.name, **r})
    return rows


def aggregate(spec: SweepSpec, results: dict[str, dict]) -> list[dict]:
    """One row per (task, setting, method): seeds done/failed, mean and std of each quantity.

    ``results[trial_id]`` is the trial's ``result.json`` (finished trials only).
    """
    rows = []
    for task in spec.tasks:
        for s in spec.settings:
            for m in spec.methods:
                trials = [t for t in spec.trials if (t.task_label, t.setting, t.method) == (task, s.name, m)]
                done = [_flat_result(results[t.id]) for t in trials if t.id in results]
                row = {"task": task, "setting": s.name, "method": m, "seeds_done": len(done),
                       "seeds_failed": len(trials) - len(done)}
                keys = list(dict.fromkeys(k for r in done for k in r))
                for k in keys:
                    vals = np.array([r[k] for r in done if r.get(k) is not None], float)
                    row[f"{k}_mean"] = float(vals.mean()) if vals.size else float("nan")
                    row[f"{k}_std"] = float(vals.std()) if vals.size else float("nan")
                rows.append(row)
    return rows


def _write_csv(path: Path, rows: list[dict]) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    files.write_text(path, buf.getvalue())


def _fmt(x) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "—"
    return f"{x:.4g}"


def _quantity_keys(rows: list[dict]) -> list[str]:
    keys = [k[: -len("_mean")] for r in rows for k in r if k.endswith("_mean")]
    return list(dict.fromkeys(keys))


def _plot_final(task: str, spec: SweepSpec, rows: list[dict], path: Path) -> Path | None:
    keys = [k for k in _quantity_keys(rows) if k == "final_cost" or k.startswith("metric_")]
    if not keys:
        return None
    settings = [s.name for s in spec.settings]
    fig, axes = plt.subplots(len(keys), 1, figsize=(max(6.0, 1.2 * len(settings) + 3), 3.2 * len(keys)),
                             squeeze=False)
    width = 0.8 / len(spec.methods)
    x = np.arange(len(settings))
    for ax, key in zip(axes[:, 0], keys):
        for j, m in enumerate(spec.methods):
            by = {r["setting"]: r for r in rows if r["method"] == m}
            mean = [by[s].get(f"{key}_mean", np.nan) for s in settings]
            std = [by[s].get(f"{key}_std", np.nan) for s in settings]
            ax.bar(x + (j - (len(spec.methods) - 1) / 2) * width, mean, width * 0.9, yerr=std, capsize=3,
                   color=COLORS.get(m, "gray"), alpha=0.7, label=LABELS.get(m, m))
        ax.set_xticks(x, settings, rotation=20 if len(settings) > 3 else 0, ha="right" if len(settings) > 3 else "center")
        ax.set_ylabel(key.replace("metric_", ""))
        ax.grid(alpha=0.3, axis="y")
    axes[0, 0].legend(fontsize=8, loc="lower right")
    axes[0, 0].set_title(f"{task}: final policies, mean ± std over seeds")
    fig.tight_layout()
    files.save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def _plot_costs(task: str, spec: SweepSpec, results: dict[str, dict], path: Path) -> Path | None:
    settings = [s.name for s in spec.settings]
    ncol = min(3, len(settings))
    nrow = -(-len(settings) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.5 * ncol, 3.3 * nrow), squeeze=False)
    drawn = False
    for ax, s in zip(axes.ravel(), settings):
        for m in spec.methods:
            curves = [results[t.id]["cost_per_iteration"] for t in spec.trials
                      if (t.task_label, t.setting, t.method) == (task, s, m) and t.id in results]
            if not curves:
                continue
            n = min(len(c) for c in curves)
            c = np.array([cv[:n] for cv in curves], float)
            it = np.arange(1, n + 1)
            ax.plot(it, c.mean(0), "o-", ms=3, color=COLORS.get(m, "gray"), label=LABELS.get(m, m))
            ax.fill_between(it, c.mean(0) - c.std(0), c.mean(0) + c.std(0), color=COLORS.get(m, "gray"), alpha=0.2)
            drawn = True
        ax.set_title(s, fontsize=9)
        ax.set_xlabel("iteration")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(settings):]:
        ax.set_visible(False)
    if not drawn:
        plt.close(fig)
        return None
    axes[0, 0].set_ylabel("mean sampled cost")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{task}: cost per iteration, mean ± std over seeds")
    fig.tight_layout()
    files.save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def versus_key(spec: SweepSpec) -> str | None:
    """The grid's single key when every setting has exactly one numeric grid value, else None."""
    labels = {s.grid[0][0] for s in spec.settings if len(s.grid) == 1}
    if len(labels) != 1 or any(len(s.grid) != 1 or isinstance(s.grid[0][1], bool)
                               or not isinstance(s.grid[0][1], (int, float)) for s in spec.settings):
        return None
    return labels.pop()


def _plot_versus(task: str, spec: SweepSpec, rows: list[dict], key: str, path: Path) -> Path | None:
    qkeys = [k for k in _quantity_keys(rows) if k == "final_cost" or k.startswith("metric_")]
    if not qkeys:
        return None
    groups = list(dict.fromkeys(s.group for s in spec.settings))
    fig, axes = plt.subplots(len(qkeys), 1, figsize=(6.5, 3.0 * len(qkeys)), squeeze=False)
    styles = ["o-", "s--", "^:", "d-.", "x--", "v:"]
    values = sorted({s.grid[0][1] for s in spec.settings})
    for ax, q in zip(axes[:, 0], qkeys):
        for gi, g in enumerate(groups):
            for m in spec.methods:
                pts = []
                for s in spec.settings:
                    r = next((r for r in rows if r["setting"] == s.name and r["method"] == m), None)
                    if s.group == g and r is not None and r.get(f"{q}_mean") is not None:
                        pts.append((s.grid[0][1], r[f"{q}_mean"], r.get(f"{q}_std", 0.0)))
                if not pts:
                    continue
                x, mean, std = (np.array(v, float) for v in zip(*sorted(pts)))
                label = LABELS.get(m, m) + (f" ({g})" if g else "")
                ax.errorbar(x, mean, yerr=std, fmt=styles[gi % len(styles)], capsize=3, ms=4,
                            color=COLORS.get(m, "gray"), label=label)
        positive = [v for v in values if v > 0]
        if positive and max(positive) / min(positive) >= 100:
            ax.set_xscale("symlog", linthresh=min(positive)) if min(values) <= 0 else ax.set_xscale("log")
        ax.set_xticks(values, [f"{v:g}" for v in values])
        ax.set_xlabel(key)
        ax.set_ylabel(q.replace("metric_", ""))
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    axes[0, 0].set_title(f"{task}: final policies against {key}, mean ± std over seeds")
    fig.tight_layout()
    files.save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def write_report(spec: SweepSpec, out: str | Path, status: dict[str, dict]) -> Path:
    """Write the tables and figures (module docstring) under ``out``; return ``report.md``."""
    out = Path(out)
    results = {}
    trial_rows = []
    for t in spec.trials:
        st = status.get(t.id, {})
        res = read_result(out / t.relpath / RESULT, finished=False) if st.get("state") == "done" else None
        if res:
            results[t.id] = res
        trial_rows.append({"task": t.task_label, "setting": t.setting, "method": t.method, "seed": t.seed,
                           "state": st.get("state", "pending"), **(_flat_result(res) if res else {}),
                           "iterations": res.get("iterations") if res else None,
                           "wall_time": res.get("wall_time") if res else None,
                           "attempt": res.get("attempt") if res else None,
                           "error": st.get("error", ""), "dir": str(t.relpath)})
    _write_csv(out / "trials.csv", trial_rows)
    rows = aggregate(spec, results)
    _write_csv(out / "summary.csv", rows)
    lines = [f"# Sweep {spec.name}", "", "## Setup", "",
             f"- **sweep file**: {spec.source or '(in memory)'}",
             f"- **grid**: {describe(spec)}",
             f"- **tasks**: {', '.join(spec.tasks)}; **methods**: {', '.join(spec.methods)}; "
             f"**seeds**: {', '.join(map(str, spec.seeds))}",
             f"- **trials**: {sum(1 for r in trial_rows if r['state'] == 'done')} done, "
             f"{sum(1 for r in trial_rows if r['state'] == 'failed')} failed, "
             f"{sum(1 for r in trial_rows if r['state'] not in ('done', 'failed'))} not finished",
             "", "## Settings", "", "| setting | overrides |", "|---|---|"]
    lines += [f"| {name} | {desc} |" for name, desc in setting_table(spec)]
    vkey = versus_key(spec)
    for task in spec.tasks:
        trows = [r for r in rows if r["task"] == task]
        keys = _quantity_keys(trows)
        lines += ["", f"## {task}: final policies (mean ± std over seeds)", "",
                  "| setting | method | seeds | " + " | ".join(keys) + " |", "|---|---|---|" + "---|" * len(keys)]
        for r in trows:
            seeds = f"{r['seeds_done']}" + (f" (+{r['seeds_failed']} failed)" if r["seeds_failed"] else "")
            cells = [f"{_fmt(r.get(k + '_mean'))} ± {_fmt(r.get(k + '_std'))}" for k in keys]
            lines.append(f"| {r['setting']} | {r['method']} | {seeds} | " + " | ".join(cells) + " |")
        for fig in (_plot_final(task, spec, trows, out / f"final_{task}.png"),
                    _plot_costs(task, spec, results, out / f"cost_{task}.png"),
                    _plot_versus(task, spec, trows, vkey, out / f"versus_{vkey}_{task}.png") if vkey else None):
            if fig is not None:
                lines += ["", f"![{fig.stem}]({fig.name})"]
    claims = claims_rows(spec, results)
    if claims:
        _write_csv(out / "claims.csv", claims)
        lines += ["", "## Claims: DPSOC-EM against LQR-FLM, paired over seeds", "",
                  "A claim holds when the 95% paired bootstrap interval of the mean difference (DPSOC-EM minus "
                  "LQR-FLM) lies below 0 and the one-sided signed-rank test agrees at 5%; it is reversed when the "
                  "interval lies wholly above 0; below 5 seeds the signed-rank test cannot reach 5% (untestable; "
                  "docs/math.md §12.3).", "",
                  "| task | setting | claim | LQR-FLM | DPSOC-EM | difference [95% CI] | signed-rank p | lower on | held |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in claims:
            lines.append(f"| {r['task']} | {r['setting']} | {r['claim'].replace('DPSOC-EM lowers the ', '')} | "
                         f"{_fmt(r['baseline_mean'])} ± {_fmt(r['baseline_std'])} | {_fmt(r['dpsoc_mean'])} ± "
                         f"{_fmt(r['dpsoc_std'])} | {_fmt(r['diff_mean'])} [{_fmt(r['ci_low'])}, {_fmt(r['ci_high'])}] | "
                         f"{_fmt(r['p_signed_rank'])} | {r['seeds_lower']}/{r['seeds']} | "
                         f"{verdict_text(r)} |")
    failed = [r for r in trial_rows if r["state"] == "failed"]
    if failed:
        lines += ["", "## Failed trials", "", "| trial | error | traceback |", "|---|---|---|"]
        lines += [f"| {r['dir']} | {r['error'].replace('|', '/')} | {r['dir']}/error.txt |" for r in failed]
    lines += ["", "Per-trial rows: `trials.csv`; aggregated rows: `summary.csv`; trial states: `status.json`.", ""]
    path = out / "report.md"
    files.write_text(path, "\n".join(lines))
    return path
