"""The scripts in examples/ run as documented (they are part of the user documentation)."""

import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.mark.parametrize("name", ["em_iteration_by_hand.py", "custom_mstep_constraint.py"])
def test_example_runs(name, capsys):
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    out = capsys.readouterr().out
    assert out.strip()
    if name == "custom_mstep_constraint.py":
        assert "status optimal" in out
