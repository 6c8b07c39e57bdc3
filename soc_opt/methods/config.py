"""The run configuration (docs/math.md §7): one TOML file holds every method's sections.

:class:`DPSOCConfig` is the whole file.  Its fields are the sections the sample-based methods share:
``[baseline]`` (:class:`~soc_opt.methods.lqr_flm.config.LQRFLMConfig`, defined in LQR-FLM's folder),
``[em]`` (:class:`~soc_opt.methods.dpsoc_em.config.EMConfig`, in DPSOC-EM's), ``i_switch`` and
:class:`EvalConfig` (``[evaluation]``); every registered method that declares ``settings`` adds its own
table named after it (iLQG's ``[ilqg]``), assembled from :data:`soc_opt.plugins.METHODS`
(:mod:`soc_opt.config`, "Plug-in tables"); likewise each estimator's options under
``[baseline.noise.NAME]``.  Which sections a method reads is declared by the method itself
(:attr:`soc_opt.methods.base.Method.sections`); this module imports the two settings modules and no
method code (``pyproject.toml``, "The core imports no plug-in").
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..config import Config, ConfigError, Interval
from ..plugins import METHODS
from .dpsoc_em.config import EMConfig
from .limits import MAX_BATCH_BYTES, MAX_ITERATIONS, MAX_SAMPLES, MAX_WORKERS
from .lqr_flm.acceptance import AS_WRITTEN, AcceptanceConfig, acceptance_limit
from .lqr_flm.config import PAPER, LoopKLStepConfig, LQRFLMConfig, PaperScale, StepSizeConfig, with_paper_scale

__all__ = ["PaperScale", "PAPER", "LoopKLStepConfig", "StepSizeConfig", "AcceptanceConfig", "AS_WRITTEN", "LQRFLMConfig",
           "EMConfig", "EvalConfig", "DPSOCConfig", "with_paper_scale", "with_task_init_var", "acceptance_limit", "check_scale",
           "MAX_ITERATIONS", "MAX_SAMPLES", "MAX_WORKERS", "MAX_BATCH_BYTES"]


@dataclass(frozen=True)
class EvalConfig(Config):
    """Evaluation of the final policies by ``soc-opt compare`` (docs/math.md §9.5).

    samples:     fresh rollouts per final policy (default: ``baseline.samples``).
    seed_offset: the evaluation generator is seeded with ``seed_offset + seed``: the same stream
                 for both methods, distinct from the training stream of that seed.
    """

    samples: int | None = None
    seed_offset: int = 10_000

    _constraints = {
        "samples": [None, Interval(1, MAX_SAMPLES)],
        "seed_offset": [Interval(0)],  # it seeds a numpy Generator
    }


@dataclass(frozen=True)
class DPSOCConfig(Config):
    """DPSOC-EM (paper Algorithm 1): baseline until ``i_switch``, EM phase, baseline again.

    The run configuration: it holds every sub-configuration of a run (one TOML file, shared by
    ``soc-opt run --method dpsoc-em|lqr-flm|ilqg`` and ``soc-opt compare``; each method reads
    its own sections (:attr:`Method.sections <soc_opt.methods.base.Method.sections>`) and ignores the
    others; its :meth:`~soc_opt.methods.base.Method.check_config` runs its own checks).

    i_switch:   the EM phase runs after this many baseline iterations (default: the paper's,
                ``PAPER.i_switch``); must be below ``baseline.iterations`` for DPSOC-EM only.
    baseline:   the LQR-FLM configuration (iterations = total baseline iterations).
    em:         the EM phase configuration.
    evaluation: evaluation of the final policies (``soc-opt compare``).

    Plus one table per registered method that declares ``settings``, named after the method
    (:data:`soc_opt.plugins.METHODS`): ``[ilqg]`` (model-based iLQG, ``soc-opt run --method ilqg``,
    :class:`soc_opt.methods.ilqg.config.ILQGConfig`), read as ``cfg.ilqg`` or ``cfg.section("ilqg")``.
    plugin_tables: where those tables are kept (the ones that differ from their defaults, by name); give
                a table by its name instead (TOML, keyword argument, ``replace``).
    """

    i_switch: int = PAPER.i_switch
    baseline: LQRFLMConfig = field(default_factory=LQRFLMConfig)
    em: EMConfig = field(default_factory=EMConfig)
    evaluation: EvalConfig = field(default_factory=EvalConfig)
    plugin_tables: tuple = ()

    _constraints = {"i_switch": [Interval(0, MAX_ITERATIONS)]}
    _plugins = METHODS


def with_task_init_var(cfg: DPSOCConfig, task) -> DPSOCConfig:
    """``cfg`` with ``baseline.init_var`` set to the task's ``init_var`` when it is unset.

    Precedence of the initial policy covariance: ``[baseline] init_var`` of the run configuration,
    else the task's ``init_var`` (task TOML; default 1.0).  Run directories record the result.
    """
    if cfg.baseline.init_var is not None:
        return cfg
    task_cfg = getattr(task, "config", None)
    var = float(getattr(task_cfg, "init_var", 1.0))
    return cfg.replace(baseline=cfg.baseline.replace(init_var=var))


def check_scale(cfg: DPSOCConfig, task) -> None:
    """:class:`ConfigError` when the largest batch this configuration samples on ``task`` at once (an iteration's
    ``samples``, the EM phase's ``y_samples`` cost sequences, the final evaluation's ``samples``) would hold more
    than :data:`MAX_BATCH_BYTES`: true and measured states, actions, measurements and costs of every step."""
    T, n, m = int(task.T), int(task.n), int(task.m)
    per_sample = 8 * (T + 1) * (2 * n + m + 2)
    sizes = {"baseline.samples": cfg.baseline.samples, "em.y_samples": cfg.em.y_samples or 0,
             "evaluation.samples": cfg.evaluation.samples or 0}
    key, biggest = max(sizes.items(), key=lambda kv: kv[1])
    if biggest * per_sample > MAX_BATCH_BYTES:
        raise ConfigError(f"{key}: {biggest} rollouts of task {task.name!r} (T = {T}, n = {n}, m = {m}) hold "
                          f"{biggest * per_sample} bytes, more than a batch may ({MAX_BATCH_BYTES}); lower it")
