"""The API reference, generated from the docstrings by pdoc (docs/api.md; ``make api-docs``).

``python -m soc_opt.api_doc [--out build/api]`` writes one HTML page per module of :data:`MODULES` (and their
submodules) and checks every link between the pages (:func:`check_links`): each relative ``href`` names a page
that was written and, with ``#anchor``, an element of that page with that ``id``.  pdoc is installed from PyPI
with the ``test`` or ``docs`` extra; building needs no network.  The docstrings are reStructuredText-flavoured
(``docformat="restructuredtext"``).
"""

from __future__ import annotations

import argparse
import re
import sys
import warnings
from pathlib import Path

__all__ = ["MODULES", "build", "check_links"]

#: the public pieces (README, "What is in it"; docs/interface.md) and the modules their signatures use
MODULES = ("soc_opt.api", "soc_opt.models", "soc_opt.lgssm", "soc_opt.estep", "soc_opt.mstep", "soc_opt.lqg",
           "soc_opt.learning", "soc_opt.tasks", "soc_opt.envs", "soc_opt.methods", "soc_opt.verification",
           "soc_opt.noise", "soc_opt.experiments", "soc_opt.config", "soc_opt.errors", "soc_opt.plugins")


def build(out: str | Path, modules=MODULES) -> list[Path]:
    """Write the reference into ``out``; returns the HTML files written."""
    import pdoc
    import pdoc.render

    out = Path(out)
    pdoc.render.configure(docformat="restructuredtext", show_source=False, search=False)
    with warnings.catch_warnings():  # forward references of NamedTuple fields pdoc cannot resolve: display only
        warnings.simplefilter("ignore")
        pdoc.pdoc(*modules, output_directory=out)
    return sorted(out.rglob("*.html"))


_LINK = re.compile(r'(?:href|src)="([^"]+)"')
_ID = re.compile(r'\bid="([^"]+)"')


def check_links(out: str | Path) -> list[str]:
    """Every broken relative link of the reference in ``out``: ``"page: href"`` (empty when all resolve).
    Links with a scheme (``https:``, ``data:``) or to the page itself without an anchor are not checked."""
    out = Path(out).resolve()
    pages = {p.resolve(): p.read_text(encoding="utf-8") for p in out.rglob("*.html")}
    ids = {p: set(_ID.findall(text)) for p, text in pages.items()}
    broken = []
    for page, text in pages.items():
        for href in _LINK.findall(text):
            if re.match(r"^[a-z][a-z0-9+.-]*:", href) or href.startswith("//"):
                continue
            path, _, anchor = href.partition("#")
            target = page if not path else (page.parent / path).resolve()
            if target not in pages and not (target.is_file() and not anchor):
                broken.append(f"{page.relative_to(out)}: {href}")
            elif anchor and anchor not in ids.get(target, ()):
                broken.append(f"{page.relative_to(out)}: {href}")
    return broken


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m soc_opt.api_doc", description="Build and link-check the API reference.")
    p.add_argument("--out", default="build/api", help="output folder (default build/api)")
    args = p.parse_args(argv)
    files = build(args.out)
    broken = check_links(args.out)
    print(f"wrote {len(files)} pages to {args.out}; {len(broken)} broken links")
    for b in broken[:50]:
        print("  " + b)
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
