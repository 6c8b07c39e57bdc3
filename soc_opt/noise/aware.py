"""Noise-aware LQR-FLM and DPSOC-EM: docs/math.md §10 wired into the loop (``docs/noise.md`` §10).

Selected by the ``[baseline.noise]`` table (:class:`NoiseConfig`).  The defaults
(``estimator = "none"``, ``fit_correction = "none"``) are the paper's methods, bit for bit: the
loop then calls exactly the paper's kernels.

``fit_correction`` (docs/math.md §10.1), how the local model is fitted from the measured rollouts:

* ``"none"``: the paper's fit (docs/math.md §2), ``s_{k+1}`` regressed on ``(s_k, a_k)``.
* ``"moments"``: the NIW posterior moments of each step's tuple ``(s_k, a_k, s_{k+1}[, y_k])``
  are mapped to moments of the true tuple ``(x_k, a_k, x_{k+1}[, y_k])`` by
  :func:`soc_opt.noise.noisefit.correct_joint` before conditioning (``fit.fit_dynamics(correct=...)``),
  with ``X_k = Cov(eps_k, a_k)`` of the policy that *sampled* the rollouts
  (:func:`sampler_noise_action_cov`).
* ``"ssm_em"``: EM for the state-space model with latent ``x`` and known ``R``, started from the
  paper's fit (the ``"moments"`` fit can be far off when ``M`` is close to ``n + m``, see
  ``docs/noise.md`` §10): E-step the RTS smoother of :func:`soc_opt.noise.noisefit.smooth_states`, M-step
  the smoothed tuple moments combined with the (noise-corrected) NIW prior of the step exactly as
  the plain fit combines empirical moments with it, then conditioned (:func:`ssm_em_fit`).
* ``"eiv"``: errors in variables (docs/math.md §13.1): the same maximum a posteriori fit with latent
  ``x``, run to convergence with SQUAREM-accelerated EM and no floor on ``W`` beyond a numerical one
  relative to ``R`` (:func:`eiv_local`, :func:`soc_opt.noise.eiv.eiv_fit`), so that a plant without
  process noise gets ``W`` near zero; started from the paper's fit, or from the estimator's own fit
  (the kinematic estimator's fit on its smoothed states).

``time_window = h > 0`` pools the tuple moments of steps ``k-h..k+h`` before either noise-aware
fit (:func:`pool_moments`): with ``M`` rollouts of a few tens of steps and ``rho2`` comparable to
the spread of the states, per-step moments cannot resolve ``A_k`` (``docs/noise.md`` §10).

``estimator = "kalman"`` (docs/math.md §10.2): the policy is a
:class:`~soc_opt.noise.estimator.FilteredPolicy` acting on ``xhat``, whose filter is built from the
model fitted in the iteration that produced it (:func:`loop_filter`); rollouts run it online.
The KL step and the step adaptation work on the innovation form (:func:`innovation_local_model`),
DPSOC-EM's E-/M-step on the augmented model in ``xhat`` (:func:`filtered_em_model`).

Filter prior.  ``task.P0`` is the covariance of the *measured* ``s_0``: ``(rho2 + 1e-6) I`` for a known
start, plus the task's ``start_cov`` with a start range (``[process_noise] start``, docs/math.md §8.1).
So the true ``x_0`` has covariance ``task.P0 - R`` (:func:`noise_model`): ``1e-6 I`` for a known start,
``start_cov + 1e-6 I`` with a start range; positive definite either way, so ``S_0 = P0 + R`` is too,
also at ``rho2 = 0`` (where the filter is exactly ``xhat = s``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np

from ..config import Config, Interval, Options, config_error
from ..learning import fit
from ..lqg import LocalModel
from ..models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    NotPositiveDefiniteError,
    QuadraticCost,
    Rollouts,
    symmetrize,
)
from ..plugins import ESTIMATORS
from .eiv import eiv_fit
from .estimator import (
    FilteredPolicy,
    KalmanFilter,
    check_noise_covariance,
    filtered_cost,
    initial_estimate,
    innovation_augmented,
    innovation_dynamics,
    kalman_filter,
    measurement_noise,
)
from .noisefit import condition_joint, correct_joint, noise_action_cov, smooth_states

__all__ = [
    "ESTIMATORS",
    "NoiseConfig",
    "NoiseModel",
    "noise_model",
    "gains",
    "with_gains",
    "mean_action",
    "sampler_noise_action_cov",
    "pool_moments",
    "pool_noise_action_cov",
    "moment_correction",
    "fit_local",
    "update_prior",
    "denoise",
    "ssm_em_fit",
    "eiv_local",
    "policy_estimates",
    "calibration",
    "calibrated_gains",
    "open_loop_gains",
    "loop_filter",
    "innovation_local_model",
    "expansion_point",
    "filtered_em_model",
]


@dataclass(frozen=True)
class NoiseConfig(Config):
    """Noise-aware variants of LQR-FLM and DPSOC-EM (docs/math.md §10; ``docs/noise.md`` §10).

    Defaults select the paper's methods (no correction, no estimator).

    estimator:       a name in :data:`soc_opt.plugins.ESTIMATORS`: ``"none"`` (the policy acts on the measured
                     ``s_k``: the paper), ``"kalman"`` (it acts on ``xhat_k`` of a time-varying
                     Kalman filter built from the iteration's fitted model; KL step on the
                     innovation form) or ``"kinematic"`` (MuJoCo tasks; docs/math.md §11: the
                     learner fits on the states of a structured smoother that knows the robot's
                     kinematics, not its masses, inertia or damping, and the policy acts on that
                     model's online filter; parameters in ``[baseline.noise.kinematic]``; needs
                     the other options at their defaults).  Allowed at ``rho2 = 0`` (the filter
                     is then ``xhat = s``).
    fit_correction:  ``"none"`` (the paper's fit), ``"moments"`` (bias-corrected NIW posterior
                     moments), ``"ssm_em"`` (EM with latent true state and the NIW prior,
                     started from the paper's fit, ``em_max_iter`` iterations) or ``"eiv"``
                     (the same model fitted to convergence, docs/math.md §13.1: ``eiv_*``).
    min_reliability: reliability floor of the moment correction (``noisefit.correct_joint``).
    filter_w_floor:  the filter's (and the innovation form's) process noise ``W_k`` has its
                     eigenvalues floored at ``filter_w_floor * rho2`` (a fitted ``W`` near zero
                     would make the filter stop listening to the measurements).
    estep_p0_jitter: added (times ``I``) to the covariance of ``xhat_0`` for DPSOC-EM's E-step,
                     which needs it positive definite (a known start makes it ~0).
    em_max_iter:     maximum EM iterations of ``"ssm_em"`` in the loop (:func:`ssm_em_fit`, one fit
                     per iteration, warm from the paper's fit and pulled by the NIW prior: 20 by
                     default).  :class:`soc_opt.noise.noisefit.NoiseFitConfig` configures the library's
                     stand-alone SSM-EM (:func:`soc_opt.noise.noisefit.ssm_em`, no prior, run to
                     convergence: 500, ``em_tol`` 1e-8); the two are different fits and keep
                     separate settings.  ``min_reliability`` has the same meaning and default in both.
    em_tol:          ``"ssm_em"`` stops when ``log p(s | a)`` changes by less than ``em_tol`` per
                     sequence and time step.
    eiv_max_iter:    ``"eiv"``: at most this many EM updates (E-steps) per fit (SQUAREM cycles of three).
    eiv_tol:         ``"eiv"`` stops when ``log p(s | a)`` changes by less than ``eiv_tol`` relative.
    eiv_w_floor:     ``"eiv"``: eigenvalue floor of the fitted ``W_k`` as a fraction of ``rho2`` (only
                     to keep the smoother's covariances positive definite; 1e-6).
    expand_at:       where LQR-FLM expands the cost (docs/math.md §3): ``"measured"`` (the sample mean of
                     the measured ``s_k``: the paper) or ``"smoothed"`` (the sample mean of the RTS
                     smoother's ``E[x_k | s, a]`` under the iteration's fitted model, which
                     averages the sensor noise out along time as well as over samples).
    prior_data:      what the mixture prior (docs/math.md §2 step 1) is fitted on: ``"measured"`` (the
                     tuples of the measured ``s``: the paper; ``"ssm_em"`` then corrects the prior's
                     moments for the noise) or ``"smoothed"`` (the tuples of the smoother's
                     ``E[x | s, a]`` under a model of the data, :func:`update_prior`; the prior is
                     then used uncorrected).  ``"smoothed"`` needs ``fit_correction = "ssm_em"``.
    pool:            how ``time_window`` pools (:func:`pool_moments`): ``"union"`` (the moments of
                     the union of the window's tuples) or ``"anchored"`` (step ``k``'s own mean, the
                     window's second moments about it).
    feedback:        what the policy's gains act on (docs/math.md §13.2): ``"estimate"`` (the KL step's
                     gains on the estimator's state, certainty equivalence: the paper and every
                     estimator so far), ``"calibrated"`` (the gains times ``Gamma_k``, the regression of
                     the learner's states on the new policy's own estimates of the batch, so that the
                     feedback responds to an estimate only as far as it predicts the state:
                     :func:`calibrated_gains`) or ``"open_loop"`` (no feedback: ``K = 0`` and the KL
                     step's mean actions ``E[a_k]``; the baseline).
    time_window:     ``h``: the noise-aware fits pool the tuple moments of the steps ``k-h..k+h``
                     (:func:`pool_moments`); ``0``: per step (docs/math.md §2's time-varying fit), ``h >= T``:
                     one time-invariant model.  Needs a ``fit_correction``.

    Plus one table per registered estimator that declares ``settings``, named after it
    (:data:`soc_opt.plugins.ESTIMATORS`): ``[baseline.noise.kinematic]``, the parameters of
    ``estimator = "kinematic"`` (:class:`soc_opt.noise.kinematic.config.KinematicConfig`), read as
    ``cfg.kinematic`` or ``cfg.section("kinematic")``.  The estimator's own rules between these options
    and its table run from its ``check_config`` (:class:`soc_opt.noise.strategy.NoiseStrategy`).
    plugin_tables: where those tables are kept (the ones that differ from their defaults, by name); give
                a table by its name instead (TOML, keyword argument, ``replace``).
    """

    estimator: str = "none"
    fit_correction: Literal["none", "moments", "ssm_em", "eiv"] = "none"
    min_reliability: float = 0.05
    filter_w_floor: float = 1e-3
    estep_p0_jitter: float = 1e-6
    em_max_iter: int = 20
    em_tol: float = 1e-4
    eiv_max_iter: int = 60
    eiv_tol: float = 1e-7
    eiv_w_floor: float = 1e-6
    feedback: Literal["estimate", "calibrated", "open_loop"] = "estimate"
    time_window: int = 0
    expand_at: Literal["measured", "smoothed"] = "measured"
    prior_data: Literal["measured", "smoothed"] = "measured"
    pool: Literal["union", "anchored"] = "union"
    plugin_tables: tuple = ()

    _constraints = {
        "estimator": [Options(lambda: tuple(ESTIMATORS))],
        "fit_correction": [Options(("none", "moments", "ssm_em", "eiv"))],
        "min_reliability": [Interval(0.0, 1.0, "right")],
        "filter_w_floor": [Interval(0.0)],
        "estep_p0_jitter": [Interval(0.0, None, "neither")],
        "em_max_iter": [Interval(1)],
        "em_tol": [Interval(0.0)],
        "eiv_max_iter": [Interval(1)],
        "eiv_tol": [Interval(0.0)],
        "eiv_w_floor": [Interval(0.0, None, "neither")],
        "feedback": [Options(("estimate", "calibrated", "open_loop"))],
        "time_window": [Interval(0)],
        "expand_at": [Options(("measured", "smoothed"))],
        "prior_data": [Options(("measured", "smoothed"))],
        "pool": [Options(("union", "anchored"))],
    }
    _plugins = ESTIMATORS

    def __post_init__(self):
        check = getattr(ESTIMATORS[self.estimator], "check_config", None)
        if check is not None:
            check(self)
        if self.prior_data == "smoothed" and self.fit_correction != "ssm_em":
            raise config_error("prior_data", "'smoothed' fits the prior on smoothed states and needs "
                               f"fit_correction = 'ssm_em' (got {self.fit_correction!r})")
        if self.time_window > 0 and self.fit_correction in ("none", "eiv"):
            raise config_error("time_window", "pools the noise-aware fits' moments; it needs fit_correction "
                               f"'moments' or 'ssm_em' (got {self.fit_correction!r}, a per-step fit)")

    @property
    def paper(self) -> bool:
        """Whether this is the paper's method (nothing noise-aware selected)."""
        return (self.estimator == "none" and self.fit_correction == "none" and self.expand_at == "measured"
                and self.prior_data == "measured" and self.feedback == "estimate")

    @property
    def label(self) -> str:
        """Short description for tables: ``"paper"`` or e.g. ``"kalman + moments"`` (``", window h"``)."""
        if self.paper:
            return "paper"
        return f"{self.estimator} + {self.fit_correction}" + (f", window {self.time_window}" if self.time_window else "")


class NoiseModel(NamedTuple):
    """The known noise model of a task (docs/math.md §10).

    Fields:
        R:   (n, n) measurement noise ``rho2 I``
        mu0: (n,)   mean of the true initial state ``x_0``
        P0:  (n, n) covariance of ``x_0``: ``task.P0 - R`` (the task's ``P0`` is that of ``s_0``)
    """

    R: np.ndarray
    mu0: np.ndarray
    P0: np.ndarray


def noise_model(task) -> NoiseModel:
    """:class:`NoiseModel` of ``task``; ``ValueError`` for ``rho2 < 0``, ``NotPositiveDefiniteError``
    when ``task.P0 - R`` is not positive semidefinite (naming it)."""
    n = int(task.n)
    R = measurement_noise(task.rho2, n)
    P0 = symmetrize(np.asarray(task.P0, dtype=float) - R)
    P0 = check_noise_covariance(f"true initial covariance task.P0 - rho2 I of task {getattr(task, 'name', '?')!r}",
                                P0, (n, n))
    return NoiseModel(R, np.asarray(task.mu0, dtype=float).copy(), P0)


def gains(policy) -> LinearGaussianPolicy:
    """The linear-Gaussian part ``(K, k, Sigma)`` of a plain or filtered policy."""
    if isinstance(policy, FilteredPolicy):
        return policy.policy
    if isinstance(policy, LinearGaussianPolicy):
        return policy
    raise TypeError(f"policy must be a LinearGaussianPolicy or a FilteredPolicy, got {type(policy).__name__}")


def with_gains(policy, new: LinearGaussianPolicy):
    """``policy`` with its linear-Gaussian part replaced by ``new`` (its filter, if any, kept)."""
    if isinstance(policy, FilteredPolicy):
        return dataclasses.replace(policy, policy=new)
    if isinstance(policy, LinearGaussianPolicy):
        return new
    raise TypeError(f"policy must be a LinearGaussianPolicy or a FilteredPolicy, got {type(policy).__name__}")


def mean_action(policy):
    """``policy`` acting with its mean action (``Sigma = 0``; its filter, if any, kept)."""
    return with_gains(policy, gains(policy).mean_policy())


def sampler_noise_action_cov(policy, R) -> np.ndarray:
    """``X_k = Cov(eps_k, a_k)`` (T, n, m) of the policy that sampled the data (``docs/noise.md`` §7):
    ``R K_k^T`` on ``s``, ``R G_k^T K_k^T`` for a filtered policy."""
    if isinstance(policy, FilteredPolicy):
        return noise_action_cov(R, policy.policy.K, policy.filter.G)
    return noise_action_cov(R, gains(policy).K)


def pool_moments(mu: np.ndarray, Lam: np.ndarray, h: int, mode: str = "union") -> tuple[np.ndarray, np.ndarray]:
    """Pooled moments of the tuples of steps ``k-h..k+h`` (clipped to ``0..T-1``), equal weights.

    ``mu (T, d)``, ``Lam (T, d, d)`` per step -> pooled ``(mu, Lam)``.  ``mode = "union"``: the
    moments of the union of the tuples: the mean of the means, and the mean of the covariances plus
    the spread of the step means about the pooled mean.  ``mode = "anchored"``: step ``k``'s own
    mean, and the window's second moments about it (the mean of the covariances plus the spread of
    the step means about ``mu_k``), so that the conditional model passes through step ``k``'s mean
    (its offset ``c_k`` carries no bias from the trajectory's curvature over the window) while its
    slopes still pool the window.  ``h = 0`` returns the inputs.  (``X_k`` pools the same way:
    :func:`pool_noise_action_cov`.)
    """
    if mode not in ("union", "anchored"):
        raise ValueError(f"pool mode must be 'union' or 'anchored', got {mode!r}")
    if h <= 0:
        return mu, Lam
    T = mu.shape[0]
    out_mu = np.empty_like(mu)
    out_L = np.empty_like(Lam)
    for k in range(T):
        lo, hi = max(0, k - h), min(T, k + h + 1)
        mk = mu[lo:hi].mean(axis=0) if mode == "union" else mu[k]
        dev = mu[lo:hi] - mk
        out_mu[k] = mk
        out_L[k] = Lam[lo:hi].mean(axis=0) + dev.T @ dev / (hi - lo)
    return out_mu, symmetrize(out_L)


def pool_noise_action_cov(X: np.ndarray, h: int) -> np.ndarray:
    """``X_k`` averaged over the window of :func:`pool_moments` (the noise part of a pooled
    covariance is the mean of the steps' noise parts; the step means carry no noise)."""
    if h <= 0:
        return X
    T = X.shape[0]
    return np.stack([X[max(0, k - h): min(T, k + h + 1)].mean(axis=0) for k in range(T)])


def moment_correction(R, X, n: int, m: int, min_reliability: float, time_window: int = 0, pool: str = "union"):
    """The ``correct`` hook of :func:`soc_opt.learning.fit.fit_dynamics` / ``fit_augmented``: joint moments of
    ``(s_k, a_k, s_{k+1}[, y_k])`` -> moments of ``(x_k, a_k, x_{k+1}[, y_k])`` (``noisefit.correct_joint``),
    after pooling over ``time_window`` (:func:`pool_moments`)."""
    Xp = pool_noise_action_cov(np.asarray(X, dtype=float), time_window)

    def correct(mu, Lam):
        mu, Lam = pool_moments(mu, Lam, time_window, pool)
        cm = correct_joint(mu, Lam, n, m, R, Xp, min_reliability=min_reliability)
        return cm.mean, cm.cov

    return correct


def _model_rows(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(model, AugmentedModel):
        return model.Ao, model.co, model.So
    return np.concatenate([model.A, model.B], axis=2), model.c, model.cov


def _as_model(Ao, co, So, n: int, include_y: bool):
    if include_y:
        return AugmentedModel(Ao, co, So, n)
    return LinearGaussianDynamics(Ao[:, :, :n], Ao[:, :, n:], co, So)


def fit_local(rollouts: Rollouts, fit_cfg: fit.FitConfig, prior, noise_cfg: NoiseConfig, noise: NoiseModel,
              sampler, *, include_y: bool = False, denoised: Rollouts | None = None):
    """The iteration's local model under ``noise_cfg.fit_correction`` (module docstring).

    ``include_y``: the augmented model of DPSOC-EM (``fit.fit_augmented``), else the dynamics
    (``fit.fit_dynamics``).  ``sampler``: the policy that sampled ``rollouts``.  ``denoised``: the
    smoothed rollouts of :func:`update_prior` when ``prior`` was fitted on them
    (``prior_data = "smoothed"``): SSM-EM then starts from the plain fit of ``denoised`` and uses
    the prior uncorrected.
    """
    fitter = fit.fit_augmented if include_y else fit.fit_dynamics
    if noise_cfg.fit_correction == "none":
        return fitter(rollouts, fit_cfg, prior)
    X = sampler_noise_action_cov(sampler, noise.R)
    if noise_cfg.fit_correction == "moments":
        hook = moment_correction(noise.R, X, rollouts.n, rollouts.m, noise_cfg.min_reliability, noise_cfg.time_window,
                                 noise_cfg.pool)
        return fitter(rollouts, fit_cfg, prior, correct=hook)
    if noise_cfg.fit_correction == "eiv":
        start = fitter(rollouts if denoised is None else denoised, fit_cfg, prior)
        return eiv_local(rollouts, fit_cfg, prior, noise_cfg, noise, start, X=X if denoised is None else None,
                         prior_tuples=rollouts if denoised is None else denoised)
    if denoised is not None:
        return ssm_em_fit(rollouts, fit_cfg, prior, noise_cfg, noise, X, fitter(denoised, fit_cfg, prior),
                          include_y=include_y, prior_measured=False)
    return ssm_em_fit(rollouts, fit_cfg, prior, noise_cfg, noise, X, fitter(rollouts, fit_cfg, prior),
                      include_y=include_y)


def denoise(rollouts: Rollouts, dynamics: LinearGaussianDynamics, noise: NoiseModel,
            noise_cfg: NoiseConfig, where: str = " (smoother of the prior's data)") -> Rollouts:
    """``rollouts`` with ``s`` replaced by the smoother's ``E[x_k | s_0..s_T, a]`` (RTS smoother of
    ``dynamics`` with the loop filter's ``W`` floor, ``R`` and prior; ``noisefit.smooth_states``).
    ``x``, ``a`` and the cost observations are kept (``y`` stays the measured one).  ``where``
    names the caller in a filter error."""
    kf = loop_filter(dynamics, noise, noise_cfg, where)
    return dataclasses.replace(rollouts, s=smooth_states(kf, rollouts.s, rollouts.a).mean)


def update_prior(prior, rollouts: Rollouts, fit_cfg: fit.FitConfig, noise_cfg: NoiseConfig, noise: NoiseModel,
                 sampler, rng: np.random.Generator) -> tuple[fit.MixturePrior, Rollouts | None]:
    """The mixture prior of one iteration (docs/math.md §2 step 1) under ``noise_cfg.prior_data``.

    ``"measured"``: ``fit.update_prior`` on the measured tuples (the paper); returns
    ``(prior, None)``.  ``"smoothed"``: the rollouts are first smoothed (:func:`denoise`) with the
    model of the sampler's own filter when it has one (the fit of the previous iteration), else with
    a first-pass fit (SSM-EM with a throwaway prior that includes the measured tuples, corrected for
    the noise); the prior is fitted on the smoothed tuples, so its buffer holds estimates of the
    true states.  Returns ``(prior, smoothed rollouts)`` for :func:`fit_local`'s ``denoised``.
    """
    if noise_cfg.prior_data == "measured":
        return fit.update_prior(prior, rollouts, fit_cfg, rng), None
    if isinstance(sampler, FilteredPolicy):
        f = sampler.filter
        model = LinearGaussianDynamics(f.A, f.B, f.c, f.W)
    else:
        first = fit.update_prior(prior, rollouts, fit_cfg, rng)
        model = fit_local(rollouts, fit_cfg, first, noise_cfg.replace(prior_data="measured"), noise, sampler)
    den = denoise(rollouts, model, noise, noise_cfg)
    return fit.update_prior(prior, den, fit_cfg, rng), den


def _smoothed_moments(sm, rollouts: Rollouts, include_y: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-step mean (T, d) and covariance (T, d, d) of ``(x_k, a_k, x_{k+1}[, y_k])`` under the
    smoother: sample moments of the smoothed means plus the (shared) posterior covariances."""
    xs = sm.mean
    n, m = rollouts.n, rollouts.m
    nz = n + m
    parts = [xs[:, :-1], rollouts.a, xs[:, 1:]] + ([rollouts.y[..., None]] if include_y else [])
    Xt = np.concatenate(parts, axis=-1)
    mu = Xt.mean(axis=0)
    Xc = Xt - mu
    Lam = np.einsum("mti,mtj->tij", Xc, Xc) / Xt.shape[0]
    Ps, cross = sm.cov[0], sm.cross[0]
    Lam[:, :n, :n] += Ps[:-1]
    Lam[:, nz : nz + n, nz : nz + n] += Ps[1:]
    Lam[:, nz : nz + n, :n] += cross
    Lam[:, :n, nz : nz + n] += np.swapaxes(cross, 1, 2)
    return mu, symmetrize(Lam)


def _floor_eig(S: np.ndarray, floor: float) -> np.ndarray:
    ev, V = np.linalg.eigh(symmetrize(S))
    return symmetrize(np.einsum("...ij,...j,...kj->...ik", V, np.maximum(ev, floor), V))


def _w_floor(noise_cfg: NoiseConfig, R: np.ndarray) -> float:
    return float(noise_cfg.filter_w_floor * np.trace(R) / R.shape[0])


def ssm_em_fit(rollouts: Rollouts, fit_cfg: fit.FitConfig, prior, noise_cfg: NoiseConfig, noise: NoiseModel,
               X: np.ndarray, start, *, include_y: bool = False, prior_measured: bool = True):
    """EM with latent true state from the ``start`` model (``docs/noise.md`` §10).

    E-step: RTS smoother of ``x`` given the measured ``s`` and the actions (filter prior
    ``noise.mu0, noise.P0``; ``W`` floored as for the loop's filter).  M-step: the smoothed tuple
    moments (pooled over ``time_window``), combined with the step's NIW prior (the mixture
    prior's moments, corrected for the noise with the sampler's ``X``; counts ``k0, n0``) as in
    ``fit.joint_posterior``, the pooled moments counting as the ``M`` samples of one step (pooling
    borrows strength across steps for the model of step ``k``; it does not weaken the prior, which
    carries the tuples of earlier iterations), ridge
    ``reg`` on the ``(x, a)`` block, conditioned with ``noisefit.condition_joint``.  With the prior
    folded in this is not exact maximum likelihood; EM stops when ``log p(s | a)`` changes by
    less than ``em_tol`` per sequence and step, or after ``em_max_iter`` iterations.
    ``prior_measured = False``: the prior was fitted on smoothed states (:func:`update_prior`) and
    is used without the noise correction.
    """
    n, m = rollouts.n, rollouts.m
    nz = n + m
    M, T = rollouts.M, rollouts.T
    Ao, co, So = _model_rows(start)
    pri = None
    if prior is not None and fit_cfg.prior == "mixture":
        mu0p, S0p = prior.step_prior(fit.tuples(rollouts, include_y), include_y)
        if prior_measured:
            cm = correct_joint(mu0p, S0p, n, m, noise.R, X, min_reliability=noise_cfg.min_reliability)
            pri = (cm.mean, cm.cov)
        else:
            pri = (mu0p, S0p)
    z = np.concatenate([rollouts.s[:, :-1], rollouts.a], axis=-1).reshape(-1, nz)
    scale = float(z.var(axis=0).mean())
    lam = fit_cfg.reg * (scale if scale > 0 and np.isfinite(scale) else 1.0)
    floor = _w_floor(noise_cfg, noise.R)
    last = -np.inf
    for _ in range(noise_cfg.em_max_iter):
        W = _floor_eig(So[:, :n, :n], floor) if floor > 0 else So[:, :n, :n]
        kf = kalman_filter(LinearGaussianDynamics(Ao[:, :n, :n], Ao[:, :n, n:], co[:, :n], W), noise.R, noise.mu0, noise.P0)
        sm = smooth_states(kf, rollouts.s, rollouts.a)
        ll = float(sm.loglik.sum())
        if abs(ll - last) < noise_cfg.em_tol * M * (T + 1):
            break
        last = ll
        mu, Lam = pool_moments(*_smoothed_moments(sm, rollouts, include_y), noise_cfg.time_window,
                               noise_cfg.pool)
        if pri is not None:
            k0, n0 = fit_cfg.k0, fit_cfg.n0
            d = mu - pri[0]
            mu = (k0 * pri[0] + M * mu) / (k0 + M)
            Lam = (n0 * pri[1] + M * Lam + (k0 * M / (k0 + M)) * np.einsum("ti,tj->tij", d, d)) / (M + n0)
        idx = np.arange(nz)
        Lam = symmetrize(Lam)
        Lam[:, idx, idx] += lam
        Ao, co, So = condition_joint(mu, Lam, nz, fit_cfg.min_eig)
    return _as_model(Ao, co, So, n, include_y)


def eiv_local(measured: Rollouts, fit_cfg: fit.FitConfig, prior, noise_cfg: NoiseConfig, noise: NoiseModel,
              start, *, X: np.ndarray | None = None, prior_tuples: Rollouts | None = None):
    """``fit_correction = "eiv"`` (docs/math.md §13.1): :func:`soc_opt.noise.eiv.eiv_fit` of the *measured*
    batch from ``start`` (its kind, dynamics or augmented model, is the kind returned), with the step's NIW
    prior from the mixture ``prior`` at the tuples of ``prior_tuples`` (default ``measured``): corrected for
    the sensor noise with the sampler's ``X`` when given (a prior fitted on measured tuples), as is otherwise
    (a prior fitted on state estimates)."""
    include_y = isinstance(start, AugmentedModel)
    pri = None
    if prior is not None and fit_cfg.prior == "mixture":
        mu0p, S0p = prior.step_prior(fit.tuples(measured if prior_tuples is None else prior_tuples, include_y),
                                     include_y)
        if X is not None:
            cm = correct_joint(mu0p, S0p, measured.n, measured.m, noise.R, X, min_reliability=noise_cfg.min_reliability)
            mu0p, S0p = cm.mean, cm.cov
        pri = (mu0p, S0p)
    return eiv_fit(measured, start, noise.R, noise.mu0, noise.P0, prior=pri, k0=fit_cfg.k0, n0=fit_cfg.n0,
                   reg=fit_cfg.reg, min_eig=fit_cfg.min_eig, w_floor=noise_cfg.eiv_w_floor,
                   max_iter=noise_cfg.eiv_max_iter, tol=noise_cfg.eiv_tol).model


def policy_estimates(policy, rollouts: Rollouts) -> np.ndarray:
    """``(M, T+1, n)``: the states ``policy`` would have acted on along ``rollouts`` (its filter run on
    their measurements and actions; the measurements themselves for a policy without a filter)."""
    if not isinstance(policy, FilteredPolicy):
        return np.array(rollouts.s)
    s, a = rollouts.s, rollouts.a
    out = np.empty_like(s)
    out[:, 0] = policy.estimate_rows(0, s[:, 0])
    for k in range(1, s.shape[1]):
        out[:, k] = policy.estimate_rows(k, s[:, k], out[:, k - 1], a[:, k - 1])
    return out


def calibration(learned: np.ndarray, estimated: np.ndarray, window: int = 5, ridge: float = 1e-3) -> np.ndarray:
    """``Gamma (T+1, n, n)``: per step the least-squares regression of the learner's states ``learned``
    on the estimates ``estimated`` (both ``(M, T+1, n)``), each centred at its step's mean and pooled over
    the steps ``k-window..k+window``; ridge ``ridge`` times the mean variance of the estimates::

        Gamma_k = Cov(x~, xhat) (Cov(xhat) + lam I)^{-1}

    ``Gamma_k = I`` when the estimates are the learner's states; below ``I`` in the directions where the
    estimate carries more than the state's spread (docs/math.md §13.2)."""
    Y = learned - learned.mean(axis=0)
    X = estimated - estimated.mean(axis=0)
    T1, n = X.shape[1], X.shape[2]
    Sxx = np.einsum("mti,mtj->tij", X, X)
    Syx = np.einsum("mti,mtj->tij", Y, X)
    c = np.concatenate([np.zeros((1, n, n)), np.cumsum(Sxx, axis=0)])
    d = np.concatenate([np.zeros((1, n, n)), np.cumsum(Syx, axis=0)])
    lo = np.clip(np.arange(T1) - window, 0, T1)
    hi = np.clip(np.arange(T1) + window + 1, 0, T1)
    Sxx_w, Syx_w = c[hi] - c[lo], d[hi] - d[lo]
    lam = ridge * np.maximum(np.trace(Sxx_w, axis1=1, axis2=2) / n, 1e-12)
    G = symmetrize(Sxx_w) + lam[:, None, None] * np.eye(n)
    return np.swapaxes(np.linalg.solve(G, np.swapaxes(Syx_w, 1, 2)), 1, 2)


def calibrated_gains(gains_: LinearGaussianPolicy, Gamma: np.ndarray, nominal: np.ndarray) -> LinearGaussianPolicy:
    """``K_k Gamma_k`` with the offset moved so that the mean action at the ``nominal (T+1, n)`` state is
    unchanged: ``k' = k + (K - K Gamma) nominal`` (docs/math.md §13.2)."""
    K2 = gains_.K @ Gamma[:-1]
    k2 = gains_.k + np.einsum("tij,tj->ti", gains_.K - K2, nominal[:-1])
    return LinearGaussianPolicy(K2, k2, gains_.cov)


def open_loop_gains(gains_: LinearGaussianPolicy, a_mean: np.ndarray) -> LinearGaussianPolicy:
    """No feedback: ``K = 0`` and ``k`` the mean actions ``a_mean (T, m)`` (docs/math.md §13.2's baseline)."""
    return LinearGaussianPolicy(np.zeros_like(gains_.K), np.array(a_mean, dtype=float), gains_.cov)


def loop_filter(dynamics: LinearGaussianDynamics, noise: NoiseModel, noise_cfg: NoiseConfig,
                where: str = "") -> KalmanFilter:
    """The Kalman filter of a fitted model (docs/math.md §10.2): ``W_k`` floored at ``filter_w_floor * rho2``,
    measurement noise ``R``, prior of the true ``x_0``.  A noise model that leaves an innovation
    covariance singular raises ``NotPositiveDefiniteError`` naming the step (and ``where``)."""
    floor = _w_floor(noise_cfg, noise.R)
    W = _floor_eig(dynamics.cov, floor) if floor > 0 else dynamics.cov
    try:
        return kalman_filter(LinearGaussianDynamics(dynamics.A, dynamics.B, dynamics.c, W), noise.R, noise.mu0, noise.P0)
    except NotPositiveDefiniteError as e:
        raise NotPositiveDefiniteError(f"estimator = 'kalman'{where}: {e}") from None


def expansion_point(rollouts: Rollouts, dynamics: LinearGaussianDynamics, noise: NoiseModel,
                    noise_cfg: NoiseConfig) -> np.ndarray:
    """``(T+1, n)`` state trajectory around which the cost is expanded (``noise_cfg.expand_at``).

    ``"measured"``: the sample mean of ``s_k`` (the paper).  ``"smoothed"``: the sample mean of
    ``E[x_k | s_0..s_T, a]``, the RTS smoother (``noisefit.smooth_states``) of the fitted
    ``dynamics`` with the loop filter's ``W`` floor, ``R`` and prior.  The measured mean carries
    ``rho2 / M`` of noise per coordinate and step; a non-quadratic cost (the point costs' ``l1``
    term) expanded there sees a gradient direction that is mostly that noise once the state is
    within about ``sqrt(rho2 / M)`` of the target.
    """
    if noise_cfg.expand_at == "measured":
        return rollouts.s.mean(axis=0)
    return denoise(rollouts, dynamics, noise, noise_cfg, " (cost expansion point)").s.mean(axis=0)


def innovation_local_model(kf: KalmanFilter, cost: QuadraticCost) -> LocalModel:
    """The KL step's model on the filtered loop (``docs/noise.md`` §5): innovation-form dynamics,
    cost with ``1/2 tr(C_xx P_k)`` added, initial distribution of ``xhat_0``."""
    mu0, P0 = initial_estimate(kf)
    return LocalModel(innovation_dynamics(kf), filtered_cost(kf, cost), mu0, P0)


def filtered_em_model(model: AugmentedModel, noise: NoiseModel, noise_cfg: NoiseConfig,
                      where: str = "") -> tuple[AugmentedModel, KalmanFilter, np.ndarray, np.ndarray]:
    """DPSOC-EM on the filtered loop (``docs/noise.md`` §6).

    ``model``: the x-frame augmented model.  Its ``W`` block is floored as in :func:`loop_filter`
    (adding a PSD matrix to the state block keeps ``So`` positive definite), the filter is built
    from it, and the result is ``(innovation_augmented(model, kf), kf, mu0, P0)`` with
    ``(mu0, P0)`` the distribution of ``xhat_0`` plus ``estep_p0_jitter * I``.
    """
    n = model.n
    floor = _w_floor(noise_cfg, noise.R)
    So = np.array(model.So)
    if floor > 0:
        So[:, :n, :n] = _floor_eig(So[:, :n, :n], floor)
    model = AugmentedModel(model.Ao, model.co, symmetrize(So), n)
    kf = loop_filter(model.dynamics(), noise, noise_cfg.replace(filter_w_floor=0.0), where)
    mu0, P0 = initial_estimate(kf)
    return innovation_augmented(model, kf), kf, mu0, symmetrize(P0 + noise_cfg.estep_p0_jitter * np.eye(n))
