"""TensorBoard event files in run directories (optional dependency: ``tensorboardX``).

With ``tensorboardX`` installed (``pip install 'soc_opt[tensorboard]'``), every run directory
gets ``events.out.tfevents.*`` files next to ``metrics.csv``:

* per iteration, every numeric field of :meth:`IterationRecord.summary` as a scalar tagged
  ``<phase>/<field>`` at step ``iteration`` (e.g. ``baseline/cost_mean``, ``baseline/kl``,
  ``baseline/metric_min_distance``, ``baseline/time_lqg``, ``em/surrogate_new``);
* the figures (``*.png`` written by ``soc-opt run`` and ``soc-opt compare``) as images tagged
  with the file name, at the last iteration's step.

Open them with ``tensorboard --logdir runs/`` (every run directory below becomes one run, so
the two methods and the seeds of a comparison sit side by side).  Without ``tensorboardX``
runs work the same and only the event files are missing (:func:`available`).
"""

from __future__ import annotations

import io
import math
import os
import uuid
from pathlib import Path
from typing import Iterable

import numpy as np

from .. import files
from ..config import ConfigError
from ..reading import read_regular

#: Largest figure logged to TensorBoard: 64 MiB.
MAX_FIGURE_BYTES = 64 << 20

__all__ = ["available", "RunLog", "MISSING_MESSAGE"]

MISSING_MESSAGE = "TensorBoard logs off: tensorboardX is not installed (pip install 'soc_opt[tensorboard]')"


def _writer_class():
    try:
        from tensorboardX import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter


def available() -> bool:
    """Whether event files can be written (``tensorboardX`` importable)."""
    return _writer_class() is not None


class RunLog:
    """The TensorBoard events of one directory; :meth:`open` returns ``None`` without tensorboardX."""

    def __init__(self, writer, dir_fd: int | None = None):
        self.writer = writer
        self.dir_fd = dir_fd

    @classmethod
    def open(cls, path: str | Path, purge_step: int | None = None, *, anchor: str | Path | None = None) -> "RunLog | None":
        """A log writing into ``path``; ``purge_step``: on resume, hide events at or after this
        step left by an interrupted earlier session (they are written again).

        The folder is opened once, from ``anchor`` (default: ``path`` itself) without following a link below
        it (:func:`soc_opt.files.open_dir`), and tensorboardX writes through that descriptor
        (``/proc/self/fd/N``): a folder swapped for a link afterwards changes nothing.  Where the system has no
        ``/proc/self/fd`` the log is off (``None``)."""
        SummaryWriter = _writer_class()
        if SummaryWriter is None:
            return None
        fd = files.open_dir(path, anchor=path if anchor is None else anchor)
        logdir = f"/proc/self/fd/{fd}"
        if not os.path.isdir(logdir):  # pragma: no cover - no /proc (not Linux): no descriptor path to write by
            os.close(fd)
            return None
        # event file names hold the time in seconds: a unique suffix keeps two sessions opened
        # within the same second (a run, then its figures) from overwriting each other
        suffix = f".{uuid.uuid4().hex[:8]}"
        try:
            writer = SummaryWriter(logdir=logdir, purge_step=purge_step, flush_secs=30, filename_suffix=suffix)
        except BaseException:
            os.close(fd)
            raise
        return cls(writer, fd)

    def iteration(self, record) -> None:
        """The numeric fields of ``record.summary()`` as scalars ``<phase>/<field>``."""
        summary = record.summary()
        step = int(record.iteration)
        phase = summary.get("phase", "baseline")
        for key, value in summary.items():
            if key in ("iteration", "phase") or isinstance(value, bool):
                continue
            if isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(float(value)):
                self.writer.add_scalar(f"{phase}/{key}", float(value), step)
        self.writer.flush()

    def series(self, tag: str, values: Iterable[float]) -> None:
        """A scalar series ``values[i]`` at steps ``i`` (e.g. iLQG's accepted costs)."""
        for i, v in enumerate(values):
            self.writer.add_scalar(tag, float(v), i)
        self.writer.flush()

    def figures(self, paths: Iterable[str | Path], step: int) -> int:
        """PNG figures of the log's folder (only their names are used) as images tagged with their file stem;
        returns how many were written.  Read through the folder's descriptor: a link, anything but a regular
        file, a file larger than :data:`MAX_FIGURE_BYTES` or one that is no PNG is skipped."""
        from matplotlib.image import imread

        count = 0
        for p in paths:
            p = Path(p)
            try:  # only the directory's own files (docs/security.md)
                data = read_regular(p.name, MAX_FIGURE_BYTES, what="figure", dir_fd=self.dir_fd) if self.dir_fd is not None \
                    else files.read_bytes(p, MAX_FIGURE_BYTES, what="figure")
                img = imread(io.BytesIO(data), format="png")
            except (OSError, ValueError, ConfigError):
                continue
            if img.dtype != np.uint8:
                img = np.clip(np.rint(np.asarray(img, float) * 255), 0, 255).astype(np.uint8)
            if img.ndim == 2:
                img = np.repeat(img[..., None], 3, axis=2)
            self.writer.add_image(p.stem, img[..., :3], int(step), dataformats="HWC")
            count += 1
        self.writer.flush()
        return count

    def close(self) -> None:
        try:
            self.writer.close()
        finally:
            if self.dir_fd is not None:
                os.close(self.dir_fd)
                self.dir_fd = None
