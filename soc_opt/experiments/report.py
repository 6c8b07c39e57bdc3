"""Figures and the Markdown report of a method comparison (docs/math.md §9.5, paper figures).

Inputs are plain arrays gathered by :func:`soc_opt.experiments.compare.compare`; this module only draws
and writes.  Figures (PNG):

- ``cost_per_iteration.png``: expected cost per iteration, box plots over samples (all seeds)
  for both methods side by side;
- ``ee_trajectories.png``: mean ± std over samples of the end-effector ``x, y, z`` of the final
  policies, dashed baseline vs solid DPSOC-EM;
- ``actions.png``: box plots of the actions per actuator (named) over samples and time, final policies;
- ``min_hinge.png`` (door): the minimum hinge angle per iteration.

Iterations are numbered from 0, as in ``metrics.csv`` and on the console.  Statistics over seeds
are shown as ``mean ± std``; with a single seed there is no spread, so only the value and
``n = 1`` are shown (:func:`mean_std`).

:func:`format_table` formats rows of dicts as a plain-text table (the CLI's tables).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .. import files  # noqa: E402

__all__ = ["plot_costs", "plot_ee", "plot_actions", "plot_metric", "claims_table", "write_markdown", "format_table",
           "mean_std", "over_seeds", "paired_test", "verdict_text", "min_signed_rank_p", "em_switch_text"]

COLORS = {"lqr-flm": "tab:blue", "dpsoc-em": "tab:red"}
LABELS = {"lqr-flm": "LQR-FLM (baseline)", "dpsoc-em": "DPSOC-EM"}
LINESTYLES = {"lqr-flm": "--"}


def _boxes(ax, data, pos, width: float, color: str) -> None:
    """Semi-transparent box plots of ``data`` (list of 1-D arrays) at ``pos``."""
    bp = ax.boxplot(data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=False,
                    manage_ticks=False)
    for b in bp["boxes"]:
        b.set_facecolor(color)
        b.set_alpha(0.5)


def _save(fig, ax, path: Path, title: str, dpi: int = 120) -> Path:
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    files.save_figure(fig, path, dpi=dpi)
    plt.close(fig)
    return path


def em_switch_text(i_switch: int) -> str:
    """Where the EM phase runs, in the console's numbering (iterations from 0): ``"iteration 4 (after
    iterations 0-3)"``."""
    after = ("before any baseline iteration" if i_switch == 0 else "after iteration 0" if i_switch == 1
             else f"after iterations 0-{i_switch - 1}")
    return f"iteration {i_switch} ({after})"


def plot_costs(costs: dict, path: Path, title: str, i_switch: int | None = None) -> Path:
    """``costs[method]`` is a list over iterations of 1-D arrays of per-sample costs."""
    fig, ax = plt.subplots(figsize=(10, 4.5))
    methods = list(costs)
    width = 0.8 / len(methods)
    for j, meth in enumerate(methods):
        data = costs[meth]
        pos = np.arange(len(data)) + (j - (len(methods) - 1) / 2) * width
        _boxes(ax, data, pos, width, COLORS.get(meth, "gray"))
        ax.plot(pos, [np.mean(d) for d in data], "o-", color=COLORS.get(meth, "gray"), ms=3, label=LABELS.get(meth, meth))
    if i_switch is not None:
        ax.axvline(i_switch - 0.5, color="k", ls=":", lw=1, label=f"EM phase at {em_switch_text(i_switch)}")
    n_it = max(len(d) for d in costs.values())
    ax.set_xticks(np.arange(n_it))
    ax.set_xlabel("iteration")
    ax.set_ylabel("total cost per sample (true state)")
    ax.set_yscale("symlog" if min(np.min(np.concatenate(d)) for d in costs.values()) <= 0 else "log")
    ax.legend()
    return _save(fig, ax, path, title)


def plot_ee(points: dict, dt: float, path: Path, title: str, point_names=None, targets=None) -> Path:
    """``points[method]``: ``(S, T+1, P, 3)`` end-effector points over samples ``S``.

    Coordinates that are identically zero for every method (e.g. ``z`` of a planar task) are
    left out; ``targets`` (``(P, 3)``, optional) are drawn as dotted lines.
    """
    P = next(iter(points.values())).shape[2]
    used = [c for c in range(3) if any(np.any(pts[..., c] != 0) for pts in points.values())] or [0]
    fig, axes = plt.subplots(P, len(used), figsize=(4 * len(used), 3 * P), squeeze=False, sharex=True)
    for meth, pts in points.items():
        t = np.arange(pts.shape[1]) * dt
        mean, std = pts.mean(axis=0), pts.std(axis=0)
        ls = LINESTYLES.get(meth, "-")
        for p in range(P):
            for j, c in enumerate(used):
                ax = axes[p, j]
                ax.plot(t, mean[:, p, c], ls, color=COLORS.get(meth, "gray"), label=LABELS.get(meth, meth))
                ax.fill_between(t, mean[:, p, c] - std[:, p, c], mean[:, p, c] + std[:, p, c],
                                color=COLORS.get(meth, "gray"), alpha=0.2)
    for p in range(P):
        for j, c in enumerate(used):
            ax = axes[p, j]
            pname = point_names[p] if point_names and p < len(point_names) else f"point {p}"
            ax.set_title(f"{pname}: {'xyz'[c]}")
            if targets is not None:
                ax.axhline(targets[p][c], color="k", lw=0.8, ls=":", label="target" if (p, j) == (0, 0) else None)
            ax.grid(alpha=0.3)
    for j in range(len(used)):
        axes[-1, j].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title + " (mean ± std over samples; dashed baseline, solid DPSOC-EM)")
    fig.tight_layout()
    files.save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def plot_actions(actions: dict, path: Path, title: str, names: list[str] | None = None) -> Path:
    """``actions[method]``: ``(S, T, m)``; ``names``: the ``m`` action (actuator) names for the axis.

    Left: box plots per actuator of the actions over samples and time.  Right: the same for the
    deviation of each action from the mean action at its time step, i.e. the spread over
    samples that the claims table measures.
    """
    m = next(iter(actions.values())).shape[-1]
    fig, axes = plt.subplots(1, 2, figsize=(max(10, 2.6 * m), 4))
    methods = list(actions)
    width = 0.8 / len(methods)
    for ax, centred in zip(axes, (False, True)):
        for j, meth in enumerate(methods):
            a = np.asarray(actions[meth])
            if centred:
                a = a - a.mean(axis=0, keepdims=True)
            a = a.reshape(-1, m)
            pos = np.arange(m) + 1 + (j - (len(methods) - 1) / 2) * width
            _boxes(ax, [a[:, i] for i in range(m)], pos, width, COLORS.get(meth, "gray"))
            ax.plot([], [], "s", color=COLORS.get(meth, "gray"), label=LABELS.get(meth, meth))
        ax.set_xticks(np.arange(1, m + 1))
        labels = list(names) if names is not None and len(names) == m else [f"action {i}" for i in range(m)]
        ax.set_xticklabels(labels, rotation=30 if m > 4 else 0)
        ax.set_ylabel("action - mean action at that step" if centred else "action")
        ax.set_title("spread over samples (centred per time step)" if centred else "actions over samples and time")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8, framealpha=0.9)
    fig.suptitle(title)
    fig.tight_layout()
    files.save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def plot_metric(values: dict, path: Path, title: str, ylabel: str, i_switch: int | None = None) -> Path:
    """``values[method]``: ``(seeds, iterations)`` metric of the sampled batches; the line is the mean over
    seeds and the band mean ± std over seeds (population std; none with one seed); ``ylabel`` should carry
    the unit; ``i_switch``: a dotted line where the EM phase runs, as in :func:`plot_costs`."""
    fig, ax = plt.subplots(figsize=(8, 4))
    n_seeds = 0
    for meth, v in values.items():
        v = np.asarray(v, float)
        n_seeds = max(n_seeds, v.shape[0])
        it = np.arange(v.shape[1])
        ls = LINESTYLES.get(meth, "-")
        ax.plot(it, v.mean(0), ls + "o", ms=3, color=COLORS.get(meth, "gray"), label=LABELS.get(meth, meth))
        ax.fill_between(it, v.mean(0) - v.std(0), v.mean(0) + v.std(0), color=COLORS.get(meth, "gray"), alpha=0.2)
    if i_switch is not None:
        ax.axvline(i_switch - 0.5, color="k", ls=":", lw=1, label=f"EM phase at {em_switch_text(i_switch)}")
    ax.set_xlabel("iteration (from 0)")
    ax.set_ylabel(ylabel)
    ax.legend()
    band = "mean over seeds ± std over seeds (shaded)" if n_seeds > 1 else "one seed"
    return _save(fig, ax, path, f"{title}\n{band}")


def min_signed_rank_p(n: int) -> float:
    """The smallest one-sided p-value the exact Wilcoxon signed-rank test can give with ``n`` nonzero paired
    differences: ``2^-n`` (every difference on the same side).  Below 5% only from ``n = 5``."""
    return 2.0 ** -n if n > 0 else 1.0


def paired_test(baseline, dpsoc, confidence: float = 0.95, resamples: int = 9999, seed: int = 0) -> dict:
    """Paired comparison over seeds of ``dpsoc - baseline`` (one value per seed each; docs/math.md §12.3).

    ``diff_mean``: the mean paired difference; ``ci_low, ci_high``: its percentile bootstrap interval
    (``scipy.stats.bootstrap``, seeded: the same data give the same interval); ``p_signed_rank``: the
    one-sided Wilcoxon signed-rank p-value for "DPSOC-EM lower", ``p_reverse`` the same for "higher"
    (``nan`` below 2 seeds or with all differences zero); ``interval``: ``"below 0"``, ``"above 0"`` or
    ``"contains 0"``.  ``verdict``:

    * ``"lower"``: the whole interval is below 0 *and* the signed-rank test gives ``p < 1 - confidence``
      (both, because the percentile bootstrap alone is too optimistic for few seeds: 3 seeds have 10
      distinct resamples);
    * ``"reversed"``: the whole interval lies on the wrong side, above 0 (the interval alone decides:
      a warning against the claim, not a claim; ``p_reverse`` says whether the signed-rank test agrees);
    * ``"untestable with N seeds"``: neither, and the signed-rank test cannot reach ``1 - confidence`` with
      this many nonzero differences (``2^-n >= 0.05`` for ``n <= 4``), whatever the data;
    * ``"not shown"``: otherwise; ``"one seed"`` (no test) with a single seed.
    """
    from scipy import stats

    d = np.asarray(dpsoc, float) - np.asarray(baseline, float)
    out = {"diff_mean": float(d.mean()), "ci_low": float("nan"), "ci_high": float("nan"),
           "p_signed_rank": float("nan"), "p_reverse": float("nan"), "interval": "n/a", "verdict": "one seed"}
    if d.size < 2:
        return out
    if np.all(d == d[0]):  # a degenerate bootstrap distribution: the interval is the point
        lo = hi = float(d[0])
    else:
        ci = stats.bootstrap((d,), np.mean, confidence_level=confidence, n_resamples=resamples,
                             method="percentile", random_state=np.random.default_rng(seed)).confidence_interval
        lo, hi = float(ci.low), float(ci.high)
    p_less = p_greater = float("nan")
    if np.any(d != 0):
        p_less = float(stats.wilcoxon(d, alternative="less").pvalue)
        p_greater = float(stats.wilcoxon(d, alternative="greater").pvalue)
    alpha = 1.0 - confidence
    side = "below 0" if hi < 0 else "above 0" if lo > 0 else "contains 0"
    if hi < 0 and p_less < alpha:
        verdict = "lower"
    elif lo > 0:
        verdict = "reversed"
    elif min_signed_rank_p(int(np.count_nonzero(d))) >= alpha:
        verdict = f"untestable with {d.size} seeds"
    else:
        verdict = "not shown"
    out.update(ci_low=lo, ci_high=hi, p_signed_rank=p_less, p_reverse=p_greater, interval=side, verdict=verdict)
    return out


def verdict_text(r: dict) -> str:
    """The claim's verdict as the reports print it: ``yes``, or ``no`` with why (reversed with its interval
    and the signed-rank p for "higher"; untestable with how many seeds the test needs and the interval's side)."""
    v = r.get("verdict", "")
    if r.get("held"):
        return "yes"
    if v == "reversed":
        return f"**no: reversed** (interval above 0; signed-rank p for higher {_fmt(r.get('p_reverse', float('nan')))})"
    if v.startswith("untestable"):
        return f"no ({v}: the signed-rank test needs 5; interval {r.get('interval', 'n/a')})"
    return f"no ({v})"


def claims_table(per_seed: dict) -> list[dict]:
    """docs/math.md §9.5 claims from per-seed final-policy statistics.

    ``per_seed[method]`` is a dict of arrays over seeds: ``cost`` (mean total cost of the final
    policy), ``state_spread`` (mean over time of the std over samples of the end-effector points),
    ``action_spread`` (mean over time and joints of the std over samples of the actions).
    A claim "DPSOC-EM lowers X" is judged by a paired comparison over seeds (:func:`paired_test`):
    it holds when the 95% bootstrap interval of the mean paired difference lies below 0 and the
    one-sided signed-rank test agrees at 5%; the number of seeds on which DPSOC-EM was lower is
    reported as well.
    """
    rows = []
    names = {
        "cost": "final expected cost",
        "state_spread": "spread of the state (end-effector) trajectories",
        "action_spread": "spread of the actions",
    }
    b, e = per_seed["lqr-flm"], per_seed["dpsoc-em"]
    for key, label in names.items():
        xb, xe = np.asarray(b[key], float), np.asarray(e[key], float)
        test = paired_test(xb, xe)
        rows.append({
            "claim": f"DPSOC-EM lowers the {label}",
            "baseline_mean": float(xb.mean()), "baseline_std": float(xb.std()),
            "dpsoc_mean": float(xe.mean()), "dpsoc_std": float(xe.std()),
            "seeds_lower": int(np.sum(xe < xb)), "seeds": int(len(xb)),
            **test,
            "held": test["verdict"] == "lower",
        })
    return rows


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def mean_std(values) -> str:
    """``"mean ± std"`` of ``values`` over seeds; one value: ``"value (n = 1)"`` (no spread to show)."""
    v = np.asarray(values, float).ravel()
    if v.size == 1:
        return f"{_fmt(v[0])} (n = 1)"
    return f"{_fmt(v.mean())} ± {v.std():.3g}"


def over_seeds(n: int) -> str:
    """How a table's statistics are taken: ``"mean ± std over N seeds"``, or ``"one seed"``."""
    return "one seed, no spread" if n == 1 else f"mean ± std over {n} seeds"


def write_markdown(path: Path, *, title: str, setup: dict, claims: list[dict], figures: dict,
                   extra_tables: dict | None = None, notes: list[str] | None = None) -> Path:
    lines = [f"# {title}", "", "## Setup", ""]
    lines += [f"- **{k}**: {v}" for k, v in setup.items()]
    n_seeds = claims[0]["seeds"] if claims else 0
    lines += ["", f"## Claims (docs/math.md §9.5), final policies, {over_seeds(n_seeds)}", "",
              "| claim | LQR-FLM | DPSOC-EM | paired difference [95% CI] | signed-rank p | seeds where DPSOC-EM lower "
              "| held |", "|---|---|---|---|---|---|---|"]

    def cell(mean, std, n):
        return f"{_fmt(mean)} (n = 1)" if n == 1 else f"{_fmt(mean)} ± {_fmt(std)}"

    for r in claims:
        lines.append(
            f"| {r['claim']} | {cell(r['baseline_mean'], r['baseline_std'], r['seeds'])} | "
            f"{cell(r['dpsoc_mean'], r['dpsoc_std'], r['seeds'])} | {_diff_cell(r)} | {_fmt(r.get('p_signed_rank', float('nan')))} | "
            f"{r['seeds_lower']}/{r['seeds']} | {verdict_text(r)} |"
        )
    for name, (header, rows) in (extra_tables or {}).items():
        lines += ["", f"## {name}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    lines += ["", "## Figures", ""]
    for caption, fig in figures.items():
        lines += [f"### {caption}", "", f"![{caption}]({Path(fig).name})", ""]
    if notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in notes]
    files.write_text(path, "\n".join(lines) + "\n")
    return path


def _diff_cell(r: dict) -> str:
    if "diff_mean" not in r:
        return "n/a"
    if r.get("verdict") == "one seed":
        return f"{_fmt(r['diff_mean'])} (one seed)"
    return f"{_fmt(r['diff_mean'])} [{_fmt(r['ci_low'])}, {_fmt(r['ci_high'])}]"


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if (abs(v) >= 1e-3 or v == 0) else f"{v:.2e}"
    return str(v)


def format_table(rows: list[dict], columns: list[str] | None = None) -> str:
    """A left-aligned plain-text table of ``rows`` (one dict per row).

    ``columns`` defaults to every key in order of first appearance; a missing key is an empty
    cell.  Floats are shown with 3 significant digits (scientific below 1e-3).
    """
    if not rows:
        return "(no rows)"
    columns = columns or list(dict.fromkeys(k for r in rows for k in r))
    cells = [[_cell(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)
