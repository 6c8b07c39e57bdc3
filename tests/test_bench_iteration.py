"""Tests for soc_opt/bench/iteration.py: the per-phase rows are the run's own timings."""

import math

from soc_opt.bench import iteration


def test_iteration_bench_reports_every_phase_and_phases_fit_inside_the_iteration():
    rows = iteration.run("linear2d", iterations=3, samples=4)
    by = {(r["method"].split()[0], r["phase"]): r for r in rows}
    for phase in ("rollouts", "fit", "lqg", "iteration (wall)"):
        r = by[("lqr-flm", phase)]
        assert r["n"] == 3 and 0 < r["min_s"] <= r["median_s"] <= r["max_s"] and math.isfinite(r["first_s"])
    # the phases are parts of the iteration: their medians cannot add up to more than its slowest
    parts = sum(by[("lqr-flm", p)]["min_s"] for p in ("rollouts", "fit", "lqg"))
    assert parts <= by[("lqr-flm", "iteration (wall)")]["max_s"]
    for phase in ("EM recursion: fit augmented", "EM recursion: E-step", "EM recursion: M-step",
                  "iteration with the EM phase (wall)", "whole run"):
        assert by[("dpsoc-em", phase)]["median_s"] > 0
