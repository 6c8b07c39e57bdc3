"""MJCF models are checked before MuJoCo opens them (issue 48 items 1 and 9): every file a model references
is a regular file read without blocking, and what the text asks MuJoCo to build is bounded."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest
from test_reading import _error, _fifo, watchdog

from soc_opt.cli import main
from soc_opt.config import ConfigError
from soc_opt.tasks import load_task
from soc_opt.tasks.loading import problems_dir

MAX_BODIES, MAX_ELEMENTS = 1000, 20_000  # soc_opt.tasks.mjcf's bounds (docs/security.md, "Models")
ARGS = ["--method", "lqr-flm", "--iterations", "2", "--samples", "4", "--progress", "lines"]
ARM = """<mujoco>
  <compiler meshdir="meshes" texturedir="textures"/>
  {assets}
  <worldbody>
    <body name="a"><joint name="j" type="hinge" axis="0 0 1"/><geom type="capsule" size=".05" fromto="0 0 0 .3 0 0"/>
      <site name="tip" pos=".3 0 0"/></body>
    {body}
  </worldbody>
  <actuator><motor joint="j"/></actuator>
</mujoco>"""
TASK = 'name = "arm"\nT = 5\nmodel = "arm.xml"\n[state]\njoints = ["j"]\nsites = ["tip"]\n[[cost]]\ntype = "torque"\n'


def _task(tmp_path: Path, assets: str = "", body: str = "") -> Path:
    (tmp_path / "meshes").mkdir(exist_ok=True)
    (tmp_path / "textures").mkdir(exist_ok=True)
    (tmp_path / "arm.xml").write_text(ARM.format(assets=assets, body=body))
    (tmp_path / "task.toml").write_text(TASK)
    return tmp_path / "task.toml"


REFERENCES = {  # a FIFO at the file each references
    "include": ("", '<include file="part.xml"/>', "part.xml"),
    "mesh": ('<asset><mesh name="m" file="m.stl"/></asset>', "", "meshes/m.stl"),
    "texture": ('<asset><texture name="t" type="2d" file="t.png"/></asset>', "", "textures/t.png"),
    "cube texture face": ('<asset><texture name="t" type="cube" fileup="up.png"/></asset>', "", "up.png"),
}


@pytest.mark.parametrize("what", list(REFERENCES))
def test_a_fifo_referenced_by_a_model_is_refused_naming_it_before_mujoco_opens_it(tmp_path, capsys, what):
    assets, body, name = REFERENCES[what]
    task = _task(tmp_path, assets, body)
    fifo = _fifo(tmp_path / name)
    with watchdog([fifo]) as released:
        rc = main(["run", str(task), *ARGS, "--out", str(tmp_path / "out")])
    assert released == []
    err = _error(capsys)
    assert rc == 2 and name.split("/")[-1] in err and "FIFO" in err, err
    assert not (tmp_path / "out").exists()


def test_a_model_without_hostile_references_loads_and_records_its_files(tmp_path):
    task = _task(tmp_path, '<asset><texture name="t" type="2d" builtin="checker" width="64" height="64"/></asset>')
    t = load_task(task)
    assert set(t.provenance["model_files"]) == {"arm.xml"}


REPLICATE = '<replicate count="1000" offset="0 0 .01"><replicate count="1000" offset=".01 0 0">' \
            '<body><geom size=".01"/></body></replicate></replicate>'


@pytest.mark.parametrize("kind", ["a 500-byte replicate of a million bodies", "bodies written out",
                                  "a composite grid", "an include repeated by a replicate"])
def test_a_model_asking_for_too_many_bodies_is_refused_before_it_is_compiled(tmp_path, kind):
    body = {"a 500-byte replicate of a million bodies": REPLICATE,
            "bodies written out": '<body><geom size=".01"/></body>' * (MAX_BODIES + 1),
            "a composite grid": '<body><composite type="grid" count="200 200 1" spacing=".01"/></body>',
            "an include repeated by a replicate": '<replicate count="100000" offset="0 0 .01"><include file="p.xml"/>'
                                                  "</replicate>"}[kind]
    (tmp_path / "p.xml").write_text('<mujoco><body><geom size=".01"/></body></mujoco>')
    task = _task(tmp_path, body=body)
    if kind.startswith("a 500"):
        assert len(REPLICATE) < 500
    with pytest.raises(ConfigError, match=rf"more than ({MAX_BODIES} bodies|{MAX_ELEMENTS} XML elements)"):
        load_task(task)


@pytest.mark.parametrize("asset,says", [
    ('<asset><hfield name="h" nrow="100000" ncol="100000" size="1 1 1 1"/></asset>', "cells"),
    ('<asset><texture name="t" type="2d" builtin="checker" width="100000" height="100000"/></asset>', "cells"),
    ('<size memory="100G"/>', "memory"),
])
def test_a_model_asking_for_a_huge_grid_or_arena_is_refused_naming_it(tmp_path, asset, says):
    with pytest.raises(ConfigError, match=says):
        load_task(_task(tmp_path, asset))


def test_a_png_texture_whose_header_claims_a_huge_image_is_refused(tmp_path):
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 50000, 50000, 8, 2, 0, 0, 0))
    task = _task(tmp_path, '<asset><texture name="t" type="2d" file="t.png"/></asset>')
    (tmp_path / "textures" / "t.png").write_bytes(png)
    with pytest.raises(ConfigError, match="t.png.*cells"):
        load_task(task)


def test_an_mjcf_with_entity_declarations_is_refused(tmp_path):
    lol = '<!DOCTYPE m [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>'
    (tmp_path / "arm.xml").write_text(lol + ARM.format(assets="", body=""))
    (tmp_path / "task.toml").write_text(TASK)
    with pytest.raises(ConfigError, match="entities"):
        load_task(tmp_path / "task.toml")
    from soc_opt.tasks.mjcf import check_xml

    with pytest.raises(ConfigError, match="entities"):
        check_xml(lol + "<mujoco/>")


def test_the_recorded_model_files_are_those_mujoco_reads():
    """The built-in arms: the model file and nothing else (no includes or assets), with their SHA-256."""
    from soc_opt.tasks.mjcf import check_model

    for name in ("peg/arm7_peg.xml", "door/arm6_door.xml"):
        path = problems_dir() / name
        files = check_model(path)
        assert files == {path.name: hashlib.sha256(path.read_bytes()).hexdigest()}


def test_an_include_that_includes_itself_is_refused_or_read_once(tmp_path):
    from soc_opt.tasks.mjcf import check_model

    (tmp_path / "loop.xml").write_text('<mujoco><include file="loop.xml"/></mujoco>')
    assert set(check_model(tmp_path / "loop.xml")) == {"loop.xml"}
    assert os.path.isfile(tmp_path / "loop.xml")


@pytest.mark.parametrize("kind", ["replicate", pytest.param("written out", marks=pytest.mark.slow)])
def test_soc_opt_run_refuses_a_model_of_a_million_bodies_within_the_memory_bound(tmp_path, kind):
    from test_reading import HOSTILE_RSS_MB, peak_run

    body = REPLICATE if kind == "replicate" else '<body><geom size=".01"/></body>' * 100_000
    task = _task(tmp_path, body=body)
    rc, peak, err = peak_run(["run", task, *ARGS, "--out", tmp_path / "out"])
    assert peak < HOSTILE_RSS_MB, f"peak resident memory {peak:.0f} MB"
    assert rc == 2 and "arm.xml" in err and "bodies" in err, err
    assert not (tmp_path / "out").exists()
