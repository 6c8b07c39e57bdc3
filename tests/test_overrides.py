"""``--set KEY=VALUE`` overrides (soc_opt/experiments/overrides.py, the ``run``, ``compare`` and ``sweep``
commands; docs/interface.md "Overrides") and what ``soc-opt tasks`` and ``--help`` tell a new user."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from soc_opt.cli import build_parser, main
from soc_opt.config import ConfigError
from soc_opt.experiments.overrides import apply_config_sets, parse_set, split_sets
from soc_opt.methods.config import DPSOCConfig

ROOT = Path(__file__).resolve().parents[1]


def test_a_set_item_reads_its_value_as_toml_and_a_bare_word_as_a_string():
    assert parse_set("baseline.iterations=5") == ("baseline.iterations", 5)
    assert parse_set("task.rho2=0.1") == ("task.rho2", 0.1)
    assert parse_set("em.entropy_floor=true") == ("em.entropy_floor", True)
    assert parse_set("baseline.noise.estimator=kinematic") == ("baseline.noise.estimator", "kinematic")
    task, sets = split_sets(["task.rho2=0.1", "task.linear.mass=2", "em.n_em=2"])
    assert task == {"rho2": 0.1, "linear": {"mass": 2}} and sets == {"em.n_em": 2}


@pytest.mark.parametrize("item", ["iterations5", "=3", "a..b=1", "task=1"])
def test_a_malformed_set_item_is_refused_naming_it(item):
    with pytest.raises(ConfigError, match="--set"):
        split_sets([item])


def test_set_values_are_checked_like_toml_values_and_name_the_key():
    cfg = apply_config_sets(DPSOCConfig(), {"baseline.iterations": 7, "em.n_em": 2}, "dpsoc-em")
    assert cfg.baseline.iterations == 7 and cfg.em.n_em == 2
    for sets, named in (({"baseline.iterations": "abc"}, "baseline.iterations"), ({"baseline.kl_budget": -1.0},
                        "kl_budget"), ({"baseline.nope": 1}, "nope"), ({"i_switch": 99}, "i_switch")):
        with pytest.raises(ConfigError, match=named):
            apply_config_sets(DPSOCConfig(), sets, "dpsoc-em")


def test_run_applies_task_and_config_sets_and_records_them(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "linear2d", "--method", "lqr-flm", "--set", "task.T=8", "--set", "baseline.iterations=1",
                 "--set", "baseline.samples=4", "--out", str(out), "--progress", "lines"]) == 0
    rec = json.loads((out / "config.json").read_text())
    assert rec["config"]["baseline"]["iterations"] == 1 and rec["config"]["baseline"]["samples"] == 4
    assert json.loads((out / "task.json").read_text())["config"]["T"] == 8


@pytest.mark.parametrize("item, named", [("baseline.iterations=abc", "baseline.iterations"),
                                         ("task.rho2=-1", "task.rho2")])
def test_a_bad_set_value_is_one_error_line_and_nothing_is_written(tmp_path, capsys, item, named):
    out = tmp_path / "run"
    assert main(["run", "linear2d", "--set", item, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("soc-opt: error:") and named in err[0]
    assert not out.exists()


def test_sweep_set_items_reach_every_trial_after_the_file_s_common_table():
    """Merged into [common] (the file sets iterations = 3 and T = 20 there); a grid key still wins."""
    from soc_opt.sweeps.sets import load_sweep_with_sets

    spec = load_sweep_with_sets(str(ROOT / "problems/sweeps/linear2d_small.toml"), ["baseline.iterations=2", "task.T=12"])
    assert all(t.config.baseline.iterations == 2 and t.task_overrides["T"] == 12 for t in spec.trials)
    assert {t.task_overrides["rho2"] for t in spec.trials} == {0.1, 0.01}


def test_tasks_lists_every_shipped_task_file():
    from soc_opt.tasks.catalog import shipped_tasks

    listed = {where for _, where in shipped_tasks()}
    on_disk = {str(p.relative_to(ROOT)) for p in ROOT.glob("problems/*/*.toml")
               if p.parent.name not in ("experiments", "sweeps")}
    assert listed == on_disk and len(listed) >= 7


def test_help_names_gym_tasks_and_the_default_output_folders():
    top = build_parser().format_help()
    assert "gym:<EnvId>" in top and "runs/compare-TASK" in top and "runs/TASK-METHOD-seedSEED" in top
    sub = build_parser()._subparsers._group_actions[0].choices
    assert "gym:<EnvId>" in sub["run"].format_help() and "runs/compare-TASK" in sub["compare"].format_help()
    assert "--set" in sub["sweep"].format_help()
