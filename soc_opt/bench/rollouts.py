"""Rollout throughput of a MuJoCo task versus raw ``mj_step`` (``soc_opt/tasks.py``).

``run()`` measures simulator steps per second (``M * T * substeps`` physics steps)
of ``task.rollouts`` serially and with ``workers=2`` threads, of a plain Python loop
of ``mujoco.mj_step`` on the same model with a constant ``ctrl``, and of an open-loop
replay of the rollouts' own actions; the ratios are the fraction of raw throughput the
rollout machinery keeps.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["run", "QUICK"]

#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"M": 2, "T": 5, "repeats": 1}


def _best_of(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run(task: str = "peg", M: int = 20, T: int = 100, seed: int = 0, repeats: int = 3) -> list[dict]:
    """Rows ``{"case", "task", "M", "T", "steps", "seconds", "steps_per_s", "ratio_to_raw", "ratio_to_replay"}``.

    Cases (best of ``repeats`` timings after one warm-up run, ``M * T * substeps`` physics steps each):

    * ``raw_mj_step``: per sample, reset to ``x_0`` and a Python loop of ``mujoco.mj_step`` with a
      constant ``ctrl = 0.1`` (the reference of ``ratio_to_raw``);
    * ``replay_mj_step_nstep``: the actions of the measured rollouts replayed open loop,
      ``mj_step(m, d, substeps)`` per action: physics of exactly the same trajectories with no
      per-step Python work (the reference of ``ratio_to_replay``);
    * ``rollouts_serial`` and ``rollouts_workers2``: ``task.rollouts`` with the initial policy;
    * ``rollouts_kinematic_filter``: the initial policy acting on the kinematic estimator's online filter
      (``gains = "online"``, learned from the serial rollouts' batch), its samples stepped in lockstep
      (one filter call per control step for all of them).
    """
    import mujoco

    from ..tasks import MujocoTask, load_task

    t = load_task(task, overrides={"T": T})
    if not isinstance(t, MujocoTask):
        raise ValueError(f"task {task!r} is not a MuJoCo task")
    policy = t.initial_policy()
    nsub = t.substeps
    steps = M * T * nsub
    model = t.model
    data = mujoco.MjData(model)
    q0 = t.qpos_from_state(t.x0)
    actions = t.rollouts(policy, M, np.random.default_rng(seed)).a
    act = t.actuator_ids

    def raw():
        step = mujoco.mj_step
        for _ in range(M):
            mujoco.mj_resetData(model, data)
            data.qpos[:] = q0
            data.ctrl[:] = 0.1
            for _ in range(T * nsub):
                step(model, data)

    def replay():
        step = mujoco.mj_step
        for i in range(M):
            mujoco.mj_resetData(model, data)
            data.qpos[:] = q0
            for k in range(T):
                data.ctrl[act] = actions[i, k]
                step(model, data, nsub)

    def roll(workers, pol=policy):
        t.rollouts(pol, M, np.random.default_rng(seed), workers=workers)

    from ..noise.kinematic import loop
    from ..noise.kinematic.config import KinematicConfig
    from ..noise.kinematic.filter import KinematicFilteredPolicy

    batch = t.rollouts(policy, max(M, 2), np.random.default_rng(seed))
    _, filt, _ = loop.learn(t, batch, policy, KinematicConfig(gains="online"))
    filtered = KinematicFilteredPolicy(policy, filt)

    cases = [
        ("raw_mj_step", raw),
        ("replay_mj_step_nstep", replay),
        ("rollouts_serial", lambda: roll(1)),
        ("rollouts_workers2", lambda: roll(2)),
        ("rollouts_kinematic_filter", lambda: roll(1, filtered)),
    ]
    rows = []
    for case, fn in cases:
        fn()
        sec = _best_of(fn, repeats)
        rows.append({"case": case, "task": task, "M": M, "T": T, "steps": steps, "seconds": sec,
                     "steps_per_s": steps / sec})
    for row in rows:
        row["ratio_to_raw"] = row["steps_per_s"] / rows[0]["steps_per_s"]
        row["ratio_to_replay"] = row["steps_per_s"] / rows[1]["steps_per_s"]
    return rows


if __name__ == "__main__":
    for row in run():
        print(f"{row['case']:>22s}: {row['steps_per_s']:10.0f} steps/s  ({row['seconds']:.3f} s)  "
              f"ratio to raw {row['ratio_to_raw']:.2f}, to replay {row['ratio_to_replay']:.2f}")
