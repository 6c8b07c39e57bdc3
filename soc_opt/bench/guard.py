"""Guarded solver calls for ``soc-opt solvers`` (docs/results/solvers/README.md, "Limits").

A solver stuck in compiled code (fatrop repeating "NaN detected" for minutes) neither returns nor sees
Python's ``KeyboardInterrupt``: the interpreter handles a signal only between bytecodes.  :class:`Guard`
therefore runs every call in a worker process (forked once, reused, forked again after a failure) and
waits on it from this process in steps of :data:`POLL_S` seconds, so that

* a call that exceeds its wall-time limit is killed and reported as :class:`GuardError` ("time limit");
* a call whose solver reports NaN more than ``nan_limit`` times (CasADi's ``NaN detected`` warnings on the
  worker's standard output and error, which the guard reads) is killed at once ("NaN");
* a worker that dies (a crash in compiled code) is reported, and the next call gets a new worker;
* Ctrl-C (``KeyboardInterrupt`` here, within ``POLL_S``) kills the worker and propagates: the command stops
  within a second whatever the solver is doing.

The worker ignores ``SIGINT`` (the terminal sends it to the whole process group; this process decides),
and it never outlives this process: it holds no copy of this process's end of their pipe, so an idle worker
sees the end of the pipe and exits when this process is gone, even by ``SIGKILL``.
An exception raised by the call itself is raised here as it was raised there.  Calls and arguments are
pickled to the worker: module-level functions and plain data.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import select
import signal
import time
from typing import Any, Callable

from ..errors import SolverError

__all__ = ["Guard", "GuardError", "POLL_S", "NAN_LIMIT"]

#: how often the waiting process wakes up (s): the latency of a Ctrl-C and of a time limit
POLL_S = 0.1
#: "NaN detected" reports tolerated in one call (a line search may step into a NaN and back out)
NAN_LIMIT = 20
_NAN = b"NaN detected"


class GuardError(SolverError):
    """A guarded call was stopped: ``status`` is ``"time limit"``, ``"NaN"`` or ``"worker died"``."""


def _worker(conn, other_end, out_fd: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    other_end.close()  # the guard's end, inherited by the fork: once the guard's process is gone, recv sees EOF
    os.dup2(out_fd, 1)  # the solvers' banners and warnings (C level) go to the guard, not the terminal
    os.dup2(out_fd, 2)
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        if job is None:
            return
        fn, args, kwargs = job
        try:
            conn.send(("ok", fn(*args, **kwargs)))
        except BaseException as exc:  # noqa: BLE001 -- handed to the parent, which raises it
            try:
                conn.send(("error", exc))
            except Exception:  # an exception that does not pickle: send its text
                conn.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))


class Guard:
    """Runs ``fn(*args, **kwargs)`` in a worker process with a wall-time limit (module docstring).

    ``call(fn, *args, limit_s=..., **kwargs)``; use as a context manager (the worker is ended on exit).
    ``last_output`` holds the tail of what the worker printed during the last call.
    """

    def __init__(self, nan_limit: int = NAN_LIMIT):
        self.nan_limit = nan_limit
        self._proc = None
        self._conn = None
        self._out = None
        self.last_output = b""

    def __enter__(self) -> Guard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _start(self) -> None:
        """Fork the worker.  The guard owns the process and its pipes before the fork, so that a Ctrl-C
        landing anywhere in here leaves :meth:`_kill` what to clean up."""
        ctx = multiprocessing.get_context("fork")
        parent, child = ctx.Pipe()
        out_r, out_w = os.pipe()
        os.set_blocking(out_r, False)
        proc = ctx.Process(target=_worker, args=(child, parent, out_w), daemon=True)
        self._proc, self._conn, self._out = proc, parent, out_r
        try:
            proc.start()
        finally:
            child.close()
            os.close(out_w)

    def _kill(self) -> None:
        proc, conn, out = self._proc, self._conn, self._out
        self._proc = self._conn = self._out = None
        if proc is not None and proc.pid is not None:  # started (a Ctrl-C may have come before the fork)
            proc.kill()
            proc.join()
        if conn is not None:
            conn.close()
        if out is not None:
            os.close(out)

    def close(self) -> None:
        """End the worker (politely if it is idle)."""
        if self._proc is not None and self._proc.is_alive():
            try:
                self._conn.send(None)
                self._proc.join(1.0)
            except OSError:
                pass
        self._kill()

    def _drain(self) -> int:
        """Read what the worker printed; the number of NaN reports in it."""
        n = 0
        while True:
            try:
                chunk = os.read(self._out, 65536)
            except BlockingIOError:
                return n
            if not chunk:
                return n
            n += chunk.count(_NAN)
            self.last_output = (self.last_output + chunk)[-4000:]

    def call(self, fn: Callable, *args, limit_s: float, **kwargs) -> Any:
        """The result of ``fn(*args, **kwargs)`` from the worker; :class:`GuardError` past ``limit_s`` seconds,
        after more than ``nan_limit`` NaN reports or when the worker dies."""
        if not limit_s > 0 or math.isnan(limit_s):
            raise ValueError(f"limit_s must be > 0, got {limit_s}")
        self.last_output = b""
        nans = 0
        deadline = time.monotonic() + limit_s
        try:
            if self._proc is None or not self._proc.is_alive():
                self._kill()
                self._start()
            self._conn.send((fn, args, kwargs))
            while True:
                ready, _, _ = select.select([self._conn, self._out], [], [], POLL_S)
                nans += self._drain()
                if self._conn in ready or self._conn.poll():
                    try:
                        status, value = self._conn.recv()
                    except EOFError:
                        code = self._proc.exitcode
                        self._kill()
                        raise GuardError(f"the solver's worker process died (exit code {code})",
                                         status="worker died") from None
                    if status == "error":
                        raise value
                    return value
                if nans > self.nan_limit:
                    self._kill()
                    raise GuardError(f"stopped after {nans} 'NaN detected' reports (more than {self.nan_limit})",
                                     status="NaN")
                if time.monotonic() > deadline:
                    self._kill()
                    raise GuardError(f"stopped at its time limit of {limit_s:g} s", status="time limit")
                if not self._proc.is_alive() and not self._conn.poll():
                    code = self._proc.exitcode
                    self._kill()
                    raise GuardError(f"the solver's worker process died (exit code {code})", status="worker died")
        except KeyboardInterrupt:
            self._kill()
            raise
