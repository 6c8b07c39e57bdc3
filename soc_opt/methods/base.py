"""The :class:`Method` protocol: what the CLI, experiments, compare and sweeps need of a method.

A method is an object with a name, the run-configuration sections it reads, and pure functions
on an explicit state (docs/math.md §7): ``initial_state`` then ``iterate`` until ``finished``.
Everything that used to be a ``method == "..."`` branch in the drivers is one of the hooks below;
:class:`MethodBase` gives the defaults of a sample-based method, so a new method overrides only
what differs.  A method owns its settings (``settings``: a Config class, the run configuration's
table named after the method) and its saved state (``state_types``: the classes a checkpoint of it
holds beyond :mod:`soc_opt.methods.state`); register an instance with one line in
:mod:`soc_opt.methods.registry` (the table :data:`soc_opt.plugins.METHODS`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Protocol, runtime_checkable

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["Method", "MethodBase", "run_method"]


@runtime_checkable
class Method(Protocol):
    """One optimisation method.

    name:       the method's name (``soc-opt run --method NAME``, run directories, sweeps).
    sections:   the top-level keys of the run configuration it reads (what a resumed run must match).
    seeded:     whether the seed is part of a run's identity (False for a deterministic method).
    sample_based: whether it learns from sampled rollouts (``soc-opt compare`` and sweeps run these).
    cost_phase: the ``IterationRecord.phase`` of the records drawn as "cost per iteration".
    settings:   its own configuration (a :class:`soc_opt.config.Config` subclass, documented defaults),
                the table ``[NAME]`` of the run configuration, read as ``cfg.section(NAME)`` (or
                ``cfg.NAME``); ``None``: it reads only shared sections.
    state_types: the classes its state holds that :mod:`soc_opt.methods.state` does not define (frozen
                dataclasses or named tuples): the state file's schema accepts them.
    """

    name: str
    sections: tuple[str, ...]
    seeded: bool
    sample_based: bool
    cost_phase: str
    settings: type | None
    state_types: tuple[type, ...]

    def check_config(self, cfg) -> None:
        """Method-specific checks of a run configuration (``ConfigError`` naming the key)."""

    def check_task(self, task: Task, cfg=None) -> None:
        """Raise ``ConfigError`` (before any simulation or file is written) if the method cannot run on
        ``task``, or, given the run configuration ``cfg``, not with that configuration (e.g. its state
        estimator cannot model the task)."""

    def check_file(self, data: dict, path: Path) -> None:
        """Extra checks of a run-configuration file's raw table (e.g. a hint for misplaced keys)."""

    def apply_overrides(self, cfg, values: dict, paper: bool):
        """``cfg`` with command-line overrides (``--iterations``, ``--samples``, ``--paper``...) applied."""

    def total_iterations(self, cfg) -> int:
        """The iteration budget of a run."""

    def initial_state(self, task: Task, cfg, seed: int) -> Any:
        """The state before the first iteration."""

    def iterate(self, task: Task, cfg, state) -> Any:
        """One iteration: a new state (pure; the state holds the RNG)."""

    def finished(self, cfg, state) -> bool:
        """Whether the run is over (iteration budget, convergence)."""

    def final_policy(self, cfg, state) -> Any:
        """The policy the run returns (docs/math.md §12.3), what ``compare`` and sweeps evaluate."""

    def progress_fields(self, record) -> dict[str, float]:
        """The numbers a progress bar shows next to the cost."""

    def progress_line(self, seed: int, where: str, state, metrics: str, times: str) -> str:
        """One console line after an iteration."""

    def finish(self, state, out: Path) -> str:
        """Write the method's own final files into ``out``; the closing console line."""


class MethodBase(ABC):
    """Defaults shared by the methods: no extra checks, the run ends at :meth:`total_iterations`
    (which every method defines)."""

    name: str = ""
    sections: tuple[str, ...] = ()
    seeded: bool = True
    sample_based: bool = False
    cost_phase: str = "baseline"
    settings: ClassVar[type | None] = None
    state_types: ClassVar[tuple[type, ...]] = ()

    def check_config(self, cfg) -> None:
        pass

    def check_task(self, task, cfg=None) -> None:
        pass

    def check_file(self, data: dict, path: Path) -> None:
        """Extra checks of a run-configuration file's raw table (e.g. a hint for misplaced keys)."""

    @abstractmethod
    def total_iterations(self, cfg) -> int:
        """How many iterations a run of this configuration makes."""

    def finished(self, cfg, state) -> bool:
        return state.iteration >= self.total_iterations(cfg)

    def final_policy(self, cfg, state):
        return state.policy

    def progress_fields(self, record) -> dict[str, float]:
        return {}

    def finish(self, state, out: Path) -> str:
        best = state.best
        return f"done: best mean cost {best.mean_cost:.6g} (iteration {best.iteration}); run directory {out}"


def run_method(method: Method, task, cfg, seed: int = 0, state=None,
               on_iteration: Callable[[Any], None] | None = None):
    """Iterate ``method`` from ``state`` (or a fresh start) until it is finished.

    ``on_iteration`` is called with the new state after every iteration (checkpoints, progress).
    """
    method.check_config(cfg)
    method.check_task(task, cfg)
    if state is None:
        state = method.initial_state(task, cfg, seed)
    while not method.finished(cfg, state):
        state = method.iterate(task, cfg, state)
        if on_iteration is not None:
            on_iteration(state)
    return state
