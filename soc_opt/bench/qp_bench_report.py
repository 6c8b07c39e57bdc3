"""Tables and the qpbenchmark export of :mod:`soc_opt.bench.qp_bench` (docs/math.md §5).

``write(rows, out, meta)`` writes ``rows.csv`` (every solve), ``summary.csv`` / ``summary.json``
and ``table.md`` (per family x accuracy level x method: success rate, shifted geometric mean of
CPU time, solution error, residuals, gap).  ``export_qpbenchmark(problems, out)`` writes the QPs
(one ``.npz`` per problem: ``P, q, G, h``) and a test-set module that qpbenchmark loads
(``qpbenchmark OUT/mstep_qpbench.py run``); the trust-region family (an SOCP) and the infeasible
family (qpbenchmark counts every "not found" as a failure) are left out.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from .qp_bench import FAMILIES, LEVELS, SHIFT_MS, TIME_LIMIT_S, Problem, qp_data, summarize

__all__ = ["write", "markdown", "by_size", "export_qpbenchmark", "load_exported", "TEST_SET_NAME", "EXPORTED_FAMILIES"]

TEST_SET_NAME = "mstep_qpbench"
EXPORTED_FAMILIES = ("well_conditioned", "ill_conditioned", "degenerate", "active")


def _f(v, spec=".1e") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return format(v, spec)


def markdown(summary: list[dict]) -> str:
    """One table per family: rows = methods, column groups = accuracy levels."""
    out = []
    for fam in FAMILIES:
        ss = [s for s in summary if s["family"] == fam]
        if not ss:
            continue
        out.append(f"\n### {fam}\n")
        if fam == "infeasible":
            out.append("| method | " + " | ".join(f"{lv}: detected / shgeom ms" for lv in LEVELS) + " |")
            out.append("|---|" + "---|" * len(LEVELS))
        else:
            out.append("| method | " + " | ".join(f"{lv}: success / shgeom ms / sol. err med, max / "
                                                 f"max primal, dual, gap" for lv in LEVELS) + " |")
            out.append("|---|" + "---|" * len(LEVELS))
        for meth in sorted({s["method"] for s in ss}):
            cells = []
            for lv in LEVELS:
                s = next((x for x in ss if x["method"] == meth and x["level"] == lv), None)
                if s is None:
                    cells.append("n/a")
                elif fam == "infeasible":
                    cells.append(f"{s['success']}/{s['problems']} / {_f(s['shgeom_ms'], '.3g')}")
                else:
                    cells.append(f"{s['success']}/{s['problems']} / {_f(s['shgeom_ms'], '.3g')} / "
                                 f"{_f(s['sol_err_median'])}, {_f(s['sol_err_max'])} / "
                                 f"{_f(s['primal_res_max'])}, {_f(s['dual_res_max'])}, {_f(s['gap_max'])}")
            out.append(f"| {meth} | " + " | ".join(cells) + " |")
    head = (f"Success: solution returned within {TIME_LIMIT_S:g} s with primal residual, dual residual and "
            f"duality gap <= the level's tolerance ({', '.join(f'{k} {v.tol:g}' for k, v in LEVELS.items())}); "
            f"infeasible family: infeasibility reported.  shgeom ms: shifted geometric mean of CPU time "
            f"(ms, shift {SHIFT_MS:g} ms, a failure counted at {TIME_LIMIT_S:g} s).  sol. err: relative "
            f"|(F, Sigma) - reference| over the solves that returned a solution (QP rows: F only).")
    return head + "\n" + "\n".join(out) + "\n"


def by_size(rows: list[dict], level: str) -> str:
    """Per method and size (all families but ``infeasible`` pooled): solved / problems, shifted
    geometric mean of CPU ms (failures at the time limit) and the largest solution error."""
    from .qp_bench import shifted_geomean

    rs = [r for r in rows if r["level"] == level and r["family"] != "infeasible"]
    sizes = sorted({(r["n"], r["m"]) for r in rs})
    lines = [f"| method ({level}) | " + " | ".join(f"n={n}, m={m}" for n, m in sizes) + " |",
             "|---|" + "---|" * len(sizes)]
    for meth in sorted({r["method"] for r in rs}):
        cells = []
        for n, m in sizes:
            x = [r for r in rs if r["method"] == meth and (r["n"], r["m"]) == (n, m)]
            if not x:
                cells.append("n/a")
                continue
            t = [1e3 * (r["cpu_s"] if r["success"] else TIME_LIMIT_S) for r in x]
            errs = [r["sol_err"] for r in x if r["found"] and not math.isnan(r["sol_err"])]
            cells.append(f"{sum(r['success'] for r in x)}/{len(x)} / {shifted_geomean(t, SHIFT_MS):.3g} / "
                         f"{_f(max(errs) if errs else math.nan)}")
        lines.append(f"| {meth} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _csv(path: Path, rows: list[dict]) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def write(rows: list[dict], out, meta: dict) -> list[Path]:
    """Write the files of the module docstring into ``out``; returns their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(rows)
    paths = [out / "rows.csv", out / "summary.csv", out / "summary.json", out / "table.md"]
    _csv(paths[0], rows)
    _csv(paths[1], summary)
    paths[2].write_text(json.dumps({"meta": meta, "summary": summary}, indent=1, default=float))
    sizes = "\n".join(by_size(rows, lv) for lv in LEVELS)
    paths[3].write_text("# M-step QP benchmark (soc_opt.bench.qp_bench)\n\n" + markdown(summary)
                        + "\n## Per size (families pooled; solved / shgeom CPU ms / max solution error)\n\n" + sizes)
    return paths


_TEST_SET = '''"""The M-step QPs of soc_opt (docs/math.md section 5) as a qpbenchmark test set.

Written by soc_opt.bench.qp_bench_report.export_qpbenchmark: one .npz per problem in
problems/ (P, q, G, h), minimise 1/2 x^T P x + q^T x subject to G x <= h.  Families:
{families}.  Run: qpbenchmark {name}.py run --results-path results/{name}.csv
"""

from pathlib import Path

import numpy as np
import qpbenchmark


class {cls}(qpbenchmark.TestSet):
    """soc_opt M-step problems (one time step each), unwhitened."""

    @property
    def description(self) -> str:
        return "soc_opt M-step QPs: P = Stilde kron H, q = -vec R from the smoother's moments."

    @property
    def title(self) -> str:
        return "soc_opt M-step test set"

    @property
    def sparse_only(self) -> bool:
        return False

    def __iter__(self):
        for path in sorted((Path(__file__).parent / "problems").glob("*.npz")):
            d = np.load(path)
            G = d["G"] if d["G"].size else None
            h = d["h"] if d["h"].size else None
            yield qpbenchmark.Problem(d["P"], d["q"], G, h, None, None, None, None, name=path.stem)
'''


def export_qpbenchmark(problems: list[Problem], out) -> list[Path]:
    """Write the QPs of ``problems`` (the exported families) and the test-set module into ``out``."""
    out = Path(out)
    (out / "problems").mkdir(parents=True, exist_ok=True)
    paths = []
    for p in problems:
        if p.family not in EXPORTED_FAMILIES:
            continue
        P, q, G, h, _ = qp_data(p)
        path = out / "problems" / f"{p.name}.npz"
        np.savez_compressed(path, P=P, q=q, G=np.zeros((0, len(q))) if G is None else G,
                            h=np.zeros(0) if h is None else h)
        paths.append(path)
    cls = TEST_SET_NAME.title().replace("_", "")
    mod = out / f"{TEST_SET_NAME}.py"
    mod.write_text(_TEST_SET.format(families=", ".join(EXPORTED_FAMILIES), name=TEST_SET_NAME, cls=cls))
    return paths + [mod]


def load_exported(out) -> list[tuple[str, dict]]:
    """The exported problems as ``(name, {P, q, G, h})`` (what the test-set module reads)."""
    res = []
    for path in sorted((Path(out) / "problems").glob("*.npz")):
        with np.load(path) as d:
            res.append((path.stem, {k: d[k] for k in ("P", "q", "G", "h")}))
    return res
