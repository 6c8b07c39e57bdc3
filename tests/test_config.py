"""Tests for soc_opt/config.py: strict TOML-loadable configuration objects."""

from dataclasses import dataclass, field
from typing import Literal

import pytest

from soc_opt.config import Config, ConfigError


@dataclass(frozen=True)
class Inner(Config):
    tol: float = 1e-6
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"


@dataclass(frozen=True)
class Outer(Config):
    iterations: int = 3
    budget: float | None = None
    sizes: tuple[int, ...] = (1, 2)
    inner: Inner = field(default_factory=Inner)


def test_round_trip_through_dict_preserves_values():
    cfg = Outer(iterations=5, budget=0.5, sizes=(3,), inner=Inner(tol=1e-3, solver="SCS"))
    assert Outer.from_dict(cfg.to_dict()) == cfg


def test_unknown_key_is_rejected_naming_the_key():
    with pytest.raises(ConfigError, match="'iteratons'"):
        Outer.from_dict({"iteratons": 3})


def test_unknown_nested_key_is_rejected_naming_the_table():
    with pytest.raises(ConfigError, match=r"'tolerance'.*\[inner\]"):
        Outer.from_dict({"inner": {"tolerance": 1.0}})


def test_wrong_type_is_rejected_naming_the_key():
    with pytest.raises(ConfigError, match="iterations: expected an integer"):
        Outer.from_dict({"iterations": "many"})
    with pytest.raises(ConfigError, match="inner.tol: expected a number"):
        Outer.from_dict({"inner": {"tol": "small"}})
    with pytest.raises(ConfigError, match="inner.solver"):
        Outer.from_dict({"inner": {"solver": "MOSEK"}})


def test_integer_is_accepted_for_float_but_bool_is_not():
    assert Outer.from_dict({"budget": 2}).budget == 2.0
    with pytest.raises(ConfigError):
        Outer.from_dict({"budget": True})


def test_missing_toml_file_is_named(tmp_path):
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match="nope.toml"):
        Outer.from_toml(missing)


def test_from_toml_reads_nested_tables(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('iterations = 7\nsizes = [4, 5]\n[inner]\nsolver = "SCS"\n')
    cfg = Outer.from_toml(p)
    assert cfg.iterations == 7 and cfg.sizes == (4, 5) and cfg.inner.solver == "SCS"


def test_invalid_toml_is_reported_with_the_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("iterations = = 3\n")
    with pytest.raises(ConfigError, match="bad.toml"):
        Outer.from_toml(p)
