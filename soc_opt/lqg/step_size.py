"""The step-size rule of the KL budget (GPS, docs/math.md §6 last bullet) under the Laplace
approximation: its settings :class:`StepSizeConfig`, :func:`laplace_improvements` and
:func:`adapt_multiplier`.  Step acceptance (docs/math.md §12) decides when the rule is applied:
:mod:`soc_opt.methods.lqr_flm.acceptance`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import Config, Interval, config_error
from ..models import LinearGaussianPolicy
from .moments import expected_cost
from .problem import LocalModel

__all__ = ["StepSizeConfig", "LocalModel", "laplace_improvements", "adapt_multiplier"]


@dataclass(frozen=True)
class StepSizeConfig(Config):
    """The GPS rule on the KL-budget multiplier (:func:`adapt_multiplier`; ``[baseline.step_size]``).

    factor_min, factor_max: clip of the per-iteration factor ``predicted / (2 (predicted - actual))``
                    (0.1, 5.0).
    min_gap:        floor of the denominator ``predicted - actual`` (1e-4, cost units).
    mult_min, mult_max: clip of the multiplier (1e-4, 1e4); ``mult_min`` also floors the multiplier
                    that a rejected step leaves (:func:`soc_opt.methods.lqr_flm.acceptance.next_multiplier`).
    """

    factor_min: float = 0.1
    factor_max: float = 5.0
    min_gap: float = 1e-4
    mult_min: float = 1e-4
    mult_max: float = 1e4

    _constraints = {name: [Interval(0, None, "neither")] for name in ("factor_min", "factor_max", "min_gap", "mult_min",
                                                                       "mult_max")}

    def __post_init__(self):
        for lo, hi in (("factor_min", "factor_max"), ("mult_min", "mult_max")):
            if getattr(self, lo) > getattr(self, hi):
                raise config_error(lo, f"must be below {hi} = {getattr(self, hi)!r}, got {getattr(self, lo)!r}")


def laplace_improvements(old_policy: LinearGaussianPolicy, new_policy: LinearGaussianPolicy,
                         previous: LocalModel, current: LocalModel) -> tuple[float, float]:
    """Predicted and actual improvement of the expected cost under the Laplace approximation.

    ``previous`` is the model (dynamics fit + cost expansion around the old trajectory) the
    KL step that produced ``new_policy`` was solved on; ``current`` is the model fitted to the
    samples of ``new_policy``.  With ``J_M(p) = sum_k E[l_k]`` in closed form under model ``M``:

        predicted = J_previous(old) - J_previous(new)     (what the step promised)
        actual    = J_previous(old) - J_current(new)      (what the new samples show)

    Returns ``(predicted, actual)`` as floats.
    """
    j_old = expected_cost(previous.dynamics, previous.cost, old_policy, previous.mu0, previous.P0).sum()
    j_pred = expected_cost(previous.dynamics, previous.cost, new_policy, previous.mu0, previous.P0).sum()
    j_act = expected_cost(current.dynamics, current.cost, new_policy, current.mu0, current.P0).sum()
    return float(j_old - j_pred), float(j_old - j_act)


def adapt_multiplier(mult, predicted_improvement: float, actual_improvement: float,
                     config: StepSizeConfig | None = None):
    """GPS step-size rule: scale the KL-budget multiplier by how well the model predicted the improvement.

    The loop's budget is ``kl_budget * T * mult``; this adapts ``mult`` (docs/math.md §6).
    ``factor = predicted / (2 max(min_gap, predicted - actual))`` clipped to
    ``[factor_min, factor_max]``; ``new_mult = clip(factor * mult, mult_min, mult_max)``
    (:class:`StepSizeConfig`).  The factor is the minimiser of the quadratic fitted to the two
    improvements: a perfect prediction (``actual = predicted``) gives ``factor_max``, ``actual = 0``
    halves the multiplier, a cost increase (or a non-positive prediction) gives ``factor_min``.
    ``mult`` may be a scalar or an array (every entry scaled by the same factor); returns the same kind.
    """
    config = StepSizeConfig() if config is None else config
    pred, act = float(predicted_improvement), float(actual_improvement)
    if not (math.isfinite(pred) and math.isfinite(act)):
        raise ValueError(f"improvements must be finite, got predicted={pred!r}, actual={act!r}")
    nu_a = np.asarray(mult, dtype=float)
    if np.any(np.isnan(nu_a)) or np.any(nu_a < 0):
        raise ValueError(f"mult must be non-negative and not NaN, got {mult!r}")
    factor = pred / (2.0 * max(config.min_gap, pred - act))
    factor = min(max(factor, config.factor_min), config.factor_max)
    out = np.clip(factor * nu_a, config.mult_min, config.mult_max)
    return float(out) if nu_a.ndim == 0 else out
