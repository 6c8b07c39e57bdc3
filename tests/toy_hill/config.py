"""The toy method's settings: the ``[hill]`` table of a run configuration."""

from dataclasses import dataclass

from soc_opt.config import Config, Interval


@dataclass(frozen=True)
class HillConfig(Config):
    """Random search on the feed-forward term (``[hill]``).

    iterations: rounds of a run (``--iterations`` sets it).
    samples:    rollouts per policy and round.
    radius:     length of a random move of the feed-forward term.
    init_var:   covariance of the initial policy (times ``I``).
    """

    iterations: int = 3
    samples: int = 4
    radius: float = 0.5
    init_var: float = 1.0

    _constraints = {
        "iterations": [Interval(1)],
        "samples": [Interval(2)],
        "radius": [Interval(0, None, "neither")],
        "init_var": [Interval(0, None, "neither")],
    }
