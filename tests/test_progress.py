"""Progress of runs and comparisons (soc_opt/progress.py): a bar on a terminal, lines otherwise."""

from __future__ import annotations

import io
import re

import pytest

from soc_opt.experiments.compare import compare
from soc_opt.experiments.progress import Progress, resolve_mode
from soc_opt.experiments.run import run_experiment
from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
from soc_opt.tasks import load_task


@pytest.fixture(scope="module")
def task():
    return load_task("linear2d", overrides={"T": 12})


def _cfg(iterations=3):
    return DPSOCConfig(i_switch=1, baseline=LQRFLMConfig(iterations=iterations, samples=5, kl_budget=1.0),
                       em=EMConfig(n_em=1))


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_auto_mode_is_a_bar_only_when_both_streams_are_terminals(monkeypatch):
    monkeypatch.setenv("TERM", "xterm")
    monkeypatch.setattr("sys.stdout", _Terminal())
    assert resolve_mode("auto", _Terminal()) == "bar"
    assert resolve_mode("auto", io.StringIO()) == "lines"  # e.g. stderr redirected to a CI log
    monkeypatch.setenv("TERM", "dumb")
    assert resolve_mode("auto", _Terminal()) == "lines"
    monkeypatch.setattr("sys.stdout", io.StringIO())
    monkeypatch.setenv("TERM", "xterm")
    assert resolve_mode("auto", _Terminal()) == "lines"  # stdout piped to a file
    assert resolve_mode("bar", io.StringIO()) == "bar"
    with pytest.raises(ValueError, match="'fancy'"):
        resolve_mode("fancy", io.StringIO())


def test_lines_mode_prints_one_line_per_iteration_with_cost_kl_and_metric(task, tmp_path):
    lines = []
    state = run_experiment(task, "lqr-flm", _cfg(), 0, tmp_path / "run", progress=Progress("lines", print_line=lines.append))
    assert len(lines) == 3
    for i, (line, rec) in enumerate(zip(lines, state.history)):
        assert line.startswith(f"[lqr-flm seed 0] iter  {i} ({i + 1}/3) cost")  # numbered like metrics.csv
        assert f"KL {rec.kl:.3g}/" in line and f"min_distance={rec.metrics['min_distance']:.4g}" in line


def test_a_plain_callable_still_receives_the_lines(task):
    lines = []
    run_experiment(task, "lqr-flm", _cfg(2), 0, None, progress=lines.append)
    assert [line[:30] for line in lines] == ["[lqr-flm seed 0] iter  0 (1/2)", "[lqr-flm seed 0] iter  1 (2/2)"]


def test_bar_mode_shows_iterations_with_cost_kl_and_metric(task, tmp_path, capsys):
    stream = io.StringIO()
    state = run_experiment(task, "lqr-flm", _cfg(), 0, tmp_path / "run", progress=Progress("bar", stream=stream))
    bar = stream.getvalue()
    assert "lqr-flm seed 0" in bar and "3/3" in bar
    last = state.history[-1]
    assert re.search(rf"cost={float(sum(last.cost) / len(last.cost)):.4g}", bar)
    assert f"KL={last.kl:.4g}" in bar and f"min_distance={last.metrics['min_distance']:.4g}" in bar
    out = capsys.readouterr().out  # the full lines go to stdout, above the bar
    assert out.count("[lqr-flm seed 0] iter") == 3


def test_resumed_run_bar_starts_at_the_checkpoint(task, tmp_path):
    class Stop(Exception):
        pass

    def stop_after_two(st):
        if st.iteration == 2:
            raise Stop

    with pytest.raises(Stop):
        run_experiment(task, "lqr-flm", _cfg(3), 0, tmp_path / "run", on_iteration=stop_after_two)
    stream = io.StringIO()
    run_experiment(task, "lqr-flm", _cfg(3), 0, tmp_path / "run", progress=Progress("bar", stream=stream))
    assert "2/3" in stream.getvalue() and "1/3" not in stream.getvalue()


def test_compare_has_a_bar_over_seeds_above_the_run_bars(task, tmp_path, capsys):
    stream = io.StringIO()
    compare(task, _cfg(2), [0, 1], tmp_path / "cmp", progress=Progress("bar", stream=stream))
    bar = stream.getvalue()
    assert "seeds" in bar and "2/2" in bar
    for name in ("lqr-flm seed 0", "dpsoc-em seed 0", "lqr-flm seed 1", "dpsoc-em seed 1"):
        assert name in bar
    out = capsys.readouterr().out
    assert out.count("seed 0: final cost LQR-FLM") == 1 and out.count("seed 1: final cost LQR-FLM") == 1


def test_compare_in_lines_mode_prints_a_line_per_seed(task, tmp_path):
    lines = []
    compare(task, _cfg(2), [0, 1], tmp_path / "cmp", progress=Progress("lines", print_line=lines.append))
    seed_lines = [line for line in lines if line.startswith("seed ")]
    assert [line.split(":")[0] for line in seed_lines] == ["seed 0", "seed 1"]
    assert sum(line.startswith("[dpsoc-em seed 1]") for line in lines) == 1  # forked after i_switch = 1
