"""One noise strategy per run: what ``[baseline.noise]`` means to the LQR-FLM / DPSOC-EM loop.

:func:`resolve` turns a task and its :class:`~soc_opt.noise.aware.NoiseConfig` into one
:class:`NoiseStrategy` object (memoised per task and configuration, so a run resolves it once).
The loop (:mod:`soc_opt.methods.lqr_flm`, :mod:`soc_opt.methods.dpsoc_em`) calls only the
strategy's operations and never branches on the configuration:

============================  ==================================================================
``estimate``                  what the estimator finds in one batch of rollouts, as an
                              :class:`Estimates`: the mixture prior, state estimates for the fit
                              correction, the rollouts the learner fits on and the estimator's
                              own per-batch result (e.g. a filter)
``fit``                       the local model (dynamics, or the augmented model for EM) under the
                              fit correction (docs/math.md §10.1)
``expansion_point``           the ``(T+1, n)`` trajectory the cost is expanded around
``lqg_model``                 the KL step's model and how its new policy is wrapped (§6, §10.2)
``em_model``                  the EM recursion's augmented model, initial distribution and wrap
``gains``                     the linear-Gaussian part ``(K, k, Sigma)`` of a policy of this
                              estimator (what the KL step and the M-step read)
============================  ==================================================================

The loop hands the :class:`Estimates` of a batch to that batch's ``fit``, ``lqg_model`` and
``em_model`` and fits on :meth:`Estimates.data`; a strategy keeps no per-iteration state (it is
shared by the whole run, and a run resumed in a new process must equal the uninterrupted one).

The estimator (``NoiseConfig.estimator``) picks the class from :data:`soc_opt.plugins.ESTIMATORS`
(filled by :mod:`soc_opt.noise.registry`); the fit correction, expansion point and prior data are
options every estimator shares through :class:`NoiseStrategy`.  Adding an estimator is one new
class (a subclass of :class:`NoiseStrategy` overriding what differs, usually ``lqg_model``,
``em_model`` and ``gains``; its own options as ``settings``, the ``[baseline.noise.NAME]`` table,
and the classes of its saved state as ``state_types``) and one registry line.  The defaults
(:class:`MeasuredState`, no correction) are the paper's methods, bit for bit.
"""

from __future__ import annotations

import types
import weakref
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Mapping, NamedTuple

import numpy as np

from ..config import ConfigError
from ..learning import fit
from ..lqg import LocalModel
from ..models import AugmentedModel, LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost, Rollouts
from ..plugins import ESTIMATORS
from . import aware as noise_aware
from .estimator import FilteredPolicy

if TYPE_CHECKING:
    from .aware import NoiseConfig

__all__ = ["NoiseStrategy", "MeasuredState", "KalmanEstimator", "Estimates", "LoopModel", "EMModel", "resolve",
           "strategy_class", "check_strategy", "kalman_lqg_model", "kalman_em_model"]


def _identity(policy: LinearGaussianPolicy):
    return policy


class Estimates(NamedTuple):
    """What :meth:`NoiseStrategy.estimate` found in one batch of rollouts, for that batch's other operations.

    prior:   the mixture prior after this batch (``None``: no mixture prior)
    states:  the rollouts with state estimates for the fit correction (``prior_data = "smoothed"``;
             ``None``: none)
    learn:   the rollouts the learner fits on instead of the measured ones (``None``: the measured)
    filter:  the estimator's own result for this batch, e.g. the filter its new policy acts on
             (``None``: none)
    moments: the posterior covariances of the states in :attr:`learn`, for a fit on expected
             sufficient statistics (``(Px (T+1, n, n), Cx (T, n, n))``; ``None``: the states are
             taken as they are)
    measured: the batch as measured, when :attr:`learn` replaced its states (for a fit that models
             the sensor, ``fit_correction = "eiv"``; ``None``: :attr:`learn` is not set)
    timings: seconds the estimator spent, by name (merged into the iteration's timings, not
             counted in its ``fit`` time)
    """

    prior: fit.MixturePrior | None = None
    states: Rollouts | None = None
    learn: Rollouts | None = None
    filter: Any = None
    moments: Any = None
    timings: Mapping[str, float] = types.MappingProxyType({})
    measured: Rollouts | None = None

    def data(self, rollouts: Rollouts) -> Rollouts:
        """The rollouts the learner fits on: :attr:`learn`, or the measured ``rollouts``."""
        return rollouts if self.learn is None else self.learn


class LoopModel(NamedTuple):
    """The KL step's model and what the step's policy becomes.

    local: the :class:`~soc_opt.lqg.LocalModel` the KL step runs on (dynamics, cost, ``mu0``, ``P0``).
    wrap:  ``LinearGaussianPolicy -> policy`` run by the task's rollouts (e.g. with its filter).
    """

    local: LocalModel
    wrap: Callable[[LinearGaussianPolicy], object]


class EMModel(NamedTuple):
    """The EM recursion's model: augmented model (§1), ``s_0 ~ N(mu0, P0)``, policy wrap."""

    model: AugmentedModel
    mu0: np.ndarray
    P0: np.ndarray
    wrap: Callable[[LinearGaussianPolicy], object]


class NoiseStrategy:
    """The loop's noise operations for one task and one ``NoiseConfig`` (module docstring).

    Construct through :func:`resolve`.  ``cfg``: the ``[baseline.noise]`` table; ``task``: the
    task (its ``mu0``, ``P0``, ``rho2``).  :attr:`noise` (the known noise model, docs/math.md
    §10) is computed on first use, so the paper's method never builds it.  Subclasses override
    ``lqg_model``, ``em_model`` and ``gains`` (the estimator in the loop), and ``estimate`` when
    the estimator works on each batch (e.g. the kinematic smoother, which returns the rollouts
    to learn from and its filter in the :class:`Estimates`); ``estimate``, ``fit`` and
    ``expansion_point`` implement the options shared by all estimators.  Nothing per iteration
    is kept on the object: it lives in the :class:`Estimates` of the batch.

    As a plug-in (:mod:`soc_opt.plugins`) the class declares ``name``, ``settings`` (its own options,
    a :class:`~soc_opt.config.Config` subclass read as ``cfg.section(name)`` from the
    ``[baseline.noise.NAME]`` table; ``None``: none) and ``state_types`` (the classes its policies and
    filters add to a checkpoint).
    """

    name = ""
    settings: ClassVar[type | None] = None
    state_types: ClassVar[tuple[type, ...]] = ()

    @classmethod
    def check_config(cls, cfg: NoiseConfig) -> None:
        """Raise ``ConfigError`` (via :func:`soc_opt.config.config_error`) if the shared options of ``cfg``
        cannot be combined with this estimator (run when a ``NoiseConfig`` selecting it is built)."""

    @classmethod
    def check_task(cls, task, cfg: NoiseConfig) -> None:
        """Raise ``ConfigError`` if this estimator cannot work on ``task`` (called before a run writes
        anything; the default estimators work on every task)."""

    def __init__(self, task, cfg: NoiseConfig):
        self.task = task
        self.cfg = cfg
        self._noise: noise_aware.NoiseModel | None = None

    @property
    def noise(self) -> noise_aware.NoiseModel:
        if self._noise is None:
            self._noise = noise_aware.noise_model(self.task)
        return self._noise

    def initial_distribution(self) -> tuple[np.ndarray, np.ndarray]:
        """``s_0 ~ N(mu0, P0)`` from the task (measurement noise included; docs/choices.md)."""
        return np.asarray(self.task.mu0, float), np.asarray(self.task.P0, float)

    def gains(self, policy) -> LinearGaussianPolicy:
        """The linear-Gaussian part ``(K, k, Sigma)`` of ``policy``."""
        return noise_aware.gains(policy)

    def estimate(self, prior, rollouts: Rollouts, fit_cfg: fit.FitConfig, sampler,
                 rng: np.random.Generator, previous: Rollouts | None = None) -> Estimates:
        """Step 2a: the mixture prior on the measured tuples (the paper), or on state estimates
        (``prior_data = "smoothed"``: :func:`soc_opt.noise.aware.update_prior`), as
        ``Estimates(prior or None, rollouts with estimated states or None)``.  ``previous``: the
        batch before this one (the one ``sampler``'s estimator was learned from), for estimators
        that validate on it; unused here."""
        if fit_cfg.prior != "mixture":
            return Estimates()
        if self.cfg.prior_data == "measured":
            return Estimates(fit.update_prior(prior, rollouts, fit_cfg, rng))
        return Estimates(*noise_aware.update_prior(prior, rollouts, fit_cfg, self.cfg, self.noise, sampler, rng))

    def fit(self, rollouts: Rollouts, fit_cfg: fit.FitConfig, estimates: Estimates, sampler,
            *, include_y: bool = False) -> LinearGaussianDynamics | AugmentedModel:
        """Step 2b: the paper's fit (§2) or the corrected one (``fit_correction``, §10.1) of
        ``rollouts`` (the loop passes ``estimates.data(measured)``) with ``estimates.prior``;
        ``include_y``: the augmented model of the EM phase."""
        if self.cfg.fit_correction == "none":
            return (fit.fit_augmented if include_y else fit.fit_dynamics)(rollouts, fit_cfg, estimates.prior)
        return noise_aware.fit_local(rollouts, fit_cfg, estimates.prior, self.cfg, self.noise, sampler,
                                     include_y=include_y, denoised=estimates.states)

    def expansion_point(self, rollouts: Rollouts, dynamics: LinearGaussianDynamics) -> np.ndarray:
        """Step 3: where the cost is expanded (``expand_at``; :func:`soc_opt.noise.aware.expansion_point`)."""
        if self.cfg.expand_at == "measured":
            return rollouts.s.mean(axis=0)
        return noise_aware.expansion_point(rollouts, dynamics, self.noise, self.cfg)

    def lqg_model(self, dynamics: LinearGaussianDynamics, cost: QuadraticCost, estimates: Estimates,
                  where: str = "") -> LoopModel:
        """Steps 4–5: the KL step's model; the policy acts on the measured state (the paper)."""
        mu0, P0 = self.initial_distribution()
        return LoopModel(LocalModel(dynamics, cost, mu0, P0), _identity)

    def em_model(self, model: AugmentedModel, estimates: Estimates, where: str = "") -> EMModel:
        """The EM recursion's model: the fit as is, ``s_0`` from the task (the paper)."""
        mu0, P0 = self.initial_distribution()
        return EMModel(model, mu0, P0, _identity)


class MeasuredState(NoiseStrategy):
    """``estimator = "none"``: policies act on the measured ``s_k`` (the paper, docs/math.md §7)."""

    name = "none"


class KalmanEstimator(NoiseStrategy):
    """``estimator = "kalman"`` (docs/math.md §10.2): policies act on ``xhat_k`` of a Kalman filter of
    the iteration's fitted model (:class:`~soc_opt.noise.estimator.FilteredPolicy`); the KL step runs on
    the innovation form, the EM phase on the augmented model in ``xhat``."""

    name = "kalman"

    def lqg_model(self, dynamics, cost, estimates: Estimates, where: str = "") -> LoopModel:
        return kalman_lqg_model(self.noise, self.cfg, dynamics, cost, where)

    def em_model(self, model, estimates: Estimates, where: str = "") -> EMModel:
        return kalman_em_model(self.noise, self.cfg, model, where)


def kalman_lqg_model(noise, cfg: NoiseConfig, dynamics, cost, where: str = "") -> LoopModel:
    """The KL step on the innovation form of ``dynamics``' Kalman filter; the policy acts on that filter."""
    kf = noise_aware.loop_filter(dynamics, noise, cfg, where)
    return LoopModel(noise_aware.innovation_local_model(kf, cost), lambda policy: FilteredPolicy(policy, kf))


def kalman_em_model(noise, cfg: NoiseConfig, model, where: str = "") -> EMModel:
    """The EM recursion on the augmented model in that filter's estimate ``xhat``."""
    model, kf, mu0, P0 = noise_aware.filtered_em_model(model, noise, cfg, where)
    return EMModel(model, mu0, P0, lambda policy: FilteredPolicy(policy, kf))


def check_strategy(cls) -> None:
    """``TypeError`` unless ``cls`` is a subclass of :class:`NoiseStrategy` (an estimator is registered as its
    class; :data:`soc_opt.plugins.ESTIMATORS` runs this on every registration)."""
    if not (isinstance(cls, type) and issubclass(cls, NoiseStrategy)):
        raise TypeError(f"an estimator is a subclass of soc_opt.noise.strategy.NoiseStrategy, got {cls!r}")


def strategy_class(name: str) -> type[NoiseStrategy]:
    """The class registered for estimator ``name`` in :data:`soc_opt.plugins.ESTIMATORS` (``ConfigError``
    naming the known ones otherwise)."""
    try:
        return ESTIMATORS.lookup(name)
    except ConfigError as e:
        raise ConfigError(f"estimator: {e}") from None


_RESOLVED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def resolve(task, cfg: NoiseConfig) -> NoiseStrategy:
    """The strategy of ``cfg.estimator`` for ``task`` (one object per task and configuration)."""
    try:
        per_task = _RESOLVED.setdefault(task, {})
    except TypeError:  # a task that cannot be weakly referenced: no memo
        return strategy_class(cfg.estimator)(task, cfg)
    strategy = per_task.get(cfg)
    if strategy is None:
        strategy = per_task[cfg] = strategy_class(cfg.estimator)(task, cfg)
    return strategy
