"""MJCF models checked before MuJoCo opens them: regular files only, bounded sizes and counts (docs/security.md).

MuJoCo opens a model's file, its includes and its assets (meshes, textures, height fields, attached models)
itself and builds whatever the text asks for.  :func:`check_model` walks that graph first, so that a model
MuJoCo would hang on (a FIFO as an include or texture) or spend minutes and gigabytes compiling (a
``<replicate>`` of a million bodies in 500 bytes) is refused in a fraction of a second, naming the file:

- every file the model names is found the ways MuJoCo may resolve it (the model's folder, the including
  file's folder, ``<compiler meshdir/texturedir/assetdir>``); each one that exists must be a regular file
  (:func:`soc_opt.reading.read_regular`: read without blocking) within its size bound, and all of them together
  within :data:`MAX_MODEL_BYTES`;
- the XML is parsed as a stream (no tree is built) with no entity declarations, counting its elements and
  bodies with every ``<replicate count>``, ``<composite count>``, ``<flexcomp count>``, include and
  ``<attach>`` multiplied out;
- height fields and textures (their ``nrow x ncol`` / ``width x height``, a PNG's header) are at most
  :data:`MAX_GRID` cells, and ``<size memory>`` at most :data:`MAX_ARENA_BYTES`.

It returns ``{file: sha256}`` of the model file, its includes and its meshes, skins, height fields and
textures (names relative to the model's folder): what a run records in ``task.json``.
"""

from __future__ import annotations

import hashlib
import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

from ..config import ConfigError
from ..reading import RefusedFile, read_regular

__all__ = ["check_model", "check_xml", "MAX_MJCF_BYTES", "MAX_ASSET_BYTES", "MAX_MODEL_BYTES", "MAX_MODEL_FILES",
           "MAX_ELEMENTS", "MAX_BODIES", "MAX_GRID", "MAX_ARENA_BYTES", "MAX_INCLUDE_DEPTH"]

#: Largest MJCF (XML) file: 4 MiB (the built-in arms are 5 kB; Gymnasium's humanoid 9 kB).
MAX_MJCF_BYTES = 4 << 20
#: Largest mesh, texture or height-field file: 64 MiB.
MAX_ASSET_BYTES = 64 << 20
#: All files of one model together: 256 MiB; at most 1000 files.
MAX_MODEL_BYTES = 256 << 20
MAX_MODEL_FILES = 1000
#: Includes nest at most this deep (a file including itself is refused at this depth).
MAX_INCLUDE_DEPTH = 16
#: XML elements and bodies of a model with its replications multiplied out: MuJoCo compiles 1000 bodies in
#: 0.3 s (2000 take 0.6 s and 340 MB, 20 000 take a minute); the built-in arms have 11.
MAX_ELEMENTS = 20_000
MAX_BODIES = 1000
#: Cells of a height field or texture (16 Mi: a 4096 x 4096 image).
MAX_GRID = 1 << 24
#: Largest ``<size memory>`` (MuJoCo's arena for the simulation data): 1 GiB.
MAX_ARENA_BYTES = 1 << 30

#: Elements whose ``file`` is an asset, and the ``<compiler>`` folder MuJoCo finds it in (recorded in task.json).
_ASSET_DIRS = {"mesh": "meshdir", "skin": "meshdir", "hfield": "meshdir", "texture": "texturedir"}
_SIZE_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40, "P": 1 << 50, "E": 1 << 60}


class _Refused(ConfigError):
    pass


def _ints(text: str | None) -> list[int]:
    try:
        return [int(float(v)) for v in (text or "").split()]
    except (ValueError, OverflowError):
        return []


def _product(values: list[int]) -> int:
    out = 1
    for v in values:
        out *= max(v, 0)
    return out


class _Target:
    """An expat target counting a file's elements (replications multiplied out) and collecting, in document
    order, the elements that name files or sizes; it builds no tree."""

    def __init__(self, walk: "_Walk", mult: int, where: Path):
        self.walk, self.where = walk, where
        self.stack = [mult]
        self.compilers: list[dict] = []
        self.refs: list[tuple[str, dict, int]] = []

    def start(self, tag, attrib):
        mult = self.stack[-1]
        w = self.walk
        w.add(mult, mult if tag == "body" else 0, self.where)
        if tag in ("composite", "flexcomp"):
            n = _product(_ints(attrib.get("count"))) * mult
            w.add(4 * n, n if tag == "composite" else 0, self.where)
        if tag == "compiler":
            self.compilers.append(dict(attrib))
        if tag in ("include", "attach", "model", "size", "hfield", "texture") or any(k.startswith("file") for k in attrib):
            self.refs.append((tag, dict(attrib), mult))
        count = _ints(attrib.get("count"))[:1] if tag == "replicate" else []
        self.stack.append(mult * max(count[0], 1) if count else mult)

    def end(self, tag):
        self.stack.pop()

    def data(self, text):
        pass

    def close(self):
        return None


class _Walk:
    def __init__(self, root: Path, name: str):
        self.root_dir, self.name = root, name
        self.files: dict[str, str] = {}
        self.seen: set[Path] = set()
        self.total = 0
        self.elements = self.bodies = 0
        self.dirs = {"meshdir": "", "texturedir": ""}
        self.models: dict[str, tuple[int, int]] = {}

    def refuse(self, what: str) -> _Refused:
        return _Refused(f"{self.name}: {what}")

    def add(self, elements: int, bodies: int, where: Path) -> None:
        self.elements += elements
        self.bodies += bodies
        if self.elements > MAX_ELEMENTS or self.bodies > MAX_BODIES:
            what = "bodies" if self.bodies > MAX_BODIES else "XML elements"
            raise self.refuse(f"{str(where)!r} asks for more than {MAX_BODIES if what == 'bodies' else MAX_ELEMENTS} "
                              f"{what} (replications multiplied out), more than a model soc_opt compiles may")

    def rel(self, p: Path) -> str:
        try:
            return p.relative_to(self.root_dir).as_posix()
        except ValueError:
            return p.as_posix()

    def read(self, p: Path, limit: int, what: str) -> bytes:
        if len(self.seen) >= MAX_MODEL_FILES:
            raise self.refuse(f"reads more than {MAX_MODEL_FILES} files")
        try:
            data = read_regular(p, limit, what=what, follow=True)
        except RefusedFile as e:
            raise self.refuse(str(e)) from None
        self.total += len(data)
        if self.total > MAX_MODEL_BYTES:
            raise self.refuse(f"its files hold more than {MAX_MODEL_BYTES} bytes together")
        return data

    def candidates(self, name: str, here: Path, dirs: tuple[str, ...]) -> list[Path]:
        p = Path(name)
        if p.is_absolute():
            return [p]
        out = [self.root_dir / d / p for d in dirs] + [self.root_dir / p, here.parent / p]
        return list(dict.fromkeys(out))

    def existing(self, name: str, here: Path, dirs: tuple[str, ...], limit: int, what: str) -> list[tuple[Path, bytes]]:
        """Every file ``name`` may resolve to that exists, read (regular files of at most ``limit`` bytes only)."""
        found = []
        for c in self.candidates(name, here, dirs):
            try:
                resolved = c.resolve()
            except (OSError, RuntimeError):
                continue
            if resolved in self.seen or not c.exists() and not c.is_symlink():
                continue
            try:
                data = self.read(c, limit, what)
            except FileNotFoundError:
                continue
            except OSError as e:
                raise self.refuse(f"{str(c)!r} cannot be read ({e.strerror or e})") from None
            self.seen.add(resolved)
            found.append((c, data))
        return found

    def visit(self, path: Path, data: bytes, mult: int, depth: int) -> None:
        if depth > MAX_INCLUDE_DEPTH:
            raise self.refuse(f"includes nest more than {MAX_INCLUDE_DEPTH} deep at {str(path)!r}")
        self.files.setdefault(self.rel(path), hashlib.sha256(data).hexdigest())
        if b"<!ENTITY" in data or b"<!DOCTYPE" in data:
            raise self.refuse(f"{str(path)!r} declares XML entities or a document type; MJCF has none")
        target = _Target(self, mult, path)
        parser = ET.XMLParser(target=target)
        try:
            parser.feed(data)
            parser.close()
        except ET.ParseError:
            return  # MuJoCo reports the file's syntax
        for comp in target.compilers:  # as MuJoCo: the file's compiler folders apply to all of its assets
            for key in ("meshdir", "texturedir"):
                self.dirs[key] = comp.get(key, comp.get("assetdir", self.dirs[key]))
        for tag, attrib, m in target.refs:
            self.ref(tag, attrib, m, path, depth)

    def ref(self, tag: str, attrib: dict, mult: int, here: Path, depth: int) -> None:
        if tag == "size":
            self.check_size(attrib, here)
        if tag == "attach":
            elements, bodies = self.models.get(attrib.get("model", ""), (0, 0))
            self.add(elements * mult, bodies * mult, here)
        grid = _product(_ints(attrib.get("nrow"))[:1] + _ints(attrib.get("ncol"))[:1]) if tag == "hfield" else 0
        if tag == "texture" and not any(k.startswith("file") for k in attrib):  # a built-in texture
            grid = _product(_ints(attrib.get("width"))[:1] + _ints(attrib.get("height"))[:1])
        if grid > MAX_GRID:
            raise self.refuse(f"a <{tag}> in {str(here)!r} has {grid} cells, more than {MAX_GRID}")
        for key, name in attrib.items():
            if not key.startswith("file") or not name:
                continue
            if tag == "include":
                for p, data in self.existing(name, here, (), MAX_MJCF_BYTES, "MJCF include"):
                    self.visit(p, data, mult, depth + 1)
            elif tag == "model":  # an asset model, counted where it is attached
                before = (self.elements, self.bodies)
                for p, data in self.existing(name, here, ("",), MAX_MJCF_BYTES, "MJCF model"):
                    self.visit(p, data, 1, depth + 1)
                self.models[attrib.get("name", "")] = (self.elements - before[0], self.bodies - before[1])
            else:
                self.asset(tag, name, here)

    def asset(self, tag: str, name: str, here: Path) -> None:
        primary = self.root_dir / self.dirs[_ASSET_DIRS[tag]] / name if tag in _ASSET_DIRS else None
        dirs = tuple(dict.fromkeys([*self.dirs.values(), ""]))
        for p, data in self.existing(name, here, dirs, MAX_ASSET_BYTES, f"{tag} file"):
            if tag in ("texture", "hfield"):
                self.check_grid(tag, p, data)
            if primary is not None and p == primary:
                self.files.setdefault(self.rel(p), hashlib.sha256(data).hexdigest())

    def check_grid(self, tag: str, p: Path, data: bytes) -> None:
        if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
            cells = _product(list(struct.unpack(">II", data[16:24])))
        elif tag == "hfield" and len(data) >= 8:
            cells = _product(list(struct.unpack("<ii", data[:8])))
        else:
            return
        if cells > MAX_GRID:
            raise self.refuse(f"{str(p)!r} is a {tag} of {cells} cells, more than {MAX_GRID}")

    def check_size(self, attrib: dict, here: Path) -> None:
        for key, value in attrib.items():
            if key == "memory":
                m = re.fullmatch(r"\s*(\d+)\s*([KMGTPE]?)\s*", value.upper())
                n = int(m.group(1)) * _SIZE_UNITS[m.group(2)] if m else 0
                bound = MAX_ARENA_BYTES
            else:
                n, bound = max(_ints(value)[:1] or [0]), 10**6
            if n > bound:
                raise self.refuse(f"<size {key}=\"{value[:40]}\"> in {str(here)!r} is more than {bound}")


def check_model(path: str | Path) -> dict[str, str]:
    """Check the MJCF file ``path`` and every file it references (module docstring) before MuJoCo opens any;
    :class:`ConfigError` naming the file and the bound otherwise.  Returns ``{file: sha256}`` of the model,
    its includes and its meshes, skins, height fields and textures (names relative to the model's folder)."""
    path = Path(path).resolve()
    walk = _Walk(path.parent, f"MJCF model {str(path)!r}")
    found = walk.existing(path.name, path, (), MAX_MJCF_BYTES, "MJCF file")
    if not found:
        raise ConfigError(f"model: MJCF file {str(path)!r} does not exist")
    walk.visit(found[0][0], found[0][1], 1, 0)
    return walk.files


def check_xml(xml: str, base_dir: str | Path = ".") -> None:
    """:func:`check_model` for an MJCF string (its files resolved against ``base_dir``)."""
    data = xml.encode()
    if len(data) > MAX_MJCF_BYTES:
        raise ConfigError(f"MJCF string of {len(data)} bytes, more than a model file may ({MAX_MJCF_BYTES})")
    base = Path(base_dir).resolve()
    walk = _Walk(base, "MJCF string")
    walk.visit(base / "<xml string>", data, 1, 0)
