"""The run configuration (docs/math.md §7): one TOML file holds every method's sections.

:class:`DPSOCConfig` is the whole file.  Its fields are the sections the sample-based loop shares:
:class:`LQRFLMConfig` (``[baseline]``), :class:`EMConfig` (``[em]``), :class:`EvalConfig`
(``[evaluation]``); every registered method that declares ``settings`` adds its own table named after
it (iLQG's ``[ilqg]``, :class:`soc_opt.methods.ilqg.ILQGConfig`), assembled from
:data:`soc_opt.plugins.METHODS` (:mod:`soc_opt.config`, "Plug-in tables"); likewise each estimator's
options under ``[baseline.noise.NAME]``.  Which sections a method reads is declared by the method
itself (:attr:`soc_opt.methods.base.Method.sections`); method-specific checks run through the
registry, so this module imports no method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

from .. import lqg
from ..config import Config, Interval, Options
from ..learning import fit
from ..learning.fit import COST_MODES
from ..lqg import KL_METHODS
from ..mstep.recipe import MStepRecipe
from ..noise.aware import NoiseConfig
from ..plugins import METHODS

__all__ = ["PaperScale", "PAPER", "LoopKLStepConfig", "AcceptanceConfig", "LQRFLMConfig", "EMConfig", "EvalConfig", "DPSOCConfig",
           "with_paper_scale", "with_task_init_var", "acceptance_limit"]


class PaperScale(NamedTuple):
    """The scale of the paper's experiments (docs/math.md §9.5), defined here once.

    iterations: baseline iterations per run (``LQRFLMConfig.iterations``).
    samples:    rollouts per iteration ``M`` (``LQRFLMConfig.samples``).
    i_switch:   EM phase after this many baseline iterations (``DPSOCConfig.i_switch``).
    """

    iterations: int = 14
    samples: int = 20
    i_switch: int = 4


PAPER = PaperScale()


@dataclass(frozen=True)
class LoopKLStepConfig(lqg.KLStepConfig):
    """:class:`soc_opt.lqg.KLStepConfig` as used by the LQR-FLM loop: the same fields and defaults,
    except that the dual is solved to ``kl_rtol = 1e-6`` (a budget is a step size, not a quantity to
    hit to 1e-10); any ``[baseline.kl]`` table starts from these defaults.
    """

    kl_rtol: float = 1e-6


@dataclass(frozen=True)
class AcceptanceConfig(Config):
    """Step acceptance of the sample-based methods (docs/math.md §12), ``[baseline.acceptance]``.

    enabled:  judge every sampled policy against the last accepted one and return the last accepted
              policy (default).  ``false`` is the paper as written, bit for bit: every step is taken
              and the policy of the last KL step (never sampled) is returned.
    kappa:    standard errors of the cost difference that sampling noise may explain (2.0).
    eps:      relative margin on the accepted cost ``|C_a|`` (0.02).  A policy is accepted iff
              ``C_i <= C_a + kappa sqrt(se_i^2 + se_a^2) + eps |C_a|``.
    shrink:   on a rejection the next step is taken around the last accepted policy with its
              multiplier times ``shrink`` (0.1, the GPS rule's ``factor_min``), floored at ``kl.mult_min``.
    cost:     the cost the test reads: "measured" (default; the total cost of the measured states,
              which is all a learner on a real robot observes) or "true" (the simulator's true states,
              what the run records; identical without sensor noise).
    ceiling:  after a rejection the multiplier is kept below ``ceiling`` times the multiplier of the
              rejected step until a step at that size is accepted (0.5; 1.0 turns it off), so that the
              step-size rule does not grow straight back to the size that just failed.
    hold_when_improved: after an accepted step whose samples improved on the last accepted policy by
              more than ``kappa`` standard errors, the multiplier is not lowered by the GPS rule (whose
              predicted and actual improvements come from fitted models, unreliable under sensor
              noise); off by default.
    actual:   the actual improvement the GPS rule reads on an accepted step: "laplace" (default, §6: the
              new samples' fitted model's expected cost, as the paper) or "samples" (the measured mean
              cost of the last accepted batch minus the new batch's, the trust-region ratio's numerator
              read from the samples the acceptance test already has).
    """

    enabled: bool = True
    kappa: float = 2.0
    eps: float = 0.02
    shrink: float = 0.1
    cost: Literal["measured", "true"] = "measured"
    ceiling: float = 0.5
    hold_when_improved: bool = False
    actual: Literal["laplace", "samples"] = "laplace"

    _constraints = {
        "kappa": [Interval(0)],
        "eps": [Interval(0)],
        "shrink": [Interval(0, 1, "neither")],
        "cost": [Options(("measured", "true"))],
        "ceiling": [Interval(0, 1, "right")],
        "actual": [Options(("laplace", "samples"))],
    }


#: The acceptance table of a run recorded before acceptance existed: those runs took every step.
AS_WRITTEN = AcceptanceConfig(enabled=False)


def acceptance_limit(cfg: AcceptanceConfig, c_a: float, se_a: float, se: float) -> float:
    """The largest mean cost a batch with standard error ``se`` may have against a reference batch of
    mean ``c_a`` and standard error ``se_a`` (docs/math.md §12.1): ``c_a + kappa sqrt(se^2 + se_a^2) + eps |c_a|``."""
    return c_a + cfg.kappa * float(np.hypot(se, se_a)) + cfg.eps * abs(c_a)


@dataclass(frozen=True)
class LQRFLMConfig(Config):
    """LQR-FLM baseline ("iLQG" in the paper), docs/math.md §7.

    iterations:  number of sample -> fit -> LQG rounds (default: the paper's, ``PAPER.iterations``).
    samples:     rollouts per iteration ``M`` (default: the paper's, ``PAPER.samples``).
    init_var:    initial policy covariance ``Sigma = init_var * I``; unset (``None``): the task's
                 ``init_var`` (its TOML, default 1.0).  Set here it overrides the task's
                 (:func:`with_task_init_var`; docs/configuration.md).
    kl_budget:   base KL budget per time step; the total budget is ``kl_budget * T * mult``.
    kl_mode:     "total" (one budget ``nu = sum nu_k``, one multiplier: the GPS form) or
                 "per_step" (``nu_k = kl_budget * mult`` with one multiplier per step).
    kl_method:   KL-step solver, a name in ``lqg.KL_METHODS``: "closed_form" (LQR backward pass +
                 dual), "casadi" (IPOPT) or "fatrop".
    adapt_multiplier:  adapt ``mult`` from predicted vs actual improvement (GPS rule, see lqg.adapt_multiplier).
    workers:     parallel rollout workers (results do not depend on it): threads.  A policy acting on
                 a filter (the noise estimators') steps its samples in lockstep, its filter once per
                 step for all of them, in threads only when a CPU is idle.
    fit:         dynamics-fitting configuration (docs/math.md §2).
    kl:          KL-step solver and step-adaptation configuration (docs/math.md §6), the loop's
                 :class:`LoopKLStepConfig` (dual solved to ``kl_rtol = 1e-6``).
    noise:       noise-aware variants (docs/math.md §10: corrected fit, estimator in the loop); the
                 defaults are the paper's method (:class:`soc_opt.noise.aware.NoiseConfig`).
    acceptance:  step acceptance (docs/math.md §12, :class:`AcceptanceConfig`); ``enabled = false``
                 is the paper as written.
    """

    iterations: int = PAPER.iterations
    samples: int = PAPER.samples
    init_var: float | None = None
    kl_budget: float = 0.5
    kl_mode: Literal["total", "per_step"] = "total"
    kl_method: str = "closed_form"
    adapt_multiplier: bool = True
    workers: int = 1
    fit: fit.FitConfig = field(default_factory=fit.FitConfig)
    kl: LoopKLStepConfig = field(default_factory=LoopKLStepConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    acceptance: AcceptanceConfig = field(default_factory=AcceptanceConfig)

    _implied_when_absent = {"baseline.acceptance": (AS_WRITTEN.to_dict(), {})}
    _constraints = {
        "iterations": [Interval(1)],
        "samples": [Interval(2)],  # dynamics fitting needs 2 rollouts
        "init_var": [Interval(0, None, "neither"), None],
        "kl_budget": [Interval(0, None, "neither")],
        "kl_mode": [Options(("total", "per_step"))],
        "kl_method": [Options(lambda: KL_METHODS)],
        "workers": [Interval(1)],
    }


@dataclass(frozen=True)
class EMConfig(MStepRecipe):
    """The EM phase of DPSOC-EM (docs/math.md §3–§5, paper Algorithm 1): the M-step recipe
    (:class:`soc_opt.mstep.recipe.MStepRecipe`, whose fields are method, variant, objective,
    cov_floor_scale, entropy_floor, trust_region, min_norm and mstep) plus:

    n_em:          EM recursions at the switch (each samples ``M`` rollouts of the current EM policy).
    y_mode:        cost observations ``Y``: "model" (the paper), "measured", "optimistic" (docs/math.md §3).
    y_samples:     number of ``Y`` sequences drawn in "model" mode (default: ``samples``).
    """

    n_em: int = 1
    y_mode: Literal["model", "measured", "optimistic"] = "model"
    y_samples: int | None = None

    _constraints = {
        **MStepRecipe._constraints,
        "n_em": [Interval(1)],
        "y_mode": [Options(COST_MODES)],
        "y_samples": [None, Interval(1)],
    }


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
        "samples": [None, Interval(1)],
        "seed_offset": [Interval(0)],  # it seeds a numpy Generator
    }


@dataclass(frozen=True)
class DPSOCConfig(Config):
    """DPSOC-EM (paper Algorithm 1): baseline until ``i_switch``, EM phase, baseline again.

    The run configuration: it holds every sub-configuration of a run (one TOML file, shared by
    ``soc-opt run --method dpsoc-em|lqr-flm|ilqg`` and ``soc-opt compare``; each method reads
    its own sections (:attr:`Method.sections <soc_opt.methods.base.Method.sections>`) and ignores the
    others; :func:`soc_opt.methods.registry.check_config` runs a method's own checks).

    i_switch:   the EM phase runs after this many baseline iterations (default: the paper's,
                ``PAPER.i_switch``); must be below ``baseline.iterations`` for DPSOC-EM only.
    baseline:   the LQR-FLM configuration (iterations = total baseline iterations).
    em:         the EM phase configuration.
    evaluation: evaluation of the final policies (``soc-opt compare``).

    Plus one table per registered method that declares ``settings``, named after the method
    (:data:`soc_opt.plugins.METHODS`): ``[ilqg]`` (model-based iLQG, ``soc-opt run --method ilqg``,
    :class:`soc_opt.methods.ilqg.ILQGConfig`), read as ``cfg.ilqg`` or ``cfg.section("ilqg")``.
    plugin_tables: where those tables are kept (the ones that differ from their defaults, by name); give
                a table by its name instead (TOML, keyword argument, ``replace``).
    """

    i_switch: int = PAPER.i_switch
    baseline: LQRFLMConfig = field(default_factory=LQRFLMConfig)
    em: EMConfig = field(default_factory=EMConfig)
    evaluation: EvalConfig = field(default_factory=EvalConfig)
    plugin_tables: tuple = ()

    _constraints = {"i_switch": [Interval(0)]}
    _plugins = METHODS


def with_paper_scale(cfg: DPSOCConfig) -> DPSOCConfig:
    """``cfg`` at the paper's scale (:data:`PAPER`: iterations, samples, switch point)."""
    base = cfg.baseline.replace(iterations=PAPER.iterations, samples=PAPER.samples)
    return cfg.replace(baseline=base, i_switch=PAPER.i_switch)



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
