"""The Python entry point ``soc_opt.compare`` (soc_opt/api.py; docs/interface.md): the claims and per-seed
numbers come back as data, equal to what the report's test computes from the same per-seed numbers."""

from __future__ import annotations

import numpy as np
import pytest

import soc_opt
from soc_opt.config import ConfigError
from soc_opt.experiments.report import paired_test


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    return soc_opt.compare("linear2d", seeds=2, out=tmp_path_factory.mktemp("cmp"),
                           set={"task.T": 12, "baseline.iterations": 3, "baseline.samples": 5, "i_switch": 1})


def test_compare_returns_the_claims_and_the_numbers_behind_them_as_data(result):
    assert isinstance(result, soc_opt.CompareResult) and result.seeds == (0, 1) and result.task == "linear2d"
    assert result.config.baseline.iterations == 3 and result.report.is_file()
    assert len(result.claims) == 3 and all(isinstance(c, soc_opt.ClaimResult) for c in result.claims)
    cost = result.claim("cost")
    test = paired_test(result.per_seed["lqr-flm"]["cost"], result.per_seed["dpsoc-em"]["cost"])
    assert cost.verdict == test["verdict"] and cost.diff_mean == pytest.approx(test["diff_mean"])
    assert cost.held == (cost.verdict == "lower") and cost.seeds == 2
    assert len(result.per_seed["dpsoc-em"]["cost"]) == 2 and np.all(np.isfinite(result.per_seed["dpsoc-em"]["cost"]))
    assert "final expected cost" in result.summary() and cost.verdict in result.summary()


def test_a_bad_override_names_its_key_before_anything_runs(tmp_path):
    with pytest.raises(ConfigError, match="baseline.samples"):
        soc_opt.compare("linear2d", seeds=1, out=tmp_path / "x", set={"baseline.samples": "many"})
    assert not (tmp_path / "x").exists()
