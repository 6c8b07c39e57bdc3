"""Step-size adaptation of the KL budget (GPS, docs/math.md §6 last bullet) under the Laplace
approximation: :func:`laplace_improvements` and :func:`adapt_multiplier`."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..models import LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost
from .moments import expected_cost
from .problem import KLStepConfig


class LocalModel(NamedTuple):
    """A fitted local model: dynamics, quadratic cost expansion and initial state distribution."""

    dynamics: LinearGaussianDynamics
    cost: QuadraticCost
    mu0: np.ndarray
    P0: np.ndarray


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
                     config: KLStepConfig | None = None):
    """GPS step-size rule: scale the KL-budget multiplier by how well the model predicted the improvement.

    The loop's budget is ``kl_budget * T * mult``; this adapts ``mult`` (docs/math.md §6).
    ``factor = predicted / (2 max(min_gap, predicted - actual))`` clipped to
    ``[factor_min, factor_max]`` (defaults 0.1, 5.0); ``new_mult = clip(factor * mult, mult_min,
    mult_max)``.  The factor is the minimiser of the quadratic fitted to the two improvements: a
    perfect prediction (``actual = predicted``) gives ``factor_max``, ``actual = 0`` halves the
    multiplier, a cost increase (or a non-positive prediction) gives ``factor_min``.  ``mult`` may
    be a scalar or an array (every entry scaled by the same factor); returns the same kind.
    """
    config = KLStepConfig() if config is None else config
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
