"""Final-policy metric against the sensor noise rho^2, with step acceptance (issue 30; docs/results/acceptance.md).

    python examples/studies/acceptance_versus_rho2.py runs/sweep-acceptance_free runs/sweep-acceptance_rho2 \\
        runs/sweep-acceptance_noise --out docs/results/acceptance

Reads the finished trials ``trials/<task>/<setting>,rho2=<r>/<method>/seed_*/result.json`` of the given
sweep directories (settings ``paper`` and ``kinematic``; the as-written settings are left out), prints one
Markdown row per (task, setting, method, rho^2) with the metric sampled and with its mean action (mean ±
std over seeds), and writes ``versus_rho2_<task>.png`` into ``--out``: sampled (solid) and mean action
(dashed) against rho^2, mean ± std over seeds.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

METRIC = {"door": "min_hinge", "peg": "success_rate"}
SETTINGS = ("paper", "kinematic")


def collect(roots: list[str]) -> dict:
    """``{(task, setting, method, rho2): {"sampled": [...], "mean": [...]}}`` over finished seeds."""
    out: dict = defaultdict(lambda: {"sampled": [], "mean": []})
    for root in map(Path, roots):
        for res in sorted(root.glob("trials/*/*,rho2=*/*/seed_*/result.json")):
            seed_dir = res.parent
            method, setting_dir, task = seed_dir.parent.name, seed_dir.parent.parent.name, seed_dir.parent.parent.parent.name
            setting, _, rho = setting_dir.partition(",rho2=")
            if setting not in SETTINGS or task not in METRIC:
                continue
            r = json.loads(res.read_text())
            key = (task, setting, method, float(rho))
            out[key]["sampled"].append(r["metrics"][METRIC[task]])
            out[key]["mean"].append(r["metrics_mean_action"][METRIC[task]])
    return dict(out)


def table(data: dict) -> str:
    lines = ["| task | setting | method | rho^2 | seeds | sampled | mean action |", "|---|---|---|---|---|---|---|"]
    for (task, setting, method, rho), v in sorted(data.items()):
        s, m = np.array(v["sampled"]), np.array(v["mean"])
        lines.append(f"| {task} | {setting} | {method} | {rho:g} | {s.size} | {s.mean():.3f} ± {s.std():.3f} | "
                     f"{m.mean():.3f} ± {m.std():.3f} |")
    return "\n".join(lines)


def figure(data: dict, task: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"lqr-flm": "tab:blue", "dpsoc-em": "tab:orange"}
    markers = {"paper": "o", "kinematic": "s"}
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    for setting in SETTINGS:
        for method in colors:
            pts = sorted((k[3], v) for k, v in data.items() if k[:3] == (task, setting, method))
            if not pts:
                continue
            x = np.array([p[0] for p in pts])
            for kind, style in (("sampled", "-"), ("mean", "--")):
                y = np.array([np.mean(p[1][kind]) for p in pts])
                e = np.array([np.std(p[1][kind]) for p in pts])
                label = f"{method}, {setting}" + (" (mean action)" if kind == "mean" else "")
                ax.errorbar(x, y, yerr=e, fmt=markers[setting] + style, color=colors[method], capsize=3, ms=4,
                            alpha=1.0 if kind == "sampled" else 0.6, label=label)
    ax.set_xscale("symlog", linthresh=1e-3)
    ax.set_xlabel("rho^2")
    ax.set_ylabel(METRIC[task])
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"{task}: final policies with step acceptance, seeds 100-109 (mean ± std)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+", help="sweep output directories")
    ap.add_argument("--out", type=Path, help="directory for versus_rho2_<task>.png")
    a = ap.parse_args(argv)
    data = collect(a.roots)
    print(table(data))
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        for task in sorted({k[0] for k in data}):
            figure(data, task, a.out / f"versus_rho2_{task}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
