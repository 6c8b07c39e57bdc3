"""A toy noise estimator for tests/test_extension.py: the whole of a new estimator, with its own
options, is this file plus one registry line (``soc_opt.plugins.ESTIMATORS.register(QuantileState)``,
or a line in ``soc_opt/noise/registry.py``).

"Quantile state": the policy still acts on the measured state, but the cost is expanded around a
per-step quantile of the measured states instead of their mean (the median by default: robust to
outliers).  Its option is the ``[baseline.noise.quantile]`` table (:class:`QuantileConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from soc_opt.config import Config, Interval
from soc_opt.noise.strategy import NoiseStrategy


@dataclass(frozen=True)
class QuantileConfig(Config):
    """The toy estimator ``quantile`` (``[baseline.noise.quantile]``).

    q: the quantile of the measured states, per step and coordinate, the cost is expanded around (0.5: the median).
    """

    q: float = 0.5

    _constraints = {"q": [Interval(0, 1)]}


class QuantileState(NoiseStrategy):
    name = "quantile"
    settings = QuantileConfig
    calls: list = []  # (expansion points handed out), for the test

    def expansion_point(self, rollouts, dynamics) -> np.ndarray:
        point = np.quantile(rollouts.s, self.cfg.section(self.name).q, axis=0)
        QuantileState.calls.append(point)
        return point
