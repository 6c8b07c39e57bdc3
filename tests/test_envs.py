"""soc_opt tasks as Gymnasium environments (soc_opt.envs; docs/gym.md).

Oracles: Gymnasium's own environment checker, and the task's vectorised
``Task.rollouts`` (an independent code path) for what an episode must produce.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import soc_opt.envs as envs
from soc_opt.config import ConfigError
from soc_opt.models import LinearGaussianPolicy
from soc_opt.tasks import load_task

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("env_id", ["soc_opt/Linear2d-v0", "soc_opt/Peg-v0", "soc_opt/Door-v0"])
def test_gymnasium_env_checker_passes(env_id, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "disabled")  # in-process GL is tested in a subprocess below
    env = gym.make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker's advice on unbounded / non-normalised boxes
        check_env(env.unwrapped)
    env.close()


def _open_loop(task, u):
    T, m, n = task.T, task.m, task.n
    return LinearGaussianPolicy(np.zeros((T, m, n)), u, np.zeros((T, m, m)), allow_singular=True)


def _episode(env, seed, actions):
    obs, info = env.reset(seed=seed)
    s, x, r, infos = [obs], [info["true_state"]], [], []
    for k, a in enumerate(actions):
        obs, rew, term, trunc, info = env.step(a)
        assert not term
        assert trunc == (k == len(actions) - 1)
        s.append(obs)
        x.append(info["true_state"])
        r.append(rew)
        infos.append(info)
    return np.array(s), np.array(x), np.array(r), infos


#: ``[process_noise]`` of the tasks (docs/math.md §8.1): a start range and actuation noise, both drawn by
#: ``reset`` after ``eps`` and ``w`` as the rollouts draw them.
PROCESS = {"start": 0.1, "actuation": 0.3}


@pytest.mark.parametrize("process", [None, PROCESS])
@pytest.mark.parametrize("name", ["linear2d", "peg", "door"])
def test_seeded_episode_equals_seeded_rollout_of_the_same_actions(name, process):
    task = load_task(name, overrides={"T": 25} | ({"process_noise": process} if process else {}))
    rng = np.random.default_rng(3)
    lo = np.maximum(envs.SocOptEnv(task).action_space.low, -3.0)
    hi = np.minimum(envs.SocOptEnv(task).action_space.high, 3.0)
    u = rng.uniform(lo, hi, size=(task.T, task.m))
    ro = task.rollouts(_open_loop(task, u), 1, np.random.default_rng(11))
    env = envs.SocOptEnv(task)
    s, x, r, infos = _episode(env, 11, u)
    np.testing.assert_array_equal(x, ro.x[0])
    np.testing.assert_array_equal(s, ro.s[0])
    np.testing.assert_array_equal(r, -ro.cost[0])
    assert infos[-1]["metrics"] == task.metrics(ro)
    np.testing.assert_array_equal(infos[-1]["episode"]["a"], ro.a[0])
    # measured observations: the noise is there and has the configured variance scale
    assert task.rho2 > 0 and not np.array_equal(s, x)
    if process:  # the start is not the nominal one, and the plant's control is not the recorded action
        assert not np.array_equal(x[0], task.x0)
        assert not np.array_equal(x, task.rollouts(_open_loop(task, u), 1, np.random.default_rng(0), noise=False).x[0])


@pytest.mark.parametrize("process", [None, PROCESS])
@pytest.mark.parametrize("name", ["linear2d", "door"])
def test_closed_loop_episode_reproduces_a_stochastic_policy_rollout(name, process):
    """Driving the env with a linear-Gaussian policy on its observations, with the policy noise
    ``w`` taken from the same draw, reproduces ``Task.rollouts`` of that policy (also with a start
    range and actuation noise, which ``reset`` draws after ``w``)."""
    task = load_task(name, overrides={"T": 20} | ({"process_noise": process} if process else {}))
    rng = np.random.default_rng(0)
    T, m, n = task.T, task.m, task.n
    K = 0.05 * rng.standard_normal((T, m, n))
    pol = LinearGaussianPolicy(K, rng.standard_normal((T, m)), np.broadcast_to(0.3 * np.eye(m), (T, m, m)).copy())
    ro = task.rollouts(pol, 1, np.random.default_rng(7))
    w = task.draw_noise(1, np.random.default_rng(7)).w[0]
    env = envs.SocOptEnv(task)
    obs, _ = env.reset(seed=7)
    S, A = [obs], []
    for k in range(T):
        a = pol.K[k] @ obs + pol.k[k] + pol.chol[k] @ w[k]
        obs, *_ = env.step(a)
        S.append(obs)
        A.append(a)
    np.testing.assert_allclose(np.array(A), ro.a[0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.array(S), ro.s[0], rtol=1e-10, atol=1e-12)


def test_unseeded_reset_continues_the_seeded_stream():
    task = load_task("linear2d", overrides={"T": 10})
    u = np.ones((task.T, task.m))
    env = envs.SocOptEnv(task)
    _episode(env, 5, u)
    s2, x2, _, _ = _episode(env, None, u)
    rng = np.random.default_rng(5)
    task.draw_noise(1, rng)  # the first episode's draw
    ro = task.rollouts(_open_loop(task, u), 1, rng)
    np.testing.assert_array_equal(s2, ro.s[0])
    np.testing.assert_array_equal(x2, ro.x[0])


def _whole_episode_cost_env(name, overrides=None):
    """The environment as it was before issue 35: each step charged ``task.cost`` evaluated on the
    whole episode so far (``(1, T+1, n)`` states and ``(1, T, m)`` actions, zeros after step ``k``),
    entry ``k``.  Built by replacing its task's ``stage_cost`` with that evaluation."""
    task = load_task(name, overrides=overrides)
    env = envs.SocOptEnv(task)
    task.stage_cost = lambda s_k, a_k, k: float(task.cost(env._s, env._a)[0, k])
    return env


def _assert_same_step(new, old):
    """Observation, reward, flags and info of two ``step`` (or ``reset``) results, bit for bit."""
    assert len(new) == len(old)
    for a, b in zip(new[:-1], old[:-1]):
        assert type(a) is type(b) and np.array_equal(a, b), (a, b)
    info, ref = new[-1], old[-1]
    assert set(info) == set(ref)
    for key in info:
        if key == "episode":
            assert set(info[key]) == set(ref[key]) and all(np.array_equal(info[key][f], ref[key][f]) for f in ref[key])
        elif key == "metrics":
            assert info[key] == ref[key]
        else:
            assert type(info[key]) is type(ref[key]) and np.array_equal(info[key], ref[key]), key


@pytest.mark.parametrize("name, rho2", [("linear2d", None), ("peg", 0.0), ("peg", 0.1), ("door", 0.0), ("door", 0.1)])
def test_o1_step_rewards_and_episodes_equal_the_whole_episode_cost_evaluation_bit_for_bit(name, rho2):
    """Issue 35: ``step`` charges the new stage alone (``Task.stage_cost``, O(1)) and reproduces,
    ``np.array_equal``, every observation, reward, flag and info of the whole-episode evaluation,
    over full seeded and unseeded episodes of random actions (the action space's samples), with and
    without sensor noise."""
    overrides = None if rho2 is None else {"rho2": rho2}
    env = envs.SocOptEnv(load_task(name, overrides=overrides))
    ref = _whole_episode_cost_env(name, overrides)
    env.action_space.seed(7)
    T = env.task.T
    for seed in (0, 1, None, 12345):
        _assert_same_step(env.reset(seed=seed), ref.reset(seed=seed))
        rewards = []
        for _ in range(T):
            a = env.action_space.sample()
            out = env.step(a)
            _assert_same_step(out, ref.step(a.copy()))
            rewards.append(out[1])
        # the episode's whole-trajectory cost is the per-step rewards, bit for bit
        assert np.array_equal(-np.array(rewards), out[-1]["episode"]["cost"])
        assert np.array_equal(env.episode().cost, ref.episode().cost)


def test_task_env_takes_a_toml_path_and_truncates_at_T():
    env = gym.make("soc_opt/Task-v0", task=str(ROOT / "problems/linear2d/linear2d.toml"), overrides={"T": 4})
    env.reset(seed=0)
    flags = [env.step(np.zeros(2))[3] for _ in range(4)]
    assert flags == [False, False, False, True]
    with pytest.raises(RuntimeError, match="T = 4"):
        env.unwrapped.step(np.zeros(2))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        env.reset()
        env.unwrapped.step(np.zeros(3))


def test_unknown_or_incomplete_env_ids_are_rejected_naming_them():
    with pytest.raises(gym.error.Error, match="Nope"):
        gym.make("soc_opt/Nope-v0")
    with pytest.raises(ConfigError, match=r"'soc_opt/Nope-v0'.*soc_opt/Peg-v0"):
        envs.make("soc_opt/Nope-v0")
    with pytest.raises(ConfigError, match="no task given"):
        gym.make("soc_opt/Task-v0")
    with pytest.raises(ConfigError, match="no_such_task.toml"):
        gym.make("soc_opt/Task-v0", task="no_such_task.toml")
    with pytest.raises(ConfigError, match="render_mode 'ansi'"):
        envs.SocOptEnv("linear2d", render_mode="ansi")


def test_module_prefix_make_imports_and_registers():
    code = ("import gymnasium as gym; e = gym.make('soc_opt.envs:soc_opt/Linear2d-v0'); "
            "print(e.unwrapped.task.name, e.observation_space.shape)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["linear2d", "(6,)"]


def test_rgb_array_frames_show_the_trajectory_without_opengl(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "disabled")
    env = gym.make("soc_opt/Linear2d-v0", render_mode="rgb_array", width=200, height=150)
    env.reset(seed=0)
    f0 = env.render()
    for _ in range(10):
        env.step(np.array([5.0, 1.0]))
    f1 = env.render()
    assert f0.shape == f1.shape == (150, 200, 3) and f0.dtype == np.uint8
    assert env.unwrapped.render_backend == "matplotlib"
    assert np.abs(f1.astype(int) - f0).sum() > 0


def test_mujoco_frames_with_egl_in_a_subprocess():
    code = (
        "import numpy as np, gymnasium as gym, soc_opt.envs\n"
        "e = gym.make('soc_opt/Door-v0', render_mode='rgb_array', width=160, height=120)\n"
        "e.reset(seed=0); f = e.render()\n"
        "for _ in range(10): e.step(np.full(6, 5.0))\n"
        "g = e.render(); e.close()\n"
        "print(e.unwrapped.render_backend, f.shape, f.dtype, int(f.std() > 5), int(np.abs(g.astype(int) - f).sum() > 0))\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, PYTHONPATH=str(ROOT), MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl"))
    if p.returncode != 0 or "matplotlib" in p.stdout:
        pytest.skip(f"EGL rendering unavailable here: {(p.stderr.strip().splitlines() or [p.stdout])[-1]}")
    assert p.stdout.split() == ["mujoco", "(120,", "160,", "3)", "uint8", "1", "1"]
