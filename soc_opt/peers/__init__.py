"""Adapters to the tools users would pick instead (docs/results/peers/).

Each submodule states one problem in soc_opt's terms and in a peer's, runs both and returns the
differences and timings; nothing here changes soc_opt's own algorithms.

* :mod:`.smoothers`: the E-step's filter/smoother (docs/math.md §4) against dynamax's
  ``lgssm_smoother`` (JAX) and pykalman's ``KalmanFilter`` on one time-varying linear-Gaussian
  model with uncorrelated process and observation noise (the case every peer can express).
* :mod:`.lqr`: the KL step's backward pass (docs/math.md §6) with ``eta = 0`` (plain LQR), and the
  KL step at its optimal multiplier, against a finite-horizon time-varying LQR peer.
* :mod:`.rl`: stable-baselines3 SAC and PPO, sbx-rl SAC and CrossQ on ``soc_opt/Peg-v0`` and
  ``soc_opt/Door-v0`` at a fixed budget of environment steps (resumable off-policy runs).

The peers are the optional extra ``pip install -e '.[peers]'``; :func:`versions` says which are
importable.
"""

from __future__ import annotations

import importlib

__all__ = ["PEERS", "versions", "require"]

#: import name -> distribution name of every peer.
PEERS = {
    "jax": "jax",
    "dynamax": "dynamax",
    "pykalman": "pykalman",
    "stable_baselines3": "stable-baselines3",
    "torch": "torch",
    "sbx": "sbx-rl",
}


def versions() -> dict[str, str | None]:
    """``{distribution: version or None}`` for every peer (None: not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist in PEERS.values():
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = None
    return out


def require(module: str):
    """Import a peer module, or raise ImportError saying which extra provides it."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{module} is not installed: it is a peer of the optional extra "
                          f"`pip install -e '.[peers]'` (docs/results/peers/README.md)") from e
