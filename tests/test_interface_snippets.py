"""docs/interface.md: every ``python`` block runs as it stands, each in a fresh interpreter (the README's
table of public pieces points there; issue 33).  A block that stops running fails here."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "interface.md"


def _blocks() -> list[tuple[str, str]]:
    """``(heading, code)`` of every fenced ``python`` block, in order."""
    out, heading = [], ""
    for m in re.finditer(r"^## ([^\n]+)$|^```python\n(.*?)^```$", DOC.read_text(), flags=re.M | re.S):
        if m.group(1) is not None:
            heading = m.group(1)
        else:
            out.append((heading, m.group(2)))
    return out


BLOCKS = _blocks()


def test_every_piece_of_the_readmes_table_has_a_snippet():
    readme = (ROOT / "README.md").read_text()
    table = readme.split("## What is in it")[1].split("\n## ")[0]
    pieces = {p for row in re.findall(r"^\| (`soc_opt[^|]*)\|", table, flags=re.M) for p in re.findall(r"`(soc_opt[\w.]*)`", row)}
    assert pieces, "no pieces found in the README's table"
    headings = " ".join(h for h, _ in BLOCKS)
    assert sorted(p for p in pieces if f"`{p}`" not in headings) == []
    assert "docs/interface.md" in readme


IDS = [f"{i}-" + re.search(r"soc_opt[\w.]*", h).group(0) for i, (h, _) in enumerate(BLOCKS)]


@pytest.mark.parametrize("heading, code", BLOCKS, ids=IDS)
def test_the_snippet_runs(heading, code, tmp_path):
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120,
                         env={"PYTHONPATH": str(ROOT), "PATH": "", "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, f"{heading}\n{out.stdout}\n{out.stderr}"
    assert out.stdout.strip(), f"{heading}: the snippet prints nothing; it should print what it checks"
