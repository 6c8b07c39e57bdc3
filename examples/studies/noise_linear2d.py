"""Paper-as-written next to noise-aware on linear2d under sensor noise (issue 9, docs/math.md §10).

Four variants, each on the same seeds: LQR-FLM and DPSOC-EM as in the paper, and both with the
noise-aware pieces of ``[baseline.noise]`` (a Kalman filter in the loop and a noise-aware fit;
``--variants`` picks the noise configurations).  DPSOC-EM starts from a copy of the LQR-FLM state of the same
variant at ``i_switch`` (as ``soc-opt compare`` does).  linear2d is linear, so the final policy is
scored *exactly* (``soc_opt.noise.lqg_reference.expected_cost``: closed-loop moments of the true
system with the policy's own filter, or with ``xhat = s`` for a policy acting on ``s``), as a
ratio to the exact LQG optimum (``task_reference``: 7,473.39 at ``rho2 = 0.1``).

Usage:
    python examples/studies/noise_linear2d.py                     # paper and kalman+ssm_em, 5 seeds, 10 iterations
    python examples/studies/noise_linear2d.py --variants kalman+none none+ssm_em kalman+moments --methods lqr-flm
    python examples/studies/noise_linear2d.py --samples 30 --out results.md

Prints a markdown report (and writes it to ``--out`` with the raw numbers next to it as JSON).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from soc_opt.experiments.run import fork_state, load_run_config
from soc_opt.methods import registry
from soc_opt.noise.aware import NoiseConfig
from soc_opt.noise.estimator import FilteredPolicy, kalman_filter, measurement_noise
from soc_opt.noise.lqg_reference import expected_cost, task_reference
from soc_opt.tasks import load_task


def exact_cost(task, policy) -> float:
    """Exact expected true-state cost of ``policy`` (plain: acts on ``s``; filtered: on ``xhat``)."""
    n = task.n
    dyn = task.linearize()
    mu0 = np.asarray(task.mu0, float)
    cost = task.cost_expansion(np.broadcast_to(mu0, (task.T + 1, n)).copy(), np.zeros((task.T, task.m)))
    if not isinstance(policy, FilteredPolicy):  # xhat = s: the filter of any model with R = 0
        policy = FilteredPolicy(policy, kalman_filter(dyn, np.zeros((n, n)), mu0, np.eye(n)))
    return float(expected_cost(dyn, cost, measurement_noise(task.rho2, n), policy, mu0, np.zeros((n, n))).sum())


def run_variant(task, cfg, seed, methods):
    """LQR-FLM to the end and DPSOC-EM forked at ``i_switch``; returns the final states (or the error)."""
    fork = []

    def keep(st):
        if st.iteration == cfg.i_switch and not fork:
            fork.append(fork_state(st))

    out = {}
    try:
        out["lqr-flm"] = registry.run(task, "lqr-flm", cfg, seed=seed, on_iteration=keep)
    except Exception as e:  # a failed run is a result too (e.g. the KL step on a diverging model)
        out["lqr-flm"] = e
    if "dpsoc-em" in methods:
        try:
            if not fork:
                raise RuntimeError("LQR-FLM failed before the switch") from None
            out["dpsoc-em"] = registry.run(task, "dpsoc-em", cfg, seed=seed, state=fork[0])
        except Exception as e:
            out["dpsoc-em"] = e
    return {m: out[m] for m in methods}


def parse_variant(text: str) -> NoiseConfig:
    """``paper`` or ``ESTIMATOR+FIT[+wH]`` (e.g. ``kalman+ssm_em``, ``kalman+ssm_em+w50``) -> NoiseConfig."""
    if text == "paper":
        return NoiseConfig()
    est, corr, *rest = text.split("+")
    window = int(rest[0].removeprefix("w")) if rest else 0
    return NoiseConfig(estimator=est, fit_correction=corr, time_window=window)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--samples", type=int, default=None, help="rollouts per iteration (default: the task's run config)")
    ap.add_argument("--rho2", type=float, default=0.1)
    ap.add_argument("--variants", nargs="+", default=["paper", "kalman+ssm_em"],
                    help="noise configs: 'paper' or ESTIMATOR+FIT[+wH], e.g. kalman+ssm_em+w50, kalman+moments, none+ssm_em")
    ap.add_argument("--methods", nargs="+", default=["lqr-flm", "dpsoc-em"], choices=["lqr-flm", "dpsoc-em"])
    ap.add_argument("--out", type=Path, default=None, help="markdown file to write (JSON next to it)")
    args = ap.parse_args()

    task = load_task("linear2d", overrides={"rho2": args.rho2})
    lqg_cost = task_reference(task).total
    base_cfg = load_run_config("linear2d", overrides={"iterations": args.iterations, "samples": args.samples})
    rows = {}  # "method (variant)" -> {"final": [...], "iter": [[...] per seed], "failed": [...]}
    t0 = time.perf_counter()
    for vname in args.variants:
        noise = parse_variant(vname)
        cfg = base_cfg.replace(baseline=base_cfg.baseline.replace(noise=noise))
        for seed in args.seeds:
            for meth, st in run_variant(task, cfg, seed, args.methods).items():
                r = rows.setdefault(f"{meth} ({noise.label})", {"final": [], "iter": [], "failed": []})
                if isinstance(st, Exception):
                    r["failed"].append(f"seed {seed}: {type(st).__name__}: {str(st)[:160]}")
                    print(f"{meth:8s} {vname:14s} seed {seed}: FAILED {r['failed'][-1]}", flush=True)
                    continue
                r["final"].append(exact_cost(task, st.policy) / lqg_cost)
                r["iter"].append([float(np.mean(h.cost)) / lqg_cost for h in st.history if h.phase == "baseline"])
                print(f"{meth:8s} {vname:14s} seed {seed}: final exact cost / LQG = {r['final'][-1]:.4f}", flush=True)
    elapsed = time.perf_counter() - t0
    md = report(args, base_cfg, lqg_cost, rows, elapsed)
    print(md)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(md)
        args.out.with_suffix(".json").write_text(json.dumps(
            {"lqg_cost": lqg_cost, "seeds": args.seeds, "rows": rows, "args": {k: str(v) for k, v in vars(args).items()}},
            indent=1))


def report(args, cfg, lqg_cost, rows, elapsed) -> str:
    b = cfg.baseline
    cmd = (f"python examples/studies/noise_linear2d.py --seeds {' '.join(map(str, args.seeds))} --iterations {args.iterations}"
           f"{f' --samples {args.samples}' if args.samples else ''} --rho2 {args.rho2:g} "
           f"--variants {' '.join(args.variants)} --methods {' '.join(args.methods)}")
    lines = [
        f"Command: `{cmd}`",
        "",
        f"Setup: linear2d (T = 50), rho^2 = {args.rho2:g}, {b.iterations} iterations x {b.samples} samples, "
        f"i_switch = {cfg.i_switch}, EM y_mode = {cfg.em.y_mode}; the rest as `problems/experiments/linear2d.toml`. "
        f"Exact LQG optimum (deterministic start): {lqg_cost:,.2f}. Wall time {elapsed / 60:.1f} min.",
        "",
        "Final policy, exact expected true-state cost / LQG (mean ± std over the seeds that finished; per seed):",
        "",
        "| method (estimator + fit) | ratio to LQG | per seed | failed runs |",
        "|---|---|---|---|",
    ]
    for name, r in rows.items():
        f = np.asarray(r["final"])
        mean = f"{f.mean():.4f} ± {f.std():.4f}" if f.size else "n/a"
        lines.append(f"| {name} | {mean} | {', '.join(f'{v:.3f}' for v in f)} | {len(r['failed'])} |")
    its = [x for r in rows.values() for x in r["iter"]]
    n_it = max((len(x) for x in its), default=0)
    lines += ["", "Sample mean cost / LQG per iteration (mean over seeds; the policy sampled in that iteration):", "",
              "| method | " + " | ".join(str(i + 1) for i in range(n_it)) + " |",
              "|---|" + "---|" * n_it]
    for name, r in rows.items():
        if not r["iter"]:
            continue
        it = np.array([x + [np.nan] * (n_it - len(x)) for x in r["iter"]])
        lines.append(f"| {name} | " + " | ".join(f"{v:.3f}" for v in np.nanmean(it, axis=0)) + " |")
    failed = [f"- {name}: {msg}" for name, r in rows.items() for msg in r["failed"]]
    if failed:
        lines += ["", "Failed runs:", ""] + failed
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
