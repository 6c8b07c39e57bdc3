"""Finding and building tasks: built-in names, TOML files, config objects (docs/math.md §8; ``docs/tasks.md``).

Every task built here carries ``task.provenance``, what a run directory records in its
``task.json`` (:mod:`soc_opt.experiments.rundir`): the resolved task configuration, the SHA-256 of every MJCF
file the model reads (:func:`mjcf_files`), and for a task TOML its path, text and SHA-256.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from pathlib import Path

from ..config import ConfigError, read_toml_file
from .config import GYM_PREFIX, PKG_PREFIX, TaskConfig
from .linear import LinearTask
from .mjcf import check_model, check_xml
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

    The package is found without importing anything: only a top-level name is looked up
    (``importlib.util.find_spec`` of a top-level name imports no module, whereas a dotted name would import
    its parents); a dotted package ``a.b`` is the folder ``b`` of ``a``.  The path must stay inside the
    package's directory (no ``..`` out of it, no absolute path).  Errors name the package or the file.
    """
    rest = model[len(PKG_PREFIX):] if model.startswith(PKG_PREFIX) else model
    package, _, inner = rest.partition("/")
    if not package or not inner:
        raise ConfigError(f"model {model!r}: expected {PKG_PREFIX}<package>/<path inside the package>")
    top, *subs = package.split(".")
    if not top.isidentifier() or not all(s.isidentifier() for s in subs):
        raise ConfigError(f"model {model!r}: {package!r} is not a package name")
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError) as e:
        raise ConfigError(f"model {model!r}: package {top!r} cannot be found ({e})") from e
    if spec is None or not spec.submodule_search_locations:
        raise ConfigError(f"model {model!r}: {top!r} is not an installed package")
    root = Path(next(iter(spec.submodule_search_locations))).joinpath(*subs).resolve()
    if not root.is_dir():
        raise ConfigError(f"model {model!r}: package {top!r} has no folder {'/'.join(subs)!r}")
    path = (root / inner).resolve()
    if Path(inner).is_absolute() or not path.is_relative_to(root):
        raise ConfigError(f"model {model!r}: the path leaves the package directory {str(root)!r}")
    if not os.path.lexists(path):
        raise ConfigError(f"model {model!r}: package {package!r} has no file {inner!r}")
    return path


BUILTIN_TASKS = {"linear2d": "linear2d/linear2d.toml", "peg": "peg/peg.toml", "door": "door/door.toml"}

def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def mjcf_files(path: str | Path) -> dict[str, str]:
    """``{file: sha256}`` of an MJCF file and of the files it reads (includes, meshes, textures...), names
    relative to the model's directory, after checking every one of them (:func:`soc_opt.tasks.mjcf.check_model`:
    regular files only, bounded sizes and counts; a referenced file that does not exist is left to MuJoCo)."""
    return check_model(path)


def build_task(config: TaskConfig | dict, base_dir: str | Path | None = None, *, xml: str | None = None,
               condition: int = 0, gym_modules: tuple[str, ...] = ()):
    """A task from a config (object or dict); ``model`` paths are relative to ``base_dir``.

    ``gym_modules``: the Python modules a ``model = "gym:<module>:<EnvId>"`` may import
    (:func:`soc_opt.tasks.gym.make_gym_env`; none by default).

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
        env = make_gym_env(config.model[len(GYM_PREFIX):], config.gym.kwargs, modules=tuple(gym_modules))
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
        check_xml(xml)
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
        if not os.path.lexists(path):
            raise ConfigError(f"model: MJCF file {str(path)!r} does not exist")
        source = str(path)
        files = check_model(path)  # every file MuJoCo would open, checked before it opens any
        try:
            model = mj.MjModel.from_xml_path(str(path))
        except ValueError as e:
            raise ConfigError(f"model: MJCF file {str(path)!r} does not compile: {e}") from e
    task = MujocoTask(config, model, condition=condition, source=source)
    task.provenance = {"name": config.name, "config": config.to_dict(), "model_files": files}
    return task


def load_task(name_or_path: str | Path, *, condition: int = 0, overrides: dict | None = None,
              gym_modules: tuple[str, ...] = ()):
    """Load a built-in task (``linear2d``, ``peg``, ``door``), a task TOML file, or ``gym:<EnvId>``.

    ``gym:<EnvId>``: a Gymnasium MuJoCo environment with its reward as the cost and the
    defaults of :func:`soc_opt.tasks.gym.load_gym_task` (a TOML with ``model = "gym:<EnvId>"``
    sets more; docs/gym.md).  ``gym:<module>:<EnvId>`` imports ``<module>``: allowed for the name given
    here, and for a ``model`` read from a file only when ``<module>`` is in ``gym_modules`` (what the
    command line's ``--gym-module`` names; docs/security.md).
    ``overrides``: top-level keys replacing the file's values (e.g. ``{"T": 20, "rho2": 0.01}``).
    """
    name = str(name_or_path)
    gym_modules = tuple(gym_modules)
    if name.startswith(GYM_PREFIX):
        from .gym import load_gym_task

        data = {"model": name, **(overrides or {})}
        own = name[len(GYM_PREFIX):].partition(":")[0] if data["model"] == name and name.count(":") > 1 else None
        return load_gym_task(data, condition=condition, modules=gym_modules + ((own,) if own else ()))
    path = problems_dir() / BUILTIN_TASKS[name] if name in BUILTIN_TASKS else Path(name)
    if not os.path.lexists(path):
        raise ConfigError(f"task {name!r}: not a built-in task ({', '.join(BUILTIN_TASKS)}), no file {str(path)!r} "
                          f"and not {GYM_PREFIX}<EnvId>")
    data, text = read_toml_file(path, what="task file")
    data.update(overrides or {})
    if str(data.get("model", "")).startswith(GYM_PREFIX):
        from .gym import load_gym_task

        try:
            return load_gym_task(data, condition=condition, modules=gym_modules)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from e
    try:
        config = TaskConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    try:
        task = build_task(config, path.parent, condition=condition, gym_modules=gym_modules)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    task.provenance = {**task.provenance, "toml_file": str(path.resolve()), "toml_sha256": _sha256(text),
                       "toml_text": text.decode(errors="replace"), "condition": condition}
    return task
