"""Tests for soc_opt/bench: every ``soc-opt bench --only`` part runs through the command line.

Each part runs at its ``QUICK`` sizes (``--quick``) through :func:`soc_opt.cli.main` with
``--json``; the rows must carry the part's columns and only finite numbers (``None`` marks a
column that does not apply to a row).  Timings are not asserted (no timed assertions).
"""

import ast
import json
import math
from pathlib import Path

import pytest

import soc_opt.bench
from soc_opt.bench import DEFAULT_PARTS, PARTS, SUPPORT
from soc_opt.cli import main

#: Columns every row of a part has (and, for some, the values that must appear).
COLUMNS = {
    "rollouts": {"case", "steps", "seconds", "steps_per_s", "ratio_to_raw"},
    "fit": {"table"},
    "estep": {"T", "n", "m", "sequences", "median_ms", "finite"},
    "mstep": {"method", "constraints", "time_per_step_s", "objective_gap", "max_gain_diff"},
    "lqg": {"n", "m", "T", "budget", "cf_ms_median", "objective_gap"},
    "iteration": {"method", "phase", "median_s", "n"},
    "compiled": {"case", "numpy_ms", "numba_ms", "ratio", "max_abs_diff"},
    "noisefit": {"M", "method", "bias_A", "bias_B"},
    "gym_envs": {"env", "cost_first", "cost_last", "cost_best", "seconds_per_iteration", "error"},
    "env_steps": {"env", "T", "steps", "repeats", "median_steps_per_s", "min_steps_per_s", "max_steps_per_s"},
}


def _numbers(value):
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return []
    if isinstance(value, (int, float)):
        return [float(value)]
    if isinstance(value, (list, tuple)):
        return [x for v in value for x in _numbers(v)]
    if isinstance(value, dict):
        return [x for v in value.values() for x in _numbers(v)]
    raise AssertionError(f"unexpected value {value!r}")


def test_every_bench_part_has_a_quick_size_and_a_column_check():
    assert set(PARTS) == set(COLUMNS) and set(DEFAULT_PARTS) <= set(PARTS)
    on_disk = {p.stem for p in Path(soc_opt.bench.__file__).parent.glob("*.py") if p.stem != "__init__"}
    assert on_disk == set(PARTS) | set(SUPPORT) and not set(PARTS) & set(SUPPORT)


@pytest.mark.parametrize("part", PARTS)
def test_bench_part_runs_from_the_command_line_with_finite_numbers(part, capsys):
    assert main(["bench", "--json", "--quick", "--only", part]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out) == [part]
    rows = out[part]
    assert rows and all(isinstance(r, dict) for r in rows)
    for r in rows:
        assert COLUMNS[part] <= set(r), (part, sorted(r))
        nums = _numbers(r)
        assert nums, r
        assert all(math.isfinite(x) for x in nums), (part, r)
    if part == "fit":  # the tables, including the settings table that replays LQR-FLM iterations
        assert {r["table"] for r in rows} == {"timing", "convergence", "few_sample", "pendulum", "settings"}
    if part == "gym_envs":
        assert all(r["error"] == "" for r in rows), rows
    if part == "estep":
        assert all(r["finite"] for r in rows)


def test_bench_prints_a_table_per_part_without_json(capsys):
    assert main(["bench", "--quick", "--only", "estep,estep"]) == 0
    out = capsys.readouterr().out
    assert out.count("== estep") == 1 and "median_ms" in out


def test_unknown_bench_part_is_a_clean_error_listing_the_valid_parts(capsys):
    assert main(["bench", "--only", "estep,nosuch"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("soc-opt: error: ") and len(err.splitlines()) == 1
    assert "'nosuch'" in err and all(p in err for p in PARTS)


def test_no_bench_module_imports_the_command_line():
    for path in Path(soc_opt.bench.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                assert not (node.module or "").endswith("cli"), (path.name, node.module)
                assert not (node.module in (None, "..") and any(a.name == "cli" for a in node.names)), path.name
            if isinstance(node, ast.Import):
                assert all(not a.name.endswith(".cli") for a in node.names), path.name
