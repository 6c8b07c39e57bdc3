"""Steps per second of the soc_opt Gymnasium environments under random actions (docs/gym.md).

``run()`` makes each environment with ``gymnasium.make`` (the wrappers an RL library sees),
draws ``steps`` actions from its action space (seeded, before the clock starts), runs
``warmup`` steps, then times ``repeats`` runs of ``steps`` steps each (``reset`` at
truncation, every ``T`` steps, included) and reports the median and the range.  One process,
one thread of Python; ``soc-opt bench --only env_steps`` prints the table of
docs/results/peers/README.md ("Environment throughput").
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["ENV_IDS", "QUICK", "run"]

#: The environments measured by default.
ENV_IDS = ("soc_opt/Peg-v0", "soc_opt/Linear2d-v0")

#: ``soc-opt bench --quick``: one short run of each environment (checks the code path).
QUICK = {"steps": 60, "warmup": 10, "repeats": 1}


def _drive(env, actions, seed: int) -> float:
    """Seconds to take ``actions`` in ``env`` from a reset with ``seed``, resetting at truncation."""
    t0 = time.perf_counter()
    env.reset(seed=seed)
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    return time.perf_counter() - t0


def run(env_ids=ENV_IDS, steps: int = 5000, warmup: int = 1000, repeats: int = 5, seed: int = 0,
        T: int | None = None) -> list[dict]:
    """Rows ``{"env", "T", "steps", "repeats", "median_steps_per_s", "min_steps_per_s", "max_steps_per_s"}``.

    ``T``: every task's horizon instead of its own (a per-step cost that grows with ``T`` shows).
    """
    from .. import envs as _envs  # registers the soc_opt ids

    rows = []
    for env_id in env_ids:
        env = _envs.make(env_id) if T is None else _envs.make(env_id, overrides={"T": int(T)})
        env.action_space.seed(seed)
        actions = [env.action_space.sample() for _ in range(steps)]
        _drive(env, actions[:warmup], seed)
        rates = np.array([steps / _drive(env, actions, seed + 1 + r) for r in range(repeats)])
        rows.append({"env": env_id, "T": int(env.unwrapped.task.T), "steps": steps, "repeats": repeats,
                     "median_steps_per_s": float(np.median(rates)), "min_steps_per_s": float(rates.min()),
                     "max_steps_per_s": float(rates.max())})
        env.close()
    return rows


if __name__ == "__main__":
    import sys

    for row in run(T=int(sys.argv[1]) if len(sys.argv) > 1 else None):
        print(f"{row['env']:>22s} (T = {row['T']}): median {row['median_steps_per_s']:8.0f} steps/s "
              f"(range {row['min_steps_per_s']:.0f}-{row['max_steps_per_s']:.0f}, {row['repeats']} x {row['steps']} steps)")
