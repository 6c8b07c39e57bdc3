"""Shared pytest fixtures.  Random instances come from :mod:`soc_opt.testing`."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh ``numpy.random.Generator`` seeded with 0 for each test (pass it to ``soc_opt.testing``)."""
    return np.random.default_rng(0)
