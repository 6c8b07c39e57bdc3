"""The one reader of files soc_opt did not just write itself: it never blocks and never reads past a bound.

Every file soc_opt reads from disk (run and sweep records, checkpoints, configuration, task and sweep
files, MJCF models and what they reference, certificates, policy files) is read by :func:`read_regular`:

- the name is looked at first (``lstat``, or ``stat`` where links are followed): anything but a regular
  file (a FIFO, a socket, a device, a folder) is refused before it is opened, so opening cannot block
  on a FIFO with no writer nor wake a device;
- it is then opened with ``O_NONBLOCK`` (and ``O_NOFOLLOW`` unless links are followed) and checked
  again on the descriptor (``fstat``): a FIFO swapped in after the first look is opened without
  blocking and refused before anything is read;
- a file larger than its limit is refused before anything is read, and reading stops one byte past
  the limit (a file growing while it is read).

:func:`check_regular` applies the same test without reading (files handed to another library that
opens them itself, e.g. MuJoCo's includes and meshes).  Refusals raise :class:`RefusedFile` naming
the file and what it is (docs/security.md, "Bounded reads").
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["RefusedFile", "read_regular", "check_regular", "kind_of"]

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_NOCTTY = getattr(os, "O_NOCTTY", 0)


class RefusedFile(ValueError):
    """A file that is not a regular file, or larger than soc_opt reads; ``path`` and ``reason`` name it."""

    def __init__(self, path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{str(path)!r} {reason}")

    def __reduce__(self):  # picklable (a worker process may send it back)
        return type(self), (self.path, self.reason)


def kind_of(mode: int) -> str:
    """What a file of mode ``mode`` is, in words (``"a FIFO (named pipe)"``, ``"a socket"``, ...)."""
    for test, name in ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISDIR, "a folder"), (stat.S_ISLNK, "a symbolic link")):
        if test(mode):
            return name
    return "not a regular file"


def _not_regular(path, mode: int, what: str) -> RefusedFile:
    return RefusedFile(path, f"is {kind_of(mode)}, not a regular file; soc_opt reads its {what} only from a "
                             "regular file")


def _too_big(path, size: int, limit: int, what: str) -> RefusedFile:
    return RefusedFile(path, f"holds {size} bytes, more than a {what} may ({limit} bytes)")


def check_regular(path: str | Path, *, what: str = "file", follow: bool = True, limit: int | None = None) -> os.stat_result:
    """The status of ``path`` if it is a regular file (of at most ``limit`` bytes); :class:`RefusedFile`
    otherwise.  Nothing is opened.  ``FileNotFoundError`` when it does not exist."""
    st = os.stat(path) if follow else os.lstat(path)
    if not stat.S_ISREG(st.st_mode):
        raise _not_regular(path, st.st_mode, what)
    if limit is not None and st.st_size > limit:
        raise _too_big(path, st.st_size, limit, what)
    return st


def read_regular(path: str | Path, limit: int, *, what: str = "file", follow: bool = False,
                 dir_fd: int | None = None) -> bytes:
    """The content of the regular file ``path`` (at most ``limit`` bytes), read without blocking.

    ``follow``: follow a symbolic link at the name (a file the user named); by default a link is refused.
    ``dir_fd``: ``path`` is relative to this open folder.  Raises :class:`RefusedFile` for a link (unless
    ``follow``), anything but a regular file, or more than ``limit`` bytes, before reading anything;
    ``FileNotFoundError`` and other ``OSError`` as ``open`` does.
    """
    st = os.stat(path, dir_fd=dir_fd, follow_symlinks=follow)
    if stat.S_ISLNK(st.st_mode):
        raise RefusedFile(path, f"is a symbolic link; soc_opt reads its {what} only from a regular file in the "
                                "directory")
    if not stat.S_ISREG(st.st_mode):
        raise _not_regular(path, st.st_mode, what)
    flags = os.O_RDONLY | _NONBLOCK | _CLOEXEC | _NOCTTY | (0 if follow else _NOFOLLOW)
    try:
        fd = os.open(path, flags, dir_fd=dir_fd)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise RefusedFile(path, f"is a symbolic link; soc_opt reads its {what} only from a regular file in "
                                    "the directory") from None
        if e.errno == errno.ENXIO:  # a socket (or a FIFO swapped in) opened without a peer
            raise RefusedFile(path, f"is a socket or FIFO, not a regular file; soc_opt reads its {what} only "
                                    "from a regular file") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(path, st.st_mode, what)
        if st.st_size > limit:
            raise _too_big(path, st.st_size, limit, what)
        chunks, n = [], 0
        while n <= limit:  # one read for a file that does not grow (its size plus one byte, to see growth)
            chunk = os.read(fd, min(limit + 1 - n, max(st.st_size + 1 - n, 1 << 16)))
            if not chunk:
                break
            chunks.append(chunk)
            n += len(chunk)
    finally:
        os.close(fd)
    if n > limit:
        raise RefusedFile(path, f"grew beyond {limit} bytes while read")
    return b"".join(chunks)
