"""Upper bounds of the run configuration's counts (docs/security.md, "Values are checked").

Far above any experiment of the paper (14 iterations of 20 samples, docs/math.md §9.5) and low enough that
a configuration cannot ask for a run that never ends or a batch that cannot be held; checked before
anything is written (:func:`soc_opt.methods.config.check_scale`).
"""

from __future__ import annotations

__all__ = ["MAX_ITERATIONS", "MAX_SAMPLES", "MAX_WORKERS", "MAX_BATCH_BYTES"]

MAX_ITERATIONS = 10_000
MAX_SAMPLES = 10_000
MAX_WORKERS = 256
#: Largest batch of rollouts (states, measurements, actions, costs; float64) a run may sample at once.
MAX_BATCH_BYTES = 1 << 30
