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


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.py")), ids=lambda p: p.name)
def test_examples_import_only_public_names(path):
    """Examples are user code: they use the public API, no ``_private`` names of soc_opt modules."""
    import ast

    tree = ast.parse(path.read_text())
    private = [f"{node.module}.{a.name}" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
               and (node.module or "").startswith("soc_opt") for a in node.names if a.name.startswith("_")]
    private += [ast.unparse(node) for node in ast.walk(tree) if isinstance(node, ast.Attribute)
                and node.attr.startswith("_") and not node.attr.startswith("__")]
    assert private == []
