"""The "final policy worse than its last sampled batch" flag (soc_opt/experiments/compare.py,
``worse_than_batch``; docs/math.md §12.3).

The oracles: the scenarios of issue 49 written as cost samples (20 batch and 20 fresh rollouts, as the
door runs have), and the flag's level under the null hypothesis measured by simulation (both samples from
one heavy-tailed distribution): a flag built from two tests at 2.5% each may not exceed 5%.
"""

from __future__ import annotations

import numpy as np

from soc_opt.experiments.compare import WORSE_ALPHA, worse_than_batch


def batch(rng, mean=57.0, sd_log=0.15, n=20):
    return mean * rng.lognormal(-0.5 * sd_log**2, sd_log, n)


def _acceptance_rule(c_last, c_fin, kappa=2.0, eps=0.02):
    """The rule the flag used before issue 49 (docs/math.md §12.1 applied to the fresh rollouts)."""
    se = lambda c: c.std(ddof=1) / np.sqrt(c.size)
    return c_fin.mean() > c_last.mean() + kappa * np.hypot(se(c_last), se(c_fin)) + eps * abs(c_last.mean())


def test_a_fourfold_rise_with_a_few_catastrophic_fresh_rollouts_is_worse():
    """4.2x: most fresh rollouts somewhat above the batch, two catastrophic (a hook off the handle); their
    standard error is so wide that the mean-based acceptance rule let it pass."""
    rng = np.random.default_rng(49)
    c_last = batch(rng)
    c_fin = np.concatenate([75.0 * rng.lognormal(0.0, 0.2, 18), [1750.0, 1700.0]])
    assert 4.0 < c_fin.mean() / c_last.mean() < 4.5
    assert not _acceptance_rule(c_last, c_fin)  # what the report said before
    w = worse_than_batch(c_last, c_fin)
    assert w["worse"] and w["p_rank"] < WORSE_ALPHA / 2


def test_a_twofold_rise_with_high_variance_fresh_rollouts_is_worse():
    """1.9x with a wide fresh spread (sd above the mean): the bulk has moved up."""
    rng = np.random.default_rng(42)
    c_last = batch(rng)
    c_fin = 57.0 * rng.lognormal(0.0, 1.1, 20)
    c_fin *= 1.9 * c_last.mean() / c_fin.mean()
    assert c_fin.std() > c_fin.mean() and not _acceptance_rule(c_last, c_fin)
    assert worse_than_batch(c_last, c_fin)["worse"]


def test_a_six_percent_rise_on_a_low_variance_batch_is_not_worse():
    """1.06x on a batch with a 1% spread: statistically clear, but not what a user means by worse."""
    rng = np.random.default_rng(7)
    c_last = batch(rng, sd_log=0.01)
    c_fin = 1.06 * batch(rng, sd_log=0.01)
    assert _acceptance_rule(c_last, c_fin)  # flagged before
    w = worse_than_batch(c_last, c_fin)
    assert w["p_rank"] < 1e-6 and not w["worse"]


def test_a_few_catastrophic_rollouts_alone_are_caught_by_the_exceedance_test():
    """The bulk unchanged, 5 of 20 fresh rollouts beyond every batch rollout: Rosenbaum's exceedance test
    (p = C(20, 5) / C(40, 5) = 0.024) flags what the rank test cannot."""
    rng = np.random.default_rng(3)
    c_last = batch(rng)
    c_fin = np.concatenate([c_last[5:], 600.0 * rng.lognormal(0.0, 0.3, 5)])  # the bulk: 15 of the batch's own
    w = worse_than_batch(c_last, c_fin)
    assert w["p_rank"] > WORSE_ALPHA / 2 and w["exceed"] == 5 and w["p_tail"] < WORSE_ALPHA / 2 and w["worse"]


def test_the_flag_keeps_its_level_when_both_samples_come_from_one_heavy_tailed_distribution():
    rng = np.random.default_rng(0)
    flagged = sum(worse_than_batch(100 * rng.lognormal(0, 1.2, 20), 100 * rng.lognormal(0, 1.2, 20))["worse"]
                  for _ in range(200))
    assert flagged <= 0.05 * 200


def test_report_says_which_estimator_ran_its_noise_settings_and_where_em_runs(tmp_path):
    """A kalman-estimator comparison's report.md names the estimator (beyond the paper) and the options changed
    from their defaults; the EM switch is stated in the console's numbering (iterations from 0)."""
    from soc_opt.experiments.compare import compare
    from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
    from soc_opt.noise.aware import NoiseConfig
    from soc_opt.tasks import load_task

    task = load_task("linear2d", overrides={"T": 15, "rho2": 0.01})
    noise = NoiseConfig(estimator="kalman", filter_w_floor=0.2)
    cfg = DPSOCConfig(i_switch=2, baseline=LQRFLMConfig(iterations=3, samples=6, kl_budget=1.0, noise=noise),
                      em=EMConfig(n_em=1))
    compare(task, cfg, [0], tmp_path / "cmp")
    md = (tmp_path / "cmp" / "report.md").read_text()
    line = next(x for x in md.splitlines() if x.startswith("- **state estimator**"))
    assert "kalman" in line and "beyond the paper" in line and "filter_w_floor = 0.2" in line
    assert "- **EM phase at**: iteration 2 (after iterations 0-1)" in md
    assert "EM switch after iteration" not in md
