"""Finding and building tasks: built-in names, TOML files, config objects (docs/math.md §8; ``docs/tasks.md``).

Every task built here carries ``task.provenance``, what a run directory records in its
``task.json`` (:mod:`soc_opt.experiments.rundir`): the resolved task configuration, the SHA-256 of every MJCF
file the model reads (:func:`mjcf_files`), and for a task TOML its path, text and SHA-256.
"""

from __future__ import annotations

import hashlib
import importlib.util
import xml.etree.ElementTree as ET
from pathlib import Path

from ..config import ConfigError, read_toml
from .config import GYM_PREFIX, PKG_PREFIX, TaskConfig
from .linear import LinearTask
from .mujoco import MujocoTask, import_mujoco

__all__ = ["BUILTIN_TASKS", "build_task", "load_task", "mjcf_files", "package_file"]


def problems_dir() -> Path:
    """The directory of the built-in task and experiment files: ``soc_opt/problems`` in an installed
    package (pyproject maps the repository's ``problems/`` there), else ``problems/`` of the source
    checkout.  Every reader of those files goes through this function."""
    installed = Path(__file__).resolve().parents[1] / "problems"
    return installed if installed.is_dir() else Path(__file__).resolve().parents[2] / "problems"


def package_file(model: str) -> Path:
    """The file named by ``pkg:<package>/<path inside the package>`` (a ``model`` of a task TOML).

    The package is found without importing it (``importlib.util.find_spec``); the path must stay
    inside the package's directory (no ``..`` out of it, no absolute path).  Errors name the package
    or the file.
    """
    rest = model[len(PKG_PREFIX):] if model.startswith(PKG_PREFIX) else model
    package, _, inner = rest.partition("/")
    if not package or not inner:
        raise ConfigError(f"model {model!r}: expected {PKG_PREFIX}<package>/<path inside the package>")
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError) as e:
        raise ConfigError(f"model {model!r}: package {package!r} cannot be found ({e})") from e
    if spec is None or not spec.submodule_search_locations:
        raise ConfigError(f"model {model!r}: {package!r} is not an installed package")
    root = Path(next(iter(spec.submodule_search_locations))).resolve()
    path = (root / inner).resolve()
    if Path(inner).is_absolute() or not path.is_relative_to(root):
        raise ConfigError(f"model {model!r}: the path leaves the package directory {str(root)!r}")
    if not path.is_file():
        raise ConfigError(f"model {model!r}: package {package!r} has no file {inner!r}")
    return path


BUILTIN_TASKS = {"linear2d": "linear2d/linear2d.toml", "peg": "peg/peg.toml", "door": "door/door.toml"}

#: MJCF elements whose ``file`` attribute names an asset, and the ``<compiler>`` directory it is in.
_ASSET_DIRS = {"mesh": "meshdir", "skin": "meshdir", "hfield": "meshdir", "texture": "texturedir"}


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def mjcf_files(path: str | Path) -> dict[str, str]:
    """``{file: sha256}`` of an MJCF file and of the files it reads (includes, meshes, textures...).

    Names are relative to the model's directory.  Includes are followed recursively; asset
    paths are resolved against ``<compiler assetdir/meshdir/texturedir>``; a referenced file that
    cannot be found (or parsed) is left out: the model's compiler is the authority on it.
    """
    path = Path(path).resolve()
    root_dir = path.parent
    out: dict[str, str] = {}
    dirs = {"meshdir": "", "texturedir": ""}

    def rel(p: Path) -> str:
        try:
            return p.relative_to(root_dir).as_posix()
        except ValueError:
            return p.as_posix()

    def visit(p: Path):
        if rel(p) in out or not p.is_file():
            return
        data = p.read_bytes()
        out[rel(p)] = _sha256(data)
        try:
            tree = ET.fromstring(data)
        except ET.ParseError:
            return
        for comp in tree.iter("compiler"):
            for key in ("meshdir", "texturedir"):
                dirs[key] = comp.get(key, comp.get("assetdir", dirs[key]))
        for el in tree.iter():
            name = el.get("file")
            if not name:
                continue
            if el.tag == "include":
                visit(root_dir / name)
            elif el.tag in _ASSET_DIRS:
                asset = root_dir / dirs[_ASSET_DIRS[el.tag]] / name
                if asset.is_file() and rel(asset) not in out:
                    out[rel(asset)] = _sha256(asset.read_bytes())

    visit(path)
    return out


def build_task(config: TaskConfig | dict, base_dir: str | Path | None = None, *, xml: str | None = None,
               condition: int = 0):
    """A task from a config (object or dict); ``model`` paths are relative to ``base_dir``.

    ``xml``: an MJCF string to use instead of the ``model`` file.  The model
    file's existence is checked (error naming the file) before anything is built.
    """
    if isinstance(config, dict):
        config = TaskConfig.from_dict(config)
    if config.model and config.model.startswith(GYM_PREFIX):
        from .gym import GymMujocoTask, make_gym_env

        if config.kind != "mujoco":
            raise ConfigError(f"{config.model}: kind must be 'mujoco' (the default) for a gym: model")
        if xml is not None:
            raise ConfigError(f"{config.model}: 'xml' cannot replace a Gymnasium environment's model")
        env = make_gym_env(config.model[len(GYM_PREFIX):], config.gym.kwargs)
        try:
            return GymMujocoTask(config, env, condition=condition)
        except Exception:
            env.close()
            raise
    if config.kind == "linear":
        task = LinearTask(config, condition=condition)
        task.provenance = {"name": config.name, "config": config.to_dict(), "model_files": {}}
        return task
    mj = import_mujoco()
    if xml is not None:
        source = "<xml string>"
        try:
            model = mj.MjModel.from_xml_string(xml)
        except ValueError as e:
            raise ConfigError(f"MJCF string does not compile: {e}") from e
        files = {source: _sha256(xml.encode())}
    else:
        if not config.model:
            raise ConfigError("model: a MuJoCo task needs 'model' (an MJCF file path relative to the config)")
        path = package_file(config.model) if config.model.startswith(PKG_PREFIX) else Path(config.model)
        if not path.is_absolute():
            path = Path(base_dir or ".") / path
        if not path.is_file():
            raise ConfigError(f"model: MJCF file {str(path)!r} does not exist")
        source = str(path)
        try:
            model = mj.MjModel.from_xml_path(str(path))
        except ValueError as e:
            raise ConfigError(f"model: MJCF file {str(path)!r} does not compile: {e}") from e
        files = mjcf_files(path)
    task = MujocoTask(config, model, condition=condition, source=source)
    task.provenance = {"name": config.name, "config": config.to_dict(), "model_files": files}
    return task


def load_task(name_or_path: str | Path, *, condition: int = 0, overrides: dict | None = None):
    """Load a built-in task (``linear2d``, ``peg``, ``door``), a task TOML file, or ``gym:<EnvId>``.

    ``gym:<EnvId>``: a Gymnasium MuJoCo environment with its reward as the cost and the
    defaults of :func:`soc_opt.tasks.gym.load_gym_task` (a TOML with ``model = "gym:<EnvId>"``
    sets more; docs/gym.md).
    ``overrides``: top-level keys replacing the file's values (e.g. ``{"T": 20, "rho2": 0.01}``).
    """
    name = str(name_or_path)
    if name.startswith(GYM_PREFIX):
        from .gym import load_gym_task

        return load_gym_task({"model": name, **(overrides or {})}, condition=condition)
    path = problems_dir() / BUILTIN_TASKS[name] if name in BUILTIN_TASKS else Path(name)
    if not path.is_file():
        raise ConfigError(f"task {name!r}: not a built-in task ({', '.join(BUILTIN_TASKS)}), no file {str(path)!r} "
                          f"and not {GYM_PREFIX}<EnvId>")
    data = read_toml(path)
    data.update(overrides or {})
    if str(data.get("model", "")).startswith(GYM_PREFIX):
        from .gym import load_gym_task

        try:
            return load_gym_task(data, condition=condition)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from e
    try:
        config = TaskConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    try:
        task = build_task(config, path.parent, condition=condition)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    text = path.read_bytes()
    task.provenance = {**task.provenance, "toml_file": str(path.resolve()), "toml_sha256": _sha256(text),
                       "toml_text": text.decode(errors="replace"), "condition": condition}
    return task
