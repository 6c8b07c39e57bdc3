"""E-step benchmark: smoother wall time on random closed loops (SPEC §4)."""

from __future__ import annotations

import time

import numpy as np

from ..models import AugmentedModel, LinearGaussianPolicy


def _instance(T: int, n: int, m: int, rng: np.random.Generator):
    A = 0.95 * np.linalg.qr(rng.standard_normal((T, n, n)))[0]
    Ao = np.concatenate([np.concatenate([A, 0.1 * rng.standard_normal((T, n, m))], axis=2),
                         0.1 * rng.standard_normal((T, 1, n + m))], axis=1)
    Lo = 0.1 * rng.standard_normal((T, n + 1, n + 1))
    So = Lo @ np.swapaxes(Lo, 1, 2) + 0.01 * np.eye(n + 1)
    model = AugmentedModel(Ao, 0.1 * rng.standard_normal((T, n + 1)), So, n)
    policy = LinearGaussianPolicy(0.1 * rng.standard_normal((T, m, n)), rng.standard_normal((T, m)),
                                  np.broadcast_to(0.1 * np.eye(m), (T, m, m)).copy())
    return model, policy


def run(cases=((100, 26, 7, 1), (100, 26, 7, 20), (1000, 26, 7, 1)), seed: int = 0, repeats: int = 3) -> list[dict]:
    from ..estep import smooth

    rng = np.random.default_rng(seed)
    rows = []
    for T, n, m, M in cases:
        model, policy = _instance(T, n, m, rng)
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
