"""M-step solver comparison: closed form vs CVXPY/Clarabel vs CVXPY/SCS (SPEC §5).

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

from ..estep import moments
from ..models import AugmentedModel, Smoothed
from ..mstep import MStepConstraints, maximize_moments

__all__ = ["QUICK", "random_instance", "run"]


def _spd(rng: np.random.Generator, d: int, floor: float) -> np.ndarray:
    R = rng.normal(size=(d, d)) / np.sqrt(d)
    return R @ R.T + floor * np.eye(d)


def random_instance(n: int, m: int, T: int, rng: np.random.Generator):
    """A random augmented model and the moments of a random smoothing distribution.

    Returns ``(model, Moments)``.  The model has ``||A_k||_2 = 0.9`` and PD ``So_k``; the smoothed
    states are the blocks of a random PD covariance over ``(s_0..s_T)`` with random means, and
    ``y_k`` is uniform in ``(0.05, 1)``.
    """
    A = rng.normal(size=(T, n + 1, n))
    A *= 0.9 / np.linalg.norm(A[:, :n], 2, axis=(1, 2))[:, None, None]
    B = rng.normal(size=(T, n + 1, m)) / np.sqrt(n)
    Ao = np.concatenate([A, B], axis=2)
    co = rng.normal(size=(T, n + 1))
    So = np.stack([_spd(rng, n + 1, 0.1) for _ in range(T)])
    model = AugmentedModel(Ao, co, So, n)
    L = rng.normal(size=((T + 1) * n, (T + 1) * n)) / np.sqrt((T + 1) * n) + 0.3 * np.eye((T + 1) * n)
    C = (L @ L.T).reshape(T + 1, n, T + 1, n)
    cov = np.stack([C[t, :, t, :] for t in range(T + 1)])
    cross = np.stack([C[t + 1, :, t, :] for t in range(T)])
    sm = Smoothed(rng.normal(size=(T + 1, n)), cov, cross, 0.0)
    y = rng.uniform(0.05, 1.0, size=T)
    return model, moments(sm, y)


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
            ref = maximize_moments(model, mom, cons, return_result=True)
            t_cf = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                maximize_moments(model, mom, cons)
                t_cf.append((time.perf_counter() - t0) / T)
            base = dict(n=n, m=m, T=T, constraints=cname)
            rows.append(dict(base, method="closed_form", time_per_step_s=statistics.median(t_cf),
                             first_call_s=None, objective_gap=0.0, max_gain_diff=0.0, max_cov_diff=0.0))
            Fref = np.concatenate([ref.policy.K, ref.policy.k[..., None]], axis=-1)
            for solver in ("CLARABEL", "SCS"):
                t0 = time.perf_counter()
                maximize_moments(model, mom, cons, method="cvxpy", solver=solver)
                first = time.perf_counter() - t0
                res = maximize_moments(model, mom, cons, method="cvxpy", solver=solver, return_result=True)
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
