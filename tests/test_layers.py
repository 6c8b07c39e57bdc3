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


def _private_imports(root: Path) -> list[str]:
    """``file:line module.name`` for every private name (``_x``) one module of the package takes from
    another: ``from m import _x``, or ``m._x`` on a module ``m`` the file imported."""
    import ast

    hits = []
    for p in sorted((root / "soc_opt").rglob("*.py")):
        tree = ast.parse(p.read_text())
        modules = set()  # names bound to modules of the package
        for n in ast.walk(tree):
            if isinstance(n, ast.ImportFrom) and n.module != "__future__":
                base = p.parent
                for _ in range(max(n.level - 1, 0)):
                    base = base.parent
                if n.level == 0:
                    base = root
                where = base.joinpath(*(n.module or "").split(".")) if n.module else base
                for a in n.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        hits.append(f"{p.relative_to(root)}:{n.lineno} {n.module}.{a.name}")
                    elif (where / f"{a.name}.py").exists() or (where / a.name / "__init__.py").exists():
                        modules.add(a.asname or a.name)
            elif isinstance(n, ast.Import):
                modules.update(a.asname for a in n.names if a.asname and a.name.startswith("soc_opt"))
        for n in ast.walk(tree):
            if (isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id in modules
                    and n.attr.startswith("_") and not n.attr.startswith("__")):
                hits.append(f"{p.relative_to(root)}:{n.lineno} {n.value.id}.{n.attr}")
    return hits


def test_no_module_of_the_package_uses_another_modules_private_names():
    assert _private_imports(ROOT) == []


def test_the_private_name_check_sees_an_injected_private_import(tmp_path):
    dst = _copy(tmp_path)
    target = dst / "soc_opt" / "bench" / "estep.py"
    target.write_text(target.read_text() + "\nfrom ..estep import _private_helper  # noqa\n")
    assert any(h.startswith("soc_opt/bench/estep.py:") and h.endswith("estep._private_helper")
               for h in _private_imports(dst))


def test_the_shims_are_retired():
    """``soc_opt.algorithms`` re-exported ``soc_opt.methods`` wholesale and ``soc_opt.ilqg`` re-exported
    ``soc_opt.methods.ilqg`` (issue 33): both are gone, nothing imports them, and no star re-export is left.

    The module is looked up on the package's own path: an editable install of another checkout in the same
    environment may map an absent top-level submodule to that checkout."""
    import importlib.machinery
    import re

    import soc_opt

    for shim in ("algorithms", "ilqg"):
        assert importlib.machinery.PathFinder.find_spec(f"soc_opt.{shim}", soc_opt.__path__) is None
    # (a relative ``from .ilqg import`` inside soc_opt.methods is the plug-in itself, not the shim)
    pattern = re.compile(r"^\s*(from soc_opt\.(algorithms|ilqg) import|import soc_opt\.(algorithms|ilqg)"
                         r"|from soc_opt import (algorithms|ilqg)|from \.+algorithms import|from \.+ import algorithms)", re.M)
    users = [str(p.relative_to(ROOT)) for folder in ("soc_opt", "tests", "examples")
             for p in sorted((ROOT / folder).rglob("*.py")) if pattern.search(p.read_text())]
    assert users == []
    star = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "soc_opt").rglob("*.py")
                  if re.search(r"^from \S+ import \*", p.read_text(), re.M))
    assert star == []


_CORE_IMPORTS_OF_PLUGINS = {  # what the core imported before issue 33 made plug-ins own their settings and state
    "experiments/statefile.py": "from ..methods import ilqg",
    "methods/config.py": "from .ilqg import ILQGConfig",
    "noise/aware.py": "from .kinematic.config import KinematicConfig",
    "experiments/run.py": "from ..methods.registry import get_method",
}


def test_the_core_importing_a_plug_in_breaks_the_plug_in_contract(tmp_path):
    """The forbidden contract "The core imports no plug-in" of pyproject.toml: each of the imports the core
    used to make (a plug-in's config or state type, the registry that imports them all) is reported."""
    root = _copy(tmp_path)
    for module, line in _CORE_IMPORTS_OF_PLUGINS.items():
        path = root / "soc_opt" / module
        path.write_text(path.read_text() + f"\n{line}  # injected by the test\n")
    out = _lint(root)
    assert out.returncode != 0, out.stdout
    report = out.stdout.split("The core imports no plug-in", 1)[1]
    assert "BROKEN" in report.splitlines()[0]
    for module in _CORE_IMPORTS_OF_PLUGINS:
        name = "soc_opt." + module.removesuffix(".py").replace("/", ".")
        assert f"{name} -> soc_opt." in report, (name, report)  # the injected line, reported as a direct import


def _contract_layers() -> list[set[str]]:
    """The layers of pyproject's layers contract, from the top: each a set of module names without ``soc_opt.``."""
    import tomllib

    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c["layers"] for c in contracts if c["type"] == "layers")
    return [{m.strip().removeprefix("soc_opt.") for m in row.replace(":", "|").split("|")} for row in layers]


def _documented_layers() -> list[set[str]]:
    """The rows of the layer table of docs/architecture.md ("Layers"), from the top, as module-name sets."""
    import re

    text = (ROOT / "docs" / "architecture.md").read_text()
    table = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in table.splitlines() if ln.startswith("| ") and not ln.startswith(("| layer", "|---"))]
    return [set(re.findall(r"`([a-z_]+)`", ln.split("|", 2)[2])) for ln in rows]


def test_the_layer_table_of_the_architecture_page_is_the_import_contract():
    assert _documented_layers() == _contract_layers()


def test_every_top_level_module_is_in_a_layer():
    modules = {p.stem for p in (ROOT / "soc_opt").glob("*.py") if p.stem != "__init__"}
    modules |= {p.parent.name for p in (ROOT / "soc_opt").glob("*/__init__.py")}
    assert not modules - set().union(*_contract_layers())


def test_the_plugin_tables_import_at_run_time_only_their_registry_modules_which_the_core_may_not_import():
    """The one import the contracts cannot see: a plug-in table importing its registry module on first read
    (soc_opt/plugins.py, floor 2, up to the methods' and the noise's floors).  It is exactly these two modules,
    and the contract "The core imports no plug-in" forbids the core to import them statically."""
    import re
    import tomllib

    from soc_opt import plugins

    source = (ROOT / "soc_opt" / "plugins.py").read_text()
    assert re.findall(r"import_module\(([^)]*)\)", source) == ["self.loader"]
    loaders = {plugins.METHODS.loader, plugins.ESTIMATORS.loader}
    assert loaders == {"soc_opt.methods.registry", "soc_opt.noise.registry"}
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    core = next(c for c in contracts if c["name"].startswith("The core imports no plug-in"))
    assert loaders <= set(core["forbidden_modules"]) and "soc_opt.plugins" in core["source_modules"]
