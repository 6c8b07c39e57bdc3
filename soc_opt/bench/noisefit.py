"""Bias of the dynamics fit under measurement noise: naive / corrected / SSM-EM (docs/math.md §10.1).

``run()`` simulates a known time-varying linear system with noisy measurements
(``rho^2 = 0.1``) under a feedback policy, fits ``A, B`` with the three estimators of
:mod:`soc_opt.noise.noisefit` for growing ``M``, and reports per method and ``M`` (over ``reps``
independent data sets):

* ``bias_A``, ``bias_B``: ``mean_k ||mean_r Ahat_r[k] - A[k]||_F / ||A[k]||_F`` (the same for ``B``);
* ``med_err_A``, ``med_err_B``: median over data sets of ``mean_k ||Ahat[k] - A[k]||_F / ||A[k]||_F``.

The naive estimator's population limit (``M -> inf``) is exact: ``naive_limit_A``, ``naive_limit_B``
(from the closed-loop moments, ``population_naive``).  Pure functions (seeded); printing only
under ``__main__``.  ``run()`` takes about 3 CPU minutes (SSM-EM dominates); the table is in
``docs/noise.md``.
"""

from __future__ import annotations

import numpy as np

from ..models import LinearGaussianDynamics, LinearGaussianPolicy
from ..noise.estimator import FilteredPolicy, kalman_filter, measurement_noise
from ..noise.lqg_reference import simulate as simulate_filtered
from ..noise.noisefit import NoiseFitConfig, corrected_fit, naive_fit, noise_action_cov, ssm_em

__all__ = ["QUICK", "problem", "simulate", "relative_errors", "population_naive", "bias_table", "format_table", "run"]


def problem(seed: int = 0, n: int = 2, m: int = 1, T: int = 8, rho2: float = 0.1, filtered: bool = False) -> dict:
    """A known LTV system, measurement noise and a feedback sampling policy.

    ``A_k`` = a rotation by 0.3 rad scaled to 0.95 plus a smooth time variation; ``B_k`` random
    with a smooth variation; ``W_k = 0.02 I``; ``x_0 ~ N(mu0, 0.5 I)``; policy
    ``a_k = K_k (s_k or xhat_k) + k_k + N(0, 0.5 I)`` with ``K_k = -0.5 B_k^T`` (stabilising
    feedback).  ``filtered = True``: the policy acts on the Kalman estimate of the true model.
    Returns ``dict(dynamics, R, mu0, P0, policy, filter)`` (``filter`` None unless filtered).
    """
    rng = np.random.default_rng(seed)
    th = 0.3
    rot = 0.95 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    A0 = rot if n == 2 else 0.95 * np.linalg.qr(rng.standard_normal((n, n)))[0]
    E = rng.standard_normal((n, n)) / np.sqrt(n)
    B0 = rng.standard_normal((n, m))
    F = rng.standard_normal((n, m))
    ph = 2 * np.pi * np.arange(T) / T
    A = A0[None] + 0.1 * np.sin(ph)[:, None, None] * E[None]
    B = B0[None] + 0.2 * np.cos(ph)[:, None, None] * F[None]
    c = 0.2 * rng.standard_normal((T, n))
    W = np.broadcast_to(0.02 * np.eye(n), (T, n, n)).copy()
    dyn = LinearGaussianDynamics(A, B, c, W)
    K = -0.5 * np.swapaxes(B, 1, 2)
    k = 0.3 * rng.standard_normal((T, m))
    policy = LinearGaussianPolicy(K, k, np.broadcast_to(0.5 * np.eye(m), (T, m, m)).copy())
    R = measurement_noise(rho2, n)
    mu0, P0 = rng.standard_normal(n), 0.5 * np.eye(n)
    kf = kalman_filter(dyn, R, mu0, P0) if filtered else None
    return {"dynamics": dyn, "R": R, "mu0": mu0, "P0": P0, "policy": policy, "filter": kf}


def simulate(prob: dict, M: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x (M,T+1,n), s (M,T+1,n), a (M,T,m))`` sampled from ``prob`` (policy on ``s`` or on ``xhat``)."""
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    if prob["filter"] is not None:
        out = simulate_filtered(dyn, R, FilteredPolicy(pol, prob["filter"]), prob["mu0"], prob["P0"], M, rng)
        return out.x, out.s, out.a
    T, n = dyn.T, dyn.n
    sr = np.sqrt(np.diag(R))
    Lw = np.linalg.cholesky(dyn.cov)
    L0 = np.linalg.cholesky(prob["P0"])
    x = np.empty((M, T + 1, n))
    s = np.empty_like(x)
    a = np.empty((M, T, pol.m))
    x[:, 0] = prob["mu0"] + rng.standard_normal((M, n)) @ L0.T
    for t in range(T):
        s[:, t] = x[:, t] + rng.standard_normal((M, n)) * sr
        a[:, t] = pol.sample_action(t, s[:, t], rng)
        x[:, t + 1] = x[:, t] @ dyn.A[t].T + a[:, t] @ dyn.B[t].T + dyn.c[t] + rng.standard_normal((M, n)) @ Lw[t].T
    s[:, T] = x[:, T] + rng.standard_normal((M, n)) * sr
    return x, s, a


def relative_errors(est: np.ndarray, true: np.ndarray) -> float:
    """``mean_k ||est[k] - true[k]||_F / ||true[k]||_F``."""
    return float(np.mean(np.linalg.norm(est - true, axis=(1, 2)) / np.linalg.norm(true, axis=(1, 2))))


def population_naive(prob: dict) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``M -> inf`` limit of the naive regression: ``Cov(s', z) Cov(z)^{-1}`` (sampler on ``s``).

    Closed-loop moments of ``(x_k, s_k, a_k)`` propagated exactly (``x_{k+1} = (A + B K) x + B K eps + ...``).
    """
    if prob["filter"] is not None:
        raise ValueError("population_naive is implemented for a sampler acting on s")
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    T, n = dyn.T, dyn.n
    A_lim, B_lim = np.empty_like(dyn.A), np.empty_like(dyn.B)
    Px = prob["P0"].copy()
    for t in range(T):
        K, S = pol.K[t], pol.cov[t]
        Css = Px + R
        Csa = Css @ K.T
        Caa = K @ Css @ K.T + S
        Czz = np.block([[Css, Csa], [Csa.T, Caa]])
        Cxz = np.hstack([Px, Px @ K.T])  # Cov(x_k, z_k)
        Caz = np.hstack([Csa.T, Caa])  # Cov(a_k, z_k)
        Cnext = dyn.A[t] @ Cxz + dyn.B[t] @ Caz  # Cov(s_{k+1}, z_k)
        coef = np.linalg.solve(Czz, Cnext.T).T
        A_lim[t], B_lim[t] = coef[:, :n], coef[:, n:]
        Acl = dyn.A[t] + dyn.B[t] @ K
        BK = dyn.B[t] @ K
        Px = Acl @ Px @ Acl.T + BK @ R @ BK.T + dyn.B[t] @ S @ dyn.B[t].T + dyn.cov[t]
    return A_lim, B_lim


def bias_table(Ms=(100, 1000, 10000), reps: int = 20, seed: int = 0, filtered: bool = False,
               config: NoiseFitConfig = NoiseFitConfig()) -> list[dict]:
    """Rows ``{M, method, bias_A, bias_B, med_err_A, med_err_B, em_iters}`` for naive / corrected / ssm_em."""
    prob = problem(seed, filtered=filtered)
    dyn, R, pol = prob["dynamics"], prob["R"], prob["policy"]
    X = noise_action_cov(R, pol.K, None if prob["filter"] is None else prob["filter"].G)
    rows = []
    for M in Ms:
        rng = np.random.default_rng([seed, M])
        est = {"naive": [], "corrected": [], "ssm_em": []}
        iters = []
        for _ in range(reps):
            _, s, a = simulate(prob, M, rng)
            est["naive"].append(naive_fit(s, a, config))
            cf = corrected_fit(s, a, R, X, config)
            est["corrected"].append(cf)
            fit = ssm_em(s, a, R, config, init=cf)
            est["ssm_em"].append(fit.dynamics)
            iters.append(fit.n_iter)
        for method, fits in est.items():
            As = np.stack([f.A for f in fits])
            Bs = np.stack([f.B for f in fits])
            rows.append({
                "M": int(M),
                "method": method,
                "bias_A": relative_errors(As.mean(0), dyn.A),
                "bias_B": relative_errors(Bs.mean(0), dyn.B),
                "med_err_A": float(np.median([relative_errors(x, dyn.A) for x in As])),
                "med_err_B": float(np.median([relative_errors(x, dyn.B) for x in Bs])),
                "em_iters": float(np.mean(iters)) if method == "ssm_em" else None,
                "reps": reps,
                "sampler": "filtered" if filtered else "on s",
            })
    if not filtered:
        A_lim, B_lim = population_naive(prob)
        for r in rows:
            r["naive_limit_A"] = relative_errors(A_lim, dyn.A)
            r["naive_limit_B"] = relative_errors(B_lim, dyn.B)
    return rows


def format_table(rows: list[dict]) -> str:
    head = f"{'sampler':>9} {'M':>7} {'method':>10} {'bias_A':>8} {'bias_B':>8} {'med_err_A':>10} {'med_err_B':>10} {'em_iters':>8}"
    lines = [head]
    for r in rows:
        it = "" if r["em_iters"] is None else f"{r['em_iters']:.0f}"
        lines.append(f"{r['sampler']:>9} {r['M']:>7} {r['method']:>10} {r['bias_A']:8.4f} {r['bias_B']:8.4f} "
                     f"{r['med_err_A']:10.4f} {r['med_err_B']:10.4f} {it:>8}")
    return "\n".join(lines)


def run(Ms=(100, 1000, 10000), reps: int = 10, seed: int = 0, config: NoiseFitConfig = NoiseFitConfig()) -> list[dict]:
    """The bias table for a sampler acting on ``s`` and for one acting on the Kalman estimate."""
    return (bias_table(Ms, reps, seed, filtered=False, config=config)
            + bias_table(Ms, reps, seed, filtered=True, config=config))


#: ``soc-opt bench --quick``: tiny sizes that run every code path in seconds.
QUICK = {"Ms": (20,), "reps": 2, "config": NoiseFitConfig(em_max_iter=20)}


if __name__ == "__main__":  # pragma: no cover
    rows = run()
    print(format_table(rows))
    if "naive_limit_A" in rows[0]:
        print(f"naive population limit (M -> inf): A {rows[0]['naive_limit_A']:.4f}, B {rows[0]['naive_limit_B']:.4f}")
