"""TensorBoard event files in run directories (soc_opt/tblog.py; optional tensorboardX).

The oracle reader is independent of the writer: the TFRecord framing parsed here by hand
(length, CRC, payload, CRC) and the ``Event`` protocol buffer, and, where TensorBoard is
installed, TensorBoard's own ``EventAccumulator``.
"""

from __future__ import annotations

import json
import struct
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from soc_opt import cli
from soc_opt.experiments.progress import Progress
from soc_opt.experiments.run import run_experiment
from soc_opt.experiments.tblog import MISSING_MESSAGE, available
from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
from soc_opt.tasks import load_task

needs_tensorboardx = pytest.mark.skipif(not available(), reason="tensorboardX not installed (test extra)")


@pytest.fixture(scope="module")
def task():
    return load_task("linear2d", overrides={"T": 12})


def _cfg(iterations=3):
    return DPSOCConfig(i_switch=1, baseline=LQRFLMConfig(iterations=iterations, samples=5, kl_budget=1.0),
                       em=EMConfig(n_em=1))


def read_events(directory: Path) -> tuple[dict, dict]:
    """``scalars[tag] = [(step, value), ...]`` and ``images[tag] = [(step, png bytes), ...]``
    from every event file in ``directory``."""
    from tensorboardX.proto import event_pb2

    scalars, images = defaultdict(list), defaultdict(list)
    files = sorted(directory.glob("events.out.tfevents.*"))
    for path in files:
        data = path.read_bytes()
        pos = 0
        while pos < len(data):
            (length,) = struct.unpack_from("<Q", data, pos)
            payload = data[pos + 12: pos + 12 + length]
            pos += 12 + length + 4
            ev = event_pb2.Event()
            ev.ParseFromString(payload)
            for v in ev.summary.value:
                if v.HasField("image"):
                    images[v.tag].append((ev.step, v.image.encoded_image_string))
                else:
                    scalars[v.tag].append((ev.step, v.simple_value))
    return dict(scalars), dict(images)


@needs_tensorboardx
def test_run_directory_holds_the_per_iteration_scalars(task, tmp_path):
    out = tmp_path / "run"
    state = run_experiment(task, "dpsoc-em", _cfg(), 0, out)
    scalars, _ = read_events(out)
    rows = json.loads((out / "metrics.json").read_text())
    base = [r for r in rows if r["phase"] == "baseline"]
    assert [s for s, _ in scalars["baseline/cost_mean"]] == [r["iteration"] for r in base] == [0, 1, 2]
    for key in ("cost_mean", "kl", "nu", "metric_min_distance", "time_lqg"):
        np.testing.assert_allclose([v for _, v in scalars[f"baseline/{key}"]], [r[key] for r in base], rtol=1e-6)
    em = [r for r in rows if r["phase"] == "em"]
    assert len(em) == 1 and scalars["em/surrogate_new"] == [(em[0]["iteration"], pytest.approx(em[0]["surrogate_new"], rel=1e-6))]
    assert state.iteration == 3


@needs_tensorboardx
def test_resumed_run_logs_every_iteration_once(task, tmp_path):
    class Stop(Exception):
        pass

    def stop(st):
        if st.iteration == 2:
            raise Stop

    out = tmp_path / "run"
    with pytest.raises(Stop):
        run_experiment(task, "lqr-flm", _cfg(4), 0, out, on_iteration=stop)
    run_experiment(task, "lqr-flm", _cfg(4), 0, out)
    scalars, _ = read_events(out)
    assert sorted(s for s, _ in scalars["baseline/cost_mean"]) == [0, 1, 2, 3]


@needs_tensorboardx
def test_cli_run_adds_the_figures_as_images(tmp_path, monkeypatch):
    cfg = tmp_path / "small.toml"
    cfg.write_text("i_switch = 1\n[baseline]\niterations = 2\nsamples = 5\n")
    out = tmp_path / "run"
    monkeypatch.setenv("MUJOCO_GL", "disabled")
    assert cli.main(["run", "linear2d", "--method", "lqr-flm", "--config", str(cfg), "--out", str(out),
                     "--progress", "lines"]) == 0
    _, images = read_events(out)
    pngs = sorted(p.stem for p in out.glob("*.png"))
    assert sorted(images) == pngs and "cost_per_iteration" in pngs
    import io

    from matplotlib.image import imread

    (step, png), = images["cost_per_iteration"]
    assert step == 1
    decoded = imread(io.BytesIO(png), format="png")
    assert decoded.shape[:2] == imread(str(out / "cost_per_iteration.png")).shape[:2]


@needs_tensorboardx
def test_tensorboard_reads_the_events(task, tmp_path):
    ea_mod = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
    out = tmp_path / "run"
    run_experiment(task, "lqr-flm", _cfg(2), 0, out)
    acc = ea_mod.EventAccumulator(str(out))
    acc.Reload()
    rows = json.loads((out / "metrics.json").read_text())
    got = [(e.step, e.value) for e in acc.Scalars("baseline/cost_mean")]
    assert [s for s, _ in got] == [0, 1]
    np.testing.assert_allclose([v for _, v in got], [r["cost_mean"] for r in rows], rtol=1e-6)


def test_without_tensorboardx_runs_work_and_say_so(task, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "tensorboardX", None)  # import fails as if not installed
    assert not available()
    lines = []
    out = tmp_path / "run"
    state = run_experiment(task, "lqr-flm", _cfg(2), 0, out, progress=Progress("lines", print_line=lines.append))
    assert state.iteration == 2 and (out / "metrics.json").is_file()
    assert not list(out.glob("events.out.tfevents.*"))
    assert lines[0] == MISSING_MESSAGE and sum(line.startswith("[lqr-flm seed 0] iter") for line in lines) == 2


@needs_tensorboardx
def test_a_folder_swapped_for_a_link_before_the_log_opens_gets_no_event_file_outside(task, tmp_path, monkeypatch):
    """Issue 48 item 3: a run inside a compare-like directory whose ``seed_0`` is swapped for a link to another
    folder just before its TensorBoard log opens: the log opens the folder from the anchor without following
    the link (and writes by descriptor), so no event file lands outside; the run stops naming the link."""
    from soc_opt.experiments.tblog import RunLog
    from soc_opt.files import UnsafePathError

    anchor, outside = tmp_path / "cmp", tmp_path / "outside"
    (outside / "lqr-flm").mkdir(parents=True)
    out = anchor / "seed_0" / "lqr-flm"
    open_log = RunLog.open.__func__

    def swap_then_open(cls, path, *args, **kw):  # the right moment: just before the log opens
        (anchor / "seed_0").rename(anchor / "seed_0.moved")
        (anchor / "seed_0").symlink_to(outside, target_is_directory=True)
        return open_log(cls, path, *args, **kw)

    monkeypatch.setattr(RunLog, "open", classmethod(swap_then_open))
    with pytest.raises(UnsafePathError, match="seed_0"):
        run_experiment(task, "lqr-flm", _cfg(), 0, out, anchor=anchor)
    assert list((outside / "lqr-flm").iterdir()) == []


@needs_tensorboardx
def test_the_log_writes_through_the_folder_it_opened_when_it_is_renamed_afterwards(task, tmp_path):
    from soc_opt.experiments.tblog import RunLog

    (tmp_path / "a").mkdir()
    log = RunLog.open(tmp_path / "a")
    (tmp_path / "a").rename(tmp_path / "b")
    (tmp_path / "a").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    (tmp_path / "elsewhere").mkdir()
    log.series("x", [1.0, 2.0])
    log.close()
    assert list((tmp_path / "elsewhere").iterdir()) == []
    assert read_events(tmp_path / "b")[0]["x"] == [(0, 1.0), (1, 2.0)]
