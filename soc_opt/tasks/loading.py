"""Finding and building tasks: built-in names, TOML files, config objects (SPEC §8; ``docs/tasks.md``)."""

from __future__ import annotations

from pathlib import Path

from ..config import ConfigError, read_toml
from .config import TaskConfig
from .linear import LinearTask
from .mujoco import MujocoTask, _mujoco

__all__ = ["BUILTIN_TASKS", "build_task", "load_task"]


def _problems_dir() -> Path:
    try:
        import problems

        return Path(problems.__file__).resolve().parent
    except ImportError:  # pragma: no cover - source checkout without install
        return Path(__file__).resolve().parents[2] / "problems"


BUILTIN_TASKS = {"linear2d": "linear2d/linear2d.toml", "peg": "peg/peg.toml", "door": "door/door.toml"}


def build_task(config: TaskConfig | dict, base_dir: str | Path | None = None, *, xml: str | None = None,
               condition: int = 0):
    """A task from a config (object or dict); ``model`` paths are relative to ``base_dir``.

    ``xml``: an MJCF string to use instead of the ``model`` file.  The model
    file's existence is checked (error naming the file) before anything is built.
    """
    if isinstance(config, dict):
        config = TaskConfig.from_dict(config)
    if config.kind == "linear":
        return LinearTask(config, condition=condition)
    mj = _mujoco()
    if xml is not None:
        source = "<xml string>"
        try:
            model = mj.MjModel.from_xml_string(xml)
        except ValueError as e:
            raise ConfigError(f"MJCF string does not compile: {e}") from e
    else:
        if not config.model:
            raise ConfigError("model: a MuJoCo task needs 'model' (an MJCF file path relative to the config)")
        path = Path(config.model)
        if not path.is_absolute():
            path = Path(base_dir or ".") / path
        if not path.is_file():
            raise ConfigError(f"model: MJCF file {str(path)!r} does not exist")
        source = str(path)
        try:
            model = mj.MjModel.from_xml_path(str(path))
        except ValueError as e:
            raise ConfigError(f"model: MJCF file {str(path)!r} does not compile: {e}") from e
    return MujocoTask(config, model, condition=condition, source=source)


def load_task(name_or_path: str | Path, *, condition: int = 0, overrides: dict | None = None):
    """Load a built-in task (``linear2d``, ``peg``, ``door``) or a task TOML file.

    ``overrides``: top-level keys replacing the file's values (e.g. ``{"T": 20, "rho2": 0.01}``).
    """
    name = str(name_or_path)
    path = _problems_dir() / BUILTIN_TASKS[name] if name in BUILTIN_TASKS else Path(name)
    if not path.is_file():
        raise ConfigError(f"task {name!r}: not a built-in task ({', '.join(BUILTIN_TASKS)}) and no file {str(path)!r}")
    data = read_toml(path)
    data.update(overrides or {})
    try:
        config = TaskConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    return build_task(config, path.parent, condition=condition)
