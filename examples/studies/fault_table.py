"""The fault table of docs/results/faults.md: runs interrupted with SIGINT or SIGKILL, each resumed
in a fresh process with the same command, compared with the uninterrupted run.

    python examples/studies/fault_table.py OUT [--task peg] [--methods lqr-flm dpsoc-em ilqg]
                                   [--after 1 4 5 8 12] [--random 6] [--seed 0] [--signals SIGINT SIGKILL]

Every run is ``soc-opt run TASK --method M --out DIR`` (``--paper`` for the sample-based methods)
in its own interpreter.  "after k" sends the signal as soon as ``metrics.json`` holds k
iterations (so the process dies inside iteration k + 1, or while writing it); "random" SIGKILLs at
a uniformly drawn time within the uninterrupted run's wall time.  A resumed run is "identical"
when every non-time column of ``metrics.json`` and every array of ``policies/``, ``samples/`` and
``best_policy.npz`` equal the uninterrupted run's exactly.  Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _cmd(task, method, out):
    paper = ["--paper"] if method != "ilqg" else []
    return [sys.executable, "-c", "import sys; from soc_opt.cli import main; sys.exit(main())", "run", task,
            "--method", method, *paper, "--out", str(out), "--progress", "lines"]


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")


def _rows(d: Path) -> int:
    try:
        return len(json.loads((d / "metrics.json").read_text()))
    except (OSError, ValueError):
        return 0


def _files(d: Path) -> dict:
    rows = json.loads((d / "metrics.json").read_text())
    out = {"metrics": [{k: v for k, v in r.items() if not k.startswith("time")} for r in rows]}
    for p in sorted(d.glob("policies/*.npz")) + sorted(d.glob("samples/*.npz")) + [d / "best_policy.npz"]:
        if p.exists():
            with np.load(p) as f:
                out[str(p.relative_to(d))] = {k: f[k] for k in f.files}
    return out


def _compare(a: Path, b: Path) -> str:
    ra, rb = _files(a), _files(b)
    if ra.keys() != rb.keys():
        return f"different files ({sorted(set(ra) ^ set(rb))[:3]})"
    if ra["metrics"] != rb["metrics"]:
        first = next(i for i, (x, y) in enumerate(zip(ra["metrics"], rb["metrics"])) if x != y)
        x, y = ra["metrics"][first], rb["metrics"][first]
        keys = [k for k in x if x[k] != y.get(k)]
        rel = max(abs(x[k] - y[k]) / max(abs(x[k]), 1e-300) for k in keys if isinstance(x[k], float))
        return f"differs from iteration {first} ({', '.join(keys[:3])}; max rel. {rel:.1e})"
    for key in ra:
        if key != "metrics" and any(not np.array_equal(ra[key][n], rb[key][n]) for n in ra[key]):
            return f"metrics equal, {key} differs"
    return "identical"


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # a background shell starts its jobs with SIGINT ignored


def _interrupted(task, method, out, sig, after=None, at=None) -> tuple[int, int]:
    p = subprocess.Popen(_cmd(task, method, out), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         preexec_fn=_default_sigint)
    t0 = time.perf_counter()
    while p.poll() is None:
        if (after is not None and _rows(out) >= after) or (at is not None and time.perf_counter() - t0 >= at):
            p.send_signal(sig)
            break
        time.sleep(0.01)
    p.wait()
    return p.returncode, _rows(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--task", default="peg")
    ap.add_argument("--methods", nargs="+", default=["lqr-flm", "dpsoc-em", "ilqg"])
    ap.add_argument("--after", nargs="+", type=int, default=[1, 4, 5, 8, 12])
    ap.add_argument("--random", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--signals", nargs="+", default=["SIGINT", "SIGKILL"], help="signals sent after k iterations")
    args = ap.parse_args(argv)
    out = Path(args.out)
    rng = np.random.default_rng(args.seed)
    print("| method | fault | exit | iterations saved | resumed in a new process |")
    print("|---|---|---|---|---|")
    for method in args.methods:
        ref = out / method / "reference"
        t0 = time.perf_counter()
        subprocess.run(_cmd(args.task, method, ref), env=_env(), check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        faults = [(f"{s.name} after iteration {k}", s, k, None) for k in args.after
                  for s in (signal.Signals[n] for n in args.signals)
                  if k < _rows(ref)]
        faults += [(f"SIGKILL at {t:.1f} s", signal.SIGKILL, None, t)
                   for t in np.sort(rng.uniform(0.05, 1.0, args.random)) * wall]
        for i, (name, sig, after, at) in enumerate(faults):
            d = out / method / f"fault{i}"
            code, saved = _interrupted(args.task, method, d, sig, after, at)
            r = subprocess.run(_cmd(args.task, method, d), env=_env(), stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
            result = _compare(ref, d) if r.returncode == 0 else f"resume failed: {r.stderr.strip()[-200:]}"
            print(f"| {method} | {name} | {code} | {saved} | {result} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
