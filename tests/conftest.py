"""Shared pytest fixtures, built on :mod:`soc_opt.testing` (the random well-posed instances the
tests, benchmarks and verification share) and on the small ``linear2d`` task."""

from __future__ import annotations

import numpy as np
import pytest

from soc_opt import testing


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh ``numpy.random.Generator`` seeded with 0 for each test (pass it to ``soc_opt.testing``)."""
    return np.random.default_rng(0)


@pytest.fixture
def kl_instance():
    """A small KL-step instance ``(dynamics, cost, reference, mu0, P0)``: ``n=4, m=2, T=10``
    (:func:`soc_opt.testing.make_kl_instance`, seed 0)."""
    return testing.make_kl_instance(4, 2, 10, np.random.default_rng(0))


@pytest.fixture
def mstep_instance():
    """A small M-step instance ``(model, Moments)``: ``n=3, m=2, T=5``
    (:func:`soc_opt.testing.random_mstep_instance`, seed 0)."""
    return testing.random_mstep_instance(3, 2, 5, np.random.default_rng(0))


@pytest.fixture
def linear2d_short():
    """The ``linear2d`` task with a horizon of 8 steps (fast loops)."""
    from soc_opt.tasks import load_task

    return load_task("linear2d", overrides={"T": 8})


@pytest.fixture
def tiny_run_config():
    """A run configuration of two iterations of 4 samples, EM phase after the first (DPSOC-EM)."""
    from soc_opt.methods.config import DPSOCConfig, LQRFLMConfig

    return DPSOCConfig(baseline=LQRFLMConfig(iterations=2, samples=4), i_switch=1)


@pytest.fixture(autouse=True)
def _fork_whatever_the_load(monkeypatch):
    """The tests of forked and threaded work run it that way on a busy machine too (``soc_opt.parallel.spare_cpu``
    otherwise sends it in turn when the load average leaves no CPU idle; tests/test_parallel.py tests that rule)."""
    import soc_opt.parallel

    monkeypatch.setattr(soc_opt.parallel, "spare_cpu", lambda: True)
