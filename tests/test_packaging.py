"""Tests of the package as users meet it: submodules on the package, install metadata."""

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["lqg", "mstep", "estep", "fit", "algorithms", "ilqg", "tasks", "experiment"])
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
