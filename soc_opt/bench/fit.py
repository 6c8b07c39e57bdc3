"""Dynamics-fitting benchmark and accuracy tables (docs/math.md §2).

``run()`` times the fit with and without the VB mixture prior on a synthetic
time-varying linear-Gaussian system of the ``peg`` task's size and appends the
accuracy tables also asserted by ``tests/test_fit.py``:

* ``convergence_table``: error of the fitted ``A, B, c, W`` against a known
  time-varying linear-Gaussian system as the number of rollouts grows;
* ``few_sample_table``: held-out one-step prediction error of least squares vs
  the mixture prior with fewer rollouts than ``n + m`` (linear system);
* ``pendulum_table``: the same comparison on a damped, torque-driven pendulum;
* ``settings_table``: fit time and held-out one-step prediction error of the
  mixture-prior settings (warm start, buffer size, component count) on a
  sequence of paper-scale LQR-FLM iterations on the ``peg`` task
  (``peg_sequence``), relative to the pre-warm-start settings.

Every function is pure (randomness from seeds); printing only under ``__main__``.
"""

from __future__ import annotations

import time

import numpy as np

from ..learning.fit import FitConfig, fit_augmented, fit_dynamics, prediction_error, update_prior
from ..models import Rollouts
from ..testing import random_ltv_system, simulate_linear, simulate_pendulum

__all__ = [
    "simulate_linear",
    "simulate_pendulum",
    "dynamics_errors",
    "convergence_table",
    "few_sample_table",
    "pendulum_table",
    "peg_sequence",
    "SETTINGS",
    "settings_table",
    "summarize",
    "format_table",
    "run",
]


# --------------------------------------------------------------------------- systems


# --------------------------------------------------------------------------- tables


def _rel(est: np.ndarray, true: np.ndarray) -> float:
    return float(np.linalg.norm(est - true) / np.linalg.norm(true))


def dynamics_errors(dyn, system: dict) -> dict:
    """Relative Frobenius errors over all steps of the fitted ``A, B, c, W`` against ``system``."""
    return {
        "err_A": _rel(dyn.A, system["A"]),
        "err_B": _rel(dyn.B, system["B"]),
        "err_c": _rel(dyn.c, system["c"]),
        "err_W": _rel(dyn.cov, system["W"]),
    }


def convergence_table(
    Ms=(5, 10, 20, 80),
    seeds=(0, 1, 2),
    n: int = 6,
    m: int = 2,
    T: int = 50,
    priors=("none", "mixture"),
    config: FitConfig = FitConfig(),
) -> list[dict]:
    """Errors of the fitted ``A, B, c, W`` vs the true time-varying system as ``M`` grows.

    Per seed a system (``soc_opt.testing.random_ltv_system``, variation 0.1) and ``max(Ms)`` rollouts
    (no measurement noise, so that regression of ``s'`` on ``(s, a)`` is
    consistent) are drawn; each ``M`` uses the first ``M`` rollouts.  With
    ``"mixture"`` the prior is fitted on those same ``M`` rollouts.  One row per
    (prior, M, seed).
    """
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        system = random_ltv_system(rng, n, m, T)
        data = simulate_linear(system, max(Ms), rng)
        for M in Ms:
            ro = Rollouts(*(np.array(getattr(data, f)[:M]) for f in ("x", "s", "a", "cost", "y")))
            for p in priors:
                cfg = config.replace(prior=p, seed=seed)
                prior = update_prior(None, ro, cfg, np.random.default_rng(seed)) if p == "mixture" else None
                dyn = fit_dynamics(ro, cfg, prior)
                rows.append({"table": "convergence", "prior": p, "M": M, "seed": seed, **dynamics_errors(dyn, system)})
    return rows


def _heldout_compare(
    train: Rollouts, test: Rollouts, config: FitConfig, seed: int, prior_data=None, reference=None
) -> dict:
    """Held-out MSEs of least squares and of the mixture prior; ``mse_ref`` of a ``reference`` dynamics model."""
    rng = np.random.default_rng(seed)
    prior = update_prior(None, prior_data, config, rng) if prior_data is not None else None
    prior = update_prior(prior, train, config, rng)
    ls = fit_augmented(train, config.replace(prior="none"))
    mix = fit_augmented(train, config.replace(prior="mixture"), prior)
    return {
        "mse_ls": float(prediction_error(ls, test).mean()),
        "mse_prior": float(prediction_error(mix, test).mean()),
        "mse_y_ls": float(prediction_error(ls, test, "y").mean()),
        "mse_y_prior": float(prediction_error(mix, test, "y").mean()),
        "mse_ref": float(prediction_error(reference, test).mean()) if reference is not None else float("nan"),
        "components": prior.n_components,
    }


def few_sample_table(
    Ms=(3, 5, 7),
    seeds=(0, 1, 2),
    n: int = 6,
    m: int = 2,
    T: int = 50,
    variation: float = 0.02,
    rho2: float = 0.01,
    M_test: int = 50,
    config: FitConfig = FitConfig(),
) -> list[dict]:
    """Held-out one-step prediction MSE (mean over steps) of least squares vs the mixture prior, ``M < n+m``.

    Slowly varying linear system (``variation``), measurement noise ``rho2``;
    the prior is fitted on the ``M`` training rollouts only (all time steps
    pooled).  ``mse_ref`` is the error of the true system matrices (the floor
    set by process and measurement noise).  One row per (M, seed).
    """
    from ..models import LinearGaussianDynamics

    rows = []
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        system = random_ltv_system(rng, n, m, T, variation=variation)
        truth = LinearGaussianDynamics(system["A"], system["B"], system["c"], system["W"])
        test = simulate_linear(system, M_test, rng, rho2=rho2)
        for M in Ms:
            train = simulate_linear(system, M, rng, rho2=rho2)
            rows.append(
                {"table": "few_sample", "M": M, "seed": seed, **_heldout_compare(train, test, config, seed, reference=truth)}
            )
    return rows


def pendulum_table(
    Ms=(2, 3, 5),
    seeds=(0, 1, 2),
    T: int = 60,
    M_test: int = 50,
    M_earlier: int = 0,
    config: FitConfig = FitConfig(),
) -> list[dict]:
    """Held-out one-step prediction MSE of least squares vs the mixture prior on the pendulum.

    The prior is fitted on the ``M`` training rollouts (all steps pooled), after
    a buffer of ``M_earlier`` rollouts from an "earlier iteration" (0: none).
    ``mse_ref`` is the error of a least-squares fit on 200 rollouts (the best
    time-varying linear model, up to its own estimation error).  One row per (M, seed).
    """
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(2000 + seed)
        test = simulate_pendulum(M_test, rng, T=T)
        ref = fit_dynamics(simulate_pendulum(200, rng, T=T), config.replace(prior="none"))
        earlier = simulate_pendulum(M_earlier, rng, T=T) if M_earlier else None
        for M in Ms:
            train = simulate_pendulum(M, rng, T=T)
            rows.append(
                {"table": "pendulum", "M": M, "seed": seed, "M_earlier": M_earlier,
                 **_heldout_compare(train, test, config, seed, earlier, ref)}
            )
    return rows


# The reference row (first) is the configuration before warm starts were introduced.
_OLD = (False, 20, 10000, 100)
_DEFAULT = (FitConfig().prior_warm_start, FitConfig().n_components, FitConfig().buffer_size, FitConfig().max_iter)
SETTINGS: tuple[tuple[str, dict], ...] = tuple(
    (f"{'warm' if w else 'cold'} C{c} buf{b} it{i}"
     + {_OLD: " (old)", _DEFAULT: " (default)"}.get((w, c, b, i), ""),
     {"prior_warm_start": w, "n_components": c, "buffer_size": b, "max_iter": i})
    for w, c, b, i in (
        _OLD,
        (True, 20, 10000, 100),
        (True, 20, 2000, 100),
        (True, 20, 0, 100),
        (True, 10, 2000, 20),
        (True, 10, 2000, 10),
        (True, 10, 0, 10),
        (True, 5, 2000, 10),
        (False, 10, 2000, 10),
    )
)

# Fit used only to *generate* the peg policy sequence (any sensible fit; held fixed so that
# every setting in the table is measured on the same rollouts).
_GENERATOR_FIT = {"prior_warm_start": True, "n_components": 10, "buffer_size": 2000, "max_iter": 100}


def peg_sequence(
    iterations: int = 10, samples: int = 20, n_test: int = 20, seed: int = 0, task: str = "peg"
) -> list[tuple[Rollouts, Rollouts]]:
    """``(train, test)`` rollouts of ``iterations`` LQR-FLM iterations on ``task`` (paper scale).

    LQR-FLM runs with the paper-scale settings of ``soc-opt --paper`` (``samples``
    rollouts per iteration) and the fit ``_GENERATOR_FIT``; ``train`` are the
    rollouts the iteration fitted on, ``test`` are ``n_test`` further rollouts of the
    same policy (an independent stream, seed ``seed + 1``).
    """
    from ..experiments.run import load_run_config
    from ..methods.lqr_flm import initial_state, lqr_flm_iteration
    from ..tasks import load_task

    t = load_task(task)
    base = load_run_config(task, paper=True, overrides={"iterations": iterations, "samples": samples},
                           method="lqr-flm").baseline
    cfg = base.replace(fit=base.fit.replace(**_GENERATOR_FIT))
    state = initial_state(t, cfg, seed)
    test_rng = np.random.default_rng(seed + 1)
    out = []
    for _ in range(iterations):
        policy = state.policy
        state = lqr_flm_iteration(t, cfg, state)
        out.append((state.last_rollouts, t.rollouts(policy, n_test, test_rng)))
    return out


def _replay(data: list[tuple[Rollouts, Rollouts]], cfg: FitConfig, seed: int) -> list[dict]:
    """Per-iteration fit wall and CPU time, VB iterations, components and held-out error of ``cfg``."""
    rng = np.random.default_rng(seed)
    prior, out = None, []
    for train, test in data:
        t0, c0 = time.perf_counter(), time.process_time()
        prior = update_prior(prior, train, cfg, rng)
        dyn = fit_dynamics(train, cfg, prior)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        out.append({"fit_s": dt, "fit_cpu_s": dc, "vb_iter": prior.n_iter, "components": prior.n_components,
                    "mse": float(prediction_error(dyn, test).mean())})
    return out


def settings_table(
    settings: tuple[tuple[str, dict], ...] = SETTINGS,
    data: list[tuple[Rollouts, Rollouts]] | None = None,
    seed: int = 0,
    config: FitConfig = FitConfig(),
) -> list[dict]:
    """Fit time vs held-out one-step prediction error per mixture-prior setting.

    Every setting (``config`` with the given changes) replays the same sequence
    ``data`` (default :func:`peg_sequence`): at each iteration the prior is updated
    with that iteration's training rollouts (warm-started or not, keeping its
    buffer) and the dynamics are fitted, as in LQR-FLM.  Columns: median and
    maximum wall time of prior update + fit per iteration (the first iteration is
    always a cold start), the median CPU time (less sensitive to other load on a
    shared machine; BLAS runs single-threaded), the total wall time over all
    iterations, median VB iterations, final component count, mean held-out MSE over
    iterations, and ``err_ratio`` = mean over iterations of the MSE relative to the
    first (reference) setting, ``worst_ratio`` its maximum.
    """
    import sklearn.mixture  # noqa: F401  (its import, ~0.5 s, is not part of any setting's time)

    data = peg_sequence(seed=seed) if data is None else data
    runs = [(name, _replay(data, config.replace(**changes), seed)) for name, changes in settings]
    ref = np.array([r["mse"] for r in runs[0][1]])
    rows = []
    for name, rs in runs:
        mse = np.array([r["mse"] for r in rs])
        t = np.array([r["fit_s"] for r in rs])
        rows.append({
            "table": "settings", "setting": name, "iterations": len(rs),
            "fit_median_s": float(np.median(t)), "fit_max_s": float(t.max()),
            "fit_cpu_median_s": float(np.median([r["fit_cpu_s"] for r in rs])), "fit_total_s": float(t.sum()),
            "vb_iter_median": float(np.median([r["vb_iter"] for r in rs])),
            "components": rs[-1]["components"], "heldout_mse": float(mse.mean()),
            "err_ratio": float(np.mean(mse / ref)), "worst_ratio": float(np.max(mse / ref)),
        })
    return rows


def summarize(rows: list[dict], keys: tuple, group: tuple) -> list[dict]:
    """Mean of ``keys`` over rows sharing the ``group`` fields (order preserved)."""
    out: dict = {}
    for r in rows:
        g = tuple(r[k] for k in group)
        out.setdefault(g, []).append(r)
    return [
        {**dict(zip(group, g)), **{k: float(np.mean([r[k] for r in rs])) for k in keys}, "n_seeds": len(rs)}
        for g, rs in out.items()
    ]


def format_table(rows: list[dict]) -> str:
    """Plain-text table of dict rows (floats in 4 significant digits)."""
    if not rows:
        return ""
    cols = list(rows[0])
    cells = [[f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c]) for c in cols] for r in rows]
    w = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.rjust(w[i]) for i, c in enumerate(cols))]
    lines += ["  ".join(v.rjust(w[i]) for i, v in enumerate(row)) for row in cells]
    return "\n".join(lines)


# --------------------------------------------------------------------------- benchmark


def _timed(f, *args, repeats: int = 1, **kw):
    """``(result, best wall time over repeats)``."""
    best = np.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = f(*args, **kw)
        best = min(best, time.perf_counter() - t0)
    return out, best


def run(
    M: int = 20,
    T: int = 100,
    n: int = 26,
    m: int = 7,
    seed: int = 0,
    tables: bool = True,
    repeats: int = 3,
    settings: bool = True,
    quick: bool = False,
) -> list[dict]:
    """Fit times with/without the mixture prior on a synthetic system of size ``(n, m, T)``, plus the tables.

    Timing rows: ``least_squares`` (posterior + conditioning only) and
    ``mixture`` (VB prior update, then posterior + conditioning), for the
    augmented model and the dynamics; the prediction error on 20 held-out
    rollouts is reported alongside.  Times are the best of ``repeats`` runs
    (the fits are deterministic).  With ``tables`` the (seed-averaged)
    convergence, few-sample and pendulum tables follow as rows, and with
    ``settings`` the peg settings table (:func:`settings_table`; ~15 minutes on the
    shared 2-core machine at load ~6, almost all of it the reference setting, which
    refits from scratch every iteration).  ``quick``: the tables and the settings table on tiny
    sizes (one seed; the settings on 2 LQR-FLM iterations of ``linear2d``), to check the code path.
    """
    rng = np.random.default_rng(seed)
    system = random_ltv_system(rng, n, m, T)
    train = simulate_linear(system, M, rng, rho2=0.01)
    test = simulate_linear(system, 20, rng, rho2=0.01)
    cfg = FitConfig(seed=seed)
    rows = []

    r = repeats
    ls, t_ls = _timed(fit_augmented, train, cfg.replace(prior="none"), repeats=r)
    _, t_ls_d = _timed(fit_dynamics, train, cfg.replace(prior="none"), repeats=r)
    prior, t_prior = _timed(lambda: update_prior(None, train, cfg, np.random.default_rng(seed)), repeats=r)
    mix, t_mix = _timed(fit_augmented, train, cfg, prior, repeats=r)
    _, t_mix_d = _timed(fit_dynamics, train, cfg, prior, repeats=r)
    base = {"table": "timing", "M": M, "T": T, "n": n, "m": m, "D": 2 * n + m + 1}
    rows.append({**base, "method": "least_squares", "prior_s": 0.0, "augmented_s": t_ls, "dynamics_s": t_ls_d,
                 "total_s": t_ls, "components": 0, "vb_iter": 0,
                 "heldout_mse": float(prediction_error(ls, test).mean())})
    rows.append({**base, "method": "mixture", "prior_s": t_prior, "augmented_s": t_mix, "dynamics_s": t_mix_d,
                 "total_s": t_prior + t_mix, "components": prior.n_components, "vb_iter": prior.n_iter,
                 "heldout_mse": float(prediction_error(mix, test).mean())})
    small = {"seeds": (0,), "T": 10} if quick else {}
    if tables:
        errs = ("err_A", "err_B", "err_c", "err_W")
        rows += summarize(convergence_table(**({"Ms": (5, 10)} if quick else {}), **small), errs,
                          ("table", "prior", "M"))
        mse = ("mse_ls", "mse_prior", "mse_ref", "mse_y_ls", "mse_y_prior")
        rows += summarize(few_sample_table(**({"Ms": (3,), "M_test": 5} if quick else {}), **small), mse,
                          ("table", "M"))
        rows += summarize(pendulum_table(**({"Ms": (2,), "M_test": 5} if quick else {}), **small), mse,
                          ("table", "M"))
    if settings:
        data = peg_sequence(iterations=2, samples=4, n_test=4, seed=seed, task="linear2d") if quick else None
        rows += settings_table(settings=SETTINGS[:2] if quick else SETTINGS, data=data, seed=seed)
    return rows


#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"M": 5, "T": 10, "n": 3, "m": 2, "repeats": 1, "quick": True}


if __name__ == "__main__":
    out = run()
    for name in ("timing", "convergence", "few_sample", "pendulum", "settings"):
        sel = [r for r in out if r["table"] == name]
        if sel:
            print(f"\n[{name}]")
            print(format_table(sel))
