"""iLQG as a :class:`~soc_opt.methods.base.Method` (docs/math.md §7): reads ``[ilqg]``
(:class:`~soc_opt.methods.ilqg.config.ILQGConfig`) and ``--iterations``; its final evaluation adds the
iterate acting on a Kalman filter of its own model and its nominal actions open loop."""

from __future__ import annotations

import io
from typing import TYPE_CHECKING

import numpy as np

from ... import files
from ...config import ConfigError
from ...models import LinearGaussianPolicy
from ...noise.aware import mean_action
from ..base import MethodBase, fresh_rollouts
from .algorithm import check_task, filtered_policy, ilqg_iteration, initial_ilqg_state, warm_start_actions
from .config import ILQGConfig
from .state import ILQGRecord, ILQGState

if TYPE_CHECKING:
    from ...tasks import Task

__all__ = ["ILQG", "ILQG_METHOD"]


class ILQG(MethodBase):
    """iLQG as a :class:`~soc_opt.methods.base.Method`: reads the ``[ilqg]`` table; deterministic
    (the seed is not part of a run's identity); stops early on convergence or without descent."""

    name = "ilqg"
    sections: tuple[str, ...] = ("ilqg",)
    seeded = False
    sample_based = False
    cost_phase = "ilqg"
    settings = ILQGConfig  # the [ilqg] table
    state_types = (ILQGState, ILQGRecord)
    flags: tuple[str, ...] = ("iterations",)

    def check_task(self, task: Task, cfg=None) -> None:
        check_task(task)

    def check_file(self, data: dict, path) -> None:
        misplaced = sorted(set(data) & set(ILQGConfig.__dataclass_fields__))
        if misplaced:
            raise ConfigError(f"{path}: iLQG settings {', '.join(map(repr, misplaced))} belong in an [ilqg] "
                              "table of the run configuration (docs/configuration.md)")

    def apply_overrides(self, cfg, values: dict, paper: bool):
        """``--iterations`` sets ``[ilqg] iterations``."""
        if "iterations" in values:
            cfg = cfg.replace(ilqg=cfg.ilqg.replace(iterations=values["iterations"]))
        return cfg

    def total_iterations(self, cfg) -> int:
        return cfg.ilqg.iterations

    def initial_state(self, task: Task, cfg, seed: int) -> ILQGState:
        return initial_ilqg_state(task, cfg.ilqg, warm_start_actions(task, cfg.ilqg.init_policy))

    def iterate(self, task: Task, cfg, state: ILQGState) -> ILQGState:
        return ilqg_iteration(task, cfg.ilqg, state)

    def finished(self, cfg, state: ILQGState) -> bool:
        return state.iteration >= cfg.ilqg.iterations or state.status != "running"

    def final_note(self, task, cfg, seed: int, state: ILQGState, score):
        """iLQG plans on the noise-free model: under sensor noise its iterate is also evaluated acting on a
        Kalman filter of its own linearisation (:func:`~soc_opt.methods.ilqg.algorithm.filtered_policy`),
        and its nominal actions without feedback, what sensor noise cannot reach."""
        n = self.evaluation_samples(cfg)
        rho2 = float(getattr(task, "rho2", 0.0))
        out = {}
        note = (f"; {self.name} plans on the noise-free model and its iterations are scored without sensor noise, "
                f"this evaluation acts on the raw measurements (rho^2 = {rho2:g})")
        if rho2 > 0:
            fp = filtered_policy(task, state, cfg.ilqg)
            out["final_eval_filtered"] = ro_f = fresh_rollouts(task, fp, n, seed, cfg)
            out["final_eval_filtered_mean_action"] = ro_fm = fresh_rollouts(task, mean_action(fp), n, seed, cfg)
            note += f"; acting on a Kalman filter of its linearised model: sampled {score(ro_f)}, mean action {score(ro_fm)}"
        T, m = state.u.shape
        open_loop = LinearGaussianPolicy(np.zeros((T, m, task.n)), state.u, np.zeros((T, m, m)), allow_singular=True)
        out["final_eval_open_loop"] = ro_open = fresh_rollouts(task, open_loop, n, seed, cfg)
        note += f"; its nominal actions open loop: {score(ro_open)}"
        return out, note

    def progress_fields(self, record: ILQGRecord) -> dict[str, float]:
        return {"mu": float(record.mu)}

    def progress_line(self, seed: int, where: str, state: ILQGState, metrics: str, times: str) -> str:
        rec = state.history[-1]
        step = f"step {rec.alpha:g}" if rec.accepted else "no descent step"
        return f"[ilqg] {where} cost {np.mean(rec.cost):.6g}  {step}  mu {rec.mu:.1e}  {metrics}  {times}"

    def finish(self, state: ILQGState, out) -> str:
        buf = io.BytesIO()
        np.savez_compressed(buf, **state.policy.to_dict())
        files.write_bytes(out / "policy.npz", buf.getvalue())  # renamed into place: no link followed
        why = {"converged": "converged (relative decrease below tol)", "no_descent": "no descent step found",
               "running": "iteration limit"}[state.status]
        return (f"iLQG: cost {state.costs[0]:.6g} -> {state.costs[-1]:.6g} in {len(state.costs) - 1} accepted "
                f"iterations ({why}); final policy {out / 'policy.npz'}; run directory {out}")


ILQG_METHOD = ILQG()
