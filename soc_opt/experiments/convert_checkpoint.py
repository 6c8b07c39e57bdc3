"""``soc-opt convert-checkpoint --trust DIR``: old pickle checkpoints to the data-only format.

Run directories of the pickle format hold ``checkpoint.pkl``, ``checkpoint.prev.pkl`` and (``soc-opt
compare``) ``seed_*/fork_state.pkl``: pickles, which run whatever code they contain when read.
soc_opt now refuses them (:class:`soc_opt.experiments.rundir.LegacyCheckpointError`).  This module is the
only place in soc_opt that unpickles, and only for a directory the user vouches for with
``--trust``: each pickle found under the directory is read, written again as a state file
(:mod:`soc_opt.experiments.statefile`: ``checkpoint.npz``, ``checkpoint.prev.npz``, ``fork_state.npz``)
and deleted.  Never run it on a directory from someone you do not trust.
"""

from __future__ import annotations

import hashlib
import io
import pickle
from pathlib import Path

from ..config import ConfigError
from ..reading import RefusedFile, read_regular
from .rundir import LEGACY_FILES, MAX_CHECKPOINT_BYTES, atomic_write_bytes
from .statefile import encode_state

__all__ = ["convert_directory", "legacy_files"]

_MAGIC = b"soc_opt checkpoint v1\n"


def legacy_files(directory: str | Path) -> list[Path]:
    """Every old pickle checkpoint under ``directory`` (recursively), sorted."""
    root = Path(directory)
    return sorted(p for name in LEGACY_FILES for p in root.rglob(name) if p.is_file())


#: Modules of the pickles written before the package was grouped by concept, and where their
#: classes live now.
_MOVED = {"soc_opt.estimator": "soc_opt.noise.estimator", "soc_opt.mixture": "soc_opt.learning.mixture",
          "soc_opt.fit": "soc_opt.learning.fit", "soc_opt.noise_aware": "soc_opt.noise.aware"}

#: The classes the ``soc_opt.algorithms`` module of pickled checkpoints defined and the modules that
#: hold them now.
_MOVED_FROM_ALGORITHMS = {
    **dict.fromkeys(("PaperScale", "LoopKLStepConfig", "LQRFLMConfig", "EMConfig", "EvalConfig", "DPSOCConfig"),
                    "soc_opt.methods.config"),
    **dict.fromkeys(("BestPolicy", "PreviousStep", "EMDiagnostics", "IterationRecord", "RunState"),
                    "soc_opt.methods.state"),
}


class _RenamingUnpickler(pickle.Unpickler):
    """An unpickler that finds the classes of old pickles at their current modules."""

    def find_class(self, module: str, name: str):
        if module == "soc_opt.algorithms":
            module = _MOVED_FROM_ALGORITHMS.get(name, module)
        return super().find_class(_MOVED.get(module, module), name)


def _unpickle_trusted(path: Path):
    """The object in an old checkpoint file (header + SHA-256 + pickle, or a bare pickle).
    Runs the pickle: call only for files the user trusts."""
    try:
        data = read_regular(path, MAX_CHECKPOINT_BYTES, what="checkpoint")  # never blocks, bounded, no link followed
    except RefusedFile as e:
        raise ConfigError(str(e)) from None
    if data.startswith(_MAGIC):
        head, sep, payload = data[len(_MAGIC):].partition(b"\n")
        if not sep or hashlib.sha256(payload).hexdigest().encode() != head:
            raise ConfigError(f"{path}: truncated or damaged (checksum mismatch); not converted")
    else:
        payload = data
    return _RenamingUnpickler(io.BytesIO(payload)).load()


def convert_directory(directory: str | Path, trust: bool = False) -> list[tuple[Path, Path]]:
    """Convert every old pickle checkpoint under ``directory``; returns ``[(old, new), ...]``.

    ``trust`` must be True (``--trust``): reading a pickle runs the code it holds.
    """
    root = Path(directory)
    if not root.is_dir():
        raise ConfigError(f"convert-checkpoint: {str(root)!r} is not a directory")
    found = legacy_files(root)
    if not trust:
        raise ConfigError(
            f"convert-checkpoint reads pickle files, which run whatever code they hold: {len(found)} found under "
            f"{str(root)!r}. Only if you trust where this directory came from, rerun with --trust")
    done = []
    for old in found:
        new = old.with_suffix(".npz")
        try:
            state = _unpickle_trusted(old)
            data = encode_state(state)
        except ConfigError:
            raise
        except Exception as e:
            raise ConfigError(f"{old}: cannot be converted ({type(e).__name__}: {e})") from e
        atomic_write_bytes(new, data)
        old.unlink()
        done.append((old, new))
    return done
