"""Subprocess side of :func:`soc_opt.tasks.render.render_filmstrip`: renders the frames offscreen.

Run as ``python -m soc_opt.tasks.render_worker WORKDIR`` with ``MUJOCO_GL`` set by the
caller, so that a broken GL driver can only take this process down.  ``WORKDIR`` holds
``model.mjb`` (the compiled model), ``qpos.npy`` (``(F, nq)`` configurations, one per
frame) and ``spec.json`` (``path``, ``width``, ``height``, ``camera`` or a free camera's
``lookat``/``distance``/``azimuth``/``elevation``).  The frames are concatenated side by
side and saved as a PNG at ``spec["path"]``.  This module itself needs only ``numpy``,
``mujoco`` and ``PIL``.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np


def render_frames(work: str) -> tuple[int, ...]:
    """Render every configuration of ``WORKDIR/qpos.npy`` and save the filmstrip; its pixel shape."""
    import mujoco

    with open(os.path.join(work, "spec.json")) as f:
        spec = json.load(f)
    m = mujoco.MjModel.from_binary_path(os.path.join(work, "model.mjb"))
    d = mujoco.MjData(m)
    Q = np.load(os.path.join(work, "qpos.npy"))
    r = mujoco.Renderer(m, spec["height"], spec["width"])
    cam = spec["camera"]
    if cam is None:
        cam = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(m, cam)
        cam.lookat[:] = spec["lookat"]
        cam.distance = spec["distance"]
        cam.azimuth = spec["azimuth"]
        cam.elevation = spec["elevation"]
    frames = []
    for q in Q:
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        r.update_scene(d, camera=cam)
        frames.append(r.render().copy())
    strip = np.concatenate(frames, axis=1)
    from PIL import Image

    Image.fromarray(strip).save(spec["path"])
    return strip.shape


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m soc_opt.tasks.render_worker WORKDIR", file=sys.stderr)
        return 2
    print("ok", render_frames(argv[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
