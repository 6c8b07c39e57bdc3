"""DPSOC-EM as a :class:`~soc_opt.methods.base.Method` (paper Algorithm 1; docs/math.md §7): the LQR-FLM
iteration with the EM phase (:func:`~soc_opt.methods.dpsoc_em.em.em_phase`) plugged in once, at the
first accepted batch from iteration ``i_switch`` on."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

from ...config import ConfigError
from ...noise.strategy import resolve
from ..lqr_flm.iteration import lqr_flm_iteration
from ..lqr_flm.method import LQRFLM
from ..state import RunState
from .em import em_phase

if TYPE_CHECKING:
    from ...tasks import Task

__all__ = ["dpsoc_iteration", "DPSOCEM", "DPSOC_EM"]


def dpsoc_iteration(task: Task, cfg, state: RunState) -> RunState:
    """One DPSOC-EM iteration: the LQR-FLM iteration, with the EM phase plugged in while it is due
    (``iteration >= i_switch`` and not yet run).

    With step acceptance (docs/math.md §12) the EM phase starts from an accepted policy: the first
    recursion's batch is the acceptance test of the policy it samples; if that policy is rejected,
    the iteration is an ordinary rejected LQR-FLM iteration and the EM phase is due again at the next.
    The EM policy is then judged like any other step, on the samples it produced.
    """
    due = state.iteration >= cfg.i_switch and not state.em_done
    return lqr_flm_iteration(task, cfg.baseline, state, noise=resolve(task, cfg.baseline.noise),
                             em=functools.partial(em_phase, cfg) if due else None)


class DPSOCEM(LQRFLM):
    """DPSOC-EM: reads ``i_switch``, ``[baseline]``, ``[em]``; its history rows are LQR-FLM's plus one
    ``"em"`` row per EM recursion (the recursion's :class:`~soc_opt.methods.state.EMDiagnostics` columns)."""

    name = "dpsoc-em"
    sections: tuple[str, ...] = ("i_switch", "baseline", "em")
    flags: tuple[str, ...] = LQRFLM.flags + ("i_switch",)

    def check_config(self, cfg) -> None:
        """DPSOC-EM needs ``0 <= i_switch < baseline.iterations``."""
        if not 0 <= cfg.i_switch < cfg.baseline.iterations:
            raise ConfigError(
                f"i_switch must be in [0, iterations={cfg.baseline.iterations}), got {cfg.i_switch}"
            )

    def iterate(self, task: Task, cfg, state: RunState) -> RunState:
        return dpsoc_iteration(task, cfg, state)


DPSOC_EM = DPSOCEM()
