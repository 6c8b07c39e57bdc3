"""The Python entry point of a comparison: :func:`compare` runs LQR-FLM and DPSOC-EM on the same seeds (what
``soc-opt compare`` does, docs/math.md §9.5) and returns the summary and the claims as data
(:class:`CompareResult`), for a notebook or a script; the files (run directories, figures, ``report.md``) are
written as the command writes them.  ``import soc_opt; soc_opt.compare("linear2d", seeds=5)``.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

__all__ = ["compare", "CompareResult", "ClaimResult"]


@dataclass(frozen=True)
class ClaimResult:
    """One claim of docs/math.md §9.5 judged over seeds (§12.3, ``soc_opt.experiments.report.paired_test``).

    ``verdict``: ``"lower"`` (``held``), ``"reversed"``, ``"untestable with N seeds"``, ``"not shown"`` or
    ``"one seed"``; ``diff_mean`` and its 95% bootstrap interval ``[ci_low, ci_high]`` are DPSOC-EM minus
    LQR-FLM; ``p_signed_rank`` the one-sided signed-rank p for "lower", ``p_reverse`` for "higher";
    ``interval`` the interval's side of 0; ``seeds_lower`` of ``seeds`` had DPSOC-EM lower.
    """

    claim: str
    verdict: str
    held: bool
    baseline_mean: float
    baseline_std: float
    dpsoc_mean: float
    dpsoc_std: float
    diff_mean: float
    ci_low: float
    ci_high: float
    p_signed_rank: float
    p_reverse: float
    interval: str
    seeds_lower: int
    seeds: int

    @classmethod
    def from_row(cls, row: dict) -> ClaimResult:
        return cls(**{f: row.get(f, float("nan")) for f in cls.__dataclass_fields__})


@dataclass(frozen=True)
class CompareResult:
    """What :func:`compare` returns: the claims and the per-seed numbers behind them, and where the files are.

    ``per_seed[method][quantity]`` (``method`` in ``"lqr-flm"``, ``"dpsoc-em"``; ``quantity`` in ``cost``,
    ``state_spread``, ``action_spread``) is a tuple over ``seeds`` of the final policy's statistic;
    ``metrics_sampled`` / ``metrics_mean_action`` the task's metrics of the final policy per method, metric and
    seed, sampled and with the mean action; ``final_vs_last[method]`` per seed the final policy against its
    run's last sampled batch (``worse``: docs/math.md §12.3); ``config`` the run configuration used.
    """

    task: str
    seeds: tuple[int, ...]
    claims: tuple[ClaimResult, ...]
    per_seed: dict
    metrics_sampled: dict
    metrics_mean_action: dict
    final_vs_last: dict
    out: Path
    report: Path
    config: object = field(repr=False)

    def claim(self, quantity: str) -> ClaimResult:
        """The claim about ``"cost"``, ``"state"`` or ``"action"`` (a word of its text)."""
        hits = [c for c in self.claims if quantity in c.claim]
        if len(hits) != 1:
            raise KeyError(f"no single claim about {quantity!r}; claims: {[c.claim for c in self.claims]}")
        return hits[0]

    def summary(self) -> str:
        """The claims table as the command prints it."""
        from .experiments.report import format_table

        return format_table([{"claim": c.claim, "LQR-FLM": c.baseline_mean, "DPSOC-EM": c.dpsoc_mean,
                              "difference": c.diff_mean, "ci_low": c.ci_low, "ci_high": c.ci_high,
                              "seeds lower": f"{c.seeds_lower}/{c.seeds}", "verdict": c.verdict} for c in self.claims])


def compare(task, *, seeds: int | Iterable[int] = 3, first_seed: int = 0, config=None, paper: bool = False,
            set: dict | None = None, out: str | Path | None = None,
            progress: bool | Callable[[str], None] = False, restart: bool = False) -> CompareResult:
    """LQR-FLM against DPSOC-EM on the same seeds (``soc-opt compare``); returns a :class:`CompareResult`.

    Args:
        task: a task name (``"linear2d"``, ``"peg"``, ``"door"``), a task TOML path, ``"gym:<EnvId>"``, or a
            :class:`~soc_opt.tasks.Task` already built.
        seeds: how many seeds (from ``first_seed``), or the seeds themselves.  The signed-rank test behind a
            claim cannot reach 5% below 5 seeds (docs/math.md §12.3).
        config: an algorithm TOML path, a :class:`~soc_opt.methods.config.DPSOCConfig`, or ``None`` for the
            task's default file (``problems/experiments/<task>.toml``) or the defaults.
        paper: the paper's scale first (14 iterations, 20 samples, EM phase at iteration 4).
        set: overrides as ``{dotted key: value}``, as ``--set`` takes them: ``{"task.rho2": 0.1,
            "baseline.iterations": 5}``; checked like TOML values, a bad one raises ``ConfigError`` naming it.
        out: the output folder (resumed when it holds this comparison); ``None``: a new temporary folder
            (``CompareResult.out``).
        progress: ``True`` prints one line per iteration, a callable receives the lines, ``False`` is silent.
        restart: discard the runs already in ``out``.
    """
    from .experiments.compare import compare as run_compare
    from .experiments.overrides import apply_config_sets, split_sets
    from .experiments.run import load_run_config
    from .methods.config import DPSOCConfig
    from .tasks import load_task

    task_sets, sets = split_sets(dict(set or {}))
    if isinstance(task, (str, Path)):
        name = Path(str(task)).stem if not str(task).startswith("gym:") else str(task)
        task_obj = load_task(task, overrides=task_sets or None)
    else:
        if task_sets:
            raise ValueError("set: task.* keys need a task name or file, not a built Task")
        name, task_obj = task.name, task
    if isinstance(config, DPSOCConfig):
        cfg = config
    else:
        cfg = load_run_config(str(task) if isinstance(task, (str, Path)) else name, config, paper=paper)
    cfg = apply_config_sets(cfg, sets, "dpsoc-em")
    seed_list = list(range(first_seed, first_seed + seeds)) if isinstance(seeds, int) else [int(s) for s in seeds]
    if not seed_list or min(seed_list) < 0:
        raise ValueError(f"seeds: expected a positive count or non-negative seeds, got {seeds!r}")
    folder = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="soc-opt-compare-"))
    prog = (print if progress is True else progress) or None
    summary = run_compare(task_obj, cfg, seed_list, folder, task_name=name, progress=prog, restart=restart)
    tup = {m: {k: tuple(v) for k, v in q.items()} for m, q in summary["per_seed"].items()}
    return CompareResult(task=name, seeds=tuple(seed_list), claims=tuple(ClaimResult.from_row(r) for r in summary["claims"]),
                         per_seed=tup, metrics_sampled=summary["metrics_sampled"],
                         metrics_mean_action=summary["metrics_mean_action"], final_vs_last=summary["final_vs_last"],
                         out=folder, report=Path(summary["report"]), config=cfg)
