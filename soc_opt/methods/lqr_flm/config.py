"""LQR-FLM's settings, the ``[baseline]`` table of a run configuration (docs/math.md §7), and the scale of
the paper's experiments.  DPSOC-EM reads the same table; the run configuration that holds it is
:class:`soc_opt.methods.config.DPSOCConfig`.  This module is data only: it imports no method code, so
the core may read it (``pyproject.toml``, "The core imports no plug-in")."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, NamedTuple

from ... import lqg
from ...config import Config, Interval, Options
from ...learning import fit
from ...lqg import KL_METHODS
from ...lqg.step_size import StepSizeConfig
from ...noise.aware import NoiseConfig
from ..limits import MAX_ITERATIONS, MAX_SAMPLES, MAX_WORKERS
from .acceptance import AS_WRITTEN, AcceptanceConfig

__all__ = ["PaperScale", "PAPER", "LoopKLStepConfig", "AcceptanceConfig", "StepSizeConfig", "LQRFLMConfig",
           "with_paper_scale"]


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


#: The step-size keys a ``[baseline.kl]`` table may still hold (read into ``[baseline.step_size]``).
_STEP_SIZE_KEYS = frozenset(StepSizeConfig.__dataclass_fields__)


@dataclass(frozen=True)
class LQRFLMConfig(Config):
    """LQR-FLM baseline ("iLQG" in the paper), docs/math.md §7.

    iterations:  number of sample -> fit -> LQG rounds (default: the paper's, ``PAPER.iterations``).
    samples:     rollouts per iteration ``M`` (default: the paper's, ``PAPER.samples``).
    init_var:    initial policy covariance ``Sigma = init_var * I``; unset (``None``): the task's
                 ``init_var`` (its TOML, default 1.0).  Set here it overrides the task's
                 (:func:`soc_opt.methods.config.with_task_init_var`; docs/configuration.md).
    kl_budget:   base KL budget per time step; the total budget is ``kl_budget * T * mult``.
    kl_mode:     "total" (one budget ``nu = sum nu_k``, one multiplier: the GPS form) or
                 "per_step" (``nu_k = kl_budget * mult`` with one multiplier per step).
    kl_method:   KL-step solver, a name in ``lqg.KL_METHODS``: "closed_form" (LQR backward pass +
                 dual), "casadi" (IPOPT) or "fatrop".
    adapt_multiplier:  adapt ``mult`` from predicted vs actual improvement (GPS rule, ``step_size``).
    workers:     parallel rollout workers (results do not depend on it): threads.  A policy acting on
                 a filter (the noise estimators') steps its samples in lockstep, its filter once per
                 step for all of them, in threads only when a CPU is idle.
    fit:         dynamics-fitting configuration (docs/math.md §2).
    kl:          the KL step's solver options (docs/math.md §6), the loop's :class:`LoopKLStepConfig`
                 (dual solved to ``kl_rtol = 1e-6``).
    step_size:   the GPS rule on the multiplier (:class:`soc_opt.lqg.step_size.StepSizeConfig`:
                 ``factor_min``, ``factor_max``, ``min_gap``, ``mult_min``, ``mult_max``).  A ``[baseline.kl]``
                 table may hold these keys too (older files do); they are read
                 into this table, over its value.
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
    step_size: StepSizeConfig = field(default_factory=StepSizeConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    acceptance: AcceptanceConfig = field(default_factory=AcceptanceConfig)

    _implied_when_absent = {"baseline.acceptance": (AS_WRITTEN.to_dict(), {})}
    _constraints = {
        "iterations": [Interval(1, MAX_ITERATIONS)],
        "samples": [Interval(2, MAX_SAMPLES)],  # dynamics fitting needs 2 rollouts
        "init_var": [Interval(0, None, "neither"), None],
        "kl_budget": [Interval(0, None, "neither")],
        "kl_mode": [Options(("total", "per_step"))],
        "kl_method": [Options(lambda: KL_METHODS)],
        "workers": [Interval(1, MAX_WORKERS)],
    }

    @classmethod
    def from_dict(cls, data: dict, _path: str = "") -> LQRFLMConfig:
        """:meth:`Config.from_dict`, reading step-size keys given in ``kl`` (where files written before
        ``[baseline.step_size]`` existed hold them, and a sweep's override may) into ``step_size``, over
        the value there."""
        kl = data.get("kl") if isinstance(data, dict) else None
        step = data.get("step_size", {}) if isinstance(data, dict) else None
        moved = sorted(_STEP_SIZE_KEYS & set(kl)) if isinstance(kl, dict) and isinstance(step, dict) else []
        if moved:
            data = {**data, "kl": {k: v for k, v in kl.items() if k not in _STEP_SIZE_KEYS},
                    "step_size": {**step, **{k: kl[k] for k in moved}}}
        return super().from_dict(data, _path)


def with_paper_scale(cfg):
    """The run configuration ``cfg`` (:class:`~soc_opt.methods.config.DPSOCConfig`) at the paper's scale
    (:data:`PAPER`: iterations, samples, switch point)."""
    base = cfg.baseline.replace(iterations=PAPER.iterations, samples=PAPER.samples)
    return cfg.replace(baseline=base, i_switch=PAPER.i_switch)
