"""The noise estimators of ``[baseline.noise] estimator``, one registry line each.

Importing this module fills :data:`soc_opt.plugins.ESTIMATORS` (the core reads that table and never
this module; the table imports it on first use).  A new estimator is one module with a subclass of
:class:`soc_opt.noise.strategy.NoiseStrategy` (its ``name``, its own options as ``settings``, the
``[baseline.noise.NAME]`` table, and its saved-state classes as ``state_types``) plus one line here,
or ``ESTIMATORS.register(...)`` from a script or test (both checked by :func:`~soc_opt.noise.strategy.check_strategy`).
"""

from __future__ import annotations

from ..plugins import ESTIMATORS
from .kinematic_strategy import KinematicEstimator
from .strategy import KalmanEstimator, MeasuredState, check_strategy

__all__ = ["ESTIMATORS"]

ESTIMATORS.check = check_strategy  # every registration, here or from a script

ESTIMATORS.register(MeasuredState)
ESTIMATORS.register(KalmanEstimator)
ESTIMATORS.register(KinematicEstimator)
