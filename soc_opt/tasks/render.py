"""Pictures of trajectories: offscreen MuJoCo filmstrips with a matplotlib fallback (docs/math.md §8).

The frames are rendered in a subprocess running :mod:`soc_opt.tasks.render_worker`, so
that a broken GL driver cannot take the caller down.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import files
from ..models import Rollouts
from .mujoco import MujocoTask, import_mujoco

__all__ = ["RenderResult", "render_filmstrip", "frame_scene"]

_WORKER = "soc_opt.tasks.render_worker"


def _worker_env(**extra) -> dict[str, str]:
    """The caller's environment plus ``extra``, with the directory holding this ``soc_opt``
    first on ``PYTHONPATH`` so that the worker imports the same package as the caller."""
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, **extra)
    env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env


@dataclass(frozen=True)
class RenderResult:
    """Where the picture went and how: ``backend`` is ``"egl"``, ``"osmesa"``, ... or ``"matplotlib"``."""

    path: str
    backend: str
    message: str


def _trajectory(traj) -> np.ndarray:
    if isinstance(traj, Rollouts):
        return np.asarray(traj.x)
    x = np.asarray(traj, dtype=float)
    return x[None] if x.ndim == 2 else x


def _geom_spheres(task, Q) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres ``(centres (G, 3), radii (G,))`` of the geoms to frame, over configurations ``Q``.

    The geoms of every body but the world body (the world usually holds the floor); planes are
    infinite and never framed.  If that leaves nothing, every non-plane geom.
    """
    mj = import_mujoco()
    m = task.model
    d = mj.MjData(m)
    plane = int(mj.mjtGeom.mjGEOM_PLANE)
    finite = np.asarray(m.geom_type) != plane
    use = finite & (np.asarray(m.geom_bodyid) != 0)
    if not use.any():
        use = finite
    centres, radii = [], []
    for q in Q:
        d.qpos[:] = q
        mj.mj_kinematics(m, d)
        centres.append(np.array(d.geom_xpos[use]))
        radii.append(np.asarray(m.geom_rbound)[use])
    return np.concatenate(centres), np.concatenate(radii)


def frame_scene(task, Q, azimuth: float = 135.0, elevation: float = -25.0, margin: float = 1.1) -> dict:
    """A free camera (``lookat``, ``distance``, ``azimuth``, ``elevation``) that sees the whole robot.

    Used when the task names no ``camera``: the bounding spheres of the geoms (see
    :func:`_geom_spheres`) in every configuration of ``Q (F, nq)`` are enclosed in one sphere
    around the centre of their bounding box, and the camera is placed far enough that this
    sphere fits in the vertical field of view ``vis.global.fovy`` (times ``margin``), whatever the
    viewing angles.  Without geoms, the model's ``stat.center``/``stat.extent``.
    """
    m = task.model
    c, r = _geom_spheres(task, Q)
    if c.size == 0:
        lookat, radius = np.asarray(m.stat.center, float), float(m.stat.extent)
    else:
        lo, hi = (c - r[:, None]).min(axis=0), (c + r[:, None]).max(axis=0)
        lookat = (lo + hi) / 2
        radius = float(np.max(np.linalg.norm(c - lookat, axis=1) + r))
    half = np.deg2rad(float(m.vis.global_.fovy)) / 2
    distance = margin * max(radius, 1e-3) / np.sin(half)
    return {"lookat": [float(v) for v in lookat], "distance": float(distance),
            "azimuth": float(azimuth), "elevation": float(elevation)}


def render_filmstrip(task, traj, path, frames: int = 8, width: int = 320, height: int = 240,
                     backends: tuple[str, ...] | None = None, timeout: float = 120.0) -> RenderResult:
    """A PNG filmstrip of a trajectory (``Rollouts``: sample 0's true states; or ``x (T+1, n)``).

    MuJoCo tasks are rendered offscreen with ``mujoco.Renderer`` in a subprocess
    (so a broken GL driver cannot take the caller down), trying ``MUJOCO_GL`` =
    ``egl`` then ``osmesa`` (a user-set ``MUJOCO_GL`` first), from the task's ``camera`` or, if it
    names none, from a free camera framing the whole robot (:func:`frame_scene`).  If no backend works,
    or the task has no MuJoCo model, a matplotlib 3-D plot of the end-effector
    points of all samples is written instead and ``message`` says why.
    """
    path = str(path)
    X = _trajectory(traj)
    reasons = []
    if isinstance(task, MujocoTask):
        if backends is None:
            env_gl = os.environ.get("MUJOCO_GL", "").lower()
            backends = tuple(dict.fromkeys([b for b in (env_gl, "egl", "osmesa") if b in ("egl", "osmesa", "glfw")]))
        x = X[0]
        idx = np.unique(np.linspace(0, x.shape[0] - 1, max(1, frames)).round().astype(int))
        Q = task.qpos_from_state(x[idx])
        mj = import_mujoco()
        m = task.model
        width = min(width, int(m.vis.global_.offwidth))
        height = min(height, int(m.vis.global_.offheight))
        spec = {"path": "", "width": width, "height": height, "camera": task.config.camera,
                **frame_scene(task, Q)}
        with tempfile.TemporaryDirectory() as work:
            spec["path"] = os.path.join(work, "filmstrip.png")  # moved into place with soc_opt.files (no link followed)
            mj.mj_saveModel(m, os.path.join(work, "model.mjb"), None)
            np.save(os.path.join(work, "qpos.npy"), Q)
            with open(os.path.join(work, "spec.json"), "w") as f:
                json.dump(spec, f)
            for b in backends:
                env = _worker_env(MUJOCO_GL=b)
                if b in ("egl", "osmesa"):
                    env["PYOPENGL_PLATFORM"] = b
                try:
                    p = subprocess.run([sys.executable, "-m", _WORKER, work], env=env, capture_output=True,
                                       text=True, timeout=timeout)
                except subprocess.TimeoutExpired:
                    reasons.append(f"{b}: timed out")
                    continue
                if p.returncode == 0 and os.path.isfile(spec["path"]):
                    with open(spec["path"], "rb") as f:
                        files.write_bytes(path, f.read())
                    return RenderResult(path, b, f"rendered {len(idx)} frames with MUJOCO_GL={b}")
                err = (p.stderr.strip().splitlines() or [f"exit code {p.returncode}"])[-1]
                reasons.append(f"{b}: {err}")
        message = "MuJoCo offscreen rendering unavailable (" + "; ".join(reasons) + "); wrote a matplotlib plot instead"
    else:
        message = f"task {task.name!r} has no MuJoCo model; wrote a matplotlib plot of its points"
    _plot_points(task, X, path, message)
    return RenderResult(path, "matplotlib", message)


def _plot_points(task, X, path, title):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pts = task.ee_points(X)  # (M, T+1, P, 3)
    fig = Figure(figsize=(6, 5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    for p in range(pts.shape[2]):
        color = f"C{p}"
        for i in range(pts.shape[0]):
            ax.plot(pts[i, :, p, 0], pts[i, :, p, 1], pts[i, :, p, 2], color=color, alpha=0.6, lw=1,
                    label=f"point {p}" if i == 0 else None)
        ax.scatter(*pts[:, 0, p].T, color=color, marker="o", s=12)
        ax.scatter(*pts[:, -1, p].T, color=color, marker="x", s=16)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.legend(loc="upper left", fontsize=7)
    fig.suptitle(f"{task.name}: end-effector points (o start, x end)", fontsize=9)
    fig.text(0.01, 0.01, title[:200], fontsize=6)
    files.save_figure(fig, path, dpi=100)
