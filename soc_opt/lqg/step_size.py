"""Step-size adaptation of the KL budget (GPS, docs/math.md §6 last bullet) under the Laplace
approximation: :func:`laplace_improvements` and :func:`adapt_step`."""

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


def adapt_step(nu, predicted_improvement: float, actual_improvement: float,
               config: KLStepConfig | None = None):
    """GPS step-size rule: scale the KL budget by how well the model predicted the improvement.

    ``mult = predicted / (2 max(min_gap, predicted - actual))`` clipped to
    ``[min_mult, max_mult]`` (defaults 0.1, 5.0); ``new_nu = clip(mult * nu, nu_min, nu_max)``.
    The multiplier is the minimiser of the quadratic fitted to the two improvements: a perfect
    prediction (``actual = predicted``) gives ``max_mult``, ``actual = 0`` halves the budget,
    a cost increase (or a non-positive prediction) gives ``min_mult``.  ``nu`` may be a scalar
    or an array (every entry scaled by the same multiplier); returns the same kind.
    """
    config = KLStepConfig() if config is None else config
    pred, act = float(predicted_improvement), float(actual_improvement)
    if not (math.isfinite(pred) and math.isfinite(act)):
        raise ValueError(f"improvements must be finite, got predicted={pred!r}, actual={act!r}")
    nu_a = np.asarray(nu, dtype=float)
    if np.any(np.isnan(nu_a)) or np.any(nu_a < 0):
        raise ValueError(f"nu must be non-negative and not NaN, got {nu!r}")
    mult = pred / (2.0 * max(config.min_gap, pred - act))
    mult = min(max(mult, config.min_mult), config.max_mult)
    out = np.clip(mult * nu_a, config.nu_min, config.nu_max)
    return float(out) if nu_a.ndim == 0 else out
