"""Dynamics fitting and cost observations (docs/math.md §2, §3).

Step 1 of DPSOC-EM: from ``M`` rollouts fit the time-varying augmented model

    zeta_k | z_k ~ N(Ao_k z_k + co_k, So_k),   z_k = (s_k, a_k),  zeta_k = (s_{k+1}, y_k)

(docs/math.md §1) from the *measured* states ``s`` (controllers only ever see ``s``).
Per time step the tuples ``D_k^m = (s_k, a_k, s_{k+1}, y_k)`` (dimension
``2n+m+1``; ``2n+m`` for :func:`fit_dynamics`, which drops ``y``) are
summarised by a joint Gaussian ``N(mu_k, Lambda_k)`` that is then conditioned
on ``(s_k, a_k)``.

Two estimators of the joint Gaussian:

* **Least squares** (``FitConfig.prior == "none"`` or no prior passed): the
  empirical mean and covariance of the ``M`` tuples of step ``k`` (``1/M``
  normalisation).  Conditioning on ``z`` gives
  ``Ao_k = Lambda_{zeta z} (Lambda_zz + lam I)^{-1}``, i.e. ridge regression of
  ``zeta`` on the centred ``z`` with penalty ``M lam ||Ao||^2`` and an
  unpenalised intercept ``co_k = mean(zeta) - Ao_k mean(z)``; ``So_k`` is the
  mean squared residual (ML normalisation, ``1/M``) plus the ridge term.
* **Mixture prior** (docs/math.md §2 steps 1-3): a Gaussian mixture over the tuples of
  all time steps (and a bounded buffer of tuples from earlier iterations),
  fitted by variational Bayes with ``sklearn.mixture.BayesianGaussianMixture``
  (Dirichlet prior on the weights, normal-Wishart priors on the components,
  Bishop §10.2), see :func:`update_prior`; the fitted mixture is a
  :class:`soc_opt.learning.mixture.MixturePrior`.  Each iteration's fit is warm-started
  from the previous iteration's variational posterior
  (``FitConfig.prior_warm_start``).  Per step it gives a single
  normal-inverse-Wishart prior

      mu0_k  = sum_c w_c^k mu_c,     w_c^k = mean responsibility of the step-k tuples,
      S0_k   = sum_c w_c^k (Sigma_c + (mu_c - mu0_k)(mu_c - mu0_k)^T)
               (the mixture's second moment about mu0_k, a covariance),
      Phi0_k = n0 * S0_k             (a scatter matrix: n0 pseudo-observations
                                      with covariance S0_k),

  and the posterior of docs/math.md §2 step 3

      mu_k     = (k0 mu0_k + M mu_emp) / (k0 + M)
      Lambda_k = (Phi0_k + M Lambda_emp + k0 M/(k0+M) (mu_emp - mu0_k)(mu_emp - mu0_k)^T) / (M + n0).

  **Normalisation.**  ``k0`` and ``n0`` are pseudo-sample counts on the same
  scale as ``M``: the prior counts as ``k0`` observations for the mean and
  ``n0`` for the covariance *of this time step*, independent of how many
  tuples the mixture was fitted on (this is the normalisation of the reference
  GPS code, where both are ~1).  With ``M = 0`` the posterior is
  ``(mu0_k, S0_k)``; with the default ``n0 = 1``, ``Phi0_k = S0_k`` is exactly
  the "second moment about mu0_k" of docs/math.md §2.

**Regulariser.**  ``lam = reg * scale`` is added to the diagonal of the
``(s, a)`` block of ``Lambda_k`` before conditioning, where ``scale`` is the
mean over the ``n+m`` columns of ``(s_k, a_k)`` of their variance pooled over
all rollouts and time steps of the data being fitted (``1`` if every column is
constant).  With ``M < n+m`` or a constant state component the empirical
covariance is singular and ``lam`` keeps the Cholesky solve well posed.

**Conditioning.**  All steps are computed at once (stacked Cholesky
factorisations, batched products; no loop over ``k``).  ``Ao_k`` is obtained
with a Cholesky solve of the ``(s, a)`` block; ``So_k = Lambda_{zeta zeta} - Ao_k Lambda_{z zeta}`` is symmetrised and
its eigenvalues are floored at ``min_eig * mean(diag Lambda_{zeta zeta})``
(absolute floor ``1e-12``) so that the result is positive definite.

**Cost observations** (docs/math.md §3): :func:`cost_observations` with mode
``"model"`` (sampled from the fitted augmented model under the policy; the
Gaussian ``y`` samples are not clipped to ``(0, 1]``), ``"measured"`` (the
rollouts' ``y``) or ``"optimistic"`` (``y = 1``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..config import Config, Interval, Options
from ..linalg import T as _T
from ..linalg import as_generator, cho_solve, chol, single_thread_blas
from ..models import (
    AugmentedModel,
    LinearGaussianDynamics,
    LinearGaussianPolicy,
    Rollouts,
    ShapeError,
    check_array,
    symmetrize,
)
from .mixture import MixturePrior, Subspace, VBState, standardisation, varying_columns

__all__ = [
    "FitConfig",
    "MixturePrior",
    "VBState",
    "COST_MODES",
    "tuples",
    "update_prior",
    "fit_augmented",
    "fit_dynamics",
    "joint_posterior",
    "cost_observations",
    "prediction_error",
]

COST_MODES = ("model", "measured", "optimistic")

_ABS_EIG_FLOOR = 1e-12


@dataclass(frozen=True)
class FitConfig(Config):
    """Hyperparameters of the dynamics fit (docs/math.md §2).

    Fields (defaults in brackets):
        prior:                ``"mixture"`` (VB mixture prior + NIW posterior) or ``"none"``
                              (per-step regularised least squares) [``"mixture"``].
        n_components:         number of mixture components of a cold (k-means initialised) VB
                              fit; VB empties the unused ones, and a warm start carries over
                              only the kept ones [10].
        weight_concentration: Dirichlet concentration of the mixture weights
                              (sklearn ``weight_concentration_prior`` with
                              ``weight_concentration_prior_type="dirichlet_distribution"``);
                              values below 1 favour few components [0.05].
        k0:                   NIW mean strength, in pseudo-samples of one time step [1.0].
        n0:                   NIW covariance strength, in pseudo-samples of one time step;
                              ``Phi0_k = n0 * S0_k`` [1.0].
        reg:                  ridge on the ``(s, a)`` block, relative to the pooled data variance [1e-6].
        buffer_size:          maximum number of tuples kept from earlier iterations for the
                              next prior fit (the newest are kept); 2000 tuples are the
                              previous iteration's 20 rollouts of 100 steps [2000].
        prior_warm_start:     start VB from the previous prior's variational posterior
                              (sklearn ``warm_start``) instead of a fresh k-means
                              initialisation; ``False`` refits from scratch every iteration
                              [True].
        max_iter:             maximum VB iterations per fit; with warm starts VB continues
                              at the next iteration, so the cap only bounds the cost of the
                              first iterations, where the data move most [10].
        tol:                  VB stops when the evidence lower bound changes by less than
                              ``tol`` per fitted tuple (sklearn's ``tol`` is absolute on the
                              total bound; we pass ``tol * N``) [1e-3].
        seed:                 seed used when no ``numpy.random.Generator`` is passed [0].
        min_weight:           mixture components with weight below this are dropped (and the
                              rest renormalised) after VB, and not carried into the next
                              warm start [1e-3].
        mixture_reg:          sklearn ``reg_covar``, added to the component covariances in
                              standardised (unit-variance) coordinates [1e-6].
        min_eig:              relative eigenvalue floor of ``So_k`` (times the mean diagonal of
                              the ``zeta`` block of ``Lambda_k``) [1e-9].

    The settings without warm starts remain selectable:
    ``prior_warm_start = false``, ``n_components = 20``, ``buffer_size = 10000``,
    ``max_iter = 100``.  The defaults were chosen by fit time against held-out
    one-step prediction error on peg (``soc_opt.bench.fit.settings_table``,
    docs/choices.md).
    """

    prior: Literal["mixture", "none"] = "mixture"
    n_components: int = 10
    weight_concentration: float = 0.05
    k0: float = 1.0
    n0: float = 1.0
    reg: float = 1e-6
    buffer_size: int = 2000
    prior_warm_start: bool = True
    max_iter: int = 10
    tol: float = 1e-3
    seed: int = 0
    min_weight: float = 1e-3
    mixture_reg: float = 1e-6
    min_eig: float = 1e-9

    _constraints = {
        "prior": [Options(("mixture", "none"))],
        "n_components": [Interval(1, 1000)],
        "max_iter": [Interval(1, 100_000)],
        "buffer_size": [Interval(0, 100_000)],  # tuples of 2n+m+1 floats kept between iterations
        **{name: [Interval(0, None, "neither")]
           for name in ("weight_concentration", "k0", "n0", "reg", "mixture_reg", "min_eig", "tol")},
        "min_weight": [Interval(0.0, 1.0, "left")],
    }


# --------------------------------------------------------------------------- data


def _check_rollouts(rollouts, min_M: int = 2) -> Rollouts:
    if not isinstance(rollouts, Rollouts):
        raise TypeError(f"rollouts must be a Rollouts, got {type(rollouts).__name__}")
    if rollouts.M < min_M:
        raise ValueError(f"dynamics fitting needs at least {min_M} rollouts, got M={rollouts.M}")
    if rollouts.T < 1:
        raise ShapeError("rollouts must have at least one time step (T >= 1)")
    return rollouts


def tuples(rollouts: Rollouts, include_y: bool = True) -> np.ndarray:
    """Tuples ``D_k^m = (s_k, a_k, s_{k+1}[, y_k])`` as ``(M, T, 2n+m[+1])`` from the measured states."""
    parts = [rollouts.s[:, :-1], rollouts.a, rollouts.s[:, 1:]]
    if include_y:
        parts.append(rollouts.y[..., None])
    return np.concatenate(parts, axis=-1)


# --------------------------------------------------------------------------- prior


def update_prior(
    prior: MixturePrior | None,
    rollouts: Rollouts,
    config: FitConfig = FitConfig(),
    rng: np.random.Generator | None = None,
) -> MixturePrior:
    """Fit the VB mixture prior on the new tuples plus ``prior``'s buffer (docs/math.md §2 step 1).

    The mixture is fitted on all tuples of all steps of ``rollouts`` together
    with the tuples buffered by ``prior`` (earlier iterations).  The returned
    prior buffers the newest ``config.buffer_size`` of these tuples (old buffer
    first, then the new tuples rollout by rollout).  Fitting is done in
    standardised coordinates (per-column mean and standard deviation of the
    fitted data; constant columns get scale 1) and mapped back.

    **Degenerate directions** (docs/math.md §2 step 1): when the fit on all coordinates fails
    because the varying columns of the standardised tuples are exactly linearly related (a
    point's position and the slide joint that moves it; a point's height and velocity when it only
    slides on a table are constant columns instead), VB runs again on the other directions only
    (:class:`~soc_opt.learning.mixture.Subspace`) and every component gets the data's mean and
    the variance ``mixture_reg`` (standardised) along those relations.  Without this, a
    warm-started component that receives no tuples keeps sklearn's covariance prior (the data's
    covariance, singular along them) and VB fails.  Constant columns stay in the fit as zero
    columns, which sklearn keeps decoupled from the rest with variance ``reg_covar``.  A fit on all
    coordinates that succeeds is kept as it is, so runs that never failed (the door's handle height
    is exactly related to its hinge, and its fits never failed) give the same numbers as before.

    Deterministic given ``rng`` (sklearn's ``random_state`` is drawn from it,
    also when warm-starting, so that the stream is consumed alike;
    ``config.seed`` is used when ``rng`` is None).
    """
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.mixture import BayesianGaussianMixture

    rollouts = _check_rollouts(rollouts, min_M=1)
    rng = as_generator(rng, config.seed)
    n, m = rollouts.n, rollouts.m
    D = 2 * n + m + 1
    X_new = tuples(rollouts).reshape(-1, D)
    if prior is not None:
        if not isinstance(prior, MixturePrior):
            raise TypeError(f"prior must be a MixturePrior or None, got {type(prior).__name__}")
        if (prior.n, prior.m) != (n, m):
            raise ShapeError(
                f"prior was fitted for n={prior.n}, m={prior.m} but the rollouts have n={n}, m={m}"
            )
        data = np.concatenate([prior.buffer, X_new], axis=0)
    else:
        data = X_new
    buffer = data[data.shape[0] - min(config.buffer_size, data.shape[0]) :].copy()

    center, scale = standardisation(data)
    Z = (data - center) / scale

    n_comp = max(1, min(config.n_components, Z.shape[0]))
    vb = getattr(prior, "vb", None)  # checkpoints written before warm starts have no vb
    warm = config.prior_warm_start and vb is not None and vb.means.shape[0] <= n_comp
    if warm:
        n_comp = vb.means.shape[0]
    seed = int(rng.integers(2**31 - 1))

    def fit(sub: Subspace | None) -> BayesianGaussianMixture:
        bgm = BayesianGaussianMixture(
            n_components=n_comp,
            covariance_type="full",
            weight_concentration_prior_type="dirichlet_distribution",
            weight_concentration_prior=config.weight_concentration,
            reg_covar=config.mixture_reg,
            max_iter=config.max_iter,
            tol=config.tol * Z.shape[0],
            random_state=seed,
            warm_start=warm,
        )
        with warnings.catch_warnings(), single_thread_blas():
            warnings.simplefilter("ignore", ConvergenceWarning)
            if warm:
                vb.to_sklearn(bgm, center, scale, sub)
            bgm.fit(Z if sub is None else Z @ sub.basis)
        return bgm

    sub = None
    try:
        bgm = fit(None)  # all coordinates: the fit of every run that never met a degenerate direction
    except ValueError as e:
        # sklearn's "ill-defined empirical covariance": a component without tuples along exactly related
        # coordinates (docs/math.md §2 step 1); fitted again on the non-degenerate directions
        sub = Subspace.of(Z, varying_columns(data.std(axis=0), center), config.mixture_reg)
        if sub is None or "covariance" not in str(e):
            raise
        bgm = fit(sub)

    w = np.asarray(bgm.weights_, dtype=float)
    keep = w >= config.min_weight
    if not np.any(keep):
        keep = w == w.max()
    vb_new = VBState.from_sklearn(bgm, center, scale, keep, sub)
    return MixturePrior(
        weights=w[keep] / w[keep].sum(),
        means=vb_new.means,
        covariances=vb_new.covariances,
        buffer=buffer,
        n=n,
        m=m,
        converged=bool(bgm.converged_),
        n_iter=int(bgm.n_iter_),
        vb=vb_new,
    )


# --------------------------------------------------------------------------- posterior + conditioning


def _reg_scale(X: np.ndarray, nz: int) -> float:
    """Pooled mean variance of the ``(s, a)`` columns of ``X (M, T, d)`` (1 if all constant)."""
    v = float(X[..., :nz].reshape(-1, nz).var(axis=0).mean())
    return v if v > 0.0 and np.isfinite(v) else 1.0


def joint_posterior(
    X: np.ndarray,
    nz: int,
    config: FitConfig,
    prior: MixturePrior | None,
    include_y: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-step joint Gaussian ``(mu (T, d), Lambda (T, d, d))`` of tuples ``X (M, T, d)``.

    Empirical (least squares) when ``prior`` is None, NIW posterior otherwise;
    the ridge ``lam I`` is added to the leading ``nz x nz`` (``(s, a)``) block.
    """
    Mr = X.shape[0]
    mu_emp = X.mean(axis=0)
    Xc = np.swapaxes(X - mu_emp, 0, 1)  # (T, M, d)
    L_emp = (_T(Xc) @ Xc) / Mr
    if prior is None:
        mu, Lam = mu_emp, L_emp
    else:
        k0, n0 = config.k0, config.n0
        mu0, S0 = prior.step_prior(X, include_y)
        d = mu_emp - mu0
        mu = (k0 * mu0 + Mr * mu_emp) / (k0 + Mr)
        Lam = (n0 * S0 + Mr * L_emp + (k0 * Mr / (k0 + Mr)) * (d[:, :, None] * d[:, None, :])) / (Mr + n0)
    Lam = symmetrize(Lam)
    lam = config.reg * _reg_scale(X, nz)
    idx = np.arange(nz)
    Lam[:, idx, idx] += lam
    return mu, Lam


def _condition(mu: np.ndarray, Lam: np.ndarray, nz: int, min_eig: float):
    """Condition ``N(mu, Lam)`` on its first ``nz`` coordinates -> ``(Ao, co, So)`` (docs/math.md §2 step 4).

    All ``T`` steps at once: one stacked Cholesky factorisation of the ``(s, a)`` blocks,
    batched solves and products, one stacked eigendecomposition for the floor.
    """
    Szz = Lam[:, :nz, :nz]
    Szy = Lam[:, :nz, nz:]
    Syy = Lam[:, nz:, nz:]
    L = chol(Szz, "joint covariance (s, a) block (increase FitConfig.reg)")
    X = cho_solve(L, Szy)  # (T, nz, dy)
    Ao = _T(X)
    co = mu[:, nz:] - np.einsum("tij,tj->ti", Ao, mu[:, :nz])
    So = symmetrize(Syy - _T(Szy) @ X)
    # floor the eigenvalues where needed (only those steps are reconstructed); a Cholesky
    # factorisation of So - floor I succeeding for every step shows there is nothing to floor
    dy = So.shape[-1]
    floor = np.maximum(min_eig * np.trace(Syy, axis1=1, axis2=2) / dy, _ABS_EIG_FLOOR)
    try:
        np.linalg.cholesky(So - floor[:, None, None] * np.eye(dy))
        return Ao, co, So
    except np.linalg.LinAlgError:
        pass
    ev, V = np.linalg.eigh(So)
    low = ev[:, 0] < floor
    if np.any(low):
        evc = np.maximum(ev[low], floor[low, None])
        So[low] = symmetrize((V[low] * evc[:, None, :]) @ _T(V[low]))
    return Ao, co, So


def _fit(rollouts, config, prior, include_y, correct=None):
    rollouts = _check_rollouts(rollouts)
    if not isinstance(config, FitConfig):
        raise TypeError(f"config must be a FitConfig, got {type(config).__name__}")
    if prior is not None:
        if not isinstance(prior, MixturePrior):
            raise TypeError(f"prior must be a MixturePrior or None, got {type(prior).__name__}")
        if (prior.n, prior.m) != (rollouts.n, rollouts.m):
            raise ShapeError(
                f"prior was fitted for n={prior.n}, m={prior.m} but the rollouts have "
                f"n={rollouts.n}, m={rollouts.m}"
            )
    use_prior = prior if config.prior == "mixture" else None
    nz = rollouts.n + rollouts.m
    X = tuples(rollouts, include_y)
    with single_thread_blas():
        mu, Lam = joint_posterior(X, nz, config, use_prior, include_y)
        if correct is not None:  # noise-aware fit (docs/math.md §10.1): moments of the true tuples
            mu, Lam = correct(mu, Lam)
        return _condition(mu, Lam, nz, config.min_eig)


def fit_augmented(
    rollouts: Rollouts, config: FitConfig = FitConfig(), prior: MixturePrior | None = None, *, correct=None
) -> AugmentedModel:
    """Fit ``zeta_k = (s_{k+1}, y_k) | (s_k, a_k)`` per time step (docs/math.md §1, §2).

    Uses the NIW posterior built from ``prior`` when ``config.prior == "mixture"``
    and a prior is given; otherwise per-step regularised least squares.
    ``correct(mu (T, d), Lam (T, d, d)) -> (mu, Lam)``, if given, maps the per-step joint
    moments (after the ridge) before conditioning: the hook of the bias-corrected fit
    (docs/math.md §10.1, :func:`soc_opt.noise.aware.moment_correction`).
    """
    Ao, co, So = _fit(rollouts, config, prior, include_y=True, correct=correct)
    return AugmentedModel(Ao, co, So, rollouts.n)


def fit_dynamics(
    rollouts: Rollouts, config: FitConfig = FitConfig(), prior: MixturePrior | None = None, *, correct=None
) -> LinearGaussianDynamics:
    """Fit ``s_{k+1} | (s_k, a_k) ~ N(A s + B a + c, W)`` per step (the ``y`` column dropped; docs/math.md §2, §6).

    With a mixture prior, ``y`` is marginalised out of the mixture.  ``correct``: as in
    :func:`fit_augmented`.
    """
    Ao, co, So = _fit(rollouts, config, prior, include_y=False, correct=correct)
    n = rollouts.n
    return LinearGaussianDynamics(Ao[:, :, :n], Ao[:, :, n:], co, So)


# --------------------------------------------------------------------------- cost observations


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    """A square root ``R`` with ``R R^T = P`` for a symmetric PSD ``P`` (Cholesky if PD)."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        ev, V = np.linalg.eigh(symmetrize(P))
        if ev[0] < -1e-10 * max(1.0, abs(ev[-1])):
            raise ValueError(f"P0 is not positive semidefinite (smallest eigenvalue {ev[0]:.3e})") from None
        return V * np.sqrt(np.clip(ev, 0.0, None))


def cost_observations(
    mode: str,
    rollouts: Rollouts | None = None,
    model: AugmentedModel | None = None,
    policy: LinearGaussianPolicy | None = None,
    mu0: np.ndarray | None = None,
    P0: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
    n_samples: int | None = None,
) -> np.ndarray:
    """Cost observation sequences ``Y (M', T)`` for the E-step (docs/math.md §3).

    Modes:
        ``"model"``:      ``M' = n_samples`` (default ``rollouts.M``) sequences sampled forward from
                          the augmented model under ``policy``: ``s_0 ~ N(mu0, P0)``,
                          ``a_k ~ policy``, ``zeta_k ~ N(Ao_k z_k + co_k, So_k)``, ``s_{k+1}`` and
                          ``y_k`` read off ``zeta_k`` (``y`` is Gaussian, not clipped).
        ``"measured"``:   the ``M`` observed sequences ``rollouts.y``.
        ``"optimistic"``: one sequence of ones (the "optimal event").
    """
    if mode == "measured":
        if rollouts is None:
            raise ValueError("cost_observations mode 'measured' needs rollouts")
        return np.array(rollouts.y)
    if mode == "optimistic":
        for src in (model, rollouts, policy):
            if src is not None:
                return np.ones((1, src.T))
        raise ValueError("cost_observations mode 'optimistic' needs a model, rollouts or policy to know T")
    if mode != "model":
        raise ValueError(f"unknown cost observation mode {mode!r}; expected one of {list(COST_MODES)}")

    if model is None or policy is None or mu0 is None or P0 is None:
        raise ValueError("cost_observations mode 'model' needs model, policy, mu0 and P0")
    if not isinstance(model, AugmentedModel):
        raise TypeError(f"model must be an AugmentedModel, got {type(model).__name__}")
    if rng is None:
        raise ValueError("cost_observations mode 'model' needs a numpy.random.Generator rng")
    T, n, m = model.T, model.n, model.m
    if (policy.T, policy.n, policy.m) != (T, n, m):
        raise ShapeError(
            f"policy (T={policy.T}, n={policy.n}, m={policy.m}) does not match the model (T={T}, n={n}, m={m})"
        )
    mu0 = check_array("mu0", mu0, (n,))
    P0 = check_array("P0", P0, (n, n))
    if n_samples is None:
        if rollouts is None:
            raise ValueError("cost_observations mode 'model' needs n_samples or rollouts")
        n_samples = rollouts.M
    n_samples = int(n_samples)
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")

    R0 = _sqrt_psd(P0)
    Lo = np.linalg.cholesky(model.So)
    s = mu0 + rng.standard_normal((n_samples, n)) @ R0.T
    Y = np.empty((n_samples, T))
    for k in range(T):
        a = policy.sample_action(k, s, rng)
        z = np.concatenate([s, a], axis=1)
        zeta = z @ model.Ao[k].T + model.co[k] + rng.standard_normal((n_samples, n + 1)) @ Lo[k].T
        s = zeta[:, :n]
        Y[:, k] = zeta[:, n]
    return Y


# --------------------------------------------------------------------------- evaluation


def prediction_error(
    model: AugmentedModel | LinearGaussianDynamics,
    rollouts: Rollouts,
    target: Literal["state", "y"] = "state",
) -> np.ndarray:
    """Per-step one-step prediction mean squared error ``(T,)`` on (held-out) rollouts.

    ``target="state"``: mean over rollouts and the ``n`` components of
    ``(s_{k+1} - A_k s_k - B_k a_k - c_k)^2``.  ``target="y"`` (augmented
    models only): mean over rollouts of ``(y_k - Ay_k s_k - By_k a_k - cy_k)^2``.
    """
    if not isinstance(rollouts, Rollouts):
        raise TypeError(f"rollouts must be a Rollouts, got {type(rollouts).__name__}")
    if isinstance(model, AugmentedModel):
        A, B, c = model.As, model.Bs, model.co
    elif isinstance(model, LinearGaussianDynamics):
        if target == "y":
            raise ValueError("prediction_error target 'y' needs an AugmentedModel")
        A, B, c = model.A, model.B, model.c
    else:
        raise TypeError(f"model must be an AugmentedModel or LinearGaussianDynamics, got {type(model).__name__}")
    if (model.T, model.n, model.m) != (rollouts.T, rollouts.n, rollouts.m):
        raise ShapeError(
            f"model (T={model.T}, n={model.n}, m={model.m}) does not match the rollouts "
            f"(T={rollouts.T}, n={rollouts.n}, m={rollouts.m})"
        )
    n = rollouts.n
    pred = (
        np.einsum("tij,mtj->mti", A, rollouts.s[:, :-1])
        + np.einsum("tij,mtj->mti", B, rollouts.a)
        + c[None]
    )
    if target == "state":
        err = rollouts.s[:, 1:] - pred[..., :n]
        return np.mean(err**2, axis=(0, 2))
    if target == "y":
        err = rollouts.y - pred[..., n]
        return np.mean(err**2, axis=0)
    raise ValueError(f"unknown prediction_error target {target!r}; expected 'state' or 'y'")
