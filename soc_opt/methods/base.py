"""The :class:`Method` protocol: what the CLI, experiments, compare and sweeps need of a method.

A method is an object with a name, the run-configuration sections it reads, and pure functions
on an explicit state (docs/math.md §7): ``initial_state`` then ``iterate`` until ``finished``.
What the drivers need of it is one of the hooks below (the command-line flags it reads, its final
evaluation, its console lines); :class:`MethodBase` gives the defaults, so a new method overrides only
what differs.  A method owns its settings (``settings``: a Config class, the run configuration's
table named after the method) and its saved state (``state_types``: the classes a checkpoint of it
holds beyond :mod:`soc_opt.methods.state`); register an instance with one line in
:mod:`soc_opt.methods.registry`, or ``soc_opt.plugins.METHODS.register(...)`` from a script (the one
registration API: it checks the protocol).  :func:`soc_opt.methods.conformance.check_method` is what any
method must pass.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar, NamedTuple, Protocol, runtime_checkable

import numpy as np

from ..config import ConfigError
from ..models import Rollouts
from ..noise.aware import mean_action

if TYPE_CHECKING:
    from ..tasks import Task

__all__ = ["Method", "MethodBase", "FinalEvaluation", "FLAGS", "check_protocol", "apply_overrides", "fresh_rollouts",
           "run_method"]

#: The command-line flags that set a run configuration (``soc-opt run``/``compare``), by override key.
FLAGS = ("iterations", "samples", "workers", "i_switch", "as_written", "paper")


class FinalEvaluation(NamedTuple):
    """What :meth:`Method.evaluate_final` returns (docs/math.md §12.3).

    policy:   the policy the run returns (written to ``final_policy.npz``).
    rollouts: fresh rollouts by file stem (``final_eval``, ``final_eval_mean_action``, then the
              method's own), each written to ``<stem>.npz``.
    line:     one console line saying what was evaluated.
    """

    policy: Any
    rollouts: dict[str, Rollouts]
    line: str


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
    flags:      the command-line flags it reads, by override key (a subset of :data:`FLAGS`); any other
                is refused naming the flag (:func:`apply_overrides`).
    """

    name: str
    sections: tuple[str, ...]
    seeded: bool
    sample_based: bool
    cost_phase: str
    settings: type | None
    state_types: tuple[type, ...]
    flags: tuple[str, ...]

    def check_config(self, cfg) -> None:
        """Method-specific checks of a run configuration (``ConfigError`` naming the key)."""

    def check_task(self, task: Task, cfg=None) -> None:
        """Raise ``ConfigError`` (before any simulation or file is written) if the method cannot run on
        ``task``, or, given the run configuration ``cfg``, not with that configuration (e.g. its state
        estimator cannot model the task)."""

    def check_file(self, data: dict, path: Path) -> None:
        """Extra checks of a run-configuration file's raw table (e.g. a hint for misplaced keys)."""

    def apply_overrides(self, cfg, values: dict, paper: bool):
        """``cfg`` with command-line overrides applied: ``values`` holds only keys of :attr:`flags`, and
        ``paper`` is true only if ``"paper"`` is one (:func:`apply_overrides` checks)."""

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

    def evaluate_final(self, task: Task, cfg, seed: int, state, score: Callable[[Rollouts], str]) -> FinalEvaluation:
        """The returned policy on fresh rollouts of the evaluation stream (``soc-opt run``'s last line);
        ``score(rollouts)`` formats a batch's cost and headline metrics."""

    def progress_fields(self, record) -> dict[str, float]:
        """The numbers a progress bar shows next to the cost."""

    def progress_line(self, seed: int, where: str, state, metrics: str, times: str) -> str:
        """One console line after an iteration."""

    def finish(self, state, out: Path) -> str:
        """Write the method's own final files into ``out``; the closing console line."""


#: Every member of :class:`Method`: what :func:`check_protocol` asks of a method.
MEMBERS = tuple(sorted(set(Method.__annotations__) | {k for k, v in vars(Method).items()
                                                       if callable(v) and not k.startswith("_")}))


def check_protocol(method: Any) -> None:
    """``TypeError`` unless ``method`` is an object implementing :class:`Method`: every member present, the
    hooks callable, ``sections`` and ``flags`` tuples of names (``flags`` among :data:`FLAGS`), ``seeded``
    and ``sample_based`` booleans.  :data:`soc_opt.plugins.METHODS` runs it on every registration."""
    if isinstance(method, type):
        raise TypeError(f"register an instance of {method.__name__}, not the class")
    missing = [m for m in MEMBERS if not hasattr(method, m)]
    if missing:
        raise TypeError(f"{method!r} does not implement the Method protocol (soc_opt.methods.base.Method): "
                        f"missing {', '.join(missing)}")
    name = method.name
    hooks = [k for k in MEMBERS if callable(getattr(Method, k, None)) and not callable(getattr(method, k))]
    if hooks:
        raise TypeError(f"method {name!r}: {', '.join(hooks)} must be callable")
    for attr in ("sections", "flags"):
        value = getattr(method, attr)
        if not isinstance(value, tuple) or not all(isinstance(v, str) for v in value):
            raise TypeError(f"method {name!r}: {attr} must be a tuple of names, got {value!r}")
    unknown = sorted(set(method.flags) - set(FLAGS))
    if unknown:
        raise TypeError(f"method {name!r}: flags {unknown} are not command-line flags ({', '.join(FLAGS)})")
    for attr in ("seeded", "sample_based"):
        if not isinstance(getattr(method, attr), bool):
            raise TypeError(f"method {name!r}: {attr} must be True or False, got {getattr(method, attr)!r}")
    if not isinstance(method.cost_phase, str):
        raise TypeError(f"method {name!r}: cost_phase must be a string, got {method.cost_phase!r}")


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
    flags: tuple[str, ...] = ()

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

    def evaluation_samples(self, cfg) -> int:
        """Fresh rollouts per evaluation: ``[evaluation] samples``, else ``[baseline] samples``."""
        return cfg.evaluation.samples or cfg.baseline.samples

    def evaluate_final(self, task, cfg, seed: int, state, score) -> FinalEvaluation:
        """:meth:`final_policy` sampled and with its mean action on ``evaluation_samples(cfg)`` fresh rollouts;
        methods add their own (:meth:`final_note`)."""
        policy = self.final_policy(cfg, state)
        n = self.evaluation_samples(cfg)
        ro = fresh_rollouts(task, policy, n, seed, cfg)
        ro_mean = fresh_rollouts(task, mean_action(policy), n, seed, cfg)
        extra, note = self.final_note(task, cfg, seed, state, score)
        rho2 = float(getattr(task, "rho2", 0.0))
        line = (f"final policy = {self.final_label(cfg, state, policy)}, {n} fresh rollouts at rho^2 = {rho2:g}: "
                f"sampled {score(ro)}; mean action {score(ro_mean)}{note} (final_eval*.npz)")
        return FinalEvaluation(policy, {"final_eval": ro, "final_eval_mean_action": ro_mean, **extra}, line)

    def final_label(self, cfg, state, policy) -> str:
        """What the returned policy is, in the final line."""
        return "the last iterate"

    def final_note(self, task, cfg, seed: int, state, score) -> tuple[dict[str, Rollouts], str]:
        """A method's own evaluations (file stem -> rollouts) and what the final line says of them
        (``"; ..."``); none by default."""
        return {}, ""

    def progress_fields(self, record) -> dict[str, float]:
        return {}

    def finish(self, state, out: Path) -> str:
        best = state.best
        return f"done: best mean cost {best.mean_cost:.6g} (iteration {best.iteration}); run directory {out}"


def fresh_rollouts(task, policy, samples: int, seed: int, cfg) -> Rollouts:
    """``samples`` rollouts of ``policy`` from the evaluation stream of ``seed`` (``[evaluation] seed_offset +
    seed``: every method on the same noise, distinct from its training samples, docs/math.md §9.5), with
    ``[baseline] workers``; the stream of :func:`soc_opt.experiments.compare.evaluate_policy`."""
    rng = np.random.default_rng(cfg.evaluation.seed_offset + seed)
    return task.rollouts(policy, samples, rng, workers=cfg.baseline.workers)


def apply_overrides(method: Method, cfg, values: dict, paper: bool = False):
    """``cfg`` with the command-line overrides ``values`` (``None`` values skipped) and ``paper`` applied by
    ``method``; a flag it does not read (not in ``method.flags``) is a :class:`ConfigError` naming the flag
    and the ones it reads."""
    values = {k: v for k, v in values.items() if v is not None}
    unread = [k for k in values if k not in method.flags] + (["paper"] if paper and "paper" not in method.flags else [])
    if unread:
        reads = ", ".join(f"--{k.replace('_', '-')}" for k in method.flags) or "no flag"
        raise ConfigError(f"--{unread[0].replace('_', '-')} does not apply to --method {method.name} "
                          f"(it reads {reads}; its settings are in its configuration tables)")
    return method.apply_overrides(cfg, values, paper)


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
