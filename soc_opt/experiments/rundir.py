"""Run directories on disk: the contract of a run, its lock, its files and verified checkpoints.

A run directory (``soc-opt run|compare --out DIR``) holds

- ``config.json``: method, seed and the resolved algorithm configuration of the run, and the
  environment it was started in (package versions, BLAS kernel: :mod:`soc_opt.experiments.environment`;
  recorded, not part of the contract);
- ``task.json``: the resolved task (its configuration after overrides, the task TOML's path,
  text and SHA-256, and the SHA-256 of every MJCF file the model reads);
- ``metrics.csv`` and ``metrics.json``: one row per iteration (``IterationRecord.summary``);
  iterations are numbered from 0, here and on the console;
- ``policies/iter_XXX.npz``: the policy after ``XXX`` iterations (``K, k, cov``; load it with
  :meth:`soc_opt.models.LinearGaussianPolicy.load`);
- ``samples/iter_XXX.npz``: the rollouts of iteration ``XXX`` (``x, s, a, cost, y``);
- ``best_policy.npz``: the best policy sampled so far (plus ``mean_cost`` and ``iteration``);
- ``checkpoint.npz`` and ``checkpoint.prev.npz``: the full run state after the last and the
  one-before-last finished iteration (:mod:`soc_opt.experiments.statefile`: arrays and JSON, no code; each
  with a SHA-256 checksum verified on load, which detects damage but is no security measure);
- ``lock``: the lock file, naming the process that runs in the directory.

**Contract.**  ``config.json`` and ``task.json`` are the contract of the run: a run started
again on the directory resumes only if the method, seed, the configuration sections that method
reads (``Method.sections``, :mod:`soc_opt.methods.registry`; compared in full: a key missing from the
record is a difference, :func:`differences`), the resolved task configuration and the MJCF
files are the same; otherwise :class:`RunDirectoryError` lists what differs.  A directory with no
finished iteration (no checkpoint) holds nothing to protect: its contract is replaced.

**Lock.**  While a run writes to the directory it holds an exclusive ``flock`` on ``lock``, and
the file names its pid and host.  The kernel drops the lock when the holder exits, even when it is
killed, so a lock file left behind by a dead process is stale and simply taken over; a live
holder makes a second writer fail at once with a message naming it.

**Ownership.**  ``config.json`` holds ``"format": "soc_opt run"``: what marks a folder as a run directory
(:func:`run_record`; a record written before the mark is recognised by its ``method``, ``seed`` and
``config``).  A folder that is neither new, empty nor a run directory is refused before anything, the
lock file included, is written (:meth:`RunDirectory.check_owned`); ``--restart`` removes only the names
a run writes.  Nothing is written, truncated or removed through a symbolic link below the folder the
caller owns (:mod:`soc_opt.files`, docs/security.md).

**Writes.**  Every file is written to a temporary name and renamed into place (atomic); the
checkpoint is written last, after the iteration's other files, and the previous one is kept as
``checkpoint.prev.npz``.  A corrupt checkpoint is reported with the choice of resuming from the
previous one or starting again (:class:`CheckpointError`).  Files are readable as the umask
allows (like files created by ``open``), not only by their owner.

**Reading is data only.**  Checkpoints are read with :func:`soc_opt.experiments.statefile.decode_state`,
which executes nothing from the file.  Checkpoints of the old pickle format (``*.pkl``, which
runs code when read) are refused with :class:`LegacyCheckpointError`; a run you trust is
converted with ``soc-opt convert-checkpoint --trust DIR``.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import socket
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from .. import files, plugins
from ..config import IMPLIED_WHEN_ABSENT, ConfigError
from ..reading import kind_of
from .statefile import MAX_STATE_BYTES, MAX_TREE_BYTES, StateFileError, decode_state, encode_state, peek_state

try:  # POSIX advisory locks; elsewhere a pid check stands in (see _PidLock)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = ["RunDirectoryError", "CheckpointError", "LegacyCheckpointError", "RunDirectory", "lock_directory",
           "differences", "atomic_write_bytes", "npz_bytes", "encode_checkpoint", "decode_checkpoint", "refuse_legacy",
           "CHECKPOINT", "PREVIOUS_CHECKPOINT", "LEGACY_FILES", "LOCK"]

CHECKPOINT = "checkpoint.npz"
PREVIOUS_CHECKPOINT = "checkpoint.prev.npz"
#: Pickle files of soc_opt before issue 18 (refused; ``soc-opt convert-checkpoint --trust``).
LEGACY_FILES = ("checkpoint.pkl", "checkpoint.prev.pkl", "fork_state.pkl")
LOCK = "lock"
_TMP = files.TMP_MARK
#: ``config.json``'s ``format``: what marks a folder as a run directory (module docstring, "Ownership").
RUN_FORMAT = "soc_opt run"
#: Largest checkpoint file read: the state's budget (arrays and views) plus its structure.
MAX_CHECKPOINT_BYTES = 2 * MAX_STATE_BYTES + MAX_TREE_BYTES
_ITER_FILE = r"iter_\d{3,}\.npz"
#: Files a run writes at the top of its directory (removed by ``RunDirectory.clear``).
RUN_FILES = ("config.json", "task.json", "metrics.csv", "metrics.json", "costs.npz", "best_policy.npz",
             CHECKPOINT, PREVIOUS_CHECKPOINT, *LEGACY_FILES[:2], "policy.npz", "final_eval.npz",
             "final_policy.npz", "final_eval_mean_action.npz", "final_eval_open_loop.npz", "final_eval_filtered.npz",
             "final_eval_filtered_mean_action.npz", "cost_per_iteration.png",
             "ee_trajectories.png", "filmstrip.png", "final.json")



class RunDirectoryError(ConfigError):
    """A run directory cannot be used as asked (different run, locked, corrupt); the message says why
    and what to do."""


class CheckpointError(RunDirectoryError):
    """A checkpoint file is empty, truncated, fails its checksum or holds something else than a run state."""


class LegacyCheckpointError(CheckpointError):
    """A checkpoint in the old pickle format, which soc_opt no longer reads (it can run code)."""


def refuse_legacy(directory: Path, names=LEGACY_FILES[:2]) -> None:
    """Raise :class:`LegacyCheckpointError` if ``directory`` holds one of the pickle files ``names``
    (nothing is read from them)."""
    found = [n for n in names if (Path(directory) / n).exists()]
    if found:
        raise LegacyCheckpointError(
            f"{str(Path(directory) / found[0])!r} is a checkpoint in the old pickle format, which soc_opt no "
            "longer reads: unpickling a file runs whatever code it holds. If you trust where this directory "
            f"came from, convert it with `soc-opt convert-checkpoint --trust {str(directory)!r}`; otherwise "
            "delete the .pkl files or rerun with --restart")


def atomic_write_bytes(path: Path, data: bytes, anchor: Path | None = None) -> None:
    """Write ``data`` to ``path`` atomically, following no link below ``anchor`` (:func:`soc_opt.files.write_bytes`)."""
    files.write_bytes(path, data, anchor=anchor)


def npz_bytes(*, compress: bool = True, **arrays) -> bytes:
    """The bytes of a ``.npz`` holding ``arrays`` (for :func:`atomic_write_bytes`), compressed unless
    ``compress=False``: sampled trajectories, whose float noise deflates by 4% (peg, 20 rollouts: 944
    against 986 kB) for 35 ms of a 1 s iteration, are stored as they are."""
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, **arrays)
    return buf.getvalue()



def _jsonable(v):
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def _short(v: Any) -> str:
    text = json.dumps(v, sort_keys=True) if not isinstance(v, str) else repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


_NOTHING = object()
_UNUSED = object()


def _implied(key: str, grandparent: Any):
    """The value :data:`soc_opt.config.IMPLIED_WHEN_ABSENT` gives a recorded key ``key`` (a dotted path) by
    its absence, ``_UNUSED`` when its condition, on the ``grandparent`` table holding the key's section, does
    not hold (the section is not in use), or ``_NOTHING`` (a key the table does not declare).  The plug-ins
    are loaded first: their settings classes declare entries too."""
    plugins.load_all()
    for suffix, (value, when) in IMPLIED_WHEN_ABSENT.items():
        if key == suffix or key.endswith("." + suffix):
            gp = grandparent if isinstance(grandparent, dict) else {}
            return value if all(gp.get(k) == v for k, v in when.items()) else _UNUSED
    return _NOTHING


def differences(old: Any, new: Any, prefix: str = "", _parent: Any = None) -> list[str]:
    """``"key: old -> new"`` for every setting whose value differs between the record ``old`` and ``new``.

    The full resolved configurations are compared: a key missing on either side is a difference, not a
    match (issue 31), except a key only in ``new`` that :data:`soc_opt.config.IMPLIED_WHEN_ABSENT` declares
    (an option added after runs were recorded, e.g. ``kinematic.gains``, absent meaning ``"nominal"`` when
    ``estimator = "kinematic"``): it is compared with the value its absence implies; likewise the settings
    table of a plug-in registered after the run was recorded, unused unless that plug-in is the one its
    table selects (:func:`_plugin_table_implied`).  Lists of tables are compared entry by entry.
    """
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k, v in old.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            out += differences(v, new[k], key, new) if k in new else [f"{key}: {_short(v)} -> (unset)"]
        for k in sorted(new.keys() - old.keys()):
            key = f"{prefix}.{k}" if prefix else str(k)
            implied = _implied(key, _parent)
            if implied is _NOTHING:
                implied = _plugin_table_implied(k, new)
            if implied is _UNUSED:
                continue
            if implied is _NOTHING:
                out.append(f"{key}: (not recorded) -> {_short(new[k])}")
            elif new[k] != implied:
                out.append(f"{key}: (unset: {_short(implied)} when recorded) -> {_short(new[k])}")
        return out
    if (isinstance(old, list) and isinstance(new, list) and len(old) == len(new)
            and any(isinstance(v, dict) for v in old)):
        return [d for i, (a, b) in enumerate(zip(old, new)) for d in differences(a, b, f"{prefix}[{i}]")]
    return [] if old == new else [f"{prefix}: {_short(old)} -> {_short(new)}"]


def _plugin_table_implied(name: str, table: dict):
    """What the absence of plug-in ``name``'s settings table from a recorded ``table`` implies, when ``table``
    selects one plug-in (``estimator = ...``, :attr:`soc_opt.plugins.Registry.selector`): ``_UNUSED`` when
    another one is selected (a plug-in registered after the run was recorded changes nothing it did), its
    defaults when it is; ``_NOTHING`` for a key that is no such table."""
    for registry in (plugins.METHODS, plugins.ESTIMATORS):
        settings = registry.settings()
        if registry.selector is not None and registry.selector in table and name in settings:
            return settings[name]().to_dict() if table[registry.selector] == name else _UNUSED
    return _NOTHING


def _task_settings(record: dict) -> dict:
    """The compared part of a ``task.json``: the resolved task configuration and its condition."""
    out = dict(record.get("config", {}))
    out["condition"] = record.get("condition", 0)  # a task built in code records none: condition 0
    return out


def _file_differences(old: dict, new: dict) -> list[str]:
    out = []
    for name in sorted(set(old) | set(new)):
        if name not in new:
            out.append(f"model file {name} no longer read")
        elif name not in old:
            out.append(f"model file {name} added")
        elif old[name] != new[name]:
            out.append(f"model file {name} changed (sha256 {old[name][:10]}... -> {new[name][:10]}...)")
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _holder(path: Path, wait: float = 0.0) -> str:
    """The lock holder as written in the lock file.  ``wait``: seconds to keep reading while the file is
    still empty (a holder between taking the lock and writing its pid)."""
    deadline = time.monotonic() + wait
    while True:
        try:
            text = files.read_bytes(path, 4096, what="lock file").decode(errors="replace").split()
        except (OSError, ConfigError):
            text = []
        if text or time.monotonic() >= deadline:
            break
        time.sleep(0.01)
    if not text:
        return "another process"
    host = f" on {text[1]}" if len(text) > 1 else ""
    return f"process {text[0]}{host}"


@contextlib.contextmanager
def lock_directory(path: str | Path, anchor: str | Path | None = None, what: str = "run directory") -> Iterator[Path]:
    """Hold the exclusive lock of the directory ``path`` (created if needed) for the ``with`` block.

    Raises :class:`RunDirectoryError` naming the holder if another live process holds it.  A lock
    file whose holder is gone is stale and taken over (module docstring, "Lock").  The lock file is
    opened without following a link (:func:`soc_opt.files.open_lock`); ``anchor``: the folder above
    ``path`` below which no link is followed; ``what`` names the directory in messages.
    """
    path = Path(path)
    lp = path / LOCK
    files.make_dirs(path, anchor=path if anchor is None else anchor)
    if fcntl is None:  # pragma: no cover - Windows
        with _pid_lock(lp):
            yield lp
        return
    try:
        fd = files.open_lock(lp, anchor=anchor)
    except OSError as e:
        if e.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise
        raise RunDirectoryError(f"{what} {str(path)!r} is not writable ({e.strerror}: cannot open its lock file "
                                f"{str(lp)!r}); soc_opt writes there to resume or finish a run: make it writable or "
                                "use another --out") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunDirectoryError(
                f"{what} {str(path)!r} is in use by {_holder(lp, wait=1.0)} (lock file {str(lp)!r}); "
                "wait for it to finish or use another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        try:
            yield lp
        finally:
            os.ftruncate(fd, 0)  # released: the file stays (unlinking it would race a waiting opener)
    finally:
        os.close(fd)


@contextlib.contextmanager
def _pid_lock(lp: Path):  # pragma: no cover - only where fcntl is missing
    try:
        fd = os.open(lp, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        text = lp.read_text().split()
        if text and text[0].isdigit() and _pid_alive(int(text[0])):
            raise RunDirectoryError(f"run directory {str(lp.parent)!r} is in use by {_holder(lp)} "
                                    f"(lock file {str(lp)!r})") from None
        os.unlink(lp)  # stale: its holder is gone
        fd = os.open(lp, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
    os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
    os.close(fd)
    try:
        yield
    finally:
        os.unlink(lp)


def encode_checkpoint(state) -> bytes:
    """The bytes of a checkpoint file (:func:`soc_opt.experiments.statefile.encode_state`)."""
    return encode_state(state)


def decode_checkpoint(path: Path):
    """The state in checkpoint file ``path``; :class:`CheckpointError` saying what is wrong.

    Nothing in the file is executed (:mod:`soc_opt.experiments.statefile`); a pickle file is refused."""
    path = Path(path)
    if path.suffix == ".pkl":
        refuse_legacy(path.parent, (path.name,))
    try:
        return decode_state(files.read_bytes(path, MAX_CHECKPOINT_BYTES, what="checkpoint"), path.name)
    except (StateFileError, files.UnsafePathError) as e:
        raise CheckpointError(str(e)) from None


def peek_checkpoint(path: Path) -> dict:
    """The top-level scalars (``iteration``, ...) of a verified checkpoint, rebuilding nothing."""
    try:
        return peek_state(files.read_bytes(path, MAX_CHECKPOINT_BYTES, what="checkpoint"), Path(path).name)
    except (StateFileError, files.UnsafePathError) as e:
        raise CheckpointError(str(e)) from None


def run_record(path: Path) -> dict | None:
    """The ``config.json`` of the run directory ``path``, or None when ``path`` is not one; a
    :class:`RunDirectoryError` naming it when ``config.json`` is not a file (a FIFO, socket or device).

    A run directory's ``config.json`` is a JSON table with ``format = "soc_opt run"`` (written since
    issue 31), or, written before, with the keys ``method`` (a string), ``seed`` and ``config`` (a table)."""
    p = Path(path) / "config.json"
    if not os.path.lexists(p):
        return None
    mode = os.lstat(p).st_mode
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):  # a FIFO, socket or device where a run keeps its record
        raise RunDirectoryError(f"{str(p)!r} is {kind_of(mode)}, not a regular file: no run of soc_opt wrote it, "
                                "so the folder is not a run directory; remove it or use another --out")
    try:
        meta = files.read_json_file(p, limit=files.MAX_JSON_BYTES)
    except (OSError, ConfigError):
        return None
    if not isinstance(meta, dict):
        return None
    if meta.get("format") == RUN_FORMAT:
        return meta
    legacy = isinstance(meta.get("method"), str) and "seed" in meta and isinstance(meta.get("config"), dict)
    return meta if legacy and "format" not in meta else None


#: Entries a folder may hold and still count as empty: what a run leaves before its config.json.
_EMPTY_OK = {LOCK, "policies", "samples"}


def unowned_entries(path: Path, owned=()) -> list[str]:
    """Entries of the folder ``path`` that no run of soc_opt put there (``[]`` for a new or empty
    folder, or one holding only a released lock, empty ``policies/`` / ``samples/`` and ``owned``)."""
    path = Path(path)
    if not os.path.lexists(path):
        return []
    out = []
    for name in sorted(os.listdir(path)):
        p = path / name
        if name in owned or name.startswith(".") and _TMP in name:
            continue
        if name == LOCK and p.is_file() and not p.is_symlink() and p.stat().st_size <= 256:
            continue
        if name in _EMPTY_OK and p.is_dir() and not p.is_symlink() and not any(
                n for n in os.listdir(p) if not (n.startswith(".") and _TMP in n)):
            continue
        out.append(name)
    return out


def refuse_foreign(path: Path, foreign: list[str], kind: str, marker: str, error: type[Exception] | None = None) -> None:
    """Raise ``error`` (default :class:`RunDirectoryError`) naming ``path`` and its first ``foreign`` entries
    (:func:`unowned_entries`) when there are any: ``path`` is not ``kind`` (marked by ``marker``) and not empty."""
    if not foreign:
        return
    shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
    raise (error or RunDirectoryError)(
        f"--out {str(path)!r} is not {kind} (no {marker}) and not empty ({shown}); soc_opt writes only into a new "
        f"or empty folder or {kind}, and --restart removes only its own files: use another --out")


@dataclass(frozen=True)
class RunDirectory:
    """Files of one run (module docstring).  ``anchor``: the folder the caller owns above ``path``
    (a compare or sweep directory; default ``path``), below which no link is followed."""

    path: Path
    anchor: Path | None = None

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "anchor", self.path if self.anchor is None else Path(self.anchor))

    def _write(self, name: str, data: bytes) -> None:
        files.write_bytes(self.path / name, data, anchor=self.anchor)

    def lock(self):
        """Context manager holding the directory's lock (:func:`lock_directory`)."""
        return lock_directory(self.path, anchor=self.anchor)

    def check_owned(self, owned=()) -> None:
        """Refuse (:class:`RunDirectoryError`) a folder that is neither new, empty nor a run directory:
        soc_opt writes no run into a folder of the user's (module docstring, "Ownership").  ``owned``:
        names the caller put there itself (a sweep trial's ``trial.json``)."""
        p = self.path
        if os.path.lexists(p) and not p.is_dir():
            raise RunDirectoryError(f"--out {str(p)!r} exists and is not a folder; use another --out")
        if self.anchor != p and p.is_symlink():
            raise RunDirectoryError(f"{str(p)!r} is a symbolic link; soc_opt writes only inside "
                                    f"{str(self.anchor)!r} and follows no link there: remove it or use another --out")
        if run_record(p) is not None:
            return
        refuse_foreign(p, unowned_entries(p, owned), "a soc_opt run directory", "config.json of a run")

    def has_checkpoint(self) -> bool:
        return os.path.lexists(self.path / CHECKPOINT) or os.path.lexists(self.path / PREVIOUS_CHECKPOINT)

    def prepare(self, meta: dict, task: dict | None = None,
                contract: Callable[[dict], dict] | None = None) -> None:
        """Check the run's contract against the directory's, or record it (module docstring).

        ``meta``: the content of ``config.json`` (method, seed, config); ``task``: of ``task.json``;
        ``contract(meta)``: the part of a ``config.json`` that must match (default: all of it).
        Call with the lock held.  A directory holding an old pickle checkpoint is refused
        (:func:`refuse_legacy`) before anything is written.
        """
        refuse_legacy(self.path)
        for sub in ("policies", "samples"):
            files.make_dirs(self.path / sub, anchor=self.anchor)
        self._remove_temporaries()
        meta = {"format": RUN_FORMAT, **json.loads(json.dumps(meta))}
        meta_path, task_path = self.path / "config.json", self.path / "task.json"
        if self.has_checkpoint() and os.path.lexists(meta_path):
            self.check_contract(meta, task, contract)
            if task is not None and not os.path.lexists(task_path):  # a directory from before task.json
                self._write("task.json", json.dumps(task, indent=2, sort_keys=True).encode())
            return
        self._write("config.json", json.dumps(meta, indent=2, sort_keys=True).encode())
        if task is not None:
            self._write("task.json", json.dumps(task, indent=2, sort_keys=True).encode())

    def _read_json(self, name: str):
        return files.read_json_file(self.path / name)

    def recorded_meta(self) -> dict:
        """The content of the directory's ``config.json`` (``{}`` when absent or unreadable)."""
        try:
            meta = self._read_json("config.json")
        except (OSError, ConfigError):
            return {}
        return meta if isinstance(meta, dict) else {}

    def check_contract(self, meta: dict, task: dict | None = None,
                       contract: Callable[[dict], dict] | None = None) -> None:
        """:class:`RunDirectoryError` listing what differs between the recorded contract and
        ``meta`` / ``task`` (see :meth:`prepare`); reads only, writes nothing."""
        meta = json.loads(json.dumps(meta))  # compared as stored: JSON has lists, no tuples
        task = None if task is None else json.loads(json.dumps(task))
        contract = contract or (lambda m: m)
        task_path = self.path / "task.json"
        try:
            old_meta = self._read_json("config.json")
            old_task = self._read_json("task.json") if task is not None and os.path.lexists(task_path) else None
        except (OSError, ConfigError) as e:
            raise RunDirectoryError(f"run directory {str(self.path)!r}: config.json or task.json cannot be read "
                                    f"({e}); use another --out, or --restart to discard that run") from None
        if not isinstance(old_meta, dict) or not (old_task is None or isinstance(old_task, dict)):
            raise RunDirectoryError(f"run directory {str(self.path)!r}: config.json or task.json is not a JSON "
                                    "table; use another --out, or --restart to discard that run")
        try:
            diffs = differences(contract(old_meta), contract(meta))
            if old_task is not None:
                diffs += differences(_task_settings(old_task), _task_settings(task), "task")
                diffs += _file_differences(dict(old_task.get("model_files", {})), task.get("model_files", {}))
        except (TypeError, ValueError, AttributeError, KeyError) as e:
            raise RunDirectoryError(f"run directory {str(self.path)!r}: config.json or task.json holds unexpected "
                                    f"content ({type(e).__name__}: {e}); use another --out, or --restart to "
                                    "discard that run") from None
        if diffs:
            more = f" (and {len(diffs) - 8} more)" if len(diffs) > 8 else ""
            raise RunDirectoryError(
                f"run directory {str(self.path)!r} holds a run with a different configuration (config.json, "
                f"task.json): "
                f"{'; '.join(diffs[:8])}{more}; use another --out, or --restart to discard that run"
            )

    def finished(self, meta: dict, task: dict | None, contract, is_done: Callable[[Any], bool]):
        """The state of a finished run in the directory (its contract matching ``meta`` / ``task``),
        or None.  Reads only: no lock, no file written, so a finished run opens on a read-only
        file system.  None when there is no intact last checkpoint or the run is not done
        (``is_done(state)``): the caller then takes the lock and resumes or reports."""
        main = self.path / CHECKPOINT
        refuse_legacy(self.path)
        if not os.path.lexists(main) or not os.path.lexists(self.path / "config.json"):
            return None
        self.check_owned()
        self.check_contract(meta, task, contract)
        try:
            state = decode_checkpoint(main)
        except CheckpointError:
            return None
        return state if is_done(state) else None

    def _remove_temporaries(self) -> None:
        """Temporary files of writes interrupted by a kill (never renamed into place)."""
        for sub in ("", "policies", "samples"):
            files.remove_matching(self.path / sub, rf"\..*{re.escape(_TMP)}.*", anchor=self.anchor)

    def clear(self) -> None:
        """Remove the files of a previous run (``--restart``): only the names a run writes, in a run
        directory (:meth:`check_owned`), never following a link; other files are left alone."""
        self.check_owned()
        for name in RUN_FILES:
            files.remove(self.path / name, anchor=self.anchor)
        for sub in ("policies", "samples"):
            files.remove_matching(self.path / sub, _ITER_FILE, anchor=self.anchor)
        self._remove_temporaries()

    def load_checkpoint(self, previous: bool = False):
        """The saved run state, or None if the run has not finished an iteration yet.

        ``previous``: load ``checkpoint.prev.npz`` (the iteration before the last) instead.  A
        damaged checkpoint raises :class:`CheckpointError` saying how to go on.
        """
        refuse_legacy(self.path)
        main, prev = self.path / CHECKPOINT, self.path / PREVIOUS_CHECKPOINT
        if previous:
            if not os.path.lexists(prev):
                raise CheckpointError(f"run directory {str(self.path)!r} has no previous checkpoint; "
                                      "rerun without --previous-checkpoint, or with --restart")
            try:
                return decode_checkpoint(prev)
            except CheckpointError as e:
                raise CheckpointError(f"run directory {str(self.path)!r}: {e}; rerun with --restart to "
                                      "start from scratch") from e
        if not os.path.lexists(main):
            return decode_checkpoint(prev) if os.path.lexists(prev) else None
        try:
            return decode_checkpoint(main)
        except CheckpointError as e:
            raise CheckpointError(f"run directory {str(self.path)!r}: {e}; {self._previous_hint()}") from e

    def _previous_hint(self) -> str:
        prev = self.path / PREVIOUS_CHECKPOINT
        try:  # verifies the checksum and reads the iteration count; rebuilds no state
            done = peek_checkpoint(prev).get("iteration") if os.path.lexists(prev) else None
        except CheckpointError:
            done = None
        if done is None:
            return "there is no intact previous checkpoint: rerun with --restart to start from scratch"
        return (f"rerun with --previous-checkpoint to resume from the previous checkpoint ({done} "
                "iterations done; later iterations are recomputed identically), or with --restart to "
                "start from scratch")

    def write_file(self, name: str, data: bytes) -> None:
        """Write ``data`` to the file ``name`` (a path relative to the directory), atomically and inside it."""
        self._write(name, data)

    def save_policy(self, iteration: int, policy) -> None:
        """``policies/iter_XXX.npz``: the policy sampled in iteration ``XXX`` (after ``XXX`` iterations)."""
        self._write(f"policies/iter_{iteration:03d}.npz", npz_bytes(**policy.to_dict()))

    def save(self, state) -> None:
        """Write the iteration's files, then the checkpoint (atomically, last; the previous one kept).

        ``state`` is a :class:`~soc_opt.methods.state.RunState` or :class:`~soc_opt.methods.ilqg.ILQGState`
        (``iteration``, ``policy``, ``history``, ``best``, ``last_rollouts``).
        """
        it = state.iteration
        self.save_policy(it, state.policy)
        if state.last_rollouts is not None:
            self._write(f"samples/iter_{it - 1:03d}.npz", npz_bytes(compress=False, **state.last_rollouts.to_dict()))
        rows = [r.summary() for r in state.history]
        self._write("metrics.json", json.dumps([{k: _jsonable(v) for k, v in r.items()} for r in rows], indent=1).encode())
        keys = list(dict.fromkeys(k for r in rows for k in r))
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\r\n")
        w.writeheader()
        w.writerows(rows)
        self._write("metrics.csv", buf.getvalue().encode())
        costs = [r.cost for r in state.history]
        self._write("costs.npz", npz_bytes(
            iteration=np.array([r.iteration for r in state.history]),
            phase=np.array([r.phase for r in state.history]),
            **{f"cost_{i:03d}": np.asarray(c, float) for i, c in enumerate(costs)},
        ))
        best = state.best
        if best is not None:
            self._write("best_policy.npz", npz_bytes(**best.policy.to_dict(), mean_cost=best.mean_cost,
                                                     iteration=best.iteration))
        self._keep_previous_checkpoint()
        self._write(CHECKPOINT, encode_checkpoint(state))

    def _keep_previous_checkpoint(self) -> None:
        """``checkpoint.npz`` becomes ``checkpoint.prev.npz`` (a hard link of the regular file, renamed into
        place; a copy where the file system has no hard links; nothing when it is not a regular file)."""
        main = self.path / CHECKPOINT
        try:
            st = os.lstat(main)
        except FileNotFoundError:
            return
        if not stat.S_ISREG(st.st_mode):
            return
        tmp = self.path / f".{PREVIOUS_CHECKPOINT}{_TMP}{os.getpid()}"
        files.remove(tmp, anchor=self.anchor)
        try:
            os.link(main, tmp, follow_symlinks=False)
            os.replace(tmp, self.path / PREVIOUS_CHECKPOINT)
        except OSError:  # no hard links on this file system
            files.remove(tmp, anchor=self.anchor)
            self._write(PREVIOUS_CHECKPOINT, files.read_bytes(main, MAX_CHECKPOINT_BYTES, what="checkpoint"))
