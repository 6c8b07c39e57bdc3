"""Time per paper-scale iteration by phase, read from the run directories of a `soc-opt compare`
(``metrics.json``: ``time_rollouts``, ``time_estimator``, ``time_fit``, ``time_lqg`` per iteration).

Usage:
    python examples/studies/noise_kinematic_timings.py runs/peg_kinematic
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None):
    root = Path((argv or sys.argv[1:])[0])
    rows = {}
    for mfile in sorted(root.glob("seed_*/*/metrics.json")):
        method = mfile.parent.name
        for rec in json.loads(mfile.read_text()):
            for k, v in rec.items():
                if k.startswith("time_") and v is not None and np.isfinite(v):
                    rows.setdefault((method, rec.get("phase", "?"), k[5:]), []).append(float(v))
    print("| method | phase of run | step | median (s) | mean (s) | n |\n|---|---|---|---|---|---|")
    for (method, phase, step), v in sorted(rows.items()):
        print(f"| {method} | {phase} | {step} | {np.median(v):.2f} | {np.mean(v):.2f} | {len(v)} |")


if __name__ == "__main__":
    main()
