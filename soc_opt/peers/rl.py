"""Model-free RL at a fixed budget of environment steps: SAC, CrossQ and PPO.

Backends: stable-baselines3 (``"sb3"``: SAC, PPO) and sbx-rl (``"sbx"``: stable-baselines3's API
in JAX; SAC and CrossQ), chosen per run (:data:`ALGOS`).  The environments are soc_opt's own
Gymnasium registrations (``soc_opt/Peg-v0``, ``soc_opt/Door-v0``; docs/gym.md): the agent sees the
measured state, its reward is minus the task's stage cost of the measured state, an episode is
``T`` steps.  The budget is counted in environment steps, the unit in which LQR-FLM / DPSOC-EM
spend ``iterations x samples x T``.

Every finished training episode is logged (``episodes``): the environment steps so far,
``cost_measured`` (sum of the stage costs of the measured states, ``-return``: what the agent
is rewarded with), and the task's own metrics (``cost``: the total cost of the true states, as
the project reports it; ``success_rate`` and ``min_distance`` for peg, ``min_hinge`` for door;
docs/tasks.md).  After training the final policy is scored on ``eval_episodes`` fresh episodes
(seeds ``10000 + seed + 1000 e``) twice: with its mean action (``final``; stable-baselines3's
``deterministic=True``) and sampled (``final_sampled``).

Off-policy runs (SAC, CrossQ) are resumable: with ``checkpoint`` a directory, the model, the
filled part of the replay buffer, the observation normaliser and the log so far are saved there
every ``checkpoint_every`` episodes, and a later call with the same directory continues from the
last checkpoint (a killed run loses at most ``checkpoint_every`` episodes).

Settings (:data:`SETTINGS`): each algorithm's defaults, and one tuned setting stated in full.
Threads: torch, XLA and BLAS on one thread (the machine is shared).

Public functions:
    make_env(task, rho2)                                    -> gymnasium.Env
    train(algo, setting, task, rho2, seed, budget, ...)     -> dict (one run)
    steps_to(log_steps, values, threshold, window)          -> int | None
"""

from __future__ import annotations

import json
import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import require

__all__ = ["ALGOS", "SETTINGS", "ENV_IDS", "OFF_POLICY", "make_env", "train", "steps_to"]

#: ``(algo, backend) -> (module, class)``: the implementation of each algorithm per backend.
ALGOS = {
    ("sac", "sb3"): ("stable_baselines3", "SAC"),
    ("ppo", "sb3"): ("stable_baselines3", "PPO"),
    ("sac", "sbx"): ("sbx", "SAC"),
    ("crossq", "sbx"): ("sbx", "CrossQ"),
}

#: the algorithms with a replay buffer: the resumable ones.
OFF_POLICY = ("sac", "crossq")

ENV_IDS = {"peg": "soc_opt/Peg-v0", "door": "soc_opt/Door-v0"}

#: ``(algo, setting) -> (constructor keyword arguments, normalise observations and rewards)``, the
#: same for either backend; CrossQ: sbx-rl's defaults.
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
    ("crossq", "default"): ({}, None),
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
        """Records ``(steps, cost, metrics)`` at the end of every training episode; every 10 episodes
        rewrites ``partial``; every ``every`` episodes calls ``save`` (a checkpoint) and, after a
        checkpoint at or past ``stop_at`` steps or the wall-clock ``deadline``, stops learning.

        The checkpoint is taken when the next rollout starts: by then stable-baselines3 has stored
        the episode's last transition and made the gradient step that follows it, so the saved
        state is the whole state between two environment steps.  Stopping discards the one step
        taken after it (neither stored nor counted in the checkpoint)."""

        def __init__(self, partial: str | None = None, header: dict | None = None, evaluate=None,
                     eval_at: tuple[int, ...] = (), rows=(), evals=(), save=None, every: int = 10,
                     stop_at: int | None = None, deadline: float | None = None):
            super().__init__()
            self.rows: list[dict] = list(rows)
            self.evals: list[dict] = list(evals)
            self._cost = 0.0
            self._partial, self._header = partial, header or {}
            self._evaluate = evaluate
            self._eval_at = sorted(int(s) for s in eval_at if all(int(s) != e["budget"] for e in evals))
            self._save, self._every, self._stop_at, self._deadline = save, int(every), stop_at, deadline
            self.stopped = self._due = False
            self._t0 = time.perf_counter()

        def _on_training_start(self) -> None:
            self._t0 = time.perf_counter()

        def elapsed(self) -> float:
            return time.perf_counter() - self._t0

        def _on_rollout_start(self) -> None:
            if not self._due:
                return
            self._due = False
            self._save(self.model, self)
            late = self._deadline is not None and time.time() >= self._deadline
            self.stopped = late or (self._stop_at is not None and self.num_timesteps >= self._stop_at)

        def _on_step(self) -> bool:
            if self.stopped:
                return False
            info = self.locals["infos"][0]
            self._cost += float(info.get("stage_cost", 0.0))
            if "metrics" not in info:
                return True
            self.rows.append({"steps": int(self.num_timesteps), "cost_measured": self._cost,
                              **{k: float(v) for k, v in info["metrics"].items()}})
            self._cost = 0.0
            while self._eval_at and self.num_timesteps >= self._eval_at[0]:
                # the policy as it is at this budget (between episodes; SB3 updates PPO only after
                # n_steps, so at an episode end the policy is the one trained so far)
                row = {"steps": int(self.num_timesteps), "budget": self._eval_at.pop(0),
                       "wall_s": self._header.get("wall_before_s", 0.0) + self.elapsed()}
                # scored like the final policy: with its mean action, and sampled;
                # the sampled score draws from the learner's generators, so it runs on a copy of
                # their state and the run goes on with the stream it would have had without it
                with _rng_kept(self.model):
                    sampled = self._evaluate(self.model, deterministic=False)
                self.evals.append({**row, **self._evaluate(self.model), "sampled": sampled})
            if self._partial is not None and len(self.rows) % 10 == 0:
                Path(self._partial).write_text(json.dumps({**self._header, "partial": True,
                                                           "episodes": self.rows, "evals": self.evals}))
            self._due = self._save is not None and len(self.rows) % self._every == 0
            return True

    return EpisodeLog


@contextmanager
def _rng_kept(model):
    """Run the body with the learner's random generators (torch's, and sbx-rl's policy keys) restored
    afterwards: a sampled evaluation in the middle of a run leaves the run's random stream alone."""
    import torch

    pol = getattr(model, "policy", None)
    keys = {k: getattr(pol, k) for k in ("key", "noise_key") if hasattr(pol, k)}
    with torch.random.fork_rng(devices=[]):
        try:
            yield
        finally:
            for k, v in keys.items():
                setattr(pol, k, v)


def _evaluate(model, task: str, rho2: float, seed: int, episodes: int, vecnorm, deterministic: bool = True) -> dict:
    """Mean over ``episodes`` fresh episodes (seeds ``10000 + seed + 1000 e``) of the policy with its
    mean action (``deterministic``) or sampled."""
    env = make_env(task, rho2)
    rows = []
    for e in range(episodes):
        obs, _ = env.reset(seed=10000 + seed + 1000 * e)
        cost, done, info = 0.0, False, {}
        while not done:
            o = vecnorm.normalize_obs(obs[None]) if vecnorm is not None else obs[None]
            action, _ = model.predict(o, deterministic=deterministic)
            obs, _, _, done, info = env.step(action[0])
            cost += info["stage_cost"]
        rows.append({"cost_measured": cost, **{k: float(v) for k, v in info["metrics"].items()}})
    env.close()
    keys = rows[0].keys()
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}


def _buffer_arrays(buf) -> dict:
    """The filled rows of every per-transition array of a stable-baselines3 replay buffer."""
    n = buf.buffer_size if buf.full else buf.pos
    return {k: v[:n] for k, v in vars(buf).items() if isinstance(v, np.ndarray) and v.shape[:1] == (buf.buffer_size,)}


def _restore_buffer(buf, path: Path) -> None:
    with np.load(path) as z:
        for k in z.files:
            if k not in ("pos", "full"):
                getattr(buf, k)[:len(z[k])] = z[k]
        buf.pos, buf.full = int(z["pos"]), bool(z["full"])


def _write_checkpoint(root: Path, model, vecnorm, state: dict) -> None:
    """``root/step-<N>/`` (model, replay buffer, normaliser), then ``root/latest.json`` (the log and
    the directory's name) replaced atomically, then older step directories removed: a kill at any
    point leaves the previous or the new checkpoint whole."""
    name = f"step-{state['steps']}"
    d = root / name
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    model.save(d / "model.zip")
    np.savez(d / "buffer.npz", pos=model.replay_buffer.pos, full=model.replay_buffer.full,
             **_buffer_arrays(model.replay_buffer))
    if vecnorm is not None:
        vecnorm.save(str(d / "vecnormalize.pkl"))
    tmp = root / "latest.json.tmp"
    tmp.write_text(json.dumps({**state, "dir": name}))
    os.replace(tmp, root / "latest.json")
    for old in root.glob("step-*"):
        if old.name != name:
            shutil.rmtree(old, ignore_errors=True)


def _read_checkpoint(root: Path | None, header: dict) -> dict | None:
    """The last checkpoint's state (None: none), after checking it is of the same run."""
    if root is None or not (root / "latest.json").exists():
        return None
    state = json.loads((root / "latest.json").read_text())
    mine = {k: header[k] for k in ("algo", "backend", "setting", "task", "rho2", "seed")}
    theirs = {k: state.get(k) for k in mine}
    if mine != theirs:
        raise ValueError(f"checkpoint {root} is of another run: {theirs} (this run: {mine})")
    if state["steps"] > header["budget"]:
        raise ValueError(f"checkpoint {root} is at {state['steps']} steps, past this run's budget {header['budget']}")
    return state


def train(algo: str, setting: str, task: str, rho2: float, seed: int, budget: int,
          eval_episodes: int = 20, partial: str | None = None, eval_at: tuple[int, ...] = (),
          backend: str = "sb3", checkpoint: str | Path | None = None, checkpoint_every: int = 10,
          stop_at: int | None = None, deadline: float | None = None) -> dict:
    """Train one agent for ``budget`` environment steps (or resume it); returns the log and the evaluation.

    Keys: ``algo, backend, setting, task, rho2, seed, budget, wall_s`` (training, summed over the
    sessions of a resumed run), ``steps_per_s``, ``eval_wall_s``, ``episodes`` (list of per-episode
    rows: ``steps, cost_measured`` and the task's metrics, ``cost`` among them), ``final`` (mean of
    the policy's ``eval_episodes`` episodes with its mean action, same keys), ``final_sampled`` (the
    same, actions sampled) and ``resumed_at`` (the steps each later session started from).
    ``partial``: a file rewritten every 10 episodes with the log so far (a run cut short by a
    time limit still leaves its learning curve).  ``eval_at``: smaller budgets (environment steps)
    at which the policy is also scored, at the first episode end at or after each (key ``evals``:
    one row per budget, ``steps``, ``budget``, the ``final`` keys (mean action) and ``sampled``
    (the ``final_sampled`` keys)); with the
    constant learning rates of every setting here, a run's first ``b`` steps are those of a run
    of budget ``b``, so one long run gives both budgets.

    ``checkpoint`` (SAC, CrossQ): directory of the checkpoints, written every ``checkpoint_every``
    episodes; a run whose directory holds one continues from it (same algorithm, backend, setting,
    task, rho2 and seed; the budget may be larger, which extends a finished run).  A resumed session
    reseeds the environment and the learner with ``seed + steps``: a resumed run is reproducible
    but not the uninterrupted run's random stream.  ``stop_at`` (steps) and ``deadline``
    (``time.time()``): stop after the first checkpoint at or past them and return the log so far
    with ``partial: True`` and no evaluation.
    """
    if (algo, backend) not in ALGOS:
        raise ValueError(f"unknown RL algorithm {(algo, backend)!r}; choose from {sorted(ALGOS)}")
    if (algo, setting) not in SETTINGS:
        raise ValueError(f"unknown RL setting {(algo, setting)!r}; choose from {sorted(SETTINGS)}")
    if checkpoint is not None and algo not in OFF_POLICY:
        raise ValueError(f"checkpoints are for the off-policy algorithms {OFF_POLICY}, not {algo!r} "
                         "(its rollout buffer is not saved)")
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    torch = require("torch")
    torch.set_num_threads(1)
    vec = require("stable_baselines3.common.vec_env")
    monitor = require("stable_baselines3.common.monitor")
    module, name = ALGOS[(algo, backend)]
    cls = getattr(require(module), name)
    kwargs, norm = SETTINGS[(algo, setting)]
    header = {"algo": algo, "backend": backend, "setting": setting, "task": task, "rho2": float(rho2),
              "seed": int(seed), "budget": int(budget)}
    root = None if checkpoint is None else Path(checkpoint)
    state = _read_checkpoint(root, header)
    steps0 = 0 if state is None else int(state["steps"])
    venv = vec.DummyVecEnv([lambda: monitor.Monitor(make_env(task, rho2))])
    venv.seed(seed + steps0)
    if state is None:
        if norm is not None:
            venv = vec.VecNormalize(venv, gamma=kwargs.get("gamma", 0.99), **norm)
        model = cls("MlpPolicy", venv, seed=seed, device="cpu", verbose=0, **kwargs)
    else:
        d = root / state["dir"]
        if norm is not None:
            venv = vec.VecNormalize.load(str(d / "vecnormalize.pkl"), venv)
        model = cls.load(d / "model.zip", env=venv, device="cpu")
        model.set_random_seed(seed + steps0)
        _restore_buffer(model.replay_buffer, d / "buffer.npz")
    vecnorm = venv if norm is not None else None
    wall_before = 0.0 if state is None else float(state["wall_s"])
    resumed_at = [] if state is None else [*state.get("resumed_at", []), steps0]
    header["wall_before_s"] = wall_before

    def evaluate(model, deterministic=True):
        if vecnorm is not None:
            vecnorm.training = False
        try:
            return _evaluate(model, task, rho2, seed, eval_episodes, vecnorm, deterministic)
        finally:
            if vecnorm is not None:
                vecnorm.training = True

    def save(model, log):
        _write_checkpoint(root, model, vecnorm, {**header, "steps": int(model.num_timesteps),
                                                "wall_s": wall_before + log.elapsed(), "resumed_at": resumed_at,
                                                "episodes": log.rows, "evals": log.evals})

    log = _callback_class()(partial, header, evaluate, tuple(b for b in eval_at if b < budget),
                            rows=() if state is None else state["episodes"],
                            evals=() if state is None else state["evals"],
                            save=None if root is None else save, every=checkpoint_every,
                            stop_at=stop_at, deadline=deadline)
    if steps0 < budget:
        model.learn(total_timesteps=int(budget) - steps0, callback=log, reset_num_timesteps=state is None)
    wall = wall_before + (log.elapsed() if steps0 < budget else 0.0)
    base = {k: v for k, v in header.items() if k != "wall_before_s"}
    steps = int(model.num_timesteps) - int(log.stopped)  # a stop discards the step after the checkpoint
    if log.stopped and steps < budget:
        return {**base, "partial": True, "steps": steps, "wall_s": wall, "resumed_at": resumed_at,
                "episodes": log.rows, "evals": log.evals}
    if root is not None and not (root / f"step-{steps}").exists():
        save(model, log)  # the finished run's last state (a larger budget extends it)
    if vecnorm is not None:
        vecnorm.training = False
    t0 = time.perf_counter()
    final = _evaluate(model, task, rho2, seed, eval_episodes, vecnorm, deterministic=True)
    final_sampled = _evaluate(model, task, rho2, seed, eval_episodes, vecnorm, deterministic=False)
    return {**base, "steps": steps, "wall_s": wall, "steps_per_s": steps / wall if wall > 0 else float("nan"),
            "eval_wall_s": time.perf_counter() - t0, "resumed_at": resumed_at, "episodes": log.rows,
            "evals": log.evals, "final": final, "final_sampled": final_sampled}


def steps_to(log_steps, values, threshold: float = 0.9, window: int = 20) -> int | None:
    """Environment steps at which the mean of the last ``window`` episodes' ``values`` first
    reaches ``threshold`` (None: never).  ``window = 20`` is one LQR-FLM iteration's batch."""
    v = np.asarray(values, dtype=float)
    for i in range(window - 1, len(v)):
        if v[i - window + 1:i + 1].mean() >= threshold:
            return int(log_steps[i])
    return None
