"""LQR-FLM on Gymnasium MuJoCo environments (``gym:<EnvId>`` tasks; docs/gym.md).

``run()`` loads each environment as a task, runs LQR-FLM (docs/math.md §7) for ``iterations``
iterations and reports the mean sampled cost (``-reward`` summed over ``T`` steps, on the
true states) at the first and the last iteration, the best, and the time per iteration.
``soc-opt bench --only gym_envs`` prints the table of docs/gym.md (a few minutes per
environment on one core).
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["ENVS", "QUICK", "run"]

#: The environments of the docs/gym.md table.
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Reacher-v5", "Swimmer-v5", "HalfCheetah-v5", "Hopper-v5")


def run(envs=ENVS, iterations: int = 10, samples: int = 20, seed: int = 0, task_overrides: dict | None = None,
        init_var: float = 0.1, kl_budget: float = 0.5) -> list[dict]:
    """Rows ``{"env", "n", "m", "T", "dt", "cost_first", "cost_last", "cost_best", "return_last",
    "seconds_per_iteration", "reward_evaluations_per_iteration", "error"}``.

    ``task_overrides``: task keys for every environment (e.g. ``{"rho2": 1e-3}``); the default
    task is ``gym:<EnvId>`` as loaded by :func:`soc_opt.tasks.load_task`.  A failing
    environment gives a row with ``error`` set instead of raising.
    """
    from ..methods import registry
    from ..methods.config import DPSOCConfig, LQRFLMConfig
    from ..tasks import load_task

    rows = []
    for env_id in envs:
        row = {"env": env_id}
        try:
            task = load_task(f"gym:{env_id}", overrides=dict(task_overrides or {}))
            row.update(n=task.n, m=task.m, T=task.T, dt=task.dt)
            cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=iterations, samples=samples,
                                                                init_var=init_var, kl_budget=kl_budget))
            t0 = time.perf_counter()
            e0 = task.reward.evaluations
            state = registry.run(task, "lqr-flm", cfg, seed=seed)
            elapsed = time.perf_counter() - t0
            costs = [float(np.mean(r.cost)) for r in state.history]
            row.update(
                cost_first=costs[0], cost_last=costs[-1], cost_best=min(costs),
                return_last=float(state.history[-1].metrics.get("return", np.nan)),
                seconds_per_iteration=elapsed / iterations,
                reward_evaluations_per_iteration=(task.reward.evaluations - e0) / iterations,
                costs=costs, error="",
            )
        except Exception as e:  # a row per environment, failures included (the table documents them)
            row.update(error=f"{type(e).__name__}: {e}")
        rows.append(row)
    return rows


#: ``soc-opt bench --quick``: one environment, 5 steps, 2 iterations of 3 samples (checks the code path).
QUICK = {"envs": ("Reacher-v5",), "iterations": 2, "samples": 3, "task_overrides": {"T": 5}}
