"""Work split over forked child processes, with results identical to running it in turn.

Used where the work is Python-bound (the kinematic estimator's EM starts, rollouts whose policy runs
a filter in Python), so threads would wait on each other.  A child is a ``fork`` of this process: it
sees the same objects without pickling them, runs one piece of the work with the same arithmetic as
the parent would, and sends the result back through a pipe.  No random state is drawn in a child
(callers draw their noise up front), so the results do not depend on how the work is split.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from typing import Any, Callable, Sequence

from .errors import WorkerDiedError

__all__ = ["can_fork", "spare_cpu", "fork_map"]



def _thread_pools_running() -> bool:
    """Whether JAX has started a backend in this process: its thread pools can leave a forked child
    deadlocked (JAX warns on such a fork).  Importing JAX alone, as CVXPY does when it probes its
    solvers, starts no threads; nor does importing PyTorch (the TensorBoard writer may), whose
    thread pool starts only with its first parallel operation, which soc_opt does not run."""
    xla = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(xla, "_backends", None))


def can_fork() -> bool:
    """Whether :func:`fork_map` can run pieces side by side: ``fork`` exists, this process may use more
    than one CPU, may have child processes (a daemonic process may not) and has not started JAX (the
    peers' benchmarks), whose thread pools a fork can leave deadlocked."""
    return (_cpus() > 1 and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon
            and not _thread_pools_running())


def _cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def spare_cpu() -> bool:
    """Whether a second process would find a CPU to run on: the 1-minute load average (runnable tasks,
    this process included) is below the CPUs this process may use minus one half (``make -l`` in
    spirit).  On a machine busy with other jobs a forked piece only takes CPU time from this process
    (and its fork and copy-on-write cost more than it saves: docs/results/noise/kinematic.md, the
    per-phase table), so :func:`fork_map` then runs the items in turn; the results are the same
    either way, only the wall time differs.  ``True`` where the load average is unavailable."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return True
    return load < _cpus() - 0.5


def _child(conn, fn, item):
    try:
        conn.send(("ok", fn(item)))
    except BaseException as exc:  # noqa: BLE001 -- handed to the parent, which raises it
        try:
            conn.send(("error", exc))
        except Exception:  # an exception that does not pickle: send its text
            conn.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))
    finally:
        conn.close()


def fork_map(fn: Callable[[Any], Any], items: Sequence, parallel: bool = True) -> list:
    """``[fn(item) for item in items]``; with ``parallel`` (and :func:`can_fork` and :func:`spare_cpu`)
    every item after the first runs in a forked child while this process runs the first.

    Errors: the exception of the first item (in order) that raised is raised here, as raised there; a
    child that ends without a result raises :class:`~soc_opt.errors.WorkerDiedError` (a ``RuntimeError``) with
    its exit code.
    """
    items = list(items)
    if not parallel or len(items) < 2 or not can_fork() or not spare_cpu():
        return [fn(item) for item in items]
    ctx = multiprocessing.get_context("fork")
    kids = []
    done = False
    try:
        for item in items[1:]:
            recv, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child, args=(send, fn, item), daemon=True)
            proc.start()
            send.close()
            kids.append((proc, recv))
        results: list = []
        errors: list = []
        try:
            results.append(fn(items[0]))
        except Exception as exc:  # the children's results are still collected (and their errors ordered)
            results.append(None)
            errors.append(exc)
        for proc, recv in kids:
            try:
                status, value = recv.recv()
            except EOFError:
                proc.join()
                status, value = "error", WorkerDiedError(
                    f"a forked worker ended without a result (exit code {proc.exitcode})")
            results.append(value if status == "ok" else None)
            if status != "ok":
                errors.append(value)
        done = True
        if errors:
            raise errors[0]
        return results
    finally:
        for proc, recv in kids:
            recv.close()
            if not done:
                proc.kill()
            proc.join()
