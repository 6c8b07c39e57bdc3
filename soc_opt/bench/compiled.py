"""The compiled kernels against the numpy path (``soc-opt bench --only compiled``; issue 51).

Rows, each timed interleaved (numpy path, compiled path, in turn, ``repeats`` rounds, medians), with the
largest absolute difference of the results (the two paths agree to rounding, not to the bit):

* ``core n=..``: the Gaussian core's smoother with covariances per sequence (:func:`soc_opt.lgssm.rts_smoother`)
  on the peers' instance (:func:`soc_opt.peers.smoothers.random_uncorrelated`: ``T = 100``, 20 sequences,
  a scalar observation), the like-for-like row of the dynamax comparison (``soc-opt bench --only peers``);
* ``kinematic ...``: the §11.2 smoother's passes on a peg batch (the extended filter's, a Gauss-Newton
  pass, a pass at a fixed linearisation; 20 rollouts at ``rho^2 = 0.1``), the kinematic filter's online
  update over a whole batch (:meth:`~soc_opt.noise.kinematic.filter.KinematicFilter.states`), and one
  call of the estimator (:func:`soc_opt.noise.kinematic.loop.learn`, both EM starts in turn);
* ``jit ...`` (``jit=True``): the one-off cost of compiling every kernel in a fresh process with an
  empty cache, and of loading them from the cache in the next process (``numba_ms``).

Times are CPU time of this thread (``time.thread_time``), less disturbed by other jobs on the machine
than wall time; ``ratio`` is numpy / compiled.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

__all__ = ["run", "QUICK"]

#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"sizes": (3,), "T": 10, "M": 2, "rollouts": 2, "repeats": 1, "jit": False}

_JIT_SCRIPT = """
import json, time, numpy as np
t0 = time.perf_counter()
from soc_opt import lgssm
from soc_opt.compiled import kinematic_kernels
from soc_opt.peers import smoothers as ps
rng = np.random.default_rng(0)
model, policy, mu0, P0 = ps.random_uncorrelated(rng, 3, 2, 5)
lg = ps.to_lgssm(model, policy)
params = lgssm.Params(lgssm.Initial(mu0, np.broadcast_to(P0, (2, 3, 3))), lgssm.Dynamics(lg.F, lg.b, lg.Q),
                      lgssm.Emissions(lg.H, lg.d, lg.R))
y = rng.standard_normal((2, 5, 1))
t1 = time.perf_counter()
lgssm.rts_smoother(params, y, kernels="numba")
lgssm.rts_smoother(params, y, linearize=lambda k, m: (np.broadcast_to(lg.H[k], (2, 1, 3)), np.broadcast_to(lg.d[k], (2, 1))),
                   kernels="numba")
kinematic_kernels.online_update(rng.standard_normal((2, 4)), rng.standard_normal((2, 4)), rng.standard_normal((2, 4, 3)),
                                np.eye(3), 0.1, np.empty((2, 3)))
print(json.dumps({"import_s": t1 - t0, "first_calls_s": time.perf_counter() - t1}))
"""


def _ab(fns: dict, repeats: int) -> dict:
    """Median CPU seconds of each callable, called in turn ``repeats`` times after one warm-up call each."""
    out = {k: f() for k, f in fns.items()}
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.thread_time()
            out[k] = f()
            times[k].append(time.thread_time() - t0)
    return {k: (float(np.median(v)), out[k]) for k, v in times.items()}


def _diff(a, b) -> float:
    if isinstance(a, (tuple, list)):
        return max(_diff(x, y) for x, y in zip(a, b))
    if a is None or not hasattr(a, "shape") or a.dtype.kind not in "fc":
        return 0.0
    return float(np.max(np.abs(a - b))) if a.size else 0.0


def _row(case: str, res: dict) -> dict:
    (tn, rn), (tc, rc) = res["numpy"], res["numba"]
    return {"case": case, "numpy_ms": 1e3 * tn, "numba_ms": 1e3 * tc, "ratio": tn / tc, "max_abs_diff": _diff(rn, rc)}


def _with_kernels(kernels: str, fn):
    def call():
        old = os.environ.get("SOC_OPT_KERNELS")
        os.environ["SOC_OPT_KERNELS"] = kernels
        try:
            return fn()
        finally:
            if old is None:
                del os.environ["SOC_OPT_KERNELS"]
            else:
                os.environ["SOC_OPT_KERNELS"] = old
    return call


def _jit_rows() -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "SOC_OPT_CACHE_DIR": cache}
        env.pop("NUMBA_CACHE_DIR", None)
        for case in ("jit: compile every kernel (empty cache)", "jit: load every kernel (cached)"):
            out = subprocess.run([sys.executable, "-c", _JIT_SCRIPT], env=env, capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append({"case": case, "numpy_ms": None, "numba_ms": 1e3 * r["first_calls_s"], "ratio": None,
                         "max_abs_diff": None})
    return rows


def run(sizes=(6, 14, 26), T: int = 100, M: int = 20, rollouts: int = 20, repeats: int = 7, jit: bool = True,
        seed: int = 0) -> list[dict]:
    from .. import compiled, lgssm
    from ..linalg import single_thread_blas
    from ..peers import smoothers as ps

    if not compiled.available():
        return [{"case": "numba not installed (pip install 'soc_opt[fast]')", "numpy_ms": None, "numba_ms": None,
                 "ratio": None, "max_abs_diff": None}]
    rng = np.random.default_rng(seed)
    rows = []
    with single_thread_blas():
        for n in sizes:
            model, policy, mu0, P0 = ps.random_uncorrelated(rng, n, 7 if n > 3 else 2, T)
            lg = ps.to_lgssm(model, policy)
            params = lgssm.Params(lgssm.Initial(mu0, np.broadcast_to(P0, (M,) + P0.shape)), lgssm.Dynamics(lg.F, lg.b, lg.Q),
                                  lgssm.Emissions(lg.H, lg.d, lg.R))
            Y = rng.standard_normal((M, T, 1))
            rows.append(_row(f"core n={n} (T={T}, {M} sequences, covariances per sequence)", _ab(
                {k: (lambda k=k: lgssm.rts_smoother(params, Y, kernels=k)) for k in ("numpy", "numba")}, repeats)))
        rows += _kinematic_rows(rollouts, repeats, seed)
    if jit:
        rows += _jit_rows()
    return rows


def _kinematic_rows(M: int, repeats: int, seed: int) -> list[dict]:
    from ..noise.kinematic import em, loop
    from ..noise.kinematic.config import KinematicConfig
    from ..noise.kinematic.filter import KinematicFilteredPolicy
    from ..noise.kinematic.model import KinematicModel
    from ..noise.kinematic.smoother import smooth
    from ..tasks import load_task

    task = load_task("peg")
    km = KinematicModel(task)
    cfg = KinematicConfig(parallel_starts=False)
    first = task.rollouts(task.initial_policy(1.0), M, np.random.default_rng(seed))
    _, filt, _ = loop.learn(task, first, task.initial_policy(1.0), cfg)
    sampler = KinematicFilteredPolicy(task.initial_policy(0.3), filt)
    ro = task.rollouts(sampler, M, np.random.default_rng(seed + 1))
    R = task.rho2 * np.eye(km.n)
    lg = em.z_model(km, filt.accel(), cfg)
    ekf = smooth(km, lg, ro.s, ro.a, R)
    kinds = ("numpy", "numba")
    rows = []
    for case, fn in (("kinematic smoother: extended filter pass", lambda: smooth(km, lg, ro.s, ro.a, R)),
                     ("kinematic smoother: Gauss-Newton pass", lambda: smooth(km, lg, ro.s, ro.a, R, ekf.mean)),
                     ("kinematic smoother: fixed linearisation", lambda: smooth(km, lg, ro.s, ro.a, R, ekf.z_lin, ekf.lin)),
                     ("kinematic filter: online update, whole batch", lambda: filt.states(ro.s, ro.a)),
                     ("kinematic estimator: loop.learn, two EM starts", lambda: loop.learn(task, ro, sampler, cfg)[0].s)):
        res = _ab({k: _with_kernels(k, fn) for k in kinds}, repeats)
        rows.append(_row(f"{case} (peg, {M} rollouts)", res))
    return rows


if __name__ == "__main__":
    for r in run():
        print(r)
