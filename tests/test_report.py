"""Verdicts of the claims over seeds as the compare and sweep reports print them (soc_opt/experiments/report.py;
docs/math.md §12.3).

The oracles: the exact one-sided signed-rank distribution (``2^-n`` is the smallest p-value with ``n``
nonzero differences) and per-seed differences chosen so that the bootstrap interval lies wholly on one side.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from soc_opt.experiments.report import claims_table, min_signed_rank_p, paired_test, verdict_text, write_markdown

#: issue 49's door at rho^2 = 0.1: DPSOC-EM's cost higher by +22.4 on average, 4 of 10 seeds higher by a lot
DOOR_DIFF = np.array([95.0, 70.0, 52.0, 30.0, -12.0, -15.0, -10.0, 14.0, -13.0, 13.0])


def _per_seed(diff):
    zeros = np.zeros(len(diff))
    return {"lqr-flm": {"cost": zeros + 100.0, "state_spread": zeros + 1.0, "action_spread": zeros + 1.0},
            "dpsoc-em": {"cost": 100.0 + diff, "state_spread": zeros + 1.0, "action_spread": zeros + 1.0}}


def test_min_signed_rank_p_is_the_exact_distribution_s_smallest_value():
    for n in range(1, 8):
        assert min_signed_rank_p(n) == pytest.approx(stats.wilcoxon(-np.arange(1.0, n + 1), alternative="less").pvalue)


def test_an_interval_wholly_on_the_wrong_side_is_reversed_not_not_shown():
    r = paired_test(np.zeros(10), DOOR_DIFF)
    assert r["ci_low"] > 0 and r["p_reverse"] > 0.05  # the signed-rank test alone would not show "higher"
    assert r["verdict"] == "reversed" and r["interval"] == "above 0"
    row = claims_table(_per_seed(DOOR_DIFF))[0]
    assert not row["held"] and verdict_text(row).startswith("**no: reversed**")


def test_three_seeds_all_lower_say_untestable_on_the_report_line(tmp_path):
    diff = np.array([-3.0, -2.0, -4.0])
    rows = claims_table(_per_seed(diff))
    cost = rows[0]
    assert cost["ci_high"] < 0 and cost["verdict"] == "untestable with 3 seeds"
    md = write_markdown(tmp_path / "report.md", title="t", setup={}, claims=rows, figures={}).read_text()
    line = next(x for x in md.splitlines() if x.startswith("| DPSOC-EM lowers the final expected cost"))
    assert "untestable with 3 seeds" in line and "interval below 0" in line and "not shown" not in line


def test_five_seeds_can_be_shown_lower():
    r = paired_test(np.zeros(5), -np.array([1.0, 1.2, 0.9, 1.1, 1.05]))
    assert r["verdict"] == "lower" and r["p_signed_rank"] == pytest.approx(1 / 32)


def test_sweep_report_prints_reversed_for_an_interval_above_zero(tmp_path):
    """The sweep report's claims table, from finished trials' result.json files (10 seeds)."""
    import json

    from soc_opt.sweeps.report import write_report
    from soc_opt.sweeps.spec import sweep_from_dict

    spec = sweep_from_dict({"name": "rev", "tasks": ["linear2d"], "methods": ["lqr-flm", "dpsoc-em"], "seeds": 10})
    status = {}
    for t in spec.trials:
        cost = 100.0 + (DOOR_DIFF[t.seed] if t.method == "dpsoc-em" else 0.0)
        (tmp_path / t.relpath).mkdir(parents=True)
        (tmp_path / t.relpath / "result.json").write_text(json.dumps(
            {"status": "done", "final_cost": cost, "state_spread": 1.0, "action_spread": 1.0,
             "cost_per_iteration": [cost]}))
        status[t.id] = {"state": "done"}
    md = write_report(spec, tmp_path, status).read_text()
    line = next(x for x in md.splitlines() if "| final expected cost |" in x)
    assert "**no: reversed**" in line and "not shown" not in line


def test_metric_figure_has_its_unit_its_band_and_the_em_switch(monkeypatch, tmp_path):
    from soc_opt.experiments import report

    seen = {}

    def keep(fig, ax, path, title, dpi=120):
        seen.update(ax=ax, title=title)
        return path

    monkeypatch.setattr(report, "_save", keep)
    vals = {"lqr-flm": np.ones((3, 6)), "dpsoc-em": np.zeros((3, 6))}
    report.plot_metric(vals, tmp_path / "m.png", "peg: minimum distance", "min distance over the rollout [m]", i_switch=4)
    ax = seen["ax"]
    assert ax.get_ylabel().endswith("[m]") and "mean over seeds ± std over seeds" in seen["title"]
    switch = [ln for ln in ax.get_lines() if "EM phase at iteration 4 (after iterations 0-3)" in ln.get_label()]
    assert len(switch) == 1 and list(switch[0].get_xdata()) == [3.5, 3.5]


def test_em_switch_text_counts_iterations_from_zero():
    from soc_opt.experiments.report import em_switch_text

    assert em_switch_text(4) == "iteration 4 (after iterations 0-3)"
    assert em_switch_text(1) == "iteration 1 (after iteration 0)"
    assert em_switch_text(0) == "iteration 0 (before any baseline iteration)"
