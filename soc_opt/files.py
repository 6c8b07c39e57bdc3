"""Files inside a directory soc_opt owns: written, removed and read without following links out of it.

Every file of a run, compare or sweep directory (metrics, checkpoints, policies, figures, reports,
the lock) is written here, relative to an **anchor**: the folder the user named (``--out``), which
may itself be a symbolic link.  Below the anchor nothing is followed:

- each folder between the anchor and the file is opened with ``O_NOFOLLOW`` (a symbolic link there,
  e.g. a planted ``policies -> /elsewhere``, is refused with :class:`UnsafePathError` naming it);
- a file is written to a new temporary name (``O_CREAT | O_EXCL | O_NOFOLLOW``) in that folder and
  renamed over the final name, which replaces a symbolic link at that name instead of writing
  through it;
- the lock is opened with ``O_NOFOLLOW`` and must be a regular file with one link;
- removals unlink names in the opened folder (a link is removed, never its target).

Reads are bounded and never block: :func:`read_bytes` (:mod:`soc_opt.reading`) opens the file with
``O_NOFOLLOW | O_NONBLOCK``, requires a regular file and refuses one larger than its limit before
reading anything; :func:`load_json` bounds the
nesting depth of what it parses.  See docs/security.md.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import re
import secrets
import stat
from pathlib import Path
from typing import Any, Iterator

from .config import MAX_DEPTH, ConfigError, check_depth
from .reading import RefusedFile, read_regular

__all__ = ["UnsafePathError", "write_bytes", "write_text", "write_json", "save_figure", "remove", "remove_matching",
           "make_dirs", "open_dir", "open_lock", "read_bytes", "load_json", "read_json_file", "MAX_JSON_BYTES", "TMP_MARK"]

#: Files written by soc_opt are renamed into place from ``.<name>.tmp-<pid>-<random>``.
TMP_MARK = ".tmp-"
#: Largest JSON file (config.json, task.json, result.json, ...) read back: 64 MiB.
MAX_JSON_BYTES = 64 << 20

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_DIRECTORY = getattr(os, "O_DIRECTORY", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)


class UnsafePathError(ConfigError):
    """A path inside an owned directory is a symbolic link, not a regular file or folder, or too big;
    the message names it."""


def _parts(path: Path, anchor: Path) -> list[str]:
    try:
        rel = Path(os.path.abspath(path)).relative_to(os.path.abspath(anchor))
    except ValueError:
        raise ValueError(f"{str(path)!r} is not inside {str(anchor)!r}") from None
    parts = [p for p in rel.parts if p not in ("", ".")]
    if ".." in parts:
        raise ValueError(f"{str(path)!r} leaves {str(anchor)!r}")
    return parts


def _named(e: OSError, path: Path) -> OSError:
    """``e`` naming ``path`` in full (an error from a call relative to a folder's descriptor names only the last
    component, or a temporary name)."""
    return type(e)(e.errno, e.strerror or str(e), str(path))


def _refuse(path: Path, anchor: Path, what: str) -> UnsafePathError:
    return UnsafePathError(f"{str(path)!r} {what}; soc_opt writes only inside {str(anchor)!r} and follows no link "
                           "there: remove it or use another --out")


@contextlib.contextmanager
def _dir_fd(directory: Path, anchor: Path, create: bool) -> Iterator[int]:
    """A descriptor of ``directory``, opened from ``anchor`` one folder at a time without following links."""
    directory, anchor = Path(directory), Path(anchor)
    try:
        if create:
            anchor.mkdir(parents=True, exist_ok=True)
        fd = os.open(anchor, os.O_RDONLY | _DIRECTORY | _CLOEXEC)
    except OSError as e:
        raise _named(e, anchor) from None
    try:
        here = anchor
        for part in _parts(directory, anchor):
            here = here / part
            try:
                if create:
                    with contextlib.suppress(FileExistsError):
                        os.mkdir(part, 0o777, dir_fd=fd)
                sub = os.open(part, os.O_RDONLY | _DIRECTORY | _NOFOLLOW | _CLOEXEC, dir_fd=fd)
            except OSError as e:
                if e.errno in (errno.ELOOP, errno.ENOTDIR):
                    kind = "is a symbolic link" if os.path.islink(here) else "is not a folder"
                    raise _refuse(here, anchor, kind) from None
                raise _named(e, here) from None
            os.close(fd)
            fd = sub
        yield fd
    finally:
        os.close(fd)


def write_bytes(path: str | Path, data: bytes, *, anchor: str | Path | None = None) -> Path:
    """Write ``data`` to ``path`` (inside ``anchor``; default: its own folder) atomically: to a new
    temporary file, flushed to disk, renamed over ``path``.  Missing folders below ``anchor`` are
    created; files get the permissions the umask allows (as ``open`` creates them)."""
    path = Path(path)
    anchor = path.parent if anchor is None else Path(anchor)
    with _dir_fd(path.parent, anchor, create=True) as dfd:
        tmp = f".{path.name}{TMP_MARK}{os.getpid()}-{secrets.token_hex(4)}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC, 0o666, dir_fd=dfd)
        except OSError as e:
            raise _named(e, path) from None
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path.name, src_dir_fd=dfd, dst_dir_fd=dfd)
        except BaseException as e:
            with contextlib.suppress(OSError):
                os.unlink(tmp, dir_fd=dfd)
            if isinstance(e, OSError) and not isinstance(e, UnsafePathError):
                raise _named(e, path) from None
            raise
    return path


def write_text(path: str | Path, text: str, *, anchor: str | Path | None = None) -> Path:
    """:func:`write_bytes` of ``text`` in UTF-8."""
    return write_bytes(path, text.encode(), anchor=anchor)


def write_json(path: str | Path, data: Any, *, anchor: str | Path | None = None, **dumps) -> Path:
    """:func:`write_bytes` of ``json.dumps(data, **dumps)``."""
    return write_bytes(path, json.dumps(data, **dumps).encode(), anchor=anchor)


def save_figure(fig, path: str | Path, *, anchor: str | Path | None = None, **savefig) -> Path:
    """A matplotlib figure rendered to PNG in memory and written with :func:`write_bytes`."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", **savefig)
    return write_bytes(path, buf.getvalue(), anchor=anchor)


def make_dirs(directory: str | Path, *, anchor: str | Path) -> Path:
    """Create ``directory`` and the folders between it and ``anchor`` (none of them a link)."""
    with _dir_fd(Path(directory), Path(anchor), create=True):
        pass
    return Path(directory)


def open_dir(directory: str | Path, *, anchor: str | Path) -> int:
    """A descriptor of the existing folder ``directory``, opened from ``anchor`` one folder at a time without
    following a link (:class:`UnsafePathError` naming one); the caller closes it.  Writing through it (e.g.
    ``/proc/self/fd/N/name``) stays in that folder whatever is renamed or linked later."""
    with _dir_fd(Path(directory), Path(anchor), create=False) as fd:
        return os.dup(fd)


def remove(path: str | Path, *, anchor: str | Path | None = None) -> bool:
    """Unlink the file ``path`` (a link is removed, not its target); False when it does not exist."""
    path = Path(path)
    anchor = path.parent if anchor is None else Path(anchor)
    if not os.path.lexists(path.parent):
        return False
    try:
        with _dir_fd(path.parent, anchor, create=False) as dfd:
            os.unlink(path.name, dir_fd=dfd)
    except FileNotFoundError:
        return False
    return True


def remove_matching(directory: str | Path, pattern: str, *, anchor: str | Path) -> list[str]:
    """Unlink the files (and links) of ``directory`` whose names match the regular expression
    ``pattern`` entirely; folders are left alone.  Returns the names removed."""
    directory = Path(directory)
    if not os.path.lexists(directory):
        return []
    rx = re.compile(pattern)
    out = []
    with _dir_fd(directory, Path(anchor), create=False) as dfd:
        for name in sorted(os.listdir(dfd)):
            if not rx.fullmatch(name):
                continue
            st = os.stat(name, dir_fd=dfd, follow_symlinks=False)
            if stat.S_ISDIR(st.st_mode):
                continue
            with contextlib.suppress(FileNotFoundError):
                os.unlink(name, dir_fd=dfd)
                out.append(name)
    return out


def open_lock(path: str | Path, *, anchor: str | Path | None = None) -> int:
    """A read-write descriptor of the lock file ``path`` (created if missing), never through a link:
    a link or a file with other hard links at that name is refused (truncating it would change
    another file)."""
    path = Path(path)
    anchor = path.parent if anchor is None else Path(anchor)
    with _dir_fd(path.parent, anchor, create=True) as dfd:
        try:
            fd = os.open(path.name, os.O_RDWR | os.O_CREAT | _NOFOLLOW | _CLOEXEC | _NONBLOCK, 0o644, dir_fd=dfd)
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise _refuse(path, anchor, "is a symbolic link") from None
            if e.errno == errno.ENXIO:
                raise _refuse(path, anchor, "is a socket, not a regular file") from None
            raise _named(e, path) from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
        os.close(fd)
        what = "is not a regular file" if not stat.S_ISREG(st.st_mode) else f"has {st.st_nlink} hard links"
        raise _refuse(path, anchor, what)
    return fd


def read_bytes(path: str | Path, limit: int, *, what: str = "file") -> bytes:
    """The content of the regular file ``path`` (no link followed at its name), read without blocking
    (:func:`soc_opt.reading.read_regular`): :class:`UnsafePathError` when it is not a regular file (a link,
    a FIFO, a socket, a device) or holds more than ``limit`` bytes, before anything is read."""
    try:
        return read_regular(path, limit, what=what)
    except RefusedFile as e:
        raise UnsafePathError(str(e)) from None


def load_json(data: bytes | str, name: str) -> Any:
    """Parsed JSON whose lists and tables nest at most :data:`MAX_DEPTH` deep; :class:`ConfigError`
    naming ``name`` for invalid JSON or deeper nesting (never a bare ``RecursionError``)."""
    try:
        value = json.loads(data)
    except RecursionError:
        raise ConfigError(f"{name}: nested more than {MAX_DEPTH} levels deep; not a file soc_opt wrote") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise ConfigError(f"{name}: not valid JSON ({e})") from None
    return check_depth(value, name)


def read_json_file(path: str | Path, *, limit: int = MAX_JSON_BYTES) -> Any:
    """:func:`load_json` of the regular file ``path`` (:func:`read_bytes`, at most ``limit`` bytes)."""
    return load_json(read_bytes(path, limit, what="JSON file"), str(path))
