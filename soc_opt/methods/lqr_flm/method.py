"""LQR-FLM as a :class:`~soc_opt.methods.base.Method` (docs/math.md §7): reads ``[baseline]``
(:class:`~soc_opt.methods.lqr_flm.config.LQRFLMConfig`); one iteration is
:func:`~soc_opt.methods.lqr_flm.iteration.lqr_flm_iteration`."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ...noise.strategy import strategy_class
from ..base import MethodBase
from ..state import RunState
from .config import with_paper_scale
from .iteration import final_policy, initial_state, lqr_flm_iteration

if TYPE_CHECKING:
    from ...tasks import Task

__all__ = ["LQRFLM", "LQR_FLM"]


class LQRFLM(MethodBase):
    """LQR-FLM: the sample-based baseline; its history rows hold the KL step's ``kl``, ``nu``, ``mult`` and,
    with step acceptance, the verdict's columns (``test_cost``, ``accepted``, ...)."""

    name = "lqr-flm"
    sections: tuple[str, ...] = ("baseline",)
    seeded = True
    sample_based = True
    cost_phase = "baseline"
    flags: tuple[str, ...] = ("iterations", "samples", "workers", "as_written", "paper")

    def apply_overrides(self, cfg, values: dict, paper: bool):
        """``--paper`` (:func:`~soc_opt.methods.lqr_flm.config.with_paper_scale`), ``--as-written`` (acceptance off:
        the paper's step rule, docs/math.md §12), ``i_switch`` at the top level, the rest in ``[baseline]``."""
        if paper:
            cfg = with_paper_scale(cfg)
        values = dict(values)
        if values.pop("as_written", False):
            values["acceptance"] = cfg.baseline.acceptance.replace(enabled=False)
        top = {k: values.pop(k) for k in ("i_switch",) if k in values}
        return cfg.replace(baseline=cfg.baseline.replace(**values) if values else cfg.baseline, **top)

    def total_iterations(self, cfg) -> int:
        return cfg.baseline.iterations

    def check_task(self, task: Task, cfg=None) -> None:
        """With ``cfg``: the state estimator of ``[baseline.noise]`` can model ``task``
        (:meth:`~soc_opt.noise.strategy.NoiseStrategy.check_task`)."""
        if cfg is not None:
            noise = cfg.baseline.noise
            strategy_class(noise.estimator).check_task(task, noise)

    def initial_state(self, task: Task, cfg, seed: int) -> RunState:
        return initial_state(task, cfg.baseline, seed)

    def iterate(self, task: Task, cfg, state: RunState) -> RunState:
        return lqr_flm_iteration(task, cfg.baseline, state)

    def final_policy(self, cfg, state: RunState):
        return final_policy(cfg.baseline, state)

    def final_label(self, cfg, state: RunState, policy) -> str:
        acc = state.accepted
        if acc is not None and policy is acc.policy:
            return f"the last accepted policy (iteration {acc.iteration})"
        return "the last iterate"

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
        verdict = ""
        if "accepted" in rec.extra:
            verdict = ("  accepted" if rec.extra["accepted"] else
                       f"  REJECTED (back to iteration {int(rec.extra['accepted_iteration'])}, mult {rec.mult:.3g})")
        return (f"[{self.name} seed {seed}] {where} cost {np.mean(rec.cost):10.4g} ± {np.std(rec.cost):.3g}"
                f"  KL {rec.kl:.3g}/{rec.nu:.3g}  {metrics}  {times}{verdict}{em_txt}")


LQR_FLM = LQRFLM()
