"""Tests for soc_opt/parallel.py: fork_map returns what running the items in turn returns, in order,
and raises the first item's error as raised there."""

import os

import numpy as np
import pytest

from soc_opt.parallel import can_fork, fork_map

pytestmark = pytest.mark.skipif(not can_fork(), reason="needs fork and two CPUs")


def test_results_are_those_of_running_in_turn_in_item_order():
    rng = np.random.default_rng(0)
    mats = [rng.standard_normal((6, 4, 4)) + 4 * np.eye(4) for _ in range(3)]
    got = fork_map(np.linalg.inv, mats)
    for g, m in zip(got, mats):
        np.testing.assert_array_equal(g, np.linalg.inv(m))
    assert fork_map(lambda i: i * i, range(5), parallel=False) == [0, 1, 4, 9, 16]


def test_items_after_the_first_run_in_other_processes():
    pids = fork_map(lambda _: os.getpid(), range(3))
    assert pids[0] == os.getpid() and len(set(pids)) == 3


def test_the_first_failing_item_in_order_is_raised_whichever_process_ran_it():
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


def test_a_child_that_dies_is_reported_with_its_exit_code():
    def die(i):
        if i == 1:
            os._exit(3)
        return i

    with pytest.raises(RuntimeError, match="exit code 3"):
        fork_map(die, range(2))
