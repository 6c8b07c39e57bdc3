"""The toy method's saved state."""

from dataclasses import dataclass

from soc_opt.methods.state import BestPolicy, IterationRecord
from soc_opt.models import LinearGaussianPolicy, Rollouts


@dataclass(frozen=True)
class HillState:
    """What a run directory reads (``iteration``, ``policy``, ``history``, ``best``, ``last_rollouts``), the RNG,
    and the number of moves kept."""

    iteration: int
    policy: LinearGaussianPolicy
    rng_state: dict
    history: tuple[IterationRecord, ...] = ()
    best: BestPolicy | None = None
    last_rollouts: Rollouts | None = None
    kept: int = 0
