"""Minimal counterexamples to the claims that fail as written, found by a deterministic search and
written as certificate files (JSON) that ``soc-opt verify --replay FILE`` re-checks in exact
rational and interval arithmetic (:mod:`soc_opt.verification.replay`, which imports nothing of the
library; docs/verification.md "Counterexamples").

The search visits sizes ``(n, m, T)`` in increasing order of ``n + m + T`` (then ``n``, ``m``,
``T``) and, per size, ``seeds`` random instances (``Generator(PCG64([seed, n, m, T]))``); the
first instance on which the library's own code path (``estep.smooth``, ``mstep.surrogate``,
``mstep.maximize``, ``mstep.surrogate_grad_hess``) shows the failure is the certificate.  Each
certificate also records the numbers of the corrected statement on the same instance
(docs/math.md §5, §9).

Every datum is written exactly (:func:`exact_text`): the instance is the exact binary value of the
floats the search used, and every point the argument needs to be *exactly* a maximiser (the two
maximisers of the uniqueness counterexample, the M-step policies) is recomputed from that instance
in exact rationals (:func:`soc_opt.verification.replay.maximiser`), not taken from the float code.
"""

from __future__ import annotations

import json
import warnings
from fractions import Fraction
from pathlib import Path

import numpy as np
from flint import fmpq, fmpq_mat

from .. import estep, mstep
from ..models import LinearGaussianPolicy
from ..testing import (
    random_augmented_model,
    random_initial_state,
    random_policy,
    random_spd_spectrum,
    sample_model_trajectory,
)
from . import replay as rp
from .checks import em_inequality_gap, policy_F, with_F
from .table import json_safe

__all__ = ["exact_text", "exact_tree", "sizes", "search_uniqueness", "search_uniqueness_sigma", "search_ltv", "search_cost_decrease",
           "search_free_energy", "SEARCHES", "write_certificates"]


def sizes(max_total: int = 7, *, m_min: int = 1):
    """``(n, m, T)`` with ``n, T >= 1``, ``m >= m_min``, by increasing ``n + m + T``, then lexicographic."""
    out = [(n, m, T) for n in range(1, max_total) for m in range(m_min, max_total) for T in range(1, max_total)
           if n + m + T <= max_total]
    return sorted(out, key=lambda s: (sum(s), s))


def _rng(seed: int, n: int, m: int, T: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64([seed, n, m, T]))


FORMAT = "soc_opt certificate v2"
#: how a reader must take the numbers of ``data``
ARITHMETIC = ("every datum is an exact rational: 'p/q', or a decimal string read exactly; the replay decides in exact "
              "rational arithmetic, logarithms as interval balls (docs/verification.md)")


def exact_text(x) -> str:
    """The exact value of one number as text: the float's shortest decimal when that decimal *is* its
    binary value, else ``"p/q"``; an ``fmpq``, ``Fraction`` or int as ``"p/q"`` / ``"p"``."""
    if isinstance(x, (fmpq, Fraction)):
        return str(x)
    if isinstance(x, str):  # already exact text
        Fraction(x)
        return x
    if isinstance(x, (bool, np.bool_)):
        raise TypeError("a boolean is not a datum")
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"{x} is not finite")
    r = repr(x)
    fr = Fraction(x)
    return r if Fraction(r) == fr else f"{fr.numerator}/{fr.denominator}"


def exact_tree(obj):
    """:func:`exact_text` applied to every number of a nested dict / list / array / ``fmpq_mat``."""
    if isinstance(obj, dict):
        return {k: (v if k in ("n", "step", "d") else exact_tree(v)) for k, v in obj.items()}
    if isinstance(obj, fmpq_mat):
        return [[str(v) for v in row] for row in obj.tolist()]
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [exact_tree(v) for v in obj]
    return exact_text(obj)


def _model_dict(model) -> dict:
    return {"Ao": model.Ao, "co": model.co, "So": model.So, "n": model.n}


def _policy_dict(p: LinearGaussianPolicy) -> dict:
    return {"K": p.K, "k": p.k, "cov": p.cov}


def _cert(kind: str, claim: str, n: int, m: int, T: int, tried: list, data: dict, numbers: dict) -> dict:
    return {"format": FORMAT, "arithmetic": ARITHMETIC, "kind": kind, "claim": claim, "n": n, "m": m, "T": T,
            "search": {"order": "n+m+T ascending, then (n, m, T); seeds per size in order", "tried": tried},
            "data": exact_tree(data), "library_numbers": json_safe(numbers)}


def _exact_moments(data: dict, policy_key: str):
    """Exact per-step model and smoothed moments of ``data`` (exact text) under ``data[policy_key]``."""
    steps, _ = rp.exact_model(data["model"])
    mean, C, _ = rp.dense_smoother(data["model"], data[policy_key], data["y"], data["mu0"], data["P0"])
    return steps, [rp.moments(mean, C, data["y"], k) for k in range(len(steps))]


def _exact_mstep(data: dict, policy_key: str, cov) -> dict:
    """The surrogate M-step from ``data[policy_key]``'s smoothing, exactly: per step the minimum-norm
    maximiser of ``Lbar_k`` in ``[K_k k_k]`` (:func:`replay.maximiser`) and covariance ``cov[k]``."""
    steps, moms = _exact_moments(data, policy_key)
    Fs = [rp.maximiser(s, mom) for s, mom in zip(steps, moms)]
    n = Fs[0].ncols() - 1
    K = [[[str(F[i, j]) for j in range(n)] for i in range(F.nrows())] for F in Fs]
    k = [[str(F[i, n]) for i in range(F.nrows())] for F in Fs]
    return {"K": K, "k": k, "cov": exact_tree(cov)}


def _search(found, seeds: int, max_total: int, m_min: int = 1):
    tried = []
    for n, m, T in sizes(max_total, m_min=m_min):
        for seed in range(seeds):
            res = found(_rng(seed, n, m, T), n, m, T)
            if res is not None:
                tried.append({"n": n, "m": m, "T": T, "seeds": seed + 1})
                return n, m, T, tried, res
        tried.append({"n": n, "m": m, "T": T, "seeds": seeds})
    raise RuntimeError(f"no counterexample found up to n+m+T <= {max_total} with {seeds} seeds per size")


def _instance(rng, n, m, T, **kw):
    model = random_augmented_model(rng, n, m, T, **kw)
    policy = random_policy(rng, T, n, m)
    mu0, P0 = random_initial_state(rng, n)
    _, y = sample_model_trajectory(rng, model, random_policy(rng, T, n, m), mu0, P0)
    return model, policy, mu0, P0, y


# --------------------------------------------------------------------------- uniqueness


def _uniqueness_found(rng, n, m, T):
    """Proportional actuators (stacked [B; By] of rank m-1, nonzero columns) when m >= 2; for m = 1 a
    random nonzero B.  Two distinct [F_0 e_0] with zero library gradient and equal surrogate."""
    model, policy, mu0, P0, y = _instance(rng, n, m, T, b_rank=m - 1 if m >= 2 else None)
    sm = estep.smooth(model, policy, y, mu0, P0)
    mom = estep.moments(sm, y)
    try:  # the library's own maximiser: unique (fine) or not unique (raises)
        mstep.maximize(model, estep.moments(sm, y), constraints=mstep.MStepConstraints(cov_floor=0.1), min_norm=False)
        return None
    except mstep.NonUniqueMaximizerError:
        pass
    with warnings.catch_warnings():  # the non-uniqueness is the point here: no MinNormWarning
        warnings.simplefilter("ignore", mstep.MinNormWarning)
        first = mstep.maximize(model, estep.moments(sm, y), constraints=mstep.MStepConstraints(cov_floor=0.1), min_norm=True).policy
    gh = mstep.surrogate_grad_hess(model, mom, 0, first)
    w, V = np.linalg.eigh(gh.hess)
    v = V[:, -1]  # null direction of the Hessian
    F1 = policy_F(first)
    F2 = F1.copy()
    F2[0] = F1[0] + v.reshape(F1[0].shape, order="F")
    second = with_F(first, F2)
    g2 = mstep.surrogate_grad_hess(model, mom, 0, second).grad
    L1 = float(mstep.surrogate(model, sm, y, first)[0])
    L2 = float(mstep.surrogate(model, sm, y, second)[0])
    scale = max(1.0, abs(L1))
    if np.abs(gh.grad).max() > 1e-8 * scale or np.abs(g2).max() > 1e-8 * scale or abs(L1 - L2) > 1e-9 * scale:
        return None
    # the certificate's points, exactly: the minimum-norm maximiser and a move along the exact null vector of B
    data = exact_tree({"model": _model_dict(model), "mu0": mu0, "P0": P0, "y": y, "policy": _policy_dict(policy),
                       "step": 0})
    steps, moms = _exact_moments(data, "policy")
    v = rp.null_vector(steps[0][1])
    if v is None:  # the float code saw a singular H that is not singular exactly
        return None
    G1 = rp.maximiser(steps[0], moms[0])
    data.update({"F1": exact_tree(G1), "F2": exact_tree(G1 + v * fmpq_mat([[1] * (n + 1)])),
                 "Sigma": [["0.1" if i == j else "0" for j in range(m)] for i in range(m)]})
    numbers = {"grad_at_F1": gh.grad, "grad_at_F2": g2, "Lbar_at_F1": L1, "Lbar_at_F2": L2,
               "hessian_eigenvalues": w, "H_eigenvalues": np.linalg.eigvalsh(
                   model.Bs[0].T @ np.linalg.solve(model.So[0], model.Bs[0])),
               "P_eigenvalues": np.linalg.eigvalsh(sm.cov[0])}
    return data, numbers


def search_uniqueness(seeds: int = 3, max_total: int = 6) -> dict:
    n, m, T, tried, (data, numbers) = _search(_uniqueness_found, seeds, max_total)
    return _cert("uniqueness_gain", "uniqueness", n, m, T, tried, data, numbers)


def _sigma_found(rng, n, m, T):
    model, policy, mu0, P0, y = _instance(rng, n, m, T)
    sm = estep.smooth(model, policy, y, mu0, P0)
    floor = random_spd_spectrum(rng, m, 0.05, 0.3)
    new = mstep.maximize(model, estep.moments(sm, y), constraints=mstep.MStepConstraints(cov_floor=floor.tolist()), min_norm=False).policy
    ts = [0.0, 0.25, 0.5, 1.0, 2.0, 4.0]
    vals = []
    for t in ts:
        cov = np.broadcast_to(t * floor, (T, m, m)).copy()
        p = LinearGaussianPolicy(new.K, new.k, cov, allow_singular=True)
        vals.append(float(mstep.surrogate(model, sm, y, p)[0]))
    if not np.all(np.diff(vals) < 0):
        return None
    data = exact_tree({"model": _model_dict(model), "mu0": mu0, "P0": P0, "y": y, "policy": _policy_dict(policy),
                       "step": 0, "Sigma_min": floor})
    F = _exact_mstep(data, "policy", [floor])  # the exact maximiser in [K k], written as one matrix [K k]
    data["F"] = [row_K + [row_k] for row_K, row_k in zip(F["K"][0], F["k"][0])]
    data["t"] = ["0", "0.25", "0.5", "1", "2", "4"]
    numbers = {"Lbar_at_t_Sigma_min": vals, "maximiser_Sigma": new.cov[0],
               "grad_Sigma": mstep.surrogate_grad_hess(model, estep.moments(sm, y), 0, new).grad_sigma}
    return data, numbers


def search_uniqueness_sigma(seeds: int = 3, max_total: int = 6) -> dict:
    n, m, T, tried, (data, numbers) = _search(_sigma_found, seeds, max_total)
    return _cert("uniqueness_sigma", "uniqueness_sigma", n, m, T, tried, data, numbers)


# --------------------------------------------------------------------------- Lemma LTV


def _ltv_found(rng, n, m, T):
    model, policy, mu0, P0, y = _instance(rng, n, m, T)
    sm = estep.smooth(model, policy, y, mu0, P0)
    new = mstep.maximize(model, estep.moments(sm, y), constraints=mstep.MStepConstraints(cov_floor=0.05), min_norm=False).policy
    g = em_inequality_gap(model, y, mu0, P0, policy, sm, new)
    if not (g["dL"] > 0 and g["dlogp"] < g["dL"] - 1e-6 * max(1.0, abs(g["logp_old"]))):
        return None
    data = exact_tree({"model": _model_dict(model), "mu0": mu0, "P0": P0, "y": y, "old": _policy_dict(policy)})
    floor = [["0.05" if i == j else "0" for j in range(m)] for i in range(m)]
    data["cov_floor"] = floor
    data["new"] = _exact_mstep(data, "old", [floor] * T)  # the M-step, exactly (floor 0.05 = 1/20)
    return data, g


def search_ltv(seeds: int = 5, max_total: int = 6) -> dict:
    n, m, T, tried, (data, numbers) = _search(_ltv_found, seeds, max_total)
    return _cert("ltv", "ltv", n, m, T, tried, data, numbers)


# --------------------------------------------------------------------------- Theorem IV.1


def _cost_found(rng, n, m, T):
    """Claim 3's pipeline at a fixed size: a stable linear system, rollouts, y = exp(-cost), a per-step
    least-squares augmented model, Y sampled from it, Sigma held at Sigma^i."""
    from .claims_em import expected_stage_costs, ls_augmented

    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    sys_ = {"A": 0.95 * Qo, "B": rng.standard_normal((n, m)) / np.sqrt(n), "c": 0.1 * rng.standard_normal(n),
            "W": random_spd_spectrum(rng, n, 0.01, 0.05), "Qs": random_spd_spectrum(rng, n, 0.05, 0.3) / n,
            "Qa": random_spd_spectrum(rng, m, 0.05, 0.3), "s_star": rng.standard_normal(n), "a_star": np.zeros(m),
            "mu0": 0.5 * rng.standard_normal(n), "P0": random_spd_spectrum(rng, n, 0.02, 0.1)}
    phi = random_policy(rng, T, n, m)
    phi = phi.with_cov(np.broadcast_to(random_spd_spectrum(rng, m, 0.2, 1.0), (T, m, m)).copy())
    M = 40
    s = np.zeros((M, T + 1, n))
    a = np.zeros((M, T, m))
    s[:, 0] = sys_["mu0"] + rng.standard_normal((M, n)) @ np.linalg.cholesky(sys_["P0"]).T
    for k in range(T):
        a[:, k] = phi.sample_action(k, s[:, k], rng)
        s[:, k + 1] = (s[:, k] @ sys_["A"].T + a[:, k] @ sys_["B"].T + sys_["c"]
                       + rng.standard_normal((M, n)) @ np.linalg.cholesky(sys_["W"]).T)
    ds = s[:, :T] - sys_["s_star"]
    cost = np.einsum("mti,ij,mtj->mt", ds, sys_["Qs"], ds) + np.einsum("mti,ij,mtj->mt", a, sys_["Qa"], a)
    model = ls_augmented(s, a, np.exp(-cost))
    _, Y = sample_model_trajectory(rng, model, phi, sys_["mu0"], sys_["P0"])
    sm = estep.smooth(model, phi, Y, sys_["mu0"], sys_["P0"])
    new = mstep.maximize(model, estep.moments(sm, Y), constraints=mstep.MStepConstraints(cov_floor=phi.cov[0].tolist()),
                         min_norm=False).policy
    g = em_inequality_gap(model, Y, sys_["mu0"], sys_["P0"], phi, sm, new)
    V = [float(expected_stage_costs(sm, p, sys_["Qs"], sys_["s_star"], sys_["Qa"], sys_["a_star"]).sum())
         for p in (phi, new)]
    if not (g["dL"] > 0 and g["dQ"] > 0 and V[1] > V[0] * (1 + 1e-6)):
        return None
    ex = mstep.maximize(model, estep.moments(sm, Y), constraints=mstep.MStepConstraints(cov_floor=1e-3), objective="exact",
                        previous=phi, config=mstep.MStepConfig(exact_max_iter=50), min_norm=False).policy
    lp_ex = float(estep.smooth(model, ex, Y, sys_["mu0"], sys_["P0"]).loglik)
    # the model's prior-predictive mean of y_0 under phi^i (an observed y below it pushes the update)
    mean_s = sys_["mu0"]
    ymean0 = float(model.Ao[0, n] @ np.concatenate([mean_s, phi.K[0] @ mean_s + phi.k[0]]) + model.co[0, n])
    data = exact_tree({"model": _model_dict(model), "mu0": sys_["mu0"], "P0": sys_["P0"], "y": Y,
                       "old": _policy_dict(phi), "exact_em": _policy_dict(ex),
                       "cost": {k: sys_[k] for k in ("Qs", "s_star", "Qa", "a_star")}, "true_system": sys_})
    data["new"] = _exact_mstep(data, "old", data["old"]["cov"])  # the surrogate M-step with Sigma held, exactly
    numbers = {**g, "EV_old": V[0], "EV_new": V[1], "logp_exact_em": lp_ex, "y0_prior_mean": ymean0}
    return data, numbers


def search_cost_decrease(seeds: int = 20, max_total: int = 6) -> dict:
    n, m, T, tried, (data, numbers) = _search(_cost_found, seeds, max_total)
    return _cert("cost_decrease", "cost_decrease", n, m, T, tried, data, numbers)


# --------------------------------------------------------------------------- free energy


def search_free_energy() -> dict:
    """Dimension ``d = 1, 2, ..`` and a small grid of ``(rho, a)`` with ``P = N(0, I)``, ``J = a/2 |x|^2``:
    the first ``rho < 0`` for which a shifted ``Q_t = N(t 1, I)`` beats the tilted ``Q*`` (the stated
    sup), with ``F(Q_t)`` over growing ``t``."""
    from .free_energy import duality_objective, log_partition, tilted_gaussian

    tried = []
    for d in (1, 2):
        for rho in (-1.0, -0.5, -2.0):
            for a in (1.0, 0.5, 2.0):
                mu, S, A, b, c = np.zeros(d), np.eye(d), a * np.eye(d), np.zeros(d), 0.0
                lhs = log_partition(mu, S, A, b, c, rho) / rho
                mq, Cq = tilted_gaussian(mu, S, A, b, c, rho)
                ts = [0.0, 1.0, 2.0, 4.0, 8.0, 16.0]
                F = [duality_objective(t * np.ones(d), S, mu, S, A, b, c, rho) for t in ts]
                tried.append({"d": d, "rho": rho, "a": a})
                if max(F) > duality_objective(mq, Cq, mu, S, A, b, c, rho) + 1e-9:
                    # the tilted Q* exactly: covariance (S^-1 - rho A)^-1, mean Cq (S^-1 mu + rho b)
                    Si_x, rho_x = rp.mat(exact_tree(S)).inv(), rp.num(exact_text(rho))
                    Cq_x = (Si_x - rp.mat(exact_tree(A)) * rho_x).inv()
                    mq_x = Cq_x * (Si_x * rp.col(exact_tree(mu)) + rp.col(exact_tree(b)) * rho_x)
                    data = exact_tree({"d": d, "rho": rho, "mu": mu, "S": S, "A": A, "b": b, "c": c, "t": ts})
                    data["Qstar"] = {"mean": [str(mq_x[i, 0]) for i in range(d)], "cov": exact_tree(Cq_x)}
                    numbers = {"lhs": lhs, "F_at_Qstar": duality_objective(mq, Cq, mu, S, A, b, c, rho),
                               "Qstar_mean": mq, "Qstar_cov": Cq, "F_at_Q_t": F}
                    return {"format": FORMAT, "arithmetic": ARITHMETIC, "kind": "free_energy", "claim": "free_energy",
                            "n": d, "m": 0, "T": 0,
                            "search": {"order": "d, then rho in (-1, -0.5, -2), a in (1, 0.5, 2)", "tried": tried},
                            "data": data, "library_numbers": json_safe(numbers)}
    raise RuntimeError("no free-energy counterexample found")


SEARCHES = {
    "uniqueness_n1_m2_T1.json": search_uniqueness,
    "uniqueness_sigma_n1_m1_T1.json": search_uniqueness_sigma,
    "ltv_n1_m1_T1.json": search_ltv,
    "cost_decrease_n1_m1_T1.json": search_cost_decrease,
    "free_energy_rho_neg_d1.json": search_free_energy,
}


def write_certificates(out_dir: str | Path) -> list[Path]:
    """Run every search and write its certificate as ``out_dir/<kind>_n{n}_m{m}_T{T}.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for fname, fn in SEARCHES.items():
        cert = fn()
        if cert["kind"] == "free_energy":
            name = f"free_energy_rho_neg_d{cert['n']}.json"
        else:
            stem = fname.rsplit("_n", 1)[0]
            name = f"{stem}_n{cert['n']}_m{cert['m']}_T{cert['T']}.json"
        p = out / name
        p.write_text(json.dumps(cert, indent=1) + "\n")
        paths.append(p)
    return paths
