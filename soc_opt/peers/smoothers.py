"""The E-step's filter/smoother against dynamax and pykalman on one model (docs/math.md §4).

soc_opt smooths the closed loop ``(s_{k+1}, y_k) | s_k ~ N(M_k s_k + m_k, S_k)``, whose state and
observation noises are correlated in general.  dynamax's ``lgssm_smoother`` and pykalman's
``KalmanFilter`` take the usual linear-Gaussian state-space model

    z_{t+1} = F_t z_t + b_t + N(0, Q_t),     y_t = H_t z_t + d_t + N(0, R_t),     z_0 ~ N(mu0, P0),

with independent noises.  The two meet when the augmented model has no action in the cost row
(``By_k = 0``) and a block-diagonal ``So_k``: then ``S_k`` is block diagonal and
``F_k = A_k + B_k K_k``, ``b_k = B_k k_k + c_k``, ``Q_k = W_k + B_k Sigma_k B_k^T``,
``H_k = Ay_k``, ``d_k = cy_k``, ``R_k = Syy_k``.  :func:`random_uncorrelated` builds such an
instance, with a constant observation noise variance ``R`` (pykalman's ``loglikelihood`` takes one
observation covariance, although its filter and smoother accept a time-varying one; everything
else varies with time); :func:`to_lgssm` gives the peers' arrays.  soc_opt also returns ``s_T`` (predicted,
unobserved): the peers' ``T`` states are compared with soc_opt's first ``T``.

The work each side does.  soc_opt's ``smooth`` (the E-step as the loop calls it: closed loop, then the
Gaussian core :mod:`soc_opt.lgssm`) knows that the ``M`` sequences share one model, so the covariance
recursion (filter and smoother covariances and gains) runs once and only the means are per sequence.
dynamax's ``lgssm_smoother`` smooths one sequence; ``jit(vmap(...))`` over the ``M`` sequences
(its documented way to batch) recomputes the covariances for every sequence: that is its design, not a
handicap added here.  The like-for-like row is therefore also timed: soc_opt's core with the
covariances made per sequence (:func:`run_soc_opt_per_sequence`, an initial covariance with a
sequence axis, as when every sequence has its own model), which does dynamax's work; it runs in the
compiled kernels when numba is installed (:mod:`soc_opt.compiled`; the row's ``kernels`` says which path ran).  pykalman has
no batch axis: one ``smooth`` call per sequence.  The calls are timed interleaved (soc_opt, its core,
its core per sequence, dynamax, in turn, in a random order drawn afresh every round from a fixed seed),
so that a change of the machine's load hits all of them and each follows each other equally often: a
call made right after a large one (the per-sequence core, dynamax) starts with cold caches, which cost
a 1.4 ms call at ``n = 6`` up to 1 ms more.  (A rotation of a fixed order, used before, keeps every
call's predecessor: the E-step always ran right after dynamax or the per-sequence core, and looked
0.3-0.6 ms slower than its core for that reason.)

Public functions:
    random_uncorrelated(rng, n, m, T)              -> (model, policy, mu0, P0)
    to_lgssm(model, policy)                        -> LGSSM
    run_soc_opt(model, policy, Y, mu0, P0)         -> SmootherOutput
    run_soc_opt_core(lg, Y, mu0, P0)                -> SmootherOutput  (the core on the peers' arrays)
    run_soc_opt_per_sequence(lg, Y, mu0, P0)        -> SmootherOutput  (covariances per sequence)
    run_dynamax(lg, Y, mu0, P0)                    -> (SmootherOutput, compile_s)
    run_pykalman(lg, Y, mu0, P0)                   -> SmootherOutput
    compare(rng, n, T, M, repeats)                 -> dict (one row of the table)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from .. import compiled, lgssm
from ..estep import closed_loop, smooth
from ..models import AugmentedModel, LinearGaussianPolicy, symmetrize
from . import require

__all__ = ["LGSSM", "SmootherOutput", "random_uncorrelated", "to_lgssm", "run_soc_opt", "run_soc_opt_core", "run_soc_opt_per_sequence",
           "run_dynamax", "run_pykalman", "compare"]


@dataclass(frozen=True)
class LGSSM:
    """Time-varying linear-Gaussian state-space model with independent noises.

    F: (T, n, n), b: (T, n), Q: (T, n, n) transition of step ``t -> t+1`` (the last unused by the
    peers, which stop at ``z_{T-1}``); H: (T, 1, n), d: (T, 1), R: (T, 1, 1) emission of ``y_t``.
    """

    F: np.ndarray
    b: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    d: np.ndarray
    R: np.ndarray


@dataclass(frozen=True)
class SmootherOutput:
    """Smoothed means ``(M, T, n)``, covariances ``(T, n, n)`` (they do not depend on ``y``),
    log-likelihoods ``(M,)`` and the wall time of the call that made them (seconds)."""

    mean: np.ndarray
    cov: np.ndarray
    loglik: np.ndarray
    seconds: float


def random_uncorrelated(rng: np.random.Generator, n: int, m: int, T: int):
    """A stable augmented model with ``By = 0`` and block-diagonal ``So``, and a policy.

    ``A_k = 0.95 Q_k`` (orthogonal), ``B_k ~ 0.1 N``, cost row ``Ay_k ~ 0.1 N``, ``So`` blocks
    ``L L^T + 0.01 I`` (``L ~ 0.1 N``) and ``Syy = 0.05`` (constant, see the module docstring); policy ``K ~ 0.1 N``,
    ``k ~ N``, ``Sigma = 0.1 I``; ``mu0 ~ N``, ``P0 = I``.  Returns ``(model, policy, mu0, P0)``.
    """
    A = 0.95 * np.linalg.qr(rng.standard_normal((T, n, n)))[0]
    B = 0.1 * rng.standard_normal((T, n, m))
    Ay = np.concatenate([0.1 * rng.standard_normal((T, 1, n)), np.zeros((T, 1, m))], axis=2)
    Ao = np.concatenate([np.concatenate([A, B], axis=2), Ay], axis=1)
    L = 0.1 * rng.standard_normal((T, n, n))
    So = np.zeros((T, n + 1, n + 1))
    So[:, :n, :n] = symmetrize(L @ np.swapaxes(L, 1, 2)) + 0.01 * np.eye(n)
    So[:, n, n] = 0.05
    model = AugmentedModel(Ao, 0.1 * rng.standard_normal((T, n + 1)), So, n)
    policy = LinearGaussianPolicy(0.1 * rng.standard_normal((T, m, n)), rng.standard_normal((T, m)),
                                  np.broadcast_to(0.1 * np.eye(m), (T, m, m)).copy())
    return model, policy, rng.standard_normal(n), np.eye(n)


def to_lgssm(model: AugmentedModel, policy: LinearGaussianPolicy, atol: float = 0.0) -> LGSSM:
    """The closed loop as an :class:`LGSSM`; ValueError if its noises are correlated.

    ``atol``: the largest ``|S_sy|`` accepted (0: exactly uncorrelated, as built by
    :func:`random_uncorrelated`).
    """
    n = model.n
    Mk, mk, Sk = closed_loop(model, policy)
    cross = float(np.abs(Sk[:, :n, n]).max())
    if cross > atol:
        raise ValueError(f"the closed loop's state and observation noises are correlated (max |S_sy| = "
                         f"{cross:.3e} > atol={atol}): the peers cannot express this model")
    return LGSSM(F=Mk[:, :n, :], b=mk[:, :n], Q=Sk[:, :n, :n], H=Mk[:, n:, :], d=mk[:, n:],
                 R=Sk[:, n:, n:])


def run_soc_opt(model, policy, Y, mu0, P0) -> SmootherOutput:
    """soc_opt's :func:`~soc_opt.estep.smooth` on ``Y (M, T)``, all sequences in one call."""
    t0 = time.perf_counter()
    sm = smooth(model, policy, Y, mu0, P0)
    dt = time.perf_counter() - t0
    T = Y.shape[1]
    return SmootherOutput(np.asarray(sm.mean)[:, :T], np.asarray(sm.cov)[0, :T], np.asarray(sm.loglik), dt)


def _core_params(lg: LGSSM, mu0, P0, M: int | None = None) -> lgssm.Params:
    """The LGSSM as the Gaussian core's model; ``M``: the initial covariance given per sequence."""
    cov = P0 if M is None else np.broadcast_to(P0, (M,) + P0.shape)
    return lgssm.Params(lgssm.Initial(mu0, cov), lgssm.Dynamics(lg.F, lg.b, lg.Q), lgssm.Emissions(lg.H, lg.d, lg.R))


def run_soc_opt_core(lg: LGSSM, Y, mu0, P0) -> SmootherOutput:
    """soc_opt's core (:func:`soc_opt.lgssm.rts_smoother`) on the peers' arrays (``params`` built before the
    clock starts, as dynamax's are): the same model and work as :func:`run_soc_opt` without building the
    closed loop from ``(model, policy)`` and validating it."""
    params = _core_params(lg, mu0, P0)
    Y3 = Y[:, :, None]
    t0 = time.perf_counter()
    post = lgssm.rts_smoother(params, Y3)
    dt = time.perf_counter() - t0
    T = Y.shape[1]
    return SmootherOutput(post.smoothed_means[:, :T], post.smoothed_covariances[:T], post.marginal_loglik, dt)


def run_soc_opt_per_sequence(lg: LGSSM, Y, mu0, P0) -> SmootherOutput:
    """soc_opt's core (:func:`soc_opt.lgssm.rts_smoother`) on ``Y (M, T)`` with covariances per sequence
    (the initial covariance given with a sequence axis): the covariance recursion runs for every
    sequence, batched over them, as dynamax's vmap does.  Covariances returned: the first sequence's."""
    M, T = Y.shape
    params = _core_params(lg, mu0, P0, M)
    t0 = time.perf_counter()
    post = lgssm.rts_smoother(params, Y[:, :, None])
    dt = time.perf_counter() - t0
    return SmootherOutput(post.smoothed_means[:, :T], post.smoothed_covariances[0, :T], post.marginal_loglik, dt)


def _dynamax_params(lg: LGSSM, mu0, P0):
    """dynamax's time-varying dynamics: entry ``t + 1`` moves ``z_t`` to ``z_{t+1}`` (entry 0 unused),
    so the transitions are shifted by one step."""
    from dynamax.linear_gaussian_ssm.inference import ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions, ParamsLGSSMInitial
    jnp = require("jax.numpy")
    T, n = lg.b.shape
    return ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=jnp.asarray(mu0), cov=jnp.asarray(P0)),
        dynamics=ParamsLGSSMDynamics(weights=jnp.asarray(np.roll(lg.F, 1, axis=0)),
                                     bias=jnp.asarray(np.roll(lg.b, 1, axis=0)),
                                     input_weights=jnp.zeros((T, n, 0)), cov=jnp.asarray(np.roll(lg.Q, 1, axis=0))),
        emissions=ParamsLGSSMEmissions(weights=jnp.asarray(lg.H), bias=jnp.asarray(lg.d),
                                       input_weights=jnp.zeros((T, 1, 0)), cov=jnp.asarray(lg.R)),
    )


def _dynamax_call(lg: LGSSM, Y, mu0, P0):
    """A timed dynamax call ``() -> SmootherOutput`` (jit + vmap over the sequences) and the first
    call's time (trace + XLA compile + one run).  float64 inside ``jax.enable_x64`` only: switching
    JAX's global flag would leave every later JAX user in the process (sbx-rl's SAC) on float64."""
    jax = require("jax")
    inference = require("dynamax.linear_gaussian_ssm.inference")
    with jax.enable_x64(True):
        params = _dynamax_params(lg, mu0, P0)
        fn = jax.jit(jax.vmap(lambda y: inference.lgssm_smoother(params, y[:, None]), in_axes=0))
        Yj = jax.numpy.asarray(Y)

    def call() -> SmootherOutput:
        with jax.enable_x64(True):
            t0 = time.perf_counter()
            post = jax.block_until_ready(fn(Yj))
            dt = time.perf_counter() - t0
        return SmootherOutput(np.asarray(post.smoothed_means), np.asarray(post.smoothed_covariances)[0],
                              np.asarray(post.marginal_loglik), dt)

    first = call().seconds
    return call, first


def run_dynamax(lg: LGSSM, Y, mu0, P0, repeats: int = 3) -> tuple[SmootherOutput, float]:
    """dynamax ``lgssm_smoother`` (float64, CPU), vmapped over the ``M`` sequences and jitted.

    Returns the output with the median run time of ``repeats`` calls after the first, and the
    first call's time (trace + XLA compile + one run) apart.
    """
    call, first = _dynamax_call(lg, Y, mu0, P0)
    runs = [call() for _ in range(repeats)]
    return replace(runs[-1], seconds=float(np.median([r.seconds for r in runs]))), first


def run_pykalman(lg: LGSSM, Y, mu0, P0) -> SmootherOutput:
    """pykalman ``KalmanFilter.smooth`` and ``loglikelihood`` per sequence (it has no batch axis).

    The time is that of the ``M`` smoother calls; ``loglikelihood`` (a second filter pass) is
    not timed.  Covariances are those of the first sequence (identical for all).  ValueError if
    ``R`` varies with time (pykalman's ``loglikelihood`` would silently mis-shape it).
    """
    pk = require("pykalman")
    if not np.all(lg.R == lg.R[0]):
        raise ValueError("pykalman's loglikelihood takes one observation covariance: R must be constant over time")
    kf = pk.KalmanFilter(transition_matrices=lg.F[:-1], transition_offsets=lg.b[:-1],
                         transition_covariance=lg.Q[:-1], observation_matrices=lg.H,
                         observation_offsets=lg.d, observation_covariance=lg.R[0],
                         initial_state_mean=mu0, initial_state_covariance=P0)
    means, covs = [], None
    t0 = time.perf_counter()
    for y in Y:
        mu, P = kf.smooth(y[:, None])
        means.append(mu)
        covs = P if covs is None else covs
    dt = time.perf_counter() - t0
    ll = np.array([kf.loglikelihood(y[:, None]) for y in Y])
    return SmootherOutput(np.stack(means), covs, ll, dt)


def _diff(a: SmootherOutput, b: SmootherOutput) -> dict:
    return {"mean": float(np.abs(a.mean - b.mean).max()), "cov": float(np.abs(a.cov - b.cov).max()),
            "loglik": float(np.abs(a.loglik - b.loglik).max())}


def compare(rng: np.random.Generator, n: int, T: int = 100, M: int = 20, m: int = 7, repeats: int = 3,
            peers=("dynamax", "pykalman")) -> dict:
    """One row: max differences to soc_opt and wall times, medians of ``repeats`` calls timed in turn
    (soc_opt with shared covariances, soc_opt with per-sequence covariances, dynamax; module docstring)."""
    model, policy, mu0, P0 = random_uncorrelated(rng, n, m, T)
    lg = to_lgssm(model, policy)
    Y = rng.standard_normal((M, T))
    calls = {"soc_opt": lambda: run_soc_opt(model, policy, Y, mu0, P0),
             "core": lambda: run_soc_opt_core(lg, Y, mu0, P0),
             "per_seq": lambda: run_soc_opt_per_sequence(lg, Y, mu0, P0)}
    first = None
    if "dynamax" in peers:
        calls["dynamax"], first = _dynamax_call(lg, Y, mu0, P0)
    for f in calls.values():  # warm up
        f()
    # each call's time, and only its last output: holding every output would make each call allocate
    # fresh memory (and fault in its pages) where a program that drops its results reuses the heap
    times: dict[str, list[float]] = {k: [] for k in calls}
    last: dict[str, SmootherOutput] = {}
    names = list(calls)
    order = np.random.default_rng(0)
    for _ in range(repeats):  # in turn, in an order drawn afresh every round (module docstring)
        for k in order.permutation(names):
            last[k] = calls[k]()
            times[k].append(last[k].seconds)
    sec = {k: float(np.median(v)) for k, v in times.items()}
    ref, so_s = last["soc_opt"], sec["soc_opt"]
    d = _diff(ref, last["per_seq"])
    dc = _diff(ref, last["core"])
    row = {"n": n, "m": m, "T": T, "sequences": M, "soc_opt_ms": 1e3 * so_s, "soc_opt_core_ms": 1e3 * sec["core"],
           "soc_opt_per_seq_ms": 1e3 * sec["per_seq"], "core_max_dmean": dc["mean"], "per_seq_max_dmean": d["mean"],
           "per_seq_max_dcov": d["cov"], "per_seq_max_dloglik": d["loglik"], "kernels": compiled.describe()}
    if "dynamax" in peers:
        dx = last["dynamax"]
        d = _diff(ref, dx)
        row.update(dynamax_ms=1e3 * sec["dynamax"], dynamax_first_call_s=first,
                   dynamax_ratio=sec["dynamax"] / so_s, dynamax_ratio_core=sec["dynamax"] / sec["core"],
                   dynamax_ratio_per_seq=sec["dynamax"] / sec["per_seq"],
                   dynamax_max_dmean=d["mean"], dynamax_max_dcov=d["cov"], dynamax_max_dloglik=d["loglik"])
    if "pykalman" in peers:
        pk = run_pykalman(lg, Y, mu0, P0)
        d = _diff(ref, pk)
        row.update(pykalman_ms=1e3 * pk.seconds, pykalman_ratio=pk.seconds / so_s, pykalman_max_dmean=d["mean"],
                   pykalman_max_dcov=d["cov"], pykalman_max_dloglik=d["loglik"])
    row["loglik_scale"] = float(np.abs(ref.loglik).max())
    return row
