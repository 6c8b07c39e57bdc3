"""Gymnasium MuJoCo environments as tasks: ``gym:<EnvId>`` (soc_opt/tasks/gym.py; docs/gym.md).

Oracles: the Gymnasium environment stepped through its own public API (rewards and
states), and a small MuJoCo environment defined here whose reward has known derivatives.
"""

from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")
pytest.importorskip("gymnasium.envs.mujoco")

from gymnasium.envs.mujoco import MujocoEnv  # noqa: E402

from soc_opt.config import ConfigError  # noqa: E402
from soc_opt.methods import registry  # noqa: E402
from soc_opt.methods.config import DPSOCConfig, LQRFLMConfig  # noqa: E402
from soc_opt.methods.ilqg import ILQGConfig, ilqg  # noqa: E402
from soc_opt.models import LinearGaussianPolicy  # noqa: E402
from soc_opt.tasks import load_task  # noqa: E402

# -- a two-joint arm whose reward is an explicit function of the state *before* the step
_XML = """
<mujoco>
  <option timestep="0.01" gravity="0 0 0"/>
  <worldbody>
    <body name="l1"><joint name="j1" type="hinge" axis="0 0 1" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/>
      <body name="l2" pos="0.2 0 0"><joint name="j2" type="slide" axis="1 0 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/>
        <site name="tip" pos="0.2 0 0"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="j1" ctrlrange="-1 1"/><motor joint="j2" ctrlrange="-2 2"/></actuator>
</mujoco>
"""
_W = np.array([1.5, 0.7, 0.2, 0.1])  # weights of (q1, q2, qd1, qd2)^2
_CROSS = 0.3  # coefficient of q1 * a1
_CTRL = 0.25  # coefficient of |a|^2


class _QuadraticArm(MujocoEnv):
    """reward = -(sum_i W_i z_i^2 + CROSS q1 a1 + CTRL |a|^2) on the state before the step, plus
    a cubic term ``q2^3`` that a second-order expansion must not reproduce away from its centre."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, xml_path, **kwargs):
        obs = gym.spaces.Box(-np.inf, np.inf, (4,), np.float64)
        super().__init__(xml_path, 2, observation_space=obs, **kwargs)

    def step(self, action):
        z = np.concatenate([self.data.qpos, self.data.qvel])
        a = np.asarray(action)
        reward = -(_W @ z**2 + _CROSS * z[0] * a[0] + _CTRL * a @ a + z[1] ** 3)
        self.do_simulation(action, self.frame_skip)
        return self._get_obs(), float(reward), False, False, {}

    def _get_obs(self):
        return np.concatenate([self.data.qpos, self.data.qvel])

    def reset_model(self):
        self.set_state(self.init_qpos + np.array([0.3, 0.1]), self.init_qvel + np.array([0.0, 0.2]))
        return self._get_obs()


@pytest.fixture(scope="module")
def arm_id(tmp_path_factory):
    path = tmp_path_factory.mktemp("arm") / "arm.xml"
    path.write_text(_XML)
    env_id = "SocOptTestQuadraticArm-v0"
    if env_id not in gym.registry:
        gym.register(env_id, entry_point=_QuadraticArm, kwargs={"xml_path": str(path)}, max_episode_steps=15)
    return env_id


def _open_loop(task, u):
    T, m, n = task.T, task.m, task.n
    return LinearGaussianPolicy(np.zeros((T, m, n)), u, np.zeros((T, m, m)), allow_singular=True)


def test_task_layout_and_initial_state_come_from_the_environment(arm_id):
    task = load_task(f"gym:{arm_id}")
    assert (task.n, task.m, task.T) == (4, 2, 15)  # T: the env's max_episode_steps
    assert task.state_labels == ["q:j1", "q:j2", "qd:j1", "qd:j2"]
    assert task.substeps == 2 and task.dt == pytest.approx(0.02)
    np.testing.assert_allclose(task.x0, [0.3, 0.1, 0.0, 0.2])


def test_reward_expansion_matches_the_known_derivatives(arm_id):
    task = load_task(f"gym:{arm_id}", overrides={"T": 3})
    rng = np.random.default_rng(0)
    s = rng.normal(size=(4, 4))
    a = rng.normal(size=(3, 2))
    d = task.cost_terms.derivatives(s, a)
    for k in range(3):
        z, u = s[k], a[k]
        lx = 2 * _W * z
        lx[1] += 3 * z[1] ** 2
        lx[0] += _CROSS * u[0]
        lxx = np.diag(2 * _W)
        lxx[1, 1] += 6 * z[1]
        np.testing.assert_allclose(d.l[k], _W @ z**2 + _CROSS * z[0] * u[0] + _CTRL * u @ u + z[1] ** 3, rtol=1e-12)
        np.testing.assert_allclose(d.lx[k], lx, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(d.lu[k], [_CROSS * z[0] + 2 * _CTRL * u[0], 2 * _CTRL * u[1]], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(d.lxx[k], lxx, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(d.luu[k], 2 * _CTRL * np.eye(2), atol=1e-5)
        np.testing.assert_allclose(d.lux[k], [[_CROSS, 0, 0, 0], [0, 0, 0, 0]], atol=1e-5)
    # the absolute quadratic form reproduces the cost at the expansion point
    q = task.cost_expansion(s, a)
    zbar = np.concatenate([s[:3], a], axis=1)
    np.testing.assert_allclose(0.5 * np.einsum("ti,tij,tj->t", zbar, q.C, zbar) + np.einsum("ti,ti->t", zbar, q.c) + q.c0,
                               task.cost(s, a), rtol=1e-9)


def test_soc_opt_env_on_a_gym_task_evaluates_one_reward_per_step_equal_to_the_whole_episode_evaluation(arm_id):
    """Issue 35 on a reward-as-cost task: ``SocOptEnv.step`` evaluates the environment's reward once
    (``RewardCost.stage``), and its rewards and episodes are bit for bit those of the former
    whole-episode evaluation (``task.cost`` on the episode so far, entry ``k``)."""
    from soc_opt.envs import SocOptEnv

    task, ref_task = (load_task(f"gym:{arm_id}", overrides={"T": 8, "rho2": 1e-3}) for _ in range(2))
    env, ref = SocOptEnv(task), SocOptEnv(ref_task)
    ref_task.stage_cost = lambda s_k, a_k, k: float(ref_task.cost(ref._s, ref._a)[0, k])
    env.action_space.seed(3)
    for seed in (0, None):
        obs, _ = env.reset(seed=seed)
        assert np.array_equal(obs, ref.reset(seed=seed)[0])
        for k in range(task.T):
            a = env.action_space.sample()
            before = task.reward.evaluations
            new, old = env.step(a), ref.step(a.copy())
            if k < task.T - 1:  # the last step also evaluates the finished episode's cost and metrics
                assert task.reward.evaluations - before == 1
            for x, y in zip(new[:4], old[:4]):
                assert np.array_equal(x, y)
            assert np.array_equal(new[-1]["stage_cost"], old[-1]["stage_cost"])
        assert np.array_equal(new[-1]["episode"]["cost"], old[-1]["episode"]["cost"])
        assert np.array_equal(new[-1]["episode"]["s"], old[-1]["episode"]["s"])


def test_rollout_costs_and_states_equal_the_environment_stepped_with_the_same_actions():
    env_id = "InvertedDoublePendulum-v5"
    task = load_task(f"gym:{env_id}", overrides={"T": 30, "rho2": 0.0})
    u = np.random.default_rng(1).uniform(-0.5, 0.5, size=(task.T, task.m))
    ro = task.rollouts(_open_loop(task, u), 1, np.random.default_rng(0), noise=False)
    env = gym.make(env_id)
    env.reset(seed=0)  # the task's reset_seed
    rewards, states = [], []
    for k in range(task.T):
        _, r, *_ = env.step(u[k])
        rewards.append(r)
        states.append(env.unwrapped.state_vector())
    np.testing.assert_allclose(ro.x[0, 1:], np.array(states), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(ro.cost[0], -np.array(rewards), rtol=1e-9, atol=1e-9)
    assert task.metrics(ro)["return"] == pytest.approx(sum(rewards), rel=1e-9)


def test_gym_task_runs_two_lqr_flm_iterations():
    task = load_task("gym:InvertedDoublePendulum-v5", overrides={"T": 20, "rho2": 1e-3})
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=2, samples=6, init_var=0.1))
    state = registry.run(task, "lqr-flm", cfg, seed=0)
    assert state.iteration == 2 and len(state.history) == 2
    for rec in state.history:
        assert np.isfinite(rec.cost).all() and rec.kl >= 0
        assert rec.metrics["return"] == pytest.approx(-np.mean(rec.cost))
    assert state.policy.T == 20 and np.isfinite(state.policy.K).all()


def test_an_indicator_reward_fails_with_a_named_cause_not_a_division_by_zero():
    """InvertedPendulum-v5's reward is 1 while the pole is within 0.2 rad, else 0: its finite-difference
    expansion is exactly zero at every step, and the KL step has nothing to follow (issue 49: it divided
    by the zero KL)."""
    from soc_opt.errors import FlatCostError

    task = load_task("gym:InvertedPendulum-v5", overrides={"T": 20})
    cfg = DPSOCConfig(i_switch=0, baseline=LQRFLMConfig(iterations=2, samples=5))
    with pytest.raises(FlatCostError, match=r"gym:InvertedPendulum-v5 .* iteration 0 is zero at every step"):
        registry.run(task, "lqr-flm", cfg, seed=0)


def test_ilqg_lowers_the_cost_of_a_gym_task(arm_id):
    task = load_task(f"gym:{arm_id}", overrides={"T": 10})
    policy, costs = ilqg(task, cfg=ILQGConfig(iterations=3))
    assert len(costs) >= 2 and costs[-1] < costs[0]


def test_toml_cost_terms_replace_the_reward(tmp_path):
    path = tmp_path / "pendulum.toml"
    path.write_text(
        'name = "pendulum_upright"\nmodel = "gym:InvertedPendulum-v5"\nT = 25\nrho2 = 0.0\n'
        '[gym]\nreset_seed = 3\n'
        '[[cost]]\ntype = "state"\njoints = ["hinge"]\ntarget = 0.0\nweights = 4.0\n'
    )
    task = load_task(path)
    assert task.name == "pendulum_upright" and not task.reward_is_cost
    u = np.full((task.T, 1), 0.2)
    ro = task.rollouts(_open_loop(task, u), 1, np.random.default_rng(0), noise=False)
    np.testing.assert_allclose(ro.cost[0], 0.5 * 4.0 * ro.x[0, :-1, 1] ** 2, rtol=1e-12)
    env = gym.make("InvertedPendulum-v5")
    env.reset(seed=3)
    ret = sum(env.unwrapped.step(u[k])[1] for k in range(task.T))  # unwrapped: no termination
    assert task.metrics(ro)["return"] == pytest.approx(ret)


@pytest.mark.parametrize(
    "name, match",
    [
        ("gym:CartPole-v1", r"gym:CartPole-v1: CartPoleEnv is not a Gymnasium MuJoCo environment"),
        ("gym:NoSuchEnv-v3", r"gym:NoSuchEnv-v3: unknown Gymnasium environment id 'NoSuchEnv-v3'"),
        ("gym:Ant-v5", r"gym:Ant-v5: joint 'root' is a free joint"),
        ("gym:", r"no environment id"),
    ],
)
def test_non_mujoco_unknown_and_unsupported_env_ids_are_rejected_naming_them(name, match):
    with pytest.raises(ConfigError, match=match):
        load_task(name)


def test_task_toml_with_a_non_mujoco_env_or_bad_keys_is_rejected(tmp_path):
    path = tmp_path / "cartpole.toml"
    path.write_text('name = "c"\nmodel = "gym:CartPole-v1"\nT = 10\n')
    with pytest.raises(ConfigError, match=r"cartpole.toml: gym:CartPole-v1: CartPoleEnv is not a Gymnasium MuJoCo"):
        load_task(path)
    path.write_text('name = "p"\nmodel = "gym:InvertedPendulum-v5"\nT = 10\nq0 = [0.0, 0.1]\n')
    with pytest.raises(ConfigError, match=r"'q0' cannot be set for a gym: task"):
        load_task(path)
    path.write_text('name = "p"\nmodel = "gym:InvertedPendulum-v5"\nT = 10\n[gym]\nkwargs = {render_mode = "human"}\n')
    with pytest.raises(ConfigError, match=r"render_mode"):
        load_task(path)


@pytest.mark.parametrize("table, named", [
    ('[gym]\nkwargs = { reward_dist_weight = "x" }', "gym.kwargs.reward_dist_weight = 'x' is rejected"),
    ('[gym]\nkwargs = { reward_control_weight = 0.1, reward_dist_weight = "x" }',
     "gym.kwargs.reward_dist_weight = 'x' is rejected"),
    ("[gym]\nkwargs = { no_such_option = 1 }", "gym.kwargs = {'no_such_option': 1}"),
    ("[gym]\nreset_seed = -1", "gym.reset_seed: must be >= 0 (a Gymnasium seed), got -1"),
])
def test_bad_gym_kwargs_or_seed_are_named_before_the_run_directory_is_written(tmp_path, capsys, table, named):
    from soc_opt.cli import main

    path = tmp_path / "reacher.toml"
    path.write_text(f'model = "gym:Reacher-v5"\nT = 5\n{table}\n')
    with pytest.raises(ConfigError) as info:
        load_task(path)
    assert str(path) in str(info.value) and named in str(info.value)
    assert main(["run", str(path), "--method", "lqr-flm", "--iterations", "1", "--samples", "2",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("soc-opt: error: ") and named in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_valid_gym_kwargs_reach_the_environment(tmp_path):
    path = tmp_path / "reacher.toml"
    path.write_text('model = "gym:Reacher-v5"\nT = 5\n[gym]\nkwargs = { reward_control_weight = 0.0 }\n')
    task = load_task(path)
    base = load_task("gym:Reacher-v5", overrides={"T": 5})
    np.testing.assert_array_equal(task.x0, base.x0)
    a = np.array([0.3, -0.2])
    # oracle: Reacher's reward is -w_dist |d| - w_ctrl |a|^2; only w_ctrl differs (0 vs the default)
    w_ctrl = base.env.unwrapped._reward_control_weight
    assert w_ctrl > 0
    np.testing.assert_allclose(task.reward(task.x0, a) - base.reward(base.x0, a), w_ctrl * a @ a, rtol=1e-12)


def test_rk4_linearisation_predicts_the_step_to_second_order():
    """Most Gymnasium models integrate with RK4, which ``mjd_transitionFD`` rejects: the task
    differentiates whole control steps instead.  The oracle is the simulator's own step."""
    task = load_task("gym:InvertedDoublePendulum-v5", overrides={"T": 6, "rho2": 0.0})
    u = np.random.default_rng(2).uniform(-0.5, 0.5, size=(task.T, task.m))
    ro = task.rollouts(_open_loop(task, u), 1, np.random.default_rng(0), noise=False)
    dyn = task.linearize(ro.x[0], u)
    rng = np.random.default_rng(3)
    dx, du = rng.standard_normal(task.n), rng.standard_normal(task.m)
    k = 4
    errors = []
    for scale in (1e-2, 1e-3):
        x, a = ro.x[0, k] + scale * dx, u[k] + scale * du
        np.testing.assert_allclose(dyn.A[k] @ ro.x[0, k] + dyn.B[k] @ u[k] + dyn.c[k], ro.x[0, k + 1], atol=1e-9)
        errors.append(np.abs(dyn.A[k] @ x + dyn.B[k] @ a + dyn.c[k] - task.step(x, a)).max())
    assert errors[1] < errors[0] / 30  # second order: a tenth of the step, a hundredth of the error


def test_example_toml_replaces_the_pendulum_reward_by_its_cost_terms():
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "gym_inverted_pendulum.toml"
    task = load_task(path)
    assert (task.name, task.n, task.m, task.T, task.rho2) == ("gym_inverted_pendulum", 4, 1, 100, 1e-3)
    assert not task.reward_is_cost
    s = np.zeros((task.T + 1, 4))
    s[:, 1] = 0.1  # hinge angle
    a = np.full((task.T, 1), 2.0)
    np.testing.assert_allclose(task.cost(s, a), 0.5 * 10.0 * 0.1**2 + 0.5 * 0.01 * 4.0)


def test_the_figure_points_of_a_gym_task_are_its_state_points_also_when_they_are_bodies(tmp_path):
    """Gymnasium's pusher has no sites: its state points are bodies.  The figures' points must be those
    points (one per name, at the state's coordinates), not the leaf bodies of the tree (issue 34: the
    run's figures failed with an IndexError after the last iteration)."""
    from soc_opt.experiments import report
    from soc_opt.experiments.compare import point_names

    path = tmp_path / "pusher.toml"
    path.write_text('model = "gym:Pusher-v5"\nT = 4\n[state]\nsites = ["tips_arm", "object"]\n')
    task = load_task(path)
    x = np.stack([task.x0, task.x0 + 0.01])
    pts = task.ee_points(x)
    assert pts.shape == (2, 2, 3) and point_names(task) == ["tips_arm", "object"]
    labels = task.state_labels
    for i, name in enumerate(("tips_arm", "object")):
        idx = [labels.index(f"{name}.{c}") for c in "xyz"]
        np.testing.assert_array_equal(pts[:, i], x[:, idx])
    fig = report.plot_ee({"lqr-flm": pts[None]}, task.dt, tmp_path / "ee.png", "pusher", point_names=point_names(task))
    assert fig.stat().st_size > 0


# ------------------------------------------------------------------ issue 48: what a file may make soc_opt import or open


@pytest.fixture
def planted_module(tmp_path, monkeypatch):
    """An importable module whose import leaves a marker file: ``(module name, marker path)``."""
    import sys
    import uuid

    name = f"planted_envs_{uuid.uuid4().hex[:8]}"
    marker = tmp_path / "imported"
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / f"{name}.py").write_text(f"open({str(marker)!r}, 'w').write('code ran')\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    yield name, marker
    sys.modules.pop(name, None)


@pytest.mark.parametrize("where", ["task file", "sweep file"])
def test_a_gym_module_named_in_a_file_is_not_imported_without_the_command_line_asking(tmp_path, capsys, planted_module,
                                                                                      where):
    from soc_opt.cli import main

    module, marker = planted_module
    (tmp_path / "task.toml").write_text(f'model = "gym:{module}:Reacher-v5"\nT = 5\n')
    if where == "task file":
        args = ["run", str(tmp_path / "task.toml"), "--method", "lqr-flm", "--out", str(tmp_path / "o")]
    else:
        (tmp_path / "sweep.toml").write_text(f'tasks = ["gym:{module}:Reacher-v5"]\nmethods = ["lqr-flm"]\nseeds = 1\n')
        args = ["sweep", str(tmp_path / "sweep.toml"), "--dry-run"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("soc-opt: error:") and module in err and "--gym-module" in err, err
    assert not marker.exists() and module not in __import__("sys").modules
    assert not (tmp_path / "o").exists()
    # asked for on the command line: the module is imported and the environment it registers made
    task = load_task(tmp_path / "task.toml", gym_modules=(module,))
    assert marker.exists() and task.m == 2


def test_a_gym_module_named_on_the_command_line_is_imported(tmp_path, planted_module):
    module, marker = planted_module
    task = load_task(f"gym:{module}:Reacher-v5", overrides={"T": 5})
    assert marker.exists() and task.m == 2


def test_a_fifo_as_gym_xml_file_is_refused_before_gymnasium_opens_it(tmp_path, capsys):
    from test_reading import _fifo, watchdog

    from soc_opt.cli import main

    fifo = _fifo(tmp_path / "model.xml")
    (tmp_path / "task.toml").write_text(f'model = "gym:Reacher-v5"\nT = 5\n[gym]\nkwargs = {{ xml_file = "{fifo}" }}\n')
    with watchdog([fifo]) as released:
        rc = main(["run", str(tmp_path / "task.toml"), "--method", "lqr-flm", "--out", str(tmp_path / "o")])
    assert released == []
    err = capsys.readouterr().err
    assert rc == 2 and "model.xml" in err and "FIFO" in err and "xml_file" in err, err
