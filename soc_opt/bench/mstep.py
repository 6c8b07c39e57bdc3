"""M-step solver comparison: closed form vs CVXPY/Clarabel vs CVXPY/SCS (docs/math.md §5).

For each size ``(n, m)`` a random well-posed instance is built (augmented model with PD ``So``;
smoothed moments from a random joint Gaussian over ``(s_0..s_T)``) and the time-varying
surrogate M-step is solved under each constraint set that has a closed form.  Per method the
row reports the median wall time per time step, the gap of the maximised objective to the
closed form and the largest parameter differences.  ``run`` returns rows and prints nothing.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from ..mstep import MStepConstraints, maximize
from ..testing import random_mstep_instance as random_instance

__all__ = ["QUICK", "random_instance", "run"]


def _constraint_sets(m: int) -> dict[str, MStepConstraints]:
    return {
        "cov_floor": MStepConstraints(cov_floor=0.1),
        "entropy_floor": MStepConstraints(entropy_floor=-0.5 * m),
    }


def run(sizes=((6, 2), (26, 7)), T: int = 20, seed: int = 0, repeats: int = 5) -> list[dict]:
    """Closed form vs CVXPY/Clarabel vs CVXPY/SCS on random instances.

    One row per ``(n, m, constraint set, method)`` with keys: ``n, m, T, constraints, method``,
    ``time_per_step_s`` (median; closed form: batched call over ``T`` divided by ``T``, median of
    ``repeats``; CVXPY: median of the per-step solve times after a warm-up call that builds the
    cached DPP problem), ``first_call_s`` (the warm-up call, including problem construction),
    ``objective_gap`` (max over steps of ``|Lbar_k - Lbar_k^cf| / |Lbar_k^cf|``),
    ``max_gain_diff`` (max abs difference of ``[K k]``) and ``max_cov_diff`` (of ``Sigma``).
    """
    rows: list[dict] = []
    rng = np.random.default_rng(seed)
    for n, m in sizes:
        model, mom = random_instance(n, m, T, rng)
        for cname, cons in _constraint_sets(m).items():
            ref = maximize(model, mom, constraints=cons, min_norm=False)
            t_cf = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                maximize(model, mom, constraints=cons, min_norm=False)
                t_cf.append((time.perf_counter() - t0) / T)
            base = dict(n=n, m=m, T=T, constraints=cname)
            rows.append(dict(base, method="closed_form", time_per_step_s=statistics.median(t_cf),
                             first_call_s=None, objective_gap=0.0, max_gain_diff=0.0, max_cov_diff=0.0))
            Fref = np.concatenate([ref.policy.K, ref.policy.k[..., None]], axis=-1)
            for solver in ("CLARABEL", "SCS"):
                t0 = time.perf_counter()
                maximize(model, mom, constraints=cons, method="cvxpy", solver=solver, min_norm=False)
                first = time.perf_counter() - t0
                res = maximize(model, mom, constraints=cons, method="cvxpy", solver=solver, min_norm=False)
                F = np.concatenate([res.policy.K, res.policy.k[..., None]], axis=-1)
                rows.append(dict(
                    base,
                    method=f"cvxpy/{solver}",
                    time_per_step_s=float(np.median(res.solve_time)),
                    first_call_s=first,
                    objective_gap=float(np.max(np.abs(res.objective - ref.objective) / np.abs(ref.objective))),
                    max_gain_diff=float(np.abs(F - Fref).max()),
                    max_cov_diff=float(np.abs(res.policy.cov - ref.policy.cov).max()),
                ))
    return rows


#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"sizes": ((3, 1),), "T": 3, "repeats": 1}


if __name__ == "__main__":
    cols = ["n", "m", "T", "constraints", "method", "time_per_step_s", "first_call_s", "objective_gap",
            "max_gain_diff", "max_cov_diff"]
    print(" | ".join(cols))
    for row in run():
        print(" | ".join(f"{row[c]:.3g}" if isinstance(row[c], float) else str(row[c]) for c in cols))
