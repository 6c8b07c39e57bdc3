"""Tests for soc_opt/parallel.py: fork_map returns what running the items in turn returns, in order,
and raises the first item's error as raised there."""

import os

import numpy as np
import pytest

from soc_opt.parallel import can_fork, fork_map


@pytest.fixture
def forking():
    """Skip at run time (another test module may have started a thread pool since collection)."""
    if not can_fork():
        pytest.skip("needs fork, two CPUs and no started JAX backend")


def test_results_are_those_of_running_in_turn_in_item_order(forking):
    rng = np.random.default_rng(0)
    mats = [rng.standard_normal((6, 4, 4)) + 4 * np.eye(4) for _ in range(3)]
    got = fork_map(np.linalg.inv, mats)
    for g, m in zip(got, mats):
        np.testing.assert_array_equal(g, np.linalg.inv(m))
    assert fork_map(lambda i: i * i, range(5), parallel=False) == [0, 1, 4, 9, 16]


def test_items_after_the_first_run_in_other_processes(forking):
    pids = fork_map(lambda _: os.getpid(), range(3))
    assert pids[0] == os.getpid() and len(set(pids)) == 3


def test_the_first_failing_item_in_order_is_raised_whichever_process_ran_it(forking):
    def f(i):
        if i >= 1:
            raise ValueError(f"item {i} failed")
        return i

    with pytest.raises(ValueError, match="item 1 failed"):
        fork_map(f, range(3))

    def first_fails(i):
        if i in (0, 2):
            raise KeyError(f"item {i}")
        return i

    with pytest.raises(KeyError, match="item 0"):
        fork_map(first_fails, range(3))


def test_a_child_that_dies_is_reported_with_its_exit_code(forking):
    parent = os.getpid()

    def die(i):
        if i == 1 and os.getpid() != parent:                      # never the test process itself
            os._exit(3)
        return i

    with pytest.raises(RuntimeError, match="exit code 3"):
        fork_map(die, range(2))


def test_runs_in_turn_once_jax_has_started_a_backend(monkeypatch):
    import sys
    import types

    xla = types.ModuleType("jax._src.xla_bridge")
    xla._backends = {}
    monkeypatch.setitem(sys.modules, "jax._src.xla_bridge", xla)
    imported_only = can_fork()                                    # JAX imported, no backend: no threads yet
    xla._backends = {"cpu": object()}
    assert not can_fork()
    assert set(fork_map(lambda _: os.getpid(), range(3))) == {os.getpid()}
    assert imported_only == (len(os.sched_getaffinity(0)) > 1)


def test_runs_in_turn_when_the_load_leaves_no_cpu_idle(monkeypatch):
    """``spare_cpu``: below ``CPUs - 1/2`` runnable tasks in the last minute a piece is forked, above it
    the items run in this process (the results are the same; a busy machine only pays for the fork)."""
    import soc_opt.parallel as par

    monkeypatch.undo()                                            # the conftest's "always spare" off
    cpus = len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "getloadavg", lambda: (cpus - 0.4, 0.0, 0.0))
    assert not par.spare_cpu()
    assert set(par.fork_map(lambda _: os.getpid(), range(3))) == {os.getpid()}
    monkeypatch.setattr(os, "getloadavg", lambda: (cpus - 0.6, 0.0, 0.0))
    assert par.spare_cpu()
    monkeypatch.setattr(os, "getloadavg", lambda: (_ for _ in ()).throw(OSError("no load average")))
    assert par.spare_cpu()
