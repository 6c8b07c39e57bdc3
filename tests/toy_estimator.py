"""A toy noise estimator for tests/test_extension.py: the whole of a new estimator is this class
plus one entry ``"name": "module:Class"`` in ``soc_opt.noise.aware.ESTIMATORS``.

"Median state": the policy still acts on the measured state, but the cost is expanded around
the per-step median of the measured states instead of their mean (robust to outliers).
"""

from __future__ import annotations

import numpy as np

from soc_opt.noise.strategy import NoiseStrategy


class MedianState(NoiseStrategy):
    name = "median"
    calls: list = []  # (expansion points handed out), for the test

    def expansion_point(self, rollouts, dynamics) -> np.ndarray:
        point = np.median(rollouts.s, axis=0)
        MedianState.calls.append(point)
        return point
