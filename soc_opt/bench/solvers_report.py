"""Tables, Dolan-More performance profiles and accuracy-vs-time plots of the M-step solver
benchmark (:mod:`soc_opt.bench.solvers`, docs/math.md §5).

``summarize(rows)`` gives one line per (size, constraint set, method): problems solved, median and
max relative objective gap to the reference, max constraint violation, median solve time, build
time, warnings.  ``write(rows, warm, out_dir)`` writes ``rows.csv`` (every solve), ``summary.csv``,
``summary.json``, ``table.md``, ``profile_<set>.png`` and ``accuracy_time_<set>.png``.

Performance profile (Dolan and More 2002): for problem ``p`` and method ``s`` with solve time
``t_{p,s}`` (infinite if the method failed: status not optimal, gap above ``tol`` or violation above
``tol``), ``r_{p,s} = t_{p,s} / min_s t_{p,s}`` and ``rho_s(tau)`` is the fraction of problems with
``r_{p,s} <= tau``.  Build time is excluded (it is paid once per size).
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["summarize", "profiles", "write", "markdown", "per_size", "quiet_stdout"]

#: a solve counts as a success when its relative objective gap and violation are at most this
SUCCESS_TOL = 1e-6


def _ok(r) -> bool:
    return (str(r["status"]).startswith("optimal") and r["abs_gap"] <= SUCCESS_TOL and r["violation"] <= SUCCESS_TOL
            and math.isfinite(r["solve_s"]))


def summarize(rows: list[dict]) -> list[dict]:
    """One dict per (n, m, constraints, method) in first-seen order."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["n"], r["m"], r["constraints"], r["method"]), []).append(r)
    out = []
    for (n, m, kind, meth), rs in groups.items():
        real = [r for r in rs if r["step"] >= 0]
        gaps = np.array([r["abs_gap"] for r in real]) if real else np.array([math.inf])
        times = np.array([r["solve_s"] for r in real if math.isfinite(r["solve_s"])])
        builds = [r["build_s"] for r in rs if r["build_s"] is not None]
        warn = [r["warning"] for r in rs if r["warning"]]
        bad = sorted({str(r["status"]) for r in rs if not str(r["status"]).startswith("optimal")})
        out.append(dict(n=n, m=m, constraints=kind, method=meth, problems=len(real),
                        solved=sum(_ok(r) for r in real),
                        median_gap=float(np.median(gaps)), max_gap=float(np.max(gaps)),
                        max_violation=float(max((r["violation"] for r in real), default=math.inf)),
                        median_solve_s=float(np.median(times)) if times.size else math.nan,
                        build_s=float(builds[0]) if builds else math.nan,
                        warnings=int(sum(r["warnings"] for r in rs)), first_warning=warn[0] if warn else "",
                        failures="; ".join(bad)[:160]))
    return out


def profiles(rows: list[dict], kind: str):
    """``(methods, ratios)`` of the performance profile of constraint set ``kind``: ``ratios[s]`` the
    sorted time ratios of method ``s`` over every problem (``inf`` where it failed)."""
    probs: dict = {}
    for r in rows:
        if r["constraints"] != kind or r["step"] < 0:
            continue
        probs.setdefault((r["n"], r["instance"], r["step"]), {})[r["method"]] = r["solve_s"] if _ok(r) else math.inf
    methods = sorted({m for p in probs.values() for m in p})
    ratios = {s: [] for s in methods}
    for p in probs.values():
        best = min(p.values())
        for s in methods:
            t = p.get(s, math.inf)
            ratios[s].append(t / best if math.isfinite(best) and best > 0 else math.inf)
    return methods, {s: np.sort(np.asarray(v)) for s, v in ratios.items()}


def _plots(rows: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for kind in sorted({r["constraints"] for r in rows}):
        methods, ratios = profiles(rows, kind)
        colors = plt.cm.tab20(np.linspace(0, 1, max(len(methods), 2)))
        fig, ax = plt.subplots(figsize=(7, 4.5))
        ax.set_prop_cycle(color=colors)
        tau_max = max([float(v[np.isfinite(v)].max()) for v in ratios.values() if np.isfinite(v).any()] + [2.0])
        for s in methods:
            v = ratios[s]
            taus = np.concatenate([[1.0], v[np.isfinite(v)], [tau_max * 1.5]])
            frac = np.concatenate([[np.mean(v <= 1.0)], np.arange(1, np.isfinite(v).sum() + 1) / len(v),
                                   [np.isfinite(v).mean()]])
            ax.step(taus, frac, where="post", label=s)
        ax.set_xscale("log")
        ax.set_xlabel("tau (CPU time / best CPU time on the problem)")
        ax.set_ylabel("fraction of problems solved within tau")
        ax.set_title(f"M-step {kind}: Dolan-More performance profile\n(success: gap and violation <= {SUCCESS_TOL:g})", fontsize=10)
        ax.legend(fontsize=7, loc="lower right")
        p = out / f"profile_{kind}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
        fig, ax = plt.subplots(figsize=(7, 4.5))
        ax.set_prop_cycle(color=colors)
        for s in methods:
            pts = [(r["solve_s"], max(r["abs_gap"], r["violation"], 1e-17)) for r in rows
                   if r["constraints"] == kind and r["method"] == s and r["step"] >= 0 and math.isfinite(r["solve_s"])
                   and math.isfinite(r["abs_gap"])]
            if pts:
                t, e = zip(*pts)
                ax.scatter(t, e, s=6, label=s, alpha=0.6)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("solve time per problem (CPU s)")
        ax.set_ylabel("max(relative objective gap, violation)")
        ax.set_title(f"M-step {kind}: accuracy vs time (all sizes)")
        ax.legend(fontsize=7, markerscale=2)
        p = out / f"accuracy_time_{kind}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def _fmt(v) -> str:
    if isinstance(v, float):
        return "-" if math.isnan(v) else f"{v:.2g}"
    return str(v)


def per_size(rows: list[dict]) -> str:
    """Markdown: per method (rows) and size (columns) over all constraint sets, ``median gap / max gap
    / median solve CPU time (ms)``."""
    sizes = sorted({(r["n"], r["m"]) for r in rows})
    methods = list(dict.fromkeys(r["method"] for r in rows))
    head = "| method | " + " | ".join(f"n={n}, m={m}" for n, m in sizes) + " |"
    lines = [head, "|---|" + "---|" * len(sizes)]
    for meth in methods:
        cells = []
        for n, m in sizes:
            rs = [r for r in rows if r["method"] == meth and (r["n"], r["m"]) == (n, m) and r["step"] >= 0]
            if not rs:
                cells.append("-")
                continue
            g = np.array([max(r["abs_gap"], r["violation"]) for r in rs])
            t = np.array([r["solve_s"] for r in rs if math.isfinite(r["solve_s"])])
            cells.append(f"{np.median(g):.0e} / {np.max(g):.0e} / {1e3 * np.median(t):.2g}" if t.size else "failed")
        lines.append(f"| {meth} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def markdown(summary: list[dict], warm: list[dict] | None = None) -> str:
    cols = ["n", "m", "constraints", "method", "problems", "solved", "median_gap", "max_gap", "max_violation",
            "median_solve_s", "build_s", "warnings"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(s[c]) for c in cols) + " |" for s in summary]
    notes = [f"- {s['method']} ({s['constraints']}, n={s['n']}): {s['warnings']} warnings, e.g. `{s['first_warning']}`"
             for s in summary if s["warnings"]]
    fails = [f"- {s['method']} ({s['constraints']}, n={s['n']}): {s['failures']}" for s in summary if s["failures"]]
    if notes:
        lines += ["", "Warnings surfaced by the solvers:", *sorted(set(notes))[:30]]
    if fails:
        lines += ["", "Non-optimal statuses:", *fails[:30]]
    if warm:
        lines += ["", "Warm vs cold start (offset-bound QP, 5 consecutive EM iterations, R moving 1%):", "",
                  "| n | m | solver | mode | median solve (CPU s) | median iterations |", "|---|---|---|---|---|---|"]
        lines += [f"| {w['n']} | {w['m']} | {w['solver']} | {w['mode']} | {w['median_solve_s']:.3g} | "
                  f"{w['median_iters']:.0f} |" for w in warm]
    return "\n".join(lines) + "\n"


def write_rows(rows: list[dict], out_dir) -> Path:
    """``out_dir/rows.csv`` only (a partial run's progress)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = out / "rows.csv"
    with open(p, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return p


def write(rows: list[dict], warm: list[dict], out_dir, meta: dict | None = None) -> list[Path]:
    """Write every file of the benchmark into ``out_dir`` (module docstring); returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(rows)
    paths = []
    for name, data in (("rows.csv", rows), ("summary.csv", summary)):
        p = out / name
        with open(p, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(data[0]))
            w.writeheader()
            w.writerows(data)
        paths.append(p)
    p = out / "summary.json"
    p.write_text(json.dumps({"meta": meta or {}, "summary": summary, "warm_vs_cold": warm}, indent=1,
                            default=lambda x: None if isinstance(x, float) and not math.isfinite(x) else str(x)))
    paths.append(p)
    p = out / "table.md"
    p.write_text("Per method and size, all constraint sets: median error / max error / median solve CPU time (ms); "
                 "error = max(relative objective gap, constraint violation) against the closed form or the "
                 "independent reference.\n\n" + per_size(rows) + "\nPer size, constraint set and method:\n\n"
                 + markdown(summary, warm))
    paths.append(p)
    return paths + _plots(rows, out)


@contextlib.contextmanager
def quiet_stdout():
    """Send file descriptor 1 to standard error while solvers run (OSQP, qpOASES and HiGHS print
    banners from C), so that ``--json`` output stays parseable."""
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _parse(v: str):
    if v == "" or v == "None":
        return None
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def rerender(out_dir, parts=()) -> list[Path]:
    """Rewrite the summary, table and plots of ``out_dir`` from its ``rows.csv`` (no solver runs), or
    from the ``rows.csv`` and ``summary.json`` of the directories ``parts`` (e.g. one run per size)."""
    out = Path(out_dir)
    rows, warm, metas = [], [], []
    for d in [Path(p) for p in parts] or [out]:
        with open(d / "rows.csv", newline="") as f:
            rows += [{k: _parse(v) for k, v in r.items()} for r in csv.DictReader(f)]
        if (d / "summary.json").exists():
            old = json.loads((d / "summary.json").read_text())
            warm += old.get("warm_vs_cold", [])
            metas.append(old.get("meta"))
    for r in rows:
        for k in ("solve_s", "abs_gap", "violation", "rel_gap", "param_err"):
            r[k] = math.nan if r[k] is None else float(r[k])
        r["warning"] = r["warning"] or ""
        r["status"] = str(r["status"])
    meta = metas[0] if len(metas) == 1 else {"parts": metas}
    return write(rows, warm, out, meta)


if __name__ == "__main__":
    import sys

    for p in rerender(sys.argv[1], sys.argv[2:]):
        print(p)
