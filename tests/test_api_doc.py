"""The API reference generated from the docstrings (soc_opt/api_doc.py; docs/api.md)."""

from __future__ import annotations

import pytest

from soc_opt.api_doc import build, check_links


def test_the_link_checker_finds_a_missing_page_and_a_missing_anchor(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.html").write_text('<a href="b.html#f">ok</a> <a href="b.html#nope">x</a> '
                                             '<a href="c.html">y</a> <a href="#here" id="here">z</a> '
                                             '<a href="https://example.org/">ext</a>')
    (tmp_path / "pkg" / "b.html").write_text('<div id="f"></div>')
    assert sorted(check_links(tmp_path)) == ["pkg/a.html: b.html#nope", "pkg/a.html: c.html"]


@pytest.mark.slow
def test_the_reference_builds_and_every_link_between_its_pages_resolves(tmp_path):
    """About 45 s of wall time (pdoc imports every public module): marked slow."""
    pytest.importorskip("pdoc")
    files = build(tmp_path)
    names = {p.relative_to(tmp_path).as_posix() for p in files}
    assert {"soc_opt/api.html", "soc_opt/mstep.html", "soc_opt/lqg.html"} <= names
    assert "CompareResult" in (tmp_path / "soc_opt" / "api.html").read_text()
    assert check_links(tmp_path) == []
