"""Model-free RL at a fixed budget of environment steps: stable-baselines3 SAC and PPO.

The environments are soc_opt's own Gymnasium registrations (``soc_opt/Peg-v0``,
``soc_opt/Door-v0``; docs/gym.md): the agent sees the measured state, its reward is minus the
task's stage cost of the measured state, an episode is ``T`` steps.  The budget is counted in
environment steps, the unit in which LQR-FLM / DPSOC-EM spend ``iterations x samples x T``.

Every finished training episode is logged (:class:`EpisodeLog`): the environment steps so far,
``cost_measured`` (sum of the stage costs of the measured states, ``-return``: what the agent
is rewarded with), and the task's own metrics (``cost``: the total cost of the true states, as
the project reports it; ``success_rate`` and ``min_distance`` for peg, ``min_hinge`` for door;
docs/tasks.md).  After
training, the deterministic policy is scored on ``eval_episodes`` fresh episodes (seed
``10000 + seed``, as the project's final evaluations).

Settings (:data:`SETTINGS`): each algorithm's stable-baselines3 defaults, and one tuned setting
stated in full.  Threads: torch and BLAS on one thread (the machine is shared).

Public functions:
    make_env(task, rho2)                                    -> gymnasium.Env
    train(algo, setting, task, rho2, seed, budget, ...)     -> dict (one run)
    steps_to(log_steps, values, threshold, window)          -> int | None
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from . import require

__all__ = ["SETTINGS", "ENV_IDS", "make_env", "train", "steps_to"]

ENV_IDS = {"peg": "soc_opt/Peg-v0", "door": "soc_opt/Door-v0"}

#: ``(algo, setting) -> (constructor keyword arguments, normalise observations and rewards)``.
#: "tuned" (stated): PPO collects 2,000 steps per update (20 episodes, one LQR-FLM iteration),
#: minibatches of 100, and VecNormalize on observations and rewards; SAC starts learning after
#: 1,000 steps (not 100), gamma 0.98 (5 s horizon of 100 steps), learning rate 1e-3 and
#: VecNormalize on observations.
SETTINGS: dict[tuple[str, str], tuple[dict, dict | None]] = {
    ("ppo", "default"): ({}, None),
    ("ppo", "tuned"): ({"n_steps": 2000, "batch_size": 100, "gae_lambda": 0.95, "ent_coef": 0.0},
                       {"norm_obs": True, "norm_reward": True}),
    ("sac", "default"): ({}, None),
    ("sac", "tuned"): ({"learning_starts": 1000, "gamma": 0.98, "learning_rate": 1e-3},
                       {"norm_obs": True, "norm_reward": False}),
}


def make_env(task: str, rho2: float):
    """``soc_opt/<Task>-v0`` with the task's ``rho2`` replaced (everything else as the task's TOML).

    The env's ``info["episode"]`` (the finished episode's arrays) is renamed
    ``info["soc_opt_episode"]``: stable-baselines3 reads ``info["episode"]`` as its Monitor's
    ``{"r", "l", "t"}`` record and fails on anything else.
    """
    import gymnasium

    import soc_opt.envs  # noqa: F401  (registers the ids)

    if task not in ENV_IDS:
        raise ValueError(f"unknown RL task {task!r}; choose from {sorted(ENV_IDS)}")

    class _RenameEpisode(gymnasium.Wrapper):
        def step(self, action):
            obs, r, term, trunc, info = self.env.step(action)
            if "episode" in info:
                info["soc_opt_episode"] = info.pop("episode")
            return obs, r, term, trunc, info

    return _RenameEpisode(gymnasium.make(ENV_IDS[task], overrides={"rho2": float(rho2)}))


def _callback_class():
    BaseCallback = require("stable_baselines3.common.callbacks").BaseCallback

    class EpisodeLog(BaseCallback):
        """Records ``(steps, cost, metrics)`` at the end of every training episode."""

        def __init__(self, partial: str | None = None, header: dict | None = None, evaluate=None,
                     eval_at: tuple[int, ...] = ()):
            super().__init__()
            self.rows: list[dict] = []
            self.evals: list[dict] = []
            self._cost = 0.0
            self._partial, self._header = partial, header or {}
            self._evaluate, self._eval_at = evaluate, sorted(int(s) for s in eval_at)
            self._t0 = time.perf_counter()

        def _on_training_start(self) -> None:
            self._t0 = time.perf_counter()

        def _on_step(self) -> bool:
            info = self.locals["infos"][0]
            self._cost += float(info.get("stage_cost", 0.0))
            if "metrics" in info:
                self.rows.append({"steps": int(self.num_timesteps), "cost_measured": self._cost,
                                  **{k: float(v) for k, v in info["metrics"].items()}})
                self._cost = 0.0
                while self._eval_at and self.num_timesteps >= self._eval_at[0]:
                    # the deterministic policy as it is at this budget (between episodes; SB3 updates
                    # PPO only after n_steps, so at an episode end the policy is the one trained so far)
                    row = {"steps": int(self.num_timesteps), "budget": self._eval_at.pop(0),
                           "wall_s": time.perf_counter() - self._t0}
                    self.evals.append({**row, **self._evaluate(self.model)})
                if self._partial is not None and len(self.rows) % 10 == 0:
                    Path(self._partial).write_text(json.dumps({**self._header, "partial": True,
                                                               "episodes": self.rows}))
            return True

    return EpisodeLog


def _evaluate(model, task: str, rho2: float, seed: int, episodes: int, vecnorm) -> dict:
    env = make_env(task, rho2)
    rows = []
    for e in range(episodes):
        obs, _ = env.reset(seed=10000 + seed + 1000 * e)
        cost, done, info = 0.0, False, {}
        while not done:
            o = vecnorm.normalize_obs(obs[None]) if vecnorm is not None else obs[None]
            action, _ = model.predict(o, deterministic=True)
            obs, _, _, done, info = env.step(action[0])
            cost += info["stage_cost"]
        rows.append({"cost_measured": cost, **{k: float(v) for k, v in info["metrics"].items()}})
    env.close()
    keys = rows[0].keys()
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}


def train(algo: str, setting: str, task: str, rho2: float, seed: int, budget: int,
          eval_episodes: int = 20, partial: str | None = None, eval_at: tuple[int, ...] = ()) -> dict:
    """Train one agent for ``budget`` environment steps; returns the log and the evaluation.

    Keys: ``algo, setting, task, rho2, seed, budget, wall_s, steps_per_s, episodes`` (list of
    per-episode rows: ``steps, cost_measured`` and the task's metrics, ``cost`` among them) and
    ``final`` (mean of the deterministic policy's ``eval_episodes`` episodes, same keys).
    ``partial``: a file rewritten every 10 episodes with the log so far (a run cut short by a
    time limit still leaves its learning curve).  ``eval_at``: smaller budgets (environment steps)
    at which the deterministic policy is also scored, at the first episode end at or after each
    (key ``evals``: one row per budget, ``steps``, ``budget`` and the ``final`` keys); with the
    constant learning rates of every setting here, a run's first ``b`` steps are those of a run
    of budget ``b``, so one long run gives both budgets.
    """
    torch = require("torch")
    sb3 = require("stable_baselines3")
    vec = require("stable_baselines3.common.vec_env")
    torch.set_num_threads(1)
    if (algo, setting) not in SETTINGS:
        raise ValueError(f"unknown RL setting {(algo, setting)!r}; choose from {sorted(SETTINGS)}")
    kwargs, norm = SETTINGS[(algo, setting)]
    monitor = require("stable_baselines3.common.monitor")
    venv = vec.DummyVecEnv([lambda: monitor.Monitor(make_env(task, rho2))])
    venv.seed(seed)
    if norm is not None:
        venv = vec.VecNormalize(venv, gamma=kwargs.get("gamma", 0.99), **norm)
    cls = {"ppo": sb3.PPO, "sac": sb3.SAC}[algo]
    model = cls("MlpPolicy", venv, seed=seed, device="cpu", verbose=0, **kwargs)
    header = {"algo": algo, "setting": setting, "task": task, "rho2": float(rho2), "seed": int(seed),
              "budget": int(budget)}
    vecnorm = venv if norm is not None else None

    def evaluate(model):
        if vecnorm is not None:
            vecnorm.training = False
        try:
            return _evaluate(model, task, rho2, seed, eval_episodes, vecnorm)
        finally:
            if vecnorm is not None:
                vecnorm.training = True

    log = _callback_class()(partial, header, evaluate, tuple(b for b in eval_at if b < budget))
    t0 = time.perf_counter()
    model.learn(total_timesteps=int(budget), callback=log)
    wall = time.perf_counter() - t0
    if vecnorm is not None:
        vecnorm.training = False
    final = _evaluate(model, task, rho2, seed, eval_episodes, vecnorm)
    return {"algo": algo, "setting": setting, "task": task, "rho2": float(rho2), "seed": int(seed),
            "budget": int(budget), "wall_s": wall, "steps_per_s": budget / wall, "episodes": log.rows,
            "evals": log.evals, "final": final}


def steps_to(log_steps, values, threshold: float = 0.9, window: int = 20) -> int | None:
    """Environment steps at which the mean of the last ``window`` episodes' ``values`` first
    reaches ``threshold`` (None: never).  ``window = 20`` is one LQR-FLM iteration's batch."""
    v = np.asarray(values, dtype=float)
    for i in range(window - 1, len(v)):
        if v[i - window + 1:i + 1].mean() >= threshold:
            return int(log_steps[i])
    return None
