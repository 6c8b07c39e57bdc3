"""Progress of long work: a tqdm bar on a terminal, plain lines otherwise (CI logs, files).

:class:`Progress` is what the command line hands to :func:`soc_opt.experiments.run.run_experiment`
and :func:`soc_opt.experiments.compare.compare`.  It opens one :class:`Bar` per loop (iterations of one
run; seeds of a comparison, with the runs' bars nested below):

* ``mode = "bar"``: a tqdm bar on ``stream`` (default ``sys.stderr``) whose postfix shows the
  latest values (cost, KL, task metric); each finished step's full line is printed to stdout
  above the bars (``tqdm.write``), so the history stays in the scroll-back;
* ``mode = "lines"``: no bar; each finished step prints its full line (the pre-bar output);
* ``mode = "auto"`` (default): ``"bar"`` when ``stream`` and stdout are terminals, else ``"lines"``.

Library code never prints: without a :class:`Progress` (``progress=None``) nothing is shown.
"""

from __future__ import annotations

import os
import sys
from typing import Callable, Literal

__all__ = ["Progress", "Bar", "resolve_mode", "as_progress"]

Mode = Literal["auto", "bar", "lines"]


def _print_line(line: str) -> None:
    print(line, flush=True)


def _isatty(stream) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # closed stream
        return False


def resolve_mode(mode: Mode, stream) -> str:
    """``"bar"`` or ``"lines"``: ``auto`` is ``bar`` when ``stream`` and stdout are terminals
    (and ``TERM`` is not ``dumb``), so that redirected output gets plain lines."""
    if mode not in ("auto", "bar", "lines"):
        raise ValueError(f"progress mode must be 'auto', 'bar' or 'lines', got {mode!r}")
    if mode != "auto":
        return mode
    tty = _isatty(stream) and _isatty(sys.stdout)
    return "bar" if tty and os.environ.get("TERM", "") != "dumb" else "lines"


class Bar:
    """One loop's progress (made by :meth:`Progress.bar`); a context manager that closes itself."""

    def __init__(self, progress: "Progress", total: int, desc: str, initial: int, level: int):
        self.progress = progress
        self.total = int(total)
        self.desc = desc
        self.n = int(initial)
        self._tqdm = None
        if progress.mode == "bar":
            from tqdm.auto import tqdm

            self._tqdm = tqdm(total=self.total, initial=self.n, desc=desc, position=level, leave=level == 0,
                              file=progress.stream, dynamic_ncols=True)

    def advance(self, line: str | None = None, **postfix) -> None:
        """One step done: show ``postfix`` (numbers are shortened) and print ``line`` (if any)."""
        self.n += 1
        if self._tqdm is not None:
            self._tqdm.set_postfix({k: _short(v) for k, v in postfix.items()}, refresh=False)
            self._tqdm.update(1)
        if line is not None:
            self.progress.message(line)

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()
            self._tqdm = None

    def __enter__(self) -> "Bar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _short(v):
    return f"{v:.4g}" if isinstance(v, float) else v


class Progress:
    """Where progress goes (module docstring).

    mode:       ``"auto"``, ``"bar"`` or ``"lines"``.
    print_line: how a line is printed in ``lines`` mode (default: ``print`` to stdout, flushed).
    stream:     the bars' stream (default ``sys.stderr``; also decides ``auto``).
    """

    def __init__(self, mode: Mode = "auto", print_line: Callable[[str], None] | None = None, stream=None):
        self.stream = sys.stderr if stream is None else stream
        self.mode = resolve_mode(mode, self.stream)
        self.print_line = print_line or _print_line

    def message(self, line: str) -> None:
        """Print a line (above any bar, so that the bars stay at the bottom)."""
        if self.mode == "bar":
            from tqdm.auto import tqdm

            tqdm.write(line, file=sys.stdout)
            sys.stdout.flush()
        else:
            self.print_line(line)

    def bar(self, total: int, desc: str, *, initial: int = 0, level: int = 0) -> Bar:
        """A bar over ``total`` steps (``initial`` already done, e.g. on resume); ``level`` nests it."""
        return Bar(self, total, desc, initial, level)


def as_progress(progress) -> Progress | None:
    """``progress`` itself, a ``lines`` :class:`Progress` printing through a callable, or ``None``."""
    if progress is None or isinstance(progress, Progress):
        return progress
    if callable(progress):
        return Progress("lines", print_line=progress)
    raise TypeError(f"progress must be a soc_opt.experiments.progress.Progress, a callable taking a line, or None; got {progress!r}")
