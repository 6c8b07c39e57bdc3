"""docs/math.md is the mathematics the code cites: every cited section exists, and nothing in the
project points at a path outside the repository."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ["soc_opt", "tests", "docs", "examples", "problems", "README.md", "Makefile", "pyproject.toml"]
SUFFIXES = {".py", ".md", ".toml", ".xml", ""}


def _files():
    for name in SCANNED:
        p = ROOT / name
        paths = [p] if p.is_file() else [q for q in p.rglob("*") if q.is_file()]
        for q in paths:
            if q.suffix in SUFFIXES and "__pycache__" not in q.parts:
                yield q


def _sections() -> set[str]:
    text = (ROOT / "docs" / "math.md").read_text()
    heads = set(re.findall(r"^##+ (\d+(?:\.\d+)?)\.? ", text, flags=re.M))
    items = {f"9.{i}" for i in re.findall(r"^(\d)\. \*\*", text.split("## 9.")[1].split("## 10.")[0], flags=re.M)}
    return heads | items


def test_math_md_has_the_sections_zero_to_eleven():
    secs = _sections()
    assert {str(i) for i in range(12)} <= secs
    assert {"9.1", "9.5", "10.1", "10.2", "10.3", "11.1", "11.2", "11.3"} <= secs


def test_every_cited_math_section_exists():
    secs = _sections()
    missing = []
    for f in _files():
        for m in re.finditer(r"docs/math\.md`? §(\d+(?:\.\d+)?)", f.read_text(errors="replace")):
            if m.group(1).rstrip(".") not in secs:
                missing.append((str(f.relative_to(ROOT)), m.group(1)))
    assert not missing, missing


def test_nothing_refers_to_a_path_outside_the_repository():
    bad = []
    pattern = re.compile(r"\.\./shared|/work/shared|\bSPEC(\.md|\b)")
    for f in _files():
        if f == Path(__file__).resolve():
            continue
        for i, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
            if pattern.search(line):
                bad.append(f"{f.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not bad, "\n".join(bad)
