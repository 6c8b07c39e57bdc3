"""A toy method for tests/test_extension.py: the whole of a new method is this file plus one
registry entry (``soc_opt.methods.registry.register`` or a line in ``METHODS``).

"Elite mean": each iteration samples ``baseline.samples`` rollouts of the current policy and
moves the policy's feed-forward term to the mean action of the cheaper half of the samples
(gains and covariance unchanged).  It reads only ``[baseline]``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from soc_opt.methods.base import MethodBase
from soc_opt.methods.lqr_flm import initial_state
from soc_opt.methods.state import RunState, improved, record, state_rng


class EliteMean(MethodBase):
    name = "elite-mean"
    sections = ("baseline",)
    sample_based = True

    def apply_overrides(self, cfg, values: dict, paper: bool):
        return cfg.replace(baseline=cfg.baseline.replace(**values)) if values else cfg

    def total_iterations(self, cfg) -> int:
        return cfg.baseline.iterations

    def initial_state(self, task, cfg, seed: int) -> RunState:
        return initial_state(task, cfg.baseline, seed)

    def iterate(self, task, cfg, state: RunState) -> RunState:
        rng = state_rng(state)
        ro = task.rollouts(state.policy, cfg.baseline.samples, rng)
        rec = record(state.iteration, "baseline", task, ro)
        elite = np.argsort(rec.cost)[: max(1, len(rec.cost) // 2)]
        pol = state.policy
        k = ro.a[elite].mean(axis=0) - np.einsum("tij,mtj->mti", pol.K, ro.s[elite, :-1]).mean(axis=0)
        new = dataclasses.replace(pol, k=k)
        return dataclasses.replace(
            state, iteration=state.iteration + 1, policy=new, rng_state=rng.bit_generator.state,
            history=state.history + (rec,), best=improved(state.best, float(np.mean(rec.cost)), pol, state.iteration),
            last_rollouts=ro,
        )

    def progress_line(self, seed, where, state, metrics, times) -> str:
        return f"[{self.name} seed {seed}] {where} cost {np.mean(state.history[-1].cost):.4g}  {times}"


ELITE_MEAN = EliteMean()
