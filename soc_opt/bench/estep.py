"""E-step benchmark: smoother wall time on random closed loops (docs/math.md §4)."""

from __future__ import annotations

import time

import numpy as np

from ..testing import random_closed_loop

#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"cases": ((5, 3, 2, 1), (5, 3, 2, 3)), "repeats": 1}


def run(cases=((100, 26, 7, 1), (100, 26, 7, 20), (1000, 26, 7, 1)), seed: int = 0, repeats: int = 3) -> list[dict]:
    from ..estep import smooth

    rng = np.random.default_rng(seed)
    rows = []
    for T, n, m, M in cases:
        model, policy = random_closed_loop(rng, n, m, T)
        y = rng.random((M, T)) if M > 1 else rng.random(T)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            sm = smooth(model, policy, y, np.zeros(n), np.eye(n))
            times.append(time.perf_counter() - t0)
        rows.append({"T": T, "n": n, "m": m, "sequences": M, "median_ms": 1e3 * float(np.median(times)),
                     "finite": bool(np.all(np.isfinite(sm.cov)))})
    return rows


if __name__ == "__main__":
    for r in run():
        print(r)
