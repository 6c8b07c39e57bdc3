"""Tests of the package as users meet it: submodules on the package, install metadata."""

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["lqg", "mstep", "estep", "lgssm", "learning", "tasks", "experiments",
                                  "methods", "noise", "sweeps"])
def test_submodules_are_attributes_of_a_freshly_imported_package(name):
    """``import soc_opt; soc_opt.<name>`` works without importing the submodule first."""
    code = f"import soc_opt; m = soc_opt.{name}; print(m.__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"soc_opt.{name}"


def test_an_unknown_attribute_still_raises_attribute_error():
    import soc_opt

    with pytest.raises(AttributeError, match="no_such_thing"):
        soc_opt.no_such_thing  # noqa: B018


def test_license_is_an_spdx_string_with_a_setuptools_that_reads_it():
    """setuptools >= 77 takes ``project.license`` as an SPDX expression; the table form is deprecated."""
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert data["project"]["license"] == "MIT"
    reqs = [r.replace(" ", "") for r in data["build-system"]["requires"] if r.replace(" ", "").startswith("setuptools")]
    assert reqs and reqs[0].startswith("setuptools>=")
    assert tuple(int(p) for p in reqs[0].split(">=")[1].split(".")) >= (77,)


def test_pyproject_lists_every_package_and_ships_problems_inside_soc_opt():
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {"soc_opt"} | {"soc_opt." + p.parent.relative_to(ROOT / "soc_opt").as_posix().replace("/", ".")
                             for p in (ROOT / "soc_opt").rglob("__init__.py") if p.parent != ROOT / "soc_opt"}
    assert set(data["packages"]) == on_disk | {"soc_opt.problems"}
    assert data["package-dir"] == {"soc_opt.problems": "problems"}


def test_problems_are_found_in_the_checkout_by_the_one_lookup():
    from soc_opt.experiments.run import EXPERIMENTS
    from soc_opt.tasks.loading import problems_dir

    assert problems_dir() == ROOT / "problems"
    assert EXPERIMENTS == ROOT / "problems" / "experiments" and (EXPERIMENTS / "peg.toml").is_file()


def test_the_package_ships_its_license_and_its_typing_marker():
    """A LICENSE file (MIT, as ``project.license``), named in ``license-files``; ``py.typed`` (PEP 561) in the
    package data, so type checkers read soc_opt's annotations."""
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert data["project"]["license-files"] == ["LICENSE"] and (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert (ROOT / "soc_opt" / "py.typed").is_file()
    assert "py.typed" in data["tool"]["setuptools"]["package-data"]["soc_opt"]
    assert (ROOT / "CHANGELOG.md").read_text().startswith("# Changelog")


def test_make_test_runs_in_parallel_workers_with_the_ray_tests_in_one_group():
    """``make test`` runs the suite on pytest-xdist workers with ``--dist loadgroup``, and every test module that
    starts a local Ray cluster is in the one ``xdist_group("ray")``, so two clusters never start at once."""
    make = (ROOT / "Makefile").read_text()
    line = next(ln for ln in make.splitlines() if "-m pytest" in ln and "lint-imports" in ln)
    assert "-n $(TEST_WORKERS)" in line and "--dist loadgroup" in line
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["test"]
    assert any(r.replace(" ", "").startswith("pytest-xdist") for r in extras)
    ray_modules = sorted(p.name for p in (ROOT / "tests").glob("test_*.py") if p.name != Path(__file__).name
                         and ("import ray" in p.read_text() or "run_sweep(" in p.read_text()))
    assert ray_modules, "no module runs a sweep"
    for name in ray_modules:
        assert 'pytestmark = pytest.mark.xdist_group("ray")' in (ROOT / "tests" / name).read_text(), name
