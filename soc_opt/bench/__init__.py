"""Benchmarks and solver comparisons (``soc-opt solvers``, ``soc-opt bench``).

Each submodule exposes ``run(...) -> list[dict]``: one row per measured case.
"""
