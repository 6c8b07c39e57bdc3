"""Adapters to the peers (soc_opt.peers, issue 21).

The conversions are checked against brute-force oracles without any peer installed; the tests
that run a peer skip, saying which extra provides it, when it is not installed.
"""

from __future__ import annotations

import numpy as np
import pytest

from soc_opt.bench.lqg import make_instance
from soc_opt.estep import smooth
from soc_opt.lqg import kl_step, lqr
from soc_opt.peers import PEERS, require, versions
from soc_opt.peers import lqr as plqr
from soc_opt.peers import smoothers as psm
from soc_opt.peers.rl import steps_to
from soc_opt.testing import random_closed_loop

EXTRA = "peer not installed: pip install -e '.[peers]'"


def _peer(name):
    return pytest.importorskip(name, reason=f"{name}: {EXTRA}")


def test_versions_lists_every_peer():
    v = versions()
    assert set(v) == set(PEERS.values())
    assert all(x is None or isinstance(x, str) for x in v.values())


def test_require_names_the_extra_when_missing():
    with pytest.raises(ImportError, match=r"\[peers\]"):
        require("soc_opt_no_such_peer_module")


def test_to_lgssm_rejects_correlated_noise():
    model, policy = random_closed_loop(np.random.default_rng(0), 3, 2, 5)
    with pytest.raises(ValueError, match="correlated"):
        psm.to_lgssm(model, policy)


def _dense_smoother(lg: psm.LGSSM, y: np.ndarray, mu0, P0):
    """Oracle: the joint Gaussian of (z_0..z_{T-1}, y_0..y_{T-1}) built state by state, conditioned on y."""
    T, n = lg.b.shape
    # z = L w + mean, w the stacked independent noises (z_0's, then the transitions')
    N = T * n
    mean = np.zeros(N)
    Lz = np.zeros((N, N))
    Lz[:n, :n] = np.linalg.cholesky(P0)
    mean[:n] = mu0
    for t in range(1, T):
        r, p = slice(t * n, (t + 1) * n), slice((t - 1) * n, t * n)
        mean[r] = lg.F[t - 1] @ mean[p] + lg.b[t - 1]
        Lz[r] = lg.F[t - 1] @ Lz[p]
        Lz[r, r] += np.linalg.cholesky(lg.Q[t - 1])
    Szz = Lz @ Lz.T
    Hb = np.zeros((T, N))
    for t in range(T):
        Hb[t, t * n:(t + 1) * n] = lg.H[t, 0]
    my = Hb @ mean + lg.d[:, 0]
    Syy = Hb @ Szz @ Hb.T + np.diag(lg.R[:, 0, 0])
    Szy = Szz @ Hb.T
    G = np.linalg.solve(Syy, Szy.T).T
    m_post = mean + G @ (y - my)
    S_post = Szz - G @ Szy.T
    v = y - my
    ll = -0.5 * (T * np.log(2 * np.pi) + np.linalg.slogdet(Syy)[1] + v @ np.linalg.solve(Syy, v))
    covs = np.stack([S_post[t * n:(t + 1) * n, t * n:(t + 1) * n] for t in range(T)])
    return m_post.reshape(T, n), covs, ll


def test_to_lgssm_gives_the_same_posterior_as_the_estep():
    rng = np.random.default_rng(1)
    model, policy, mu0, P0 = psm.random_uncorrelated(rng, 3, 2, 6)
    lg = psm.to_lgssm(model, policy)
    y = rng.standard_normal(6)
    mean, covs, ll = _dense_smoother(lg, y, mu0, P0)
    sm = smooth(model, policy, y, mu0, P0)
    np.testing.assert_allclose(sm.mean[:6], mean, atol=1e-10)
    np.testing.assert_allclose(sm.cov[:6], covs, atol=1e-10)
    assert sm.loglik == pytest.approx(ll, abs=1e-10)


def test_kl_cost_lqr_reproduces_the_kl_step_gains():
    """At the KL step's multiplier, LQR on l - eta log phat gives the new policy's K and k."""
    dyn, cost, ref, mu0, P0 = make_instance(4, 2, 12, np.random.default_rng(2))
    res = kl_step(dyn, cost, ref, 1.0, mu0, P0)
    assert res.eta[0] > 0
    pol = lqr(dyn, plqr.kl_cost(cost, ref, res.eta[0]), mu0, P0)
    np.testing.assert_allclose(pol.K, res.policy.K, atol=1e-8)
    np.testing.assert_allclose(pol.k, res.policy.k, atol=1e-8)


def test_mean_trajectory_follows_the_policy_and_the_dynamics():
    dyn, cost, ref, mu0, P0 = make_instance(3, 2, 5, np.random.default_rng(3))
    x, u = plqr.mean_trajectory(dyn, ref, mu0)
    np.testing.assert_allclose(x[0], mu0)
    for t in range(4):
        np.testing.assert_allclose(u[t], ref.K[t] @ x[t] + ref.k[t])
        np.testing.assert_allclose(x[t + 1], dyn.A[t] @ x[t] + dyn.B[t] @ u[t] + dyn.c[t])


def test_steps_to_finds_the_first_window_at_the_threshold():
    steps = np.arange(1, 8) * 100
    assert steps_to(steps, [0, 1, 1, 0, 1, 1, 1], threshold=0.9, window=3) == 700
    assert steps_to(steps, [0, 1, 1, 0, 1, 1, 1], threshold=0.6, window=3) == 300
    assert steps_to(steps, [0, 0, 0, 0, 0, 0, 0], threshold=0.9, window=3) is None


def test_a_long_run_is_also_reported_at_each_budget_it_was_scored_at(tmp_path):
    """A 300-step run scored at 200 steps gives a 200-step run: its episodes up to the score, the
    score as its final evaluation, the wall time to it; the run itself stays as it is."""
    import json

    from soc_opt.bench.peers.report import _rl_runs

    run = {"algo": "ppo", "setting": "default", "task": "peg", "rho2": 0.1, "seed": 2, "budget": 300,
           "wall_s": 9.0, "episodes": [{"steps": s, "success_rate": s / 1000, "cost": 1.0} for s in (100, 200, 300)],
           "evals": [{"steps": 200, "budget": 200, "wall_s": 5.0, "success_rate": 0.25, "cost": 2.0}],
           "final": {"success_rate": 0.5, "cost": 1.5}}
    (tmp_path / "r.json").write_text(json.dumps(run))
    runs = _rl_runs(tmp_path)
    assert [r["budget"] for r in runs] == [300, 200]
    assert runs[0] == run
    cut = runs[1]
    assert [e["steps"] for e in cut["episodes"]] == [100, 200]
    assert cut["final"] == {"success_rate": 0.25, "cost": 2.0} and cut["wall_s"] == 5.0 and cut["seed"] == 2


def test_sweep_curves_read_a_noise_sweeps_trials_per_setting_method_and_rho2(tmp_path):
    """``--sweep``: the paper / noise-aware / kinematic trials at rho^2 0 and 0.1, one curve per
    (label, task, rho2) with a row per finished seed; other settings, rho^2 and unfinished seeds left out."""
    import json

    from soc_opt.bench.peers.report import sweep_curves

    def trial(setting, method, seed, values, done=True):
        d = tmp_path / "trials" / "peg" / setting / method / f"seed_{seed}"
        d.mkdir(parents=True)
        lines = ["iteration,metric_success_rate,metric_cost"] + [f"{i},{v},{10 - i}" for i, v in enumerate(values)]
        (d / "metrics.csv").write_text("\n".join(lines) + "\n")
        if done:
            (d / "result.json").write_text(json.dumps({"final_cost": 1.5 + seed}))

    trial("kinematic,rho2=0.1", "lqr-flm", 0, [0.0, 0.5, 1.0])
    trial("kinematic,rho2=0.1", "lqr-flm", 1, [0.0, 0.25, 0.75])
    trial("kinematic,rho2=0.1", "lqr-flm", 2, [0.0, 0.0, 0.0], done=False)
    trial("kinematic-means,rho2=0.1", "lqr-flm", 0, [0.0, 0.0, 0.0])
    trial("paper,rho2=0.01", "lqr-flm", 0, [0.0, 0.0, 0.0])
    trial("paper,rho2=0", "dpsoc-em", 0, [0.5, 1.0, 1.0])
    out = sweep_curves(tmp_path)
    assert set(out) == {("LQR-FLM kinematic", "peg", 0.1), ("DPSOC-EM", "peg", 0.0)}
    c = out[("LQR-FLM kinematic", "peg", 0.1)]
    np.testing.assert_array_equal(c["steps"], [2000, 4000, 6000])
    np.testing.assert_array_equal(c["seeds"]["success_rate"], [[0.0, 0.5, 1.0], [0.0, 0.25, 0.75]])
    assert c["eval_cost"] == [1.5, 2.5]


def test_peers_table_scores_soc_opt_sampled_and_with_its_mean_action_beside_sb3_deterministic(tmp_path):
    """Like with like (docs/math.md §12.3): soc_opt rows carry the final policy's metric sampled and
    with its mean action (from the sweeps' result.json); an RL row's deterministic score is its
    mean-action column, its sampled column stays empty."""
    import json

    from soc_opt.bench.peers.report import rl_table, sweep_curves

    for seed, (samp, mean) in enumerate([(0.8, 0.9), (0.6, 1.0)]):
        d = tmp_path / "trials" / "peg" / "kinematic,rho2=0.1" / "lqr-flm" / f"seed_{seed}"
        d.mkdir(parents=True)
        (d / "metrics.csv").write_text("iteration,metric_success_rate,metric_cost\n0,0.5,3\n1,0.7,2\n")
        (d / "result.json").write_text(json.dumps({
            "final_cost": 2.0 + seed, "metrics": {"success_rate": samp}, "final_cost_mean_action": 1.0 + seed,
            "metrics_mean_action": {"success_rate": mean}}))
    soc = sweep_curves(tmp_path)
    rl = {("PPO default", "peg", 0.1, 1000): {
        "reached": [1000], "n_seeds": 1, "last20": {"success_rate": [0.2], "cost": [9.0]},
        "final": {"success_rate": [0.4], "cost": [8.0]}, "steps_to_90": [None], "wall_s": np.array([1.0])}}
    rows = rl_table(soc, rl)
    mine = next(r for r in rows if r["method"] == "LQR-FLM kinematic")
    assert mine["metric_eval_sampled"] == "0.70 ± 0.10" and mine["metric_eval_mean_action"] == "0.95 ± 0.05"
    assert mine["cost_eval_mean_action"] == "1.50 ± 0.50"
    ppo = next(r for r in rows if r["method"] == "PPO default")
    assert ppo["metric_eval_sampled"] == "" and ppo["metric_eval_mean_action"] == "0.40"


def test_rl_rows_average_finished_runs_and_name_the_steps_of_the_others():
    """A cell with two finished runs and one still going: the statistics are the finished runs'
    (a run at 1,000 steps would drag the last-20 average down), and the row says how far the other got."""
    from soc_opt.bench.peers.report import rl_table

    nan = float("nan")
    rl = {("CrossQ default (sbx)", "peg", 0.0, 28000): {
        "reached": [28000, 28000, 1000], "n_seeds": 3, "finished": [True, True, False],
        "last20": {"success_rate": [1.0, 0.9, 0.0], "cost": [10.0, 12.0, 400.0]},
        "final": {"success_rate": [1.0, 1.0, nan], "cost": [8.0, 10.0, nan]},
        "final_sampled": {"success_rate": [1.0, 0.8, nan], "cost": [9.0, 11.0, nan]},
        "steps_to_90": [6000, 5000, None], "wall_s": np.array([900.0, 1100.0, 30.0])}}
    (row,) = rl_table({}, rl)
    assert row["seeds"] == 2 and row["env_steps"] == "28,000 (2 finished; 1,000 reached by the rest)"
    assert row["metric_last20"] == "0.95 ± 0.05" and row["cost_last20"] == "11.00 ± 1.00"
    assert row["metric_eval_sampled"] == "0.90 ± 0.10" and row["metric_eval_mean_action"] == "1.00 ± 0.00"
    assert row["steps_to_90"] == "5,500 (2/2 seeds)" and row["wall_s"] == "1000 ± 100"


def test_stored_rows_keep_unrepeated_rl_cells_labelled_and_say_what_they_did_not_record(tmp_path):
    """An earlier table's RL rows that no new run repeats are kept with their source in the method
    name; their deterministic score becomes the mean-action column, the sampled one 'not recorded';
    soc_opt rows and repeated RL cells are not carried."""
    import json

    from soc_opt.bench.peers.report import stored_rows

    old = [{"method": "PPO default", "task": "peg", "rho2": 0.0, "env_steps": "280,000", "seeds": 3,
            "metric_last20": "1.00 ± 0.00", "cost_last20": "5.2", "metric_eval": "1.00 ± 0.00", "cost_eval": "4.1",
            "steps_to_90": "82,900 (3/3 seeds)", "wall_s": "1418"},
           {"method": "PPO default", "task": "peg", "rho2": 0.0, "env_steps": "28,000", "seeds": 3, "metric_eval": "0.00"},
           {"method": "LQR-FLM", "task": "peg", "rho2": 0.0, "env_steps": 28000, "seeds": 10, "metric_eval": ""}]
    f = tmp_path / "rl.json"
    f.write_text(json.dumps(old))
    present = [{"method": "PPO default", "task": "peg", "rho2": 0.0, "env_steps": "28,000"}]
    (row,) = stored_rows(f, present, "older runs")
    assert row["method"] == "PPO default [older runs]" and row["env_steps"] == "280,000"
    assert row["metric_eval_mean_action"] == "1.00 ± 0.00" and row["metric_eval_sampled"] == "not recorded"
    assert row["steps_to_90"] == "82,900 (3/3 seeds)"


def test_a_cut_at_a_smaller_budget_carries_its_sampled_score(tmp_path):
    import json

    from soc_opt.bench.peers.report import _rl_runs

    run = {"algo": "sac", "backend": "sbx", "setting": "default", "task": "peg", "rho2": 0.0, "seed": 0, "budget": 300,
           "wall_s": 9.0, "episodes": [{"steps": s, "success_rate": 0.0, "cost": 1.0} for s in (100, 200, 300)],
           "evals": [{"steps": 200, "budget": 200, "wall_s": 5.0, "success_rate": 0.25, "cost": 2.0,
                      "sampled": {"success_rate": 0.2, "cost": 2.5}}],
           "final": {"success_rate": 0.5, "cost": 1.5}, "final_sampled": {"success_rate": 0.4, "cost": 1.7}}
    (tmp_path / "r.json").write_text(json.dumps(run))
    cut = _rl_runs(tmp_path)[1]
    assert cut["final"] == {"success_rate": 0.25, "cost": 2.0} and cut["final_sampled"] == {"success_rate": 0.2, "cost": 2.5}



def test_a_run_of_a_budget_supersedes_the_cut_of_a_longer_run_of_the_same_seed(tmp_path):
    """A 300-step run extended from a finished 200-step run (same seed) is not counted a second time
    at 200 steps; another seed's cut still is."""
    import json

    from soc_opt.bench.peers.report import _rl_runs

    def run(seed, budget, evals=()):
        return {"algo": "sac", "backend": "sbx", "setting": "default", "task": "peg", "rho2": 0.0, "seed": seed,
                "budget": budget, "wall_s": 9.0,
                "episodes": [{"steps": s, "success_rate": 0.0, "cost": 1.0} for s in range(100, budget + 1, 100)],
                "evals": list(evals), "final": {"success_rate": 0.5, "cost": 1.5}}

    ev = [{"steps": 300, "budget": 200, "wall_s": 5.0, "success_rate": 0.25, "cost": 2.0}]
    (tmp_path / "a-200.json").write_text(json.dumps(run(0, 200)))
    (tmp_path / "b-400.json").write_text(json.dumps(run(0, 400, ev)))
    (tmp_path / "c-400.json").write_text(json.dumps(run(1, 400, ev)))
    at200 = [(r["seed"], "cut_from" in r) for r in _rl_runs(tmp_path) if r["budget"] == 200]
    assert sorted(at200) == [(0, False), (1, True)]

# ------------------------------------------------------------------ with the peers installed


def test_pykalman_agrees_with_the_estep():
    _peer("pykalman")
    row = psm.compare(np.random.default_rng(4), 3, T=10, M=2, m=2, repeats=1, peers=("pykalman",))
    assert row["pykalman_max_dmean"] < 1e-10
    assert row["pykalman_max_dcov"] < 1e-10
    assert row["pykalman_max_dloglik"] < 1e-10


def test_dynamax_agrees_with_the_estep_without_its_diagonal_boost(monkeypatch):
    """dynamax adds 1e-9 I to every matrix it Cholesky-solves with (``psd_solve``); with the boost
    set to 0 it is the same smoother to rounding."""
    _peer("dynamax")
    from dynamax.utils import utils as dxu

    monkeypatch.setattr(dxu.psd_solve, "__defaults__", (0.0,))
    row = psm.compare(np.random.default_rng(4), 3, T=10, M=2, m=2, repeats=1, peers=("dynamax",))
    assert row["dynamax_max_dmean"] < 1e-10
    assert row["dynamax_max_dcov"] < 1e-10
    assert row["dynamax_max_dloglik"] < 1e-10


def test_dynamax_runs_in_float64_without_switching_jax_to_float64_for_the_rest_of_the_process():
    """The dynamax peer computes in float64 inside ``jax.enable_x64`` only: left on globally, sbx-rl's SAC
    later in the same process fails (its optimiser's float32 learning rate meets float64)."""
    _peer("dynamax")
    import jax

    before = bool(jax.config.jax_enable_x64)
    row = psm.compare(np.random.default_rng(4), 3, T=10, M=2, m=2, repeats=1, peers=("dynamax",))
    assert row["dynamax_max_dmean"] < 1e-6  # float64 agreement up to dynamax's 1e-9 diagonal boost
    assert bool(jax.config.jax_enable_x64) == before
    assert jax.numpy.asarray([1.0]).dtype == (jax.numpy.float64 if before else jax.numpy.float32)


def test_mpc_lqr_step_agrees_with_lqr_and_the_kl_step():
    _peer("torch")
    _peer("mpc")
    row = plqr.compare(np.random.default_rng(5), 3, 2, 10, nu=1.0, repeats=1)
    assert row["lqr_max_du"] < 1e-8 and row["lqr_max_dx"] < 1e-8
    assert row["kl_max_du"] < 1e-8 and row["kl_max_dx"] < 1e-8


@pytest.mark.slow  # two SAC episodes and one evaluation: about 2 min on a loaded 2-core machine
def test_sb3_run_logs_every_episode_and_evaluates():
    _peer("stable_baselines3")
    from soc_opt.peers.rl import train

    res = train("sac", "default", "peg", 0.1, seed=0, budget=200, eval_episodes=1, eval_at=(100,))
    assert [r["steps"] for r in res["episodes"]] == [100, 200]
    assert [(e["steps"], e["budget"]) for e in res["evals"]] == [(100, 100)] and res["evals"][0]["cost"] > 0
    assert {"cost", "cost_measured", "success_rate", "min_distance"} <= set(res["episodes"][0])
    assert res["final"]["cost"] > 0


@pytest.mark.parametrize("backend", ["sb3", "sbx"])
def test_a_score_at_a_smaller_budget_is_sampled_too_and_leaves_the_run_unchanged(backend):
    """The policy at a smaller budget is scored like the final one (mean action and sampled), and the
    sampled score does not touch the learner's random stream: the run's episodes are those of the
    same run without it, bit for bit."""
    _peer("stable_baselines3")
    if backend == "sbx":
        _peer("sbx")
    from soc_opt.peers.rl import train

    kw = dict(budget=300, eval_episodes=1, backend=backend)
    scored = train("sac", "default", "peg", 0.1, seed=0, eval_at=(200,), **kw)
    plain = train("sac", "default", "peg", 0.1, seed=0, **kw)
    (ev,) = scored["evals"]
    assert ev["budget"] == 200 and ev["cost"] > 0 and ev["sampled"]["cost"] > 0 and ev["sampled"] != {k: ev[k] for k in ev["sampled"]}
    assert scored["episodes"] == plain["episodes"]
    assert scored["final"] == plain["final"] and scored["final_sampled"] == plain["final_sampled"]


@pytest.mark.parametrize("algo, backend", [("sac", "sb3"), ("sac", "sbx"),
                                           pytest.param("crossq", "sbx", marks=pytest.mark.slow)])  # CrossQ: 45 s
def test_a_stopped_off_policy_run_resumes_from_its_checkpoint_and_completes_its_budget(algo, backend, tmp_path):
    """Stopped after its checkpoint at 200 steps (as a kill would leave it), the run continues from
    there with its model, replay buffer and log: 400 steps in all, one episode row per 100 steps,
    the evaluation at 300 steps made once, both final scores; a checkpoint of another run is refused."""
    _peer("stable_baselines3")
    if backend == "sbx":
        _peer("sbx")
    from soc_opt.peers.rl import train

    ckpt = tmp_path / "ckpt"
    kw = dict(budget=400, eval_episodes=1, eval_at=(300,), backend=backend, checkpoint=ckpt, checkpoint_every=1)
    first = train(algo, "default", "peg", 0.1, seed=0, stop_at=200, **kw)
    assert first["partial"] and first["steps"] == 200 and [r["steps"] for r in first["episodes"]] == [100, 200]
    assert [p.name for p in ckpt.glob("step-*")] == ["step-200"]
    done = train(algo, "default", "peg", 0.1, seed=0, **kw)
    assert done["steps"] == 400 and done["resumed_at"] == [200]
    assert [r["steps"] for r in done["episodes"]] == [100, 200, 300, 400]
    assert done["episodes"][:2] == first["episodes"]
    assert [(e["steps"], e["budget"]) for e in done["evals"]] == [(300, 300)]
    assert done["final"]["cost"] > 0 and done["final_sampled"]["cost"] > 0
    assert done["wall_s"] > first["wall_s"] > 0
    with pytest.raises(ValueError, match="another run"):
        train(algo, "default", "peg", 0.1, seed=1, **kw)


def test_resumable_runs_are_the_off_policy_ones_and_the_plan_names_each_backend(tmp_path):
    """PPO's rollout buffer is not saved, so it refuses a checkpoint; CrossQ runs on sbx-rl, PPO on
    stable-baselines3 whatever the SAC backend, and the run files name a backend other than sb3."""
    from soc_opt.bench.peers.rl import plan, run_file
    from soc_opt.peers.rl import train

    with pytest.raises(ValueError, match="off-policy"):
        train("ppo", "default", "peg", 0.0, seed=0, budget=100, checkpoint=tmp_path)
    specs = plan(algos=("ppo", "sac", "crossq"), settings=("default", "tuned"), tasks=("peg",), rho2s=(0.0,),
                 seeds=(0,), backend="sbx")
    assert [(s["algo"], s["backend"], s["setting"]) for s in specs] == [
        ("ppo", "sb3", "default"), ("ppo", "sb3", "tuned"), ("sac", "sbx", "default"), ("sac", "sbx", "tuned"),
        ("crossq", "sbx", "default")]
    assert [run_file(tmp_path, s).name for s in specs[1:3]] == [
        "ppo-tuned-peg-rho2_0-seed0-28000.json", "sac-sbx-default-peg-rho2_0-seed0-28000.json"]


def test_the_runs_table_shows_finished_checkpointed_and_partial_runs_with_both_final_scores(tmp_path):
    """A finished run gives its final scores with its mean action and sampled; a stopped run the steps
    of its last checkpoint and where it was resumed; a run with a partial log only, its episodes."""
    import json

    from soc_opt.bench.peers.runs import markdown, rows

    ep = [{"steps": s, "success_rate": 1.0, "cost": 2.0} for s in (100, 200)]
    base = {"algo": "crossq", "backend": "sbx", "setting": "default", "task": "peg", "rho2": 0.0, "budget": 200}
    (tmp_path / "a.json").write_text(json.dumps({**base, "seed": 0, "steps": 200, "wall_s": 4.0, "episodes": ep,
                                                 "final": {"success_rate": 1.0, "cost": 3.0},
                                                 "final_sampled": {"success_rate": 0.5, "cost": 5.0}}))
    (tmp_path / "b.json.ckpt").mkdir()
    (tmp_path / "b.json.ckpt" / "latest.json").write_text(json.dumps({**base, "seed": 1, "steps": 100, "wall_s": 2.0,
                                                                      "resumed_at": [50], "episodes": ep[:1]}))
    (tmp_path / "c.json.partial").write_text(json.dumps({**base, "seed": 2, "partial": True, "episodes": ep[:1]}))
    rs = rows(tmp_path)
    assert [(r["seed"], r["steps"], r["status"]) for r in rs] == [
        (0, 200, "finished"), (1, 100, "stopped (checkpoint)"), (2, 100, "partial log")]
    assert (rs[0]["metric_mean_action"], rs[0]["metric_sampled"], rs[0]["steps_per_s"]) == (1.0, 0.5, 50.0)
    assert rs[1]["resumed_at"] == [50] and rs[1]["metric_sampled"] is None
    table = markdown(rs)
    assert "CrossQ default (sbx)" in table and "1.00 (3.0) | 0.50 (5.0)" in table and table.count("\n") == 5


def test_the_runs_table_takes_the_budget_from_the_file_name_for_a_copied_checkpoint(tmp_path):
    """A finished 200-step run's checkpoint copied to the 400-step run's name (to extend it) is listed
    at 200 of 400 steps, as an extension not started; once the long run has checkpointed, as stopped."""
    import json

    from soc_opt.bench.peers.runs import rows

    ep = [{"steps": s, "success_rate": 1.0, "cost": 2.0} for s in (100, 200)]
    base = {"algo": "sac", "backend": "sbx", "setting": "default", "task": "peg", "rho2": 0.0, "steps": 200,
            "wall_s": 4.0, "episodes": ep}
    for seed, budget in ((0, 200), (1, 400)):
        d = tmp_path / f"sac-sbx-default-peg-rho2_0-seed{seed}-400.json.ckpt"
        d.mkdir()
        (d / "latest.json").write_text(json.dumps({**base, "seed": seed, "budget": budget}))
    assert [(r["seed"], r["steps"], r["budget"], r["status"]) for r in rows(tmp_path)] == [
        (0, 200, 400, "extension of a 200-step run, not started"), (1, 200, 400, "stopped (checkpoint)")]
