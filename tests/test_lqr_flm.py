"""Step acceptance of the sample-based methods (soc_opt/methods/lqr_flm/, dpsoc_em/; docs/math.md §12).

A step is made bad on purpose by wrapping the KL step so that one chosen call returns a policy with
its offsets pushed far off (the damage a step at the multiplier's cap does on the door): the run
must not return that policy, must go back to the last accepted one with a smaller multiplier, and
with acceptance off must equal the paper as written.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from soc_opt import lqg
from soc_opt.experiments.compare import compare
from soc_opt.experiments.report import paired_test
from soc_opt.experiments.run import load_run_config
from soc_opt.methods.base import run_method
from soc_opt.methods.config import AcceptanceConfig
from soc_opt.methods.lqr_flm import acceptance_threshold
from soc_opt.methods.registry import get_method
from soc_opt.methods.state import AcceptedPolicy
from soc_opt.models import LinearGaussianPolicy
from soc_opt.tasks import load_task

GOLDEN = Path(__file__).parent / "data" / "as_written_linear2d.npz"


@pytest.fixture(scope="module")
def task():
    return load_task("linear2d")


def _cfg(method, iterations=5, samples=6, i_switch=2, enabled=True):
    cfg = load_run_config("linear2d", method=method, overrides={"iterations": iterations, "samples": samples})
    acc = cfg.baseline.acceptance.replace(enabled=enabled)
    return cfg.replace(i_switch=i_switch, baseline=cfg.baseline.replace(acceptance=acc))


def _damage_call(monkeypatch, which: set[int]):
    """Make the KL steps numbered ``which`` (0-based, in call order) return a wrecked policy."""
    real = lqg.kl_step_local  # the loop's call
    calls = []

    def kl_step(*args, **kwargs):
        res = real(*args, **kwargs)
        calls.append(len(calls))
        if len(calls) - 1 in which:
            p = res.policy
            bad = LinearGaussianPolicy(p.K, p.k + 200.0, p.cov)
            res = res._replace(policy=bad)
        return res

    monkeypatch.setattr(lqg, "kl_step_local", kl_step)
    return calls


def _mean_cost(task, policy, seed=123, m=30):
    ro = task.rollouts(policy, m, np.random.default_rng(seed))
    return float(np.mean(task.true_cost(ro).sum(-1)))


def test_damaging_last_step_is_not_the_reported_result(task, tmp_path, monkeypatch):
    """The last KL step wrecks the policy (no sample ever sees it): compare must report the last
    accepted policy, whose cost is that of the run's last sampled iteration, not the wrecked one."""
    cfg = _cfg("lqr-flm", iterations=4)
    _damage_call(monkeypatch, {3, 3 + 4})  # the last step of LQR-FLM and of DPSOC-EM (forked at i_switch)
    summary = compare(task, cfg, [0], tmp_path / "cmp")
    for meth in ("lqr-flm", "dpsoc-em"):
        rows = json.loads((tmp_path / "cmp" / "seed_0" / meth / "metrics.json").read_text())
        last = [r for r in rows if r["phase"] == "baseline"][-1]["cost_mean"]
        assert summary["per_seed"][meth]["cost"][0] < 1.2 * last, meth  # the reported final cost
        fvl = summary["final_vs_last"][meth][0]
        assert not fvl["worse"], (meth, fvl)
        assert fvl["ratio"] < 1.2, (meth, fvl)


def test_returned_policy_is_the_last_accepted_one(task, monkeypatch):
    cfg = _cfg("lqr-flm", iterations=4)
    _damage_call(monkeypatch, {3})
    meth = get_method("lqr-flm")
    state = run_method(meth, task, cfg, 0)
    assert state.accepted is not None and state.accepted.iteration == 3
    final = meth.final_policy(cfg, state)
    assert final is state.accepted.policy
    assert _mean_cost(task, final) < 0.5 * _mean_cost(task, state.policy)  # state.policy is the wrecked one


def test_rejected_step_is_retried_around_the_accepted_policy_with_a_smaller_multiplier(task, monkeypatch):
    cfg = _cfg("lqr-flm", iterations=5)
    _damage_call(monkeypatch, {1})  # p_2 is wrecked, sampled in iteration 2
    state = run_method(get_method("lqr-flm"), task, cfg, 0)
    rec = {r.iteration: r for r in state.history}
    assert rec[1].extra["accepted"] == 1.0
    assert rec[2].extra["accepted"] == 0.0
    assert rec[2].extra["test_cost"] > rec[2].extra["accept_threshold"]
    assert rec[2].extra["accepted_iteration"] == 1.0
    assert rec[2].mult == pytest.approx(max(rec[1].mult * cfg.baseline.acceptance.shrink, cfg.baseline.step_size.mult_min))
    # the retry p_3 is accepted again and is not the wrecked policy: its cost is close to p_1's
    assert rec[3].extra["accepted"] == 1.0
    assert np.mean(rec[3].cost) < 2.0 * np.mean(rec[1].cost)
    assert np.mean(rec[2].cost) > 10.0 * np.mean(rec[1].cost)
    # after the rejection the multiplier stays below the ceiling (half the rejected step's)
    assert rec[3].mult <= cfg.baseline.acceptance.ceiling * rec[1].mult * (1 + 1e-12)


def test_dpsoc_em_phase_waits_for_an_accepted_policy(task, monkeypatch):
    """The policy the EM phase would start from is wrecked: that iteration is an ordinary rejected
    step and the EM phase runs at the next iteration, from an accepted policy."""
    cfg = _cfg("dpsoc-em", iterations=5, i_switch=2)
    _damage_call(monkeypatch, {1})  # p_2, the policy sampled at i_switch = 2
    state = run_method(get_method("dpsoc-em"), task, cfg, 0)
    phases = [(r.iteration, r.phase, r.extra.get("accepted")) for r in state.history]
    assert (2, "baseline", 0.0) in phases
    assert not any(it == 2 and ph == "em" for it, ph, _ in phases)
    em = [r for r in state.history if r.phase == "em"]
    assert len(em) == 1 and em[0].iteration == 3 and em[0].extra["accepted"] == 1.0
    assert state.em_done


def test_acceptance_off_equals_the_paper_as_written(task):
    """``acceptance.enabled = false`` reproduces the runs of the code before acceptance existed
    (golden arrays recorded with that code: the same numbers to rounding, bit for bit on the
    machine that recorded them)."""
    gold = np.load(GOLDEN)
    for meth in ("lqr-flm", "dpsoc-em"):
        cfg = _cfg(meth, enabled=False)
        state = run_method(get_method(meth), task, cfg, 7)
        key = meth.replace("-", "_")
        np.testing.assert_allclose(np.concatenate([r.cost for r in state.history]), gold[key + "_costs"], rtol=1e-9)
        for f in ("K", "k", "cov"):
            np.testing.assert_allclose(getattr(state.policy, f), gold[f"{key}_{f}"], rtol=1e-7, atol=1e-9)
        assert all("accepted" not in r.extra for r in state.history)
        assert get_method(meth).final_policy(cfg, state) is state.policy


def test_acceptance_on_without_a_rejection_takes_the_same_steps(task):
    """Acceptance changes nothing while every step passes: the same sampled costs and policies."""
    for meth in ("lqr-flm", "dpsoc-em"):
        on = run_method(get_method(meth), task, _cfg(meth), 7)
        off = run_method(get_method(meth), task, _cfg(meth, enabled=False), 7)
        assert all(r.extra.get("accepted", 1.0) == 1.0 for r in on.history)
        for a, b in zip(on.history, off.history):
            np.testing.assert_array_equal(a.cost, b.cost)
        np.testing.assert_array_equal(on.policy.K, off.policy.K)


def test_samples_actual_improvement_adapts_the_multiplier_from_the_batch_means(task):
    """``acceptance.actual = "samples"``: on an accepted step the GPS factor reads the measured mean
    cost of the last accepted batch minus the new batch's (docs/math.md §12.2), not the fitted models'."""
    cfg = _cfg("lqr-flm", iterations=5)
    cfg = cfg.replace(baseline=cfg.baseline.replace(acceptance=cfg.baseline.acceptance.replace(actual="samples")))
    state = run_method(get_method("lqr-flm"), task, cfg, 7)
    rec = state.history
    checked = 0
    for prev, cur in zip(rec, rec[1:]):
        if cur.extra["accepted"] != 1.0 or prev.extra["accepted"] != 1.0 or not np.isfinite(cur.extra["predicted_improvement"]):
            continue
        seen = prev.extra["test_cost"] - cur.extra["test_cost"]
        expected = lqg.adapt_multiplier(prev.mult, cur.extra["predicted_improvement"], seen, cfg.baseline.step_size)
        assert cur.mult == pytest.approx(expected, rel=1e-12)
        laplace = lqg.adapt_multiplier(prev.mult, cur.extra["predicted_improvement"], cur.extra["actual_improvement"],
                                       cfg.baseline.step_size)
        checked += not np.isclose(laplace, expected, rtol=1e-9)
    assert checked >= 1  # at least one step where the two rules differ, so the option is what was read


@settings(max_examples=50, deadline=None)
@given(c_a=st.floats(-1e3, 1e3), se_a=st.floats(0, 50), se_i=st.floats(0, 50),
       kappa=st.floats(0, 5), eps=st.floats(0, 0.5))
def test_threshold_is_the_documented_formula(c_a, se_a, se_i, kappa, eps):
    cfg = AcceptanceConfig(kappa=kappa, eps=eps)
    acc = AcceptedPolicy(None, c_a, se_a, 0, None, None, 1.0)
    thr = acceptance_threshold(cfg, se_i, acc)
    assert thr == pytest.approx(c_a + kappa * np.sqrt(se_i ** 2 + se_a ** 2) + eps * abs(c_a), rel=1e-12, abs=1e-9)
    assert thr >= c_a
    assert acceptance_threshold(cfg, se_i, None) == np.inf


def test_acceptance_config_refuses_bad_values():
    from soc_opt.config import ConfigError

    for bad in ({"shrink": 0.0}, {"shrink": 1.5}, {"kappa": -1.0}, {"cost": "guess"}, {"ceiling": 0.0}):
        with pytest.raises(ConfigError):
            AcceptanceConfig(**bad)


def test_paired_test_judges_by_the_interval_not_the_mean():
    # 2 of 5 seeds lower, the mean lower only because of one seed: not shown
    base = np.array([10.0, 10.0, 10.0, 10.0, 10.0])
    dpsoc = np.array([2.0, 9.0, 10.5, 10.5, 10.5])
    r = paired_test(base, dpsoc)
    assert r["diff_mean"] < 0 and r["verdict"] == "not shown"
    # lower on every seed by a clear margin: lower
    r = paired_test(base, base - np.array([1.0, 1.2, 0.9, 1.1, 1.05]))
    assert r["verdict"] == "lower" and r["ci_high"] < 0 and r["p_signed_rank"] < 0.05
    r = paired_test(base, base + 1.0)
    assert r["verdict"] == "reversed" and r["p_reverse"] < 0.05
    assert paired_test([1.0], [0.5])["verdict"] == "one seed"


def test_a_run_with_rejections_resumed_from_its_checkpoint_equals_the_uninterrupted_one(task, tmp_path):
    """The accepted policy, its step and the multiplier's ceiling are part of the checkpoint: a run
    interrupted after a rejection and resumed in the same directory ends with the same numbers."""
    from soc_opt.experiments.run import run_experiment

    cfg = _cfg("lqr-flm", iterations=7)
    cfg = cfg.replace(baseline=cfg.baseline.replace(acceptance=cfg.baseline.acceptance.replace(kappa=0.0, eps=0.0)))
    full = run_method(get_method("lqr-flm"), task, cfg, 4)
    rejected = [r.iteration for r in full.history if r.extra["accepted"] == 0.0]
    assert rejected, "the strict test (kappa = eps = 0) should reject a step on linear2d"

    class Stop(Exception):
        pass

    def stop_after(st):
        if st.iteration == rejected[0] + 1:
            raise Stop

    with pytest.raises(Stop):
        run_experiment(task, "lqr-flm", cfg, 4, tmp_path / "run", on_iteration=stop_after)
    resumed = run_experiment(task, "lqr-flm", cfg, 4, tmp_path / "run")
    assert [r.extra["accepted"] for r in resumed.history] == [r.extra["accepted"] for r in full.history]
    for a, b in zip(resumed.history, full.history):
        np.testing.assert_array_equal(a.cost, b.cost)
    np.testing.assert_array_equal(resumed.accepted.policy.K, full.accepted.policy.K)
    assert resumed.mult_ceiling == full.mult_ceiling and resumed.mult == full.mult


def test_a_retry_below_the_dual_s_resolution_samples_the_accepted_policy_again(task, monkeypatch):
    """Rejections shrink the budget; when the dual cannot reach it (KL at eta_max above the budget) the
    retry is the zero step: the accepted policy's own gains, sampled again, not a crash."""
    real = lqg.kl_step_local  # the loop's call
    calls = []

    def kl_step(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:  # the retry after the rejected p_2
            raise lqg.BudgetUnreachable("KL budget nu=0.005 not reachable: KL(eta_max=1e+16) = 4.1e-01")
        res = real(*args, **kwargs)
        if len(calls) == 2:
            res = res._replace(policy=LinearGaussianPolicy(res.policy.K, res.policy.k + 200.0, res.policy.cov))
        return res

    monkeypatch.setattr(lqg, "kl_step_local", kl_step)
    cfg = _cfg("lqr-flm", iterations=4)
    state = run_method(get_method("lqr-flm"), task, cfg, 0)
    rec = {r.iteration: r for r in state.history}
    assert rec[2].extra["accepted"] == 0.0 and rec[2].extra["zero_step"] == 1.0 and rec[2].kl == 0.0
    assert rec[3].extra["accepted"] == 1.0 and rec[3].extra["accepted_iteration"] == 3.0
    assert np.mean(rec[3].cost) < 2.0 * np.mean(rec[1].cost)


def test_paired_test_shows_nothing_with_too_few_seeds_for_the_signed_rank_test():
    """3 seeds all lower: the percentile bootstrap interval excludes 0, but the signed-rank test
    cannot reach 5% (p = 1/8): untestable with 3 seeds, not a claim held."""
    r = paired_test([10.0, 11.0, 12.0], [9.0, 9.5, 10.0])
    assert r["ci_high"] < 0 and r["p_signed_rank"] == pytest.approx(0.125)
    assert r["verdict"] == "untestable with 3 seeds" and r["interval"] == "below 0"
