"""LQR kernels vs mpc.pytorch (``soc-opt bench --only peers.lqr``).

One row per size ``(n, m, T)``: plain LQR (soc_opt's backward pass with ``eta = 0``) and the KL
step with a total budget against the peer's LQR step on the same cost (the KL step's at its
multiplier); times (median of ``repeats``), ratios (peer / soc_opt) and the largest differences
of the optimal trajectories.  See :mod:`soc_opt.peers.lqr`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["run", "SIZES"]

SIZES = ((6, 2, 50), (14, 7, 100), (26, 7, 100))


def run(sizes=SIZES, seed: int = 0, repeats: int = 5, nu: float = 1.0) -> list[dict]:
    from ...peers import lqr

    rng = np.random.default_rng(seed)
    rows = []
    for n, m, T in sizes:
        try:
            rows.append(lqr.compare(rng, n, m, T, nu=nu, repeats=repeats))
        except ImportError as e:
            return [{"n": n, "m": m, "T": T, "error": str(e)}]
    return rows


if __name__ == "__main__":
    for r in run():
        print(r)
