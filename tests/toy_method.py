"""A toy method for tests/test_extension.py: the whole of a new method, with its own settings and its
own saved state, is this file plus one registry line (``soc_opt.plugins.METHODS.register(SHOOT)``, or a
line in ``soc_opt/methods/registry.py``).

"Shoot": each iteration samples ``[shoot] samples`` rollouts of the current policy and moves the
policy's feed-forward term the fraction ``step`` of the way to the mean action of the cheapest
``elite`` fraction of them (gains and covariance unchanged).  It reads only its own ``[shoot]`` table
(:class:`ShootConfig`) and keeps its own state (:class:`ShootState`, which records each round's elite
cost besides what a run directory reads).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from soc_opt.config import Config, Interval
from soc_opt.methods.base import MethodBase
from soc_opt.methods.state import BestPolicy, IterationRecord, improved, record, state_rng
from soc_opt.models import LinearGaussianPolicy, Rollouts


@dataclass(frozen=True)
class ShootConfig(Config):
    """The toy method ``shoot`` (the ``[shoot]`` table of a run configuration).

    iterations: sampling rounds of a run.
    samples:    rollouts per round.
    elite:      the fraction of the cheapest rollouts whose mean action the feed-forward moves to.
    step:       the fraction of the way it moves (1: all the way).
    init_var:   covariance of the initial policy (times ``I``).
    """

    iterations: int = 2
    samples: int = 6
    elite: float = 0.5
    step: float = 1.0
    init_var: float = 1.0

    _constraints = {
        "iterations": [Interval(1)],
        "samples": [Interval(2)],
        "elite": [Interval(0, 1, "right")],
        "step": [Interval(0, 1, "right")],
        "init_var": [Interval(0, None, "neither")],
    }


@dataclass(frozen=True)
class ShootState:
    """The toy method's state: what a run directory reads (``iteration``, ``policy``, ``history``, ``best``,
    ``last_rollouts``), the RNG, and its own ``elite_costs`` (each round's mean elite cost)."""

    iteration: int
    policy: LinearGaussianPolicy
    rng_state: dict
    history: tuple[IterationRecord, ...] = ()
    best: BestPolicy | None = None
    last_rollouts: Rollouts | None = None
    elite_costs: tuple[float, ...] = ()


class Shoot(MethodBase):
    name = "shoot"
    sections = ("shoot",)
    settings = ShootConfig
    state_types = (ShootState,)
    flags = ("iterations", "samples")  # --iterations, --samples set its own table; the others are refused

    def apply_overrides(self, cfg, values: dict, paper: bool):
        return cfg.replace(shoot=cfg.shoot.replace(**values)) if values else cfg

    def total_iterations(self, cfg) -> int:
        return cfg.shoot.iterations

    def initial_state(self, task, cfg, seed: int) -> ShootState:
        rng = np.random.default_rng(seed)
        return ShootState(0, task.initial_policy(cfg.shoot.init_var), rng.bit_generator.state)

    def iterate(self, task, cfg, state: ShootState) -> ShootState:
        s = cfg.shoot
        rng = state_rng(state)
        ro = task.rollouts(state.policy, s.samples, rng)
        rec = record(state.iteration, "baseline", task, ro)
        elite = np.argsort(rec.cost)[: max(1, int(round(s.elite * len(rec.cost))))]
        pol = state.policy
        target = ro.a[elite].mean(axis=0) - np.einsum("tij,mtj->mti", pol.K, ro.s[elite, :-1]).mean(axis=0)
        new = dataclasses.replace(pol, k=pol.k + s.step * (target - pol.k))
        return dataclasses.replace(
            state, iteration=state.iteration + 1, policy=new, rng_state=rng.bit_generator.state,
            history=state.history + (rec,), best=improved(state.best, float(np.mean(rec.cost)), pol, state.iteration),
            last_rollouts=ro, elite_costs=state.elite_costs + (float(rec.cost[elite].mean()),),
        )

    def progress_line(self, seed, where, state, metrics, times) -> str:
        return f"[{self.name} seed {seed}] {where} cost {np.mean(state.history[-1].cost):.4g}  {times}"


SHOOT = Shoot()
