"""E-step smoother vs dynamax and pykalman (``soc-opt bench --only peers.smoothers``).

One row per state size ``n`` (``T = 100``, 20 sequences, ``m = 7``): max absolute differences
of smoothed means, covariances and log-likelihoods to soc_opt, wall times and their ratios
(peer / soc_opt; dynamax's first call, which traces and compiles, apart).  See
:mod:`soc_opt.peers.smoothers` for the model.
"""

from __future__ import annotations

import numpy as np

__all__ = ["run", "SIZES"]

SIZES = (6, 14, 26)


def run(sizes=SIZES, T: int = 100, M: int = 20, seed: int = 0, repeats: int = 15) -> list[dict]:
    from ...peers import smoothers

    rng = np.random.default_rng(seed)
    rows = []
    for n in sizes:
        try:
            rows.append(smoothers.compare(rng, n, T=T, M=M, repeats=repeats))
        except ImportError as e:
            return [{"n": n, "error": str(e)}]
    return rows


if __name__ == "__main__":
    for r in run():
        print(r)
