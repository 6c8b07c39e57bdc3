"""Tables and figures of docs/results/peers/ from the parts' outputs.

    python -m soc_opt.bench.peers.report --out docs/results/peers \
        [--rl runs/peers-rl] [--soc runs/peers-soc] [--sweep runs/sweep-noise_peg ...] [--skip-kernels]

* runs the smoother and LQR parts (unless ``--skip-kernels``) and writes ``smoothers.json``,
  ``lqr.json``;
* reads the RL runs (``--rl``: one JSON per run, :mod:`.rl`) and the soc_opt runs (``--soc``:
  ``soc-opt compare`` directories named ``<task>-<paper|noiseaware>-rho<rho2>``, per-iteration
  ``metrics.csv`` of each seed and method; or ``--sweep``: the noise sweeps' trials, 10 seeds, with
  the kinematic estimator too);
* writes ``rl.json`` (per method, task and rho2: the metric at each budget, mean and std over
  seeds, steps to 90% peg success), ``tables.md`` and ``<task>_vs_steps.png``.

Environment steps of soc_opt's iteration ``i`` (0-based): ``(i + 1) x samples x T``.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from ...peers.rl import steps_to
from .rl import PAPER_BUDGET

__all__ = ["soc_curves", "sweep_curves", "rl_curves", "rl_table", "stored_rows", "main"]

METRIC = {"peg": "success_rate", "door": "min_hinge"}
SOC_LABEL = {"paper": "{m}", "noiseaware": "{m} noise-aware"}
#: the noise sweeps' settings (problems/sweeps/noise_*.toml) shown beside RL, and their labels
SWEEP_LABEL = {"paper": "{m}", "noise-aware": "{m} noise-aware", "kinematic": "{m} kinematic",
               "paper-as-written": "{m} (as written)", "kinematic-as-written": "{m} kinematic (as written)"}
METHODS = {"lqr-flm": "LQR-FLM", "dpsoc-em": "DPSOC-EM"}


def soc_curves(root: Path, samples: int = 20, T: int = 100) -> dict:
    """``{(label, task, rho2): {"steps": (I,), "seeds": {metric: (S, I)}}}`` from compare runs."""
    out = {}
    for d in sorted(Path(root).glob("*-*-rho*")):
        task, variant, rho = d.name.split("-")
        rho2 = float(rho[3:])
        for method, name in METHODS.items():
            per_seed = []
            for f in sorted(d.glob(f"seed_*/{method}/metrics.csv")):
                with open(f) as fh:
                    rows = list(csv.DictReader(fh))
                per_seed.append(rows)
            if not per_seed:
                continue
            key = (SOC_LABEL[variant].format(m=name), task, rho2)
            summary = d / "summary.json"
            eval_cost = (json.loads(summary.read_text())["per_seed"].get(method, {}).get("cost")
                         if summary.exists() else None)
            out[key] = _curve(per_seed, task, samples, T, eval_cost)
    return out


def _curve(per_seed: list[list[dict]], task: str, samples: int, T: int, eval_cost, results=None) -> dict:
    """``results``: the trials' ``result.json`` (sweeps), for the final policy's evaluation sampled and
    with its mean action (docs/math.md §12.3)."""
    n_it = min(len(r) for r in per_seed)
    res = [r for r in (results or []) if "metrics_mean_action" in r]
    return {
        "eval_cost": eval_cost,
        "eval_metric": [r["metrics"][METRIC[task]] for r in res] if res else None,
        "eval_metric_mean_action": [r["metrics_mean_action"][METRIC[task]] for r in res] if res else None,
        "eval_cost_mean_action": [r["final_cost_mean_action"] for r in res] if res else None,
        "wall_s": [r["wall_time"] for r in (results or []) if "wall_time" in r] or None,
        "steps": (np.arange(n_it) + 1) * samples * T,
        "seeds": {m: np.array([[float(r[i][f"metric_{m}"]) for i in range(n_it)] for r in per_seed])
                  for m in (METRIC[task], "cost")},
    }


def sweep_curves(root: Path, rho2s=(0.0, 0.1), samples: int = 20, T: int = 100) -> dict:
    """The same from a noise sweep's trials (``soc-opt sweep problems/sweeps/noise_<task>.toml``:
    ``trials/<task>/<setting>,rho2=<r>/<method>/seed_<s>/metrics.csv``) for the settings of
    :data:`SWEEP_LABEL` at ``rho2s``; ``eval_cost`` from each trial's ``result.json``."""
    out = {}
    for task_dir in sorted((Path(root) / "trials").glob("*")):
        task = task_dir.name
        if task not in METRIC:
            continue
        for d in sorted(task_dir.glob("*,rho2=*")):
            setting, _, rho = d.name.partition(",rho2=")
            if setting not in SWEEP_LABEL or float(rho) not in rho2s:
                continue
            for method, name in METHODS.items():
                per_seed, costs, results = [], [], []
                for sd in sorted(d.glob(f"{method}/seed_*"), key=lambda p: int(p.name.split("_")[1])):
                    if not (sd / "result.json").exists():
                        continue
                    with open(sd / "metrics.csv") as fh:
                        per_seed.append(list(csv.DictReader(fh)))
                    results.append(json.loads((sd / "result.json").read_text()))
                    costs.append(results[-1]["final_cost"])
                if per_seed:
                    key = (SWEEP_LABEL[setting].format(m=name), task, float(rho))
                    out[key] = _curve(per_seed, task, samples, T, costs, results)
    return out


def _rl_runs(root: Path) -> list[dict]:
    """Finished runs (``*.json``) and, for runs cut short, their partial logs (``*.json.partial``:
    no ``final`` evaluation); then each long run at the smaller budgets it was scored at, unless a
    run of that budget (same algorithm, backend, setting, task, rho2 and seed) is there itself: a
    long run extended from a finished short run's checkpoint would otherwise count that seed twice."""
    runs = []
    for f in sorted(Path(root).glob("*.json")):
        runs.append(json.loads(f.read_text()))
    for f in sorted(Path(root).glob("*.json.partial")):
        if not f.with_suffix("").exists():
            runs.append(json.loads(f.read_text()))
    have = {_run_key(r) for r in runs}
    return runs + [cut for r in runs for cut in _at_smaller_budgets(r) if _run_key(cut) not in have]


def _run_key(run: dict) -> tuple:
    return (run["algo"], run.get("backend", "sb3"), run["setting"], run["task"], float(run["rho2"]), int(run["seed"]),
            int(run["budget"]))


def _at_smaller_budgets(run: dict) -> list[dict]:
    """A long run seen at each smaller budget it was scored at (``evals``, :func:`soc_opt.peers.rl.train`):
    its episodes up to that budget, the deterministic policy's score there as ``final`` and the wall
    time to it.  With constant learning rates this is the run of that budget, up to where PPO's last
    update falls (PPO updates every ``n_steps``, so the run of budget ``b`` makes one update more when
    ``b`` is not a multiple of ``n_steps``)."""
    out = []
    for ev in run.get("evals", []):
        b = int(ev["budget"])
        final = {k: v for k, v in ev.items() if k not in ("steps", "budget", "wall_s", "sampled")}
        out.append({**{k: run[k] for k in ("algo", "setting", "task", "rho2", "seed")},
                    "backend": run.get("backend", "sb3"), "budget": b,
                    "wall_s": ev["wall_s"], "episodes": [e for e in run["episodes"] if e["steps"] <= ev["steps"]],
                    "final": final, "cut_from": run["budget"],
                    **({"final_sampled": ev["sampled"]} if "sampled" in ev else {})})
    return out


def rl_label(run: dict) -> str:
    """``PPO default``, ``SAC tuned``, ``SAC default (sbx)``, ``CrossQ default (sbx)``: the algorithm,
    its setting and, unless stable-baselines3, the backend."""
    name = {"crossq": "CrossQ"}.get(run["algo"], run["algo"].upper())
    backend = run.get("backend", "sb3")
    return f"{name} {run['setting']}" + ("" if backend == "sb3" else f" ({backend})")


def rl_curves(root: Path, bin_steps: int = 2000) -> dict:
    """``{(label, task, rho2, budget): {"steps", "seeds": {metric: (S, B)}, "final", "last20", "wall_s",
    "steps_to_90", "reached"}}``; bins a run did not reach are NaN."""
    groups: dict = {}
    for r in _rl_runs(root):
        key = (rl_label(r), r["task"], r["rho2"], r["budget"])
        groups.setdefault(key, []).append(r)
    out = {}
    nan = float("nan")
    for key, runs in groups.items():
        task, budget = key[1], key[3]
        edges = np.arange(bin_steps, budget + 1, bin_steps)
        seeds = {}
        for m in (METRIC[task], "cost"):
            arr = []
            for r in runs:
                st = np.array([e["steps"] for e in r["episodes"]])
                v = np.array([e[m] for e in r["episodes"]])
                arr.append([v[(st > b - bin_steps) & (st <= b)].mean() if (st >= b).any() else nan for b in edges])
            seeds[m] = np.array(arr)
        s90 = None
        if task == "peg":
            s90 = [steps_to([e["steps"] for e in r["episodes"]], [e["success_rate"] for e in r["episodes"]])
                   for r in runs]
        out[key] = {"steps": edges, "seeds": seeds, "n_seeds": len(runs), "finished": ["final" in r for r in runs],
                    "final": {m: [r["final"][m] if "final" in r else nan for r in runs] for m in (METRIC[task], "cost")},
                    "final_sampled": {m: [r["final_sampled"][m] if "final_sampled" in r else nan for r in runs]
                                      for m in (METRIC[task], "cost")},
                    "last20": {m: [np.mean([e[m] for e in r["episodes"][-20:]]) for r in runs]
                               for m in (METRIC[task], "cost")},
                    "wall_s": [r.get("wall_s", nan) for r in runs], "steps_to_90": s90,
                    "reached": [r["episodes"][-1]["steps"] if r["episodes"] else 0 for r in runs]}
    return out


def _ms(v) -> str:
    v = np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return "n/a"
    f = ".2e" if 0 < abs(v.mean()) < 0.01 else ".2f"
    return f"{v.mean():{f}} ± {v.std():{f}}" if v.size > 1 else f"{v.mean():{f}}"


def _wall(v) -> str:
    """Seconds per run, mean ± std over the runs (whole seconds)."""
    v = np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    return f"{v.mean():.0f} ± {v.std():.0f}" if v.size > 1 else f"{v.mean():.0f}"


def _s90_soc(c) -> list:
    v = c["seeds"]["success_rate"]
    return [int(c["steps"][np.argmax(row >= 0.9)]) if (row >= 0.9).any() else None for row in v]


def _fmt_s90(v) -> str:
    hit = [x for x in v if x is not None]
    return (f"{int(np.median(hit)):,} ({len(hit)}/{len(v)} seeds)" if hit else f"not within budget (0/{len(v)})")


def rl_table(soc: dict, rl: dict) -> list[dict]:
    """Rows: method, task, rho2, env steps, seeds; the task metric (success rate / min hinge) and
    the true-state cost of the last 20 sampled episodes (mean ± std over seeds); the final policy on
    fresh episodes, sampled (soc_opt: with its exploration covariance) and with its mean action
    (stable-baselines3: ``deterministic=True``; soc_opt: ``K s + k``), so that like is compared with
    like; steps to 90% peg success; wall time per run."""
    rows = []
    for (label, task, rho2), c in sorted(soc.items(), key=lambda kv: (kv[0][1], kv[0][2], kv[0][0])):
        m = METRIC[task]
        rows.append({"method": label, "task": task, "rho2": rho2, "env_steps": int(c["steps"][-1]),
                     "seeds": c["seeds"][m].shape[0], "metric_last20": _ms(c["seeds"][m][:, -1]),
                     "cost_last20": _ms(c["seeds"]["cost"][:, -1]),
                     "metric_eval_sampled": _ms(c["eval_metric"]) if c.get("eval_metric") else "",
                     "cost_eval_sampled": _ms(c["eval_cost"]) if c.get("eval_cost") else "",
                     "metric_eval_mean_action": _ms(c["eval_metric_mean_action"]) if c.get("eval_metric_mean_action") else "",
                     "cost_eval_mean_action": _ms(c["eval_cost_mean_action"]) if c.get("eval_cost_mean_action") else "",
                     "steps_to_90": _fmt_s90(_s90_soc(c)) if task == "peg" else "",
                     "wall_s": _wall(c["wall_s"]) if c.get("wall_s") else ""})
    for (label, task, rho2, budget), c in sorted(rl.items(), key=lambda kv: (kv[0][1], kv[0][2], kv[0][3], kv[0][0])):
        m = METRIC[task]
        done = np.array(c.get("finished", [True] * c["n_seeds"]))
        # statistics over the finished runs; runs still going (or cut) are named with the steps they reached
        sel = done if done.any() else np.ones_like(done)
        pick = (lambda v: [x for x, k in zip(v, sel) if k])
        rest = ", ".join(f"{x:,}" for x, k in zip(c["reached"], done) if not k)
        steps = f"{budget:,}" if done.all() else f"{budget:,} ({int(done.sum())} finished; {rest} reached by the rest)"
        s90 = pick(c["steps_to_90"]) if c["steps_to_90"] is not None else None
        rows.append({"method": label, "task": task, "rho2": rho2, "env_steps": steps, "seeds": int(sel.sum()),
                     "metric_last20": _ms(pick(c["last20"][m])), "cost_last20": _ms(pick(c["last20"]["cost"])),
                     "metric_eval_sampled": _ms(pick(c["final_sampled"][m])) if "final_sampled" in c else "",
                     "cost_eval_sampled": _ms(pick(c["final_sampled"]["cost"])) if "final_sampled" in c else "",
                     "metric_eval_mean_action": _ms(pick(c["final"][m])), "cost_eval_mean_action": _ms(pick(c["final"]["cost"])),
                     "steps_to_90": _fmt_s90(s90) if task == "peg" else "",
                     "wall_s": _wall(pick(c["wall_s"])) if np.isfinite(pick(c["wall_s"])).any() else "cut"})
    return rows


def stored_rows(path: Path, present: list[dict], source: str) -> list[dict]:
    """Rows of an earlier ``rl.json`` for the (method, task, rho2, env_steps) that ``present`` lacks,
    marked with ``source``: runs that were not repeated keep their numbers, labelled.  Older tables
    scored RL with the mean action only (``metric_eval``, ``cost_eval``); their sampled columns
    say ``not recorded``."""
    have = {(r["method"], r["task"], float(r["rho2"]), str(r["env_steps"])) for r in present}
    out = []
    for r in json.loads(Path(path).read_text()):
        if (r["method"], r["task"], float(r["rho2"]), str(r["env_steps"])) in have:
            continue
        if not any(r["method"].startswith(p) for p in ("PPO", "SAC", "CrossQ")):
            continue  # soc_opt's rows come from the runs given
        row = {k: r.get(k, "") for k in ("method", "task", "rho2", "env_steps", "seeds", "metric_last20", "cost_last20")}
        row["method"] = f"{r['method']} [{source}]"
        row["metric_eval_sampled"] = r.get("metric_eval_sampled", "not recorded")
        row["cost_eval_sampled"] = r.get("cost_eval_sampled", "not recorded")
        row["metric_eval_mean_action"] = r.get("metric_eval_mean_action", r.get("metric_eval", ""))
        row["cost_eval_mean_action"] = r.get("cost_eval_mean_action", r.get("cost_eval", ""))
        row["steps_to_90"], row["wall_s"] = r.get("steps_to_90", ""), r.get("wall_s", "")
        out.append(row)
    return out


def _md(rows: list[dict]) -> str:
    if not rows:
        return "(no rows)\n"
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(k, "")) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:,.0f}"
    return str(v)


_COLORS = {"LQR-FLM": "tab:blue", "DPSOC-EM": "tab:orange", "PPO default": "tab:green",
           "PPO tuned": "tab:olive", "SAC default": "tab:red", "SAC tuned": "tab:purple",
           "CrossQ default": "tab:brown"}


def _figure(task: str, soc: dict, rl: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb

    m = METRIC[task]
    rhos = sorted({k[2] for k in soc if k[1] == task} | {k[2] for k in rl if k[1] == task})
    if not rhos:
        return
    fig, axes = plt.subplots(2, len(rhos), figsize=(5.5 * len(rhos), 7), squeeze=False)
    for j, rho2 in enumerate(rhos):
        # the paper-as-written rows are in the table; the figure shows the methods' defaults
        series = [(k[0], c) for k, c in soc.items() if k[1] == task and k[2] == rho2 and "as written" not in k[0]]
        series += [(f"{k[0]} ({k[3] // 1000}k)", c, k[3]) for k, c in rl.items() if k[1] == task and k[2] == rho2]
        for label, c, *budget in series:
            base = label.split(" (")[0]
            color = _COLORS.get(base.replace(" noise-aware", "").replace(" kinematic", ""), "gray")
            if budget and budget[0] > PAPER_BUDGET:  # the longer runs of one method: darker, no markers
                color = tuple(0.55 * x for x in to_rgb(color))
            ls = ":" if "noise-aware" in base else "-." if "kinematic" in base else \
                ("-" if base.startswith(("LQR", "DPSOC")) else "--")
            for i, key in enumerate((m, "cost")):
                v = c["seeds"][key]
                with np.errstate(all="ignore"):
                    import warnings

                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        mu, sd = np.nanmean(v, axis=0), np.nanstd(v, axis=0)
                long = bool(budget) and budget[0] > PAPER_BUDGET
                axes[i, j].plot(c["steps"], mu, ls, color=color, marker=None if long else ".", lw=1.2 if long else 1.5,
                                label=label)
                axes[i, j].fill_between(c["steps"], mu - sd, mu + sd, color=color, alpha=0.12)
        axes[0, j].set_title(f"{task}, rho^2 = {rho2:g}")
        axes[0, j].set_ylabel({"success_rate": "success rate", "min_hinge": "min hinge angle (rad)"}[m])
        axes[1, j].set_ylabel("task cost (true states)")
        axes[1, j].set_yscale("log")
        for i in range(2):
            axes[i, j].set_xscale("log")  # the paper's budget (28k) and 10x it on one axis
            axes[i, j].set_xlabel("environment steps (log scale)")
            axes[i, j].grid(alpha=0.3)
        axes[0, j].legend(fontsize=7, loc="best")
    fig.suptitle(f"{task}: soc_opt (solid) vs model-free RL (dashed), mean ± std over seeds; "
                 "RL: training episodes in bins of 2,000 steps")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/results/peers")
    ap.add_argument("--rl", nargs="+", default=["runs/peers-rl"], help="directories of RL runs (one JSON per run)")
    ap.add_argument("--stored", default=None,
                    help="an earlier rl.json: its RL rows that no run given here repeats are kept, labelled (see --stored-label)")
    ap.add_argument("--stored-label", default="stored")
    ap.add_argument("--soc", default="runs/peers-soc")
    ap.add_argument("--sweep", nargs="*", default=[],
                    help="noise sweep output directories (runs/sweep-noise_peg ...): their paper, noise-aware and "
                         "kinematic trials at rho^2 0 and 0.1 replace --soc's rows of the same method, task and rho^2")
    ap.add_argument("--skip-kernels", action="store_true")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    parts = []
    if not a.skip_kernels:
        from . import lqr, smoothers

        (out / "smoothers.json").write_text(json.dumps(smoothers.run(), indent=1))
        (out / "lqr.json").write_text(json.dumps(lqr.run(), indent=1))
    for name in ("smoothers", "lqr"):
        f = out / f"{name}.json"
        if f.exists():
            parts.append(f"## {name}\n\n" + _md(json.loads(f.read_text())))
    soc = soc_curves(Path(a.soc)) if Path(a.soc).exists() else {}
    for d in a.sweep:
        soc.update(sweep_curves(Path(d)))
    rl = {}
    for d in a.rl:
        if Path(d).exists():
            rl.update(rl_curves(Path(d)))
    table = rl_table(soc, rl)
    if a.stored:
        table += stored_rows(Path(a.stored), table, a.stored_label)
    (out / "rl.json").write_text(json.dumps(table, indent=1))
    parts.append("## sample efficiency\n\n" + _md(table))
    for task in METRIC:
        _figure(task, soc, rl, out / f"{task}_vs_steps.png")
    (out / "tables.md").write_text("\n".join(parts))
    print((out / "tables.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
