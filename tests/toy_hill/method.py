"""The toy method ``hill`` as a :class:`soc_opt.methods.base.Method`."""

import dataclasses

import numpy as np

from soc_opt.methods.base import MethodBase
from soc_opt.methods.state import improved, record, state_rng

from .config import HillConfig
from .state import HillState


class Hill(MethodBase):
    name = "hill"
    sections = ("hill",)
    sample_based = True
    settings = HillConfig
    state_types = (HillState,)
    flags = ("iterations",)

    def apply_overrides(self, cfg, values: dict, paper: bool):
        return cfg.replace(**{self.name: cfg.section(self.name).replace(**values)}) if values else cfg

    def total_iterations(self, cfg) -> int:
        return cfg.section(self.name).iterations

    def evaluation_samples(self, cfg) -> int:
        return cfg.evaluation.samples or cfg.section(self.name).samples

    def initial_state(self, task, cfg, seed: int) -> HillState:
        return HillState(0, task.initial_policy(cfg.section(self.name).init_var), np.random.default_rng(seed).bit_generator.state)

    def iterate(self, task, cfg, state: HillState) -> HillState:
        h = cfg.section(self.name)
        rng = state_rng(state)
        pol = state.policy
        move = rng.standard_normal(pol.k.shape)
        trial = dataclasses.replace(pol, k=pol.k + h.radius * move / np.linalg.norm(move))
        ro = task.rollouts(pol, h.samples, rng)
        ro_trial = task.rollouts(trial, h.samples, rng)
        rec = record(state.iteration, "baseline", task, ro)
        better = float(np.mean(task.true_cost(ro_trial).sum(-1))) < float(np.mean(rec.cost))
        return dataclasses.replace(
            state, iteration=state.iteration + 1, policy=trial if better else pol, rng_state=rng.bit_generator.state,
            history=state.history + (rec,), best=improved(state.best, float(np.mean(rec.cost)), pol, state.iteration),
            last_rollouts=ro, kept=state.kept + better,
        )

    def progress_line(self, seed, where, state, metrics, times) -> str:
        return f"[{self.name} seed {seed}] {where} cost {np.mean(state.history[-1].cost):.4g}  kept {state.kept}  {times}"


HILL = Hill()
