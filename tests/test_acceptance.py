"""The step acceptance test (soc_opt/methods/lqr_flm/acceptance.py, ``judge``; docs/math.md §12.1) with
``[baseline.acceptance] test = "rank"`` beside the default "mean" test.

The oracles: cost samples written as the door runs produce them (20 rollouts a batch; a converged policy's
tight batch, then a batch with a few catastrophic rollouts: the hook off the handle), the rank test's level
under the null hypothesis measured by simulation (both batches from one heavy-tailed distribution), and
the accepted batch's costs carried through the state file.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from soc_opt.config import ConfigError
from soc_opt.experiments.run import load_run_config
from soc_opt.experiments.statefile import decode_state, encode_state
from soc_opt.methods.base import run_method
from soc_opt.methods.config import AcceptanceConfig
from soc_opt.methods.lqr_flm.acceptance import judge, rank_level, rank_worse
from soc_opt.methods.registry import get_method
from soc_opt.methods.state import AcceptedPolicy, IterationRecord
from soc_opt.tasks import load_task

RANK = AcceptanceConfig(test="rank")
MEAN = AcceptanceConfig()


def _record(costs) -> IterationRecord:
    c = np.asarray(costs, float)
    return IterationRecord(iteration=3, phase="baseline", cost=c, cost_measured=c, kl=0.0, nu=0.0, mult=1.0,
                           metrics={}, timings={})


def _accepted(costs, keep_costs: bool = True) -> AcceptedPolicy:
    c = np.asarray(costs, float)
    return AcceptedPolicy(None, float(c.mean()), float(c.std(ddof=1) / np.sqrt(c.size)), 2, None, None, 1.0,
                          c if keep_costs else None)


def _converged(rng, n=20):
    """A converged door policy's batch: every rollout opens the door, costs about 1.9."""
    return 1.9 * rng.lognormal(0.0, 0.05, n)


def test_rank_test_rejects_the_catastrophic_rollout_the_mean_test_lets_through():
    """Door seed 614 (DPSOC-EM, init_var 2, iterations 11 and 13; the costs rounded): after a converged
    batch (every cost 1.9-2.0) a step gives 19 rollouts around it (1.93-2.08) and one with the hook
    off the handle (303): the mean is 8.8x the reference, but one rollout widens the standard error so far
    that the mean test accepts it, and the run returned that policy.  The rank test sees 9 of 20 costs
    above the reference's largest (exceedance p = C(20, 9) / C(40, 9) = 6e-4)."""
    ref = np.array([1.90] * 10 + [1.91] * 7 + [1.95] * 3)
    new = np.array([1.93] * 11 + [2.02] * 7 + [2.08, 302.7])
    mean_verdict = judge(MEAN, _record(new), None, _accepted(ref))
    rank_verdict = judge(RANK, _record(new), None, _accepted(ref))
    assert new.mean() > 8 * ref.mean()
    assert mean_verdict.accept and not rank_verdict.accept
    w = rank_worse(ref, new, rank_level(RANK), RANK.eps)
    assert w["exceed"] == 9 and w["p_tail"] == pytest.approx(0.000614, rel=1e-3)
    assert rank_verdict.cost == mean_verdict.cost and rank_verdict.threshold == mean_verdict.threshold  # recorded alike
    np.testing.assert_array_equal(rank_verdict.costs, new)


def test_three_catastrophic_rollouts_with_the_bulk_unchanged_are_not_significant_at_twenty_samples():
    """The limit of a distribution-free test on 20 rollouts: 3 failures where the reference had none
    (one-sided Fisher p = 0.12) with the other 17 drawn like the reference's are within chance at the
    level of kappa = 2, and the batch is accepted, as the mean test accepts it."""
    rng = np.random.default_rng(614)
    ref = _converged(rng)
    new = np.concatenate([_converged(rng, 17), [90.0, 100.0, 110.0]])
    assert judge(RANK, _record(new), None, _accepted(ref)).accept
    assert judge(MEAN, _record(new), None, _accepted(ref)).accept


def test_rank_test_rejects_a_shift_of_the_whole_batch():
    rng = np.random.default_rng(1)
    ref = 50.0 * rng.lognormal(0.0, 0.1, 20)
    assert not judge(RANK, _record(1.5 * 50.0 * rng.lognormal(0.0, 0.1, 20)), None, _accepted(ref)).accept
    assert judge(RANK, _record(0.7 * ref), None, _accepted(ref)).accept  # an improvement


def test_rank_test_keeps_its_level_when_both_batches_come_from_one_heavy_tailed_distribution():
    """Rejections of a batch no worse than the reference: at most the level ``Phi(-kappa)`` the mean test
    has for normal costs (0.023 at kappa = 2), measured on 400 pairs with a binomial margin."""
    rng = np.random.default_rng(0)
    level = rank_level(RANK)
    assert level == pytest.approx(stats.norm.sf(2.0))
    rejected = sum(not judge(RANK, _record(100 * rng.lognormal(0, 1.2, 20)), None,
                             _accepted(100 * rng.lognormal(0, 1.2, 20))).accept for _ in range(400))
    assert rejected <= stats.binom.ppf(0.999, 400, level)


def test_a_small_rise_is_not_worse_even_when_it_is_significant():
    """Below the material margin ``eps`` (2% of the reference mean) the rank test does not reject, as the
    mean test's ``eps |C_a|`` does not."""
    rng = np.random.default_rng(7)
    ref = 50.0 * rng.lognormal(0.0, 0.002, 20)
    new = 1.01 * 50.0 * rng.lognormal(0.0, 0.002, 20)
    assert rank_worse(ref, new, rank_level(RANK), RANK.eps)["p_rank"] < 1e-6
    assert judge(RANK, _record(new), None, _accepted(ref)).accept


def test_without_the_accepted_costs_the_rank_test_is_the_mean_test():
    """A state written before the option existed has no costs of its accepted batch: the mean test judges."""
    ref = np.array([1.90] * 10 + [1.91] * 7 + [1.95] * 3)
    new = np.array([1.93] * 11 + [2.02] * 7 + [2.08, 302.7])
    got = judge(RANK, _record(new), None, _accepted(ref, keep_costs=False))
    want = judge(MEAN, _record(new), None, _accepted(ref))
    assert got.accept and got.accept == want.accept and got.threshold == want.threshold
    assert judge(RANK, _record(new), None, None).accept  # the first batch is always accepted


def test_a_run_with_the_rank_test_keeps_the_accepted_batch_costs_in_its_state_file():
    task = load_task("linear2d")
    cfg = load_run_config("linear2d", method="lqr-flm", overrides={"iterations": 4})
    state = run_method(get_method("lqr-flm"), task, _with_test(cfg, "rank"), 0)
    acc = state.accepted
    assert acc is not None and acc.costs is not None and acc.costs.shape == (cfg.baseline.samples,)
    rec = [r for r in state.history if r.phase == "baseline" and r.iteration == acc.iteration][-1]
    np.testing.assert_array_equal(acc.costs, rec.cost_measured)
    back = decode_state(encode_state(state))
    np.testing.assert_array_equal(back.accepted.costs, acc.costs)


def _with_test(cfg, test: str):
    return cfg.replace(baseline=cfg.baseline.replace(acceptance=cfg.baseline.acceptance.replace(test=test)))


def test_the_test_loads_from_toml_and_a_bad_value_names_the_key(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text('[baseline.acceptance]\ntest = "rank"\n')
    assert load_run_config("linear2d", good, method="lqr-flm").baseline.acceptance.test == "rank"
    assert load_run_config("linear2d", method="lqr-flm").baseline.acceptance.test == "mean"
    bad = tmp_path / "bad.toml"
    bad.write_text('[baseline.acceptance]\ntest = "median"\n')
    with pytest.raises(ConfigError, match=r"baseline\.acceptance\.test"):
        load_run_config("linear2d", bad, method="lqr-flm")
