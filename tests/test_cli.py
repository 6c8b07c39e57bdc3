"""Tests for soc_opt/cli.py: configuration errors are caught before any simulation."""

import pytest

from soc_opt.cli import main
from soc_opt.config import ConfigError
from soc_opt.experiment import load_run_config


def test_unknown_config_key_is_rejected_naming_it(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[baseline]\niteratons = 3\n")
    assert main(["run", "linear2d", "--config", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "iteratons" in err and "baseline" in err
    assert not (tmp_path / "o").exists()


def test_wrong_type_is_rejected_naming_the_key(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text('[em]\nn_em = "two"\n')
    assert main(["compare", "linear2d", "--config", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "em.n_em" in capsys.readouterr().err


def test_missing_task_file_is_named(tmp_path, capsys):
    missing = tmp_path / "nope.toml"
    assert main(["run", str(missing), "--out", str(tmp_path / "o")]) == 2
    assert "nope.toml" in capsys.readouterr().err


def test_task_with_missing_model_file_is_named(tmp_path, capsys):
    p = tmp_path / "task.toml"
    p.write_text('name = "x"\nT = 5\nmodel = "missing_arm.xml"\n')
    assert main(["run", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "missing_arm.xml" in capsys.readouterr().err


def test_invalid_switch_point_is_rejected():
    with pytest.raises(ConfigError, match="i_switch"):
        load_run_config("linear2d", overrides={"iterations": 3, "i_switch": 5})


def test_paper_flag_sets_the_paper_scale():
    cfg = load_run_config("peg", paper=True)
    assert (cfg.baseline.iterations, cfg.baseline.samples, cfg.i_switch) == (14, 20, 4)
    # the rest of the task's default file is kept
    assert cfg.baseline.init_var == load_run_config("peg").baseline.init_var


def test_flags_override_the_paper_scale_and_lqr_flm_clamps_the_switch():
    cfg = load_run_config("linear2d", paper=True, overrides={"iterations": 3, "samples": None},
                          method="lqr-flm")
    assert (cfg.baseline.iterations, cfg.baseline.samples, cfg.i_switch) == (3, 20, 2)


def test_config_doc_lists_every_field(capsys):
    assert main(["config-doc"]) == 0
    out = capsys.readouterr().out
    for key in ("`[em.mstep]`", "`clarabel_tol`", "`[baseline.kl]`", "`seed_offset`", "`mu_restart`"):
        assert key in out
