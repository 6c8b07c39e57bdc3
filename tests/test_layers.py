"""The layering in pyproject.toml ([tool.importlinter]) is enforced: the package keeps the
contracts, and a copy with one deliberately added upward import breaks them."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")

pytestmark = pytest.mark.skipif(not LINT_IMPORTS.exists(), reason="import-linter is not installed (test extra)")


def _lint(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(LINT_IMPORTS), "--config", str(root / "pyproject.toml"), "--no-cache"],
                          capture_output=True, text=True, cwd=root, env={"PYTHONPATH": str(root), "PATH": ""})


def _copy(tmp_path: Path) -> Path:
    dst = tmp_path / "repo"
    shutil.copytree(ROOT / "soc_opt", dst / "soc_opt", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", dst / "pyproject.toml")
    return dst


def test_the_package_keeps_its_import_contracts(tmp_path):
    out = _lint(_copy(tmp_path))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 broken" in out.stdout


@pytest.mark.parametrize("module, upward", [
    ("models.py", "from soc_opt.methods import registry"),  # a foundation importing a method
    ("lqg/step.py", "from soc_opt import mstep"),  # lqg and mstep are independent
    ("bench/estep.py", "from soc_opt import cli"),  # bench never imports the command line
])
def test_an_injected_upward_import_breaks_a_contract(tmp_path, module, upward):
    root = _copy(tmp_path)
    path = root / "soc_opt" / module
    path.write_text(path.read_text() + f"\n{upward}  # injected by the test\n")
    out = _lint(root)
    assert out.returncode != 0, out.stdout
    assert "BROKEN" in out.stdout
