"""LQR-FLM, the paper's baseline ("iLQG" in the paper; docs/math.md §7), as a pure step function.

One iteration on an explicit :class:`~soc_opt.methods.state.RunState`:

1. sample ``M`` rollouts of the current policy ``p_i`` on the task;
2. fit linear-Gaussian dynamics (mixture prior + NIW posterior, docs/math.md §2);
3. expand the cost to second order around the sample mean trajectory;
4. adapt the KL budget from predicted vs actual improvement (docs/math.md §6, GPS rule);
5. KL-constrained LQG step against the reference policy -> ``p_{i+1}``.

Noise-aware variants (docs/math.md §10, ``[baseline.noise]``): steps 2–5 call the run's
:class:`~soc_opt.noise.strategy.NoiseStrategy` (state estimates for the prior, corrected fit,
expansion point, the KL step's model and the new policy's estimator); the defaults are the
paper's method.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Callable

import numpy as np

from .. import lqg
from ..models import LinearGaussianPolicy
from ..noise.estimator import FilteredPolicy
from ..noise.strategy import NoiseStrategy, resolve
from .base import MethodBase
from .config import LQRFLMConfig, with_paper_scale
from .state import PreviousStep, RunState, improved, record, state_rng

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["initial_state", "lqr_flm_iteration", "LQRFLM", "LQR_FLM"]


def initial_state(task: Task, cfg: LQRFLMConfig, seed: int) -> RunState:
    rng = np.random.default_rng(seed)
    return RunState(
        iteration=0,
        policy=task.initial_policy(cfg.init_var),
        mult=1.0,
        prior=None,
        rng_state=rng.bit_generator.state,
    )


_BUDGETS: dict[str, Callable[[LQRFLMConfig, int, float], float | np.ndarray]] = {
    "total": lambda cfg, T, mult: cfg.kl_budget * T * mult,
    "per_step": lambda cfg, T, mult: np.full(T, cfg.kl_budget * mult),
}


def _budget(cfg: LQRFLMConfig, T: int, mult: float):
    """The KL budget of one step: a total ``nu`` or per-step ``(T,)`` budgets (``cfg.kl_mode``)."""
    return _BUDGETS[cfg.kl_mode](cfg, T, mult)


def lqr_flm_iteration(task: Task, cfg: LQRFLMConfig, state: RunState,
                      reference: LinearGaussianPolicy | FilteredPolicy | None = None,
                      phase: str = "baseline", noise: NoiseStrategy | None = None) -> RunState:
    """One LQR-FLM iteration (module docstring, steps 1–5). Pure: returns a new state.

    ``noise``: the run's noise strategy (default: resolved from ``cfg.noise`` for ``task``).
    """
    noise = resolve(task, cfg.noise) if noise is None else noise
    rng = state_rng(state)
    timings = {}
    t0 = time.perf_counter()
    rollouts = task.rollouts(state.policy, cfg.samples, rng, workers=cfg.workers)
    timings["rollouts"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    est = noise.estimate(state.prior, rollouts, cfg.fit, state.policy, rng, previous=state.last_rollouts)
    timings.update(est.timings)
    data = est.data(rollouts)  # what the learner fits on: the measured rollouts unless the estimator says
    dyn = noise.fit(data, cfg.fit, est, state.policy)
    timings["fit"] = time.perf_counter() - t0 - sum(est.timings.values())

    s_bar = noise.expansion_point(data, dyn)
    a_bar = rollouts.a.mean(axis=0)
    cost = task.cost_expansion(s_bar, a_bar)
    local, wrap = noise.lqg_model(dyn, cost, est, f" (iteration {state.iteration})")
    ref = noise.gains(state.policy if reference is None else reference)

    mult = state.mult
    if cfg.adapt_multiplier and state.prev is not None:
        predicted, actual = lqg.laplace_improvements(state.prev.reference, noise.gains(state.policy),
                                                     state.prev.model, local)
        mult = lqg.adapt_multiplier(mult, predicted, actual, cfg.kl)

    t0 = time.perf_counter()
    nu = _budget(cfg, task.T, mult)
    res = lqg.kl_step(local.dynamics, local.cost, ref, nu, local.mu0, local.P0, method=cfg.kl_method, config=cfg.kl)
    timings["lqg"] = time.perf_counter() - t0

    rec = record(
        state.iteration, phase, task, rollouts,
        kl=float(np.sum(res.kl)), nu=float(np.sum(nu)), mult=mult, timings=timings,
        extra={"eta_mean": float(np.mean(res.eta)), "predicted_cost": float(res.expected_cost)},
    )
    return dataclasses.replace(
        state,
        iteration=state.iteration + 1,
        policy=wrap(res.policy),
        mult=mult,
        prior=est.prior,
        rng_state=rng.bit_generator.state,
        history=state.history + (rec,),
        prev=PreviousStep(local, ref),
        best=improved(state.best, float(np.mean(rec.cost)), state.policy, state.iteration),
        last_rollouts=rollouts,
    )



#: Keys of the command-line overrides that set a top-level field of the run configuration; the
#: others set ``baseline``'s.
_TOP_LEVEL = {"i_switch"}


class LQRFLM(MethodBase):
    """LQR-FLM as a :class:`~soc_opt.methods.base.Method`: reads ``[baseline]``."""

    name = "lqr-flm"
    sections: tuple[str, ...] = ("baseline",)
    seeded = True
    sample_based = True
    cost_phase = "baseline"

    def apply_overrides(self, cfg, values: dict, paper: bool):
        if paper:
            cfg = with_paper_scale(cfg)
        base = {k: v for k, v in values.items() if k not in _TOP_LEVEL}
        top = {k: v for k, v in values.items() if k in _TOP_LEVEL}
        return cfg.replace(baseline=cfg.baseline.replace(**base) if base else cfg.baseline, **top)

    def total_iterations(self, cfg) -> int:
        return cfg.baseline.iterations

    def initial_state(self, task: Task, cfg, seed: int) -> RunState:
        return initial_state(task, cfg.baseline, seed)

    def iterate(self, task: Task, cfg, state: RunState) -> RunState:
        return lqr_flm_iteration(task, cfg.baseline, state)

    def progress_fields(self, record) -> dict[str, float]:
        return {"KL": float(record.kl)}

    def progress_line(self, seed: int, where: str, state: RunState, metrics: str, times: str) -> str:
        rec = state.history[-1]
        em = [r for r in state.history if r.em is not None and r.iteration == rec.iteration]
        em_txt = ""
        if em:
            e = em[-1].em
            em_txt = (f" | EM: cost {np.mean(em[-1].cost):.4g}, surrogate {e.surrogate_old:.4g}->{e.surrogate_new:.4g},"
                      f" logp(Y) {e.loglik_old:.4g}->{e.loglik_new:.4g}")
        return (f"[{self.name} seed {seed}] {where} cost {np.mean(rec.cost):10.4g} ± {np.std(rec.cost):.3g}"
                f"  KL {rec.kl:.3g}/{rec.nu:.3g}  {metrics}  {times}{em_txt}")


LQR_FLM = LQRFLM()
