"""The methods' public face (docs/math.md §7): LQR-FLM, DPSOC-EM (paper Algorithm 1), model-based iLQG.

The code lives in :mod:`soc_opt.methods` (run configuration, run state, one module per method,
the registry); this module re-exports the names scripts use (``from soc_opt.algorithms import
DPSOCConfig, run_algorithm``), so those imports keep working.
"""

from __future__ import annotations

from typing import Callable

from .methods.config import (
    PAPER,
    DPSOCConfig,
    EMConfig,
    EvalConfig,
    LoopKLStepConfig,
    LQRFLMConfig,
    PaperScale,
    with_paper_scale,
    with_task_init_var,
)
from .methods.dpsoc_em import dpsoc_iteration, em_update
from .methods.ilqg import ILQGConfig, ilqg
from .methods.lqr_flm import initial_state, lqr_flm_iteration
from .methods.registry import METHODS, check_config, get_method, run
from .methods.state import BestPolicy, EMDiagnostics, IterationRecord, PreviousStep, RunState

__all__ = [
    "PaperScale",
    "PAPER",
    "LoopKLStepConfig",
    "LQRFLMConfig",
    "EMConfig",
    "EvalConfig",
    "DPSOCConfig",
    "ILQGConfig",
    "with_paper_scale",
    "with_task_init_var",
    "BestPolicy",
    "PreviousStep",
    "EMDiagnostics",
    "RunState",
    "IterationRecord",
    "METHODS",
    "get_method",
    "check_config",
    "initial_state",
    "lqr_flm_iteration",
    "em_update",
    "dpsoc_iteration",
    "run_algorithm",
    "ilqg",
]


def run_algorithm(task, method: str, cfg: DPSOCConfig, seed: int = 0, state: RunState | None = None,
                  on_iteration: Callable[[RunState], None] | None = None):
    """Run ``method`` (a name in :data:`METHODS`) to the end from ``state`` (or a fresh start).

    ``on_iteration`` is called with the new state after every finished iteration
    (checkpointing, progress lines).  The final state's ``best`` is the best policy sampled.
    """
    return run(task, method, cfg, seed=seed, state=state, on_iteration=on_iteration)
