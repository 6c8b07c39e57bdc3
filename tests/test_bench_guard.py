"""Guarded solver calls (soc_opt/bench/guard.py) and ``soc-opt solvers`` stopping on Ctrl-C.

The worker ignores SIGINT and a call can block in compiled code for as long as it likes (``time.sleep`` in
the worker stands for fatrop looping on NaN): the limits and Ctrl-C must act from the waiting process.
Every wait below has a timeout guard; nothing asserts how long anything took.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time

import pytest

from soc_opt.bench.guard import Guard, GuardError


def _print_nan_then_sleep(times: int, seconds: float) -> None:
    for _ in range(times):
        os.write(2, b'WARNING("nlp_g failed: NaN detected for output g")\n')
    time.sleep(seconds)


def test_a_call_returns_its_value_and_raises_its_own_exceptions():
    with Guard() as g:
        assert g.call(pow, 3, 4, limit_s=30) == 81
        with pytest.raises(ValueError, match="invalid literal"):
            g.call(int, "x", limit_s=30)
        assert g.call(abs, -2, limit_s=30) == 2  # the same worker, still alive


def test_a_call_past_its_time_limit_is_stopped_and_the_next_call_gets_a_new_worker():
    with Guard() as g:
        with pytest.raises(GuardError, match="time limit of 0.5 s") as e:
            g.call(time.sleep, 60, limit_s=0.5)
        assert e.value.status == "time limit"
        assert g.call(pow, 2, 10, limit_s=30) == 1024


def test_a_call_that_keeps_reporting_nan_is_stopped_without_waiting_for_its_limit():
    with Guard(nan_limit=20) as g:
        with pytest.raises(GuardError, match="21 'NaN detected' reports") as e:
            g.call(_print_nan_then_sleep, 21, 60, limit_s=600)
        assert e.value.status == "NaN"
        assert g.call(_print_nan_then_sleep, 3, 0, limit_s=30) is None  # a few NaN reports are tolerated


def _line(stream, timeout: float = 120.0) -> bytes:
    """The next line of ``stream``, or a failure after ``timeout`` seconds (a guard, not a measurement)."""
    ready, _, _ = select.select([stream], [], [], timeout)
    assert ready, f"no output within {timeout} s"
    return stream.readline()


_SCRIPT = """
import sys, time
from soc_opt.bench.guard import Guard

def nap(path):
    open(path, "w").close()  # the worker is in its call
    time.sleep(120)

with Guard() as g:
    print("calling", flush=True)
    g.call(nap, sys.argv[1], limit_s=600)
"""


def _wait_for(path, timeout: float = 120.0) -> None:
    """Until ``path`` exists (a guard of ``timeout`` seconds, not a measurement)."""
    end = time.monotonic() + timeout
    while not os.path.exists(path):
        assert time.monotonic() < end, f"{path} did not appear within {timeout} s"
        time.sleep(0.01)


def _group_gone(pgid: int, timeout: float = 60.0) -> bool:
    """Whether every process of group ``pgid`` has exited within ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


def _interruptible(args: list[str]) -> subprocess.Popen:
    """``args`` in a new session with Ctrl-C's default action restored: a shell's background job (``make test &``)
    starts its children with SIGINT ignored, and an interpreter started that way never raises KeyboardInterrupt."""
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def test_ctrl_c_stops_a_guarded_call_blocked_in_the_worker(tmp_path):
    marker = tmp_path / "asleep"
    proc = _interruptible([sys.executable, "-c", _SCRIPT, str(marker)])
    try:
        assert _line(proc.stdout).strip() == b"calling"
        _wait_for(marker)  # the worker is asleep in its call
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)  # the guard: a hang fails here instead of hanging the suite
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert b"KeyboardInterrupt" in err
    with pytest.raises(ProcessLookupError):  # no worker left behind in the process group
        os.killpg(proc.pid, 0)


def test_ctrl_c_at_once_still_leaves_no_worker_behind():
    """Ctrl-C as soon as the script announces its call: it may land before, during or after the fork."""
    proc = _interruptible([sys.executable, "-c", _SCRIPT, os.devnull])
    try:
        assert _line(proc.stdout).strip() == b"calling"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert b"KeyboardInterrupt" in err
    assert _group_gone(proc.pid), "a worker outlived the interrupted script"


_IDLE = """
import time
from soc_opt.bench.guard import Guard
g = Guard()
g.call(pow, 2, 3, limit_s=30)
print("idle", flush=True)
time.sleep(120)
"""


def test_an_idle_worker_exits_when_its_guards_process_is_killed():
    """SIGKILL gives the guard no chance to end its worker: the worker sees the end of its pipe and exits."""
    proc = subprocess.Popen([sys.executable, "-c", _IDLE], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        assert _line(proc.stdout).strip() == b"idle"
        proc.kill()
        proc.wait(timeout=60)
        assert _group_gone(proc.pid), "the worker outlived its guard's process"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.slow
def test_soc_opt_solvers_stops_on_ctrl_c_with_exit_status_130():
    """The command itself (about 10-20 s: it starts the benchmark, waits for its first progress line)."""
    proc = _interruptible([sys.executable, "-m", "soc_opt.cli", "solvers", "--sizes", "2x1", "--instances", "1"])
    try:
        assert b"guarded worker" in _line(proc.stderr)
        assert b"M-step [1/" in _line(proc.stderr)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130 and b"soc-opt: interrupted" in err and b"resume" not in err
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)
