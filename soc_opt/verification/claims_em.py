"""Claims 2 and 3 (docs/math.md §5, §9): EM monotonicity in ``log p(Y)`` and surrogate increase => cost decrease.

Claim 2 (EM lemma, docs/math.md §5 "exact-EM option"): exact EM never decreases ``log p(Y)``.
Claim 3 (Theorem IV.1 of the earlier paper): an M-step that increases the surrogate
``L = sum_k Lbar_k`` does not increase the expected cost ``E[V|Y]``.
"""

from __future__ import annotations

import numpy as np

from ..estep import moments, smooth
from ..models import AugmentedModel, LinearGaussianPolicy, Smoothed, symmetrize
from ..testing import (
    random_augmented_model,
    random_initial_state,
    random_policy,
    random_spd_spectrum,
    sample_model_trajectory,
)
from .common import ClaimResult, child_rng, mstep_module, tolist
from .hypotheses import require_standing_hypotheses

__all__ = ["claim2_em_monotone", "claim3_cost_decrease", "expected_stage_costs"]


# ---------------------------------------------------------------------------
# Claim 2: exact EM never decreases log p(Y)
# ---------------------------------------------------------------------------

_CLAIM2_VARIANTS = (("exact", "exact", 1e-3), ("surrogate", "surrogate", 0.1))


def _em_run(model, policy, Y, mu0, P0, *, objective: str, constraints, iterations: int, inner: int):
    """``iterations`` EM steps; returns the list of ``log p(Y)`` (summed over sequences) and the policies.

    ``inner`` caps the exact M-step's inner (action-latent) EM iterations.
    """
    ms = mstep_module()
    config = ms.MStepConfig(exact_max_iter=inner) if objective == "exact" else None
    lls, pols = [], [policy]
    sm = smooth(model, policy, Y, mu0, P0)
    lls.append(float(np.sum(sm.loglik)))
    for _ in range(iterations):
        policy = ms.maximize(
            model, moments(sm, Y), constraints=constraints, method="closed_form", variant="time_varying",
            objective=objective, previous=policy, config=config, min_norm=False,
        ).policy
        sm = smooth(model, policy, Y, mu0, P0)
        lls.append(float(np.sum(sm.loglik)))
        pols.append(policy)
    return lls, pols


def _cov_floor_constraints(floor):
    """``MStepConstraints(cov_floor=...)``: a scalar (``v I``) or one ``m x m`` matrix for all steps."""
    ms = mstep_module()
    if np.isscalar(floor):
        return ms.MStepConstraints(cov_floor=float(floor))
    return ms.MStepConstraints(cov_floor=symmetrize(np.asarray(floor, dtype=float)).tolist())


def claim2_em_monotone(
    seed: int = 0,
    instances: int = 20,
    *,
    iterations: int = 20,
    sequences: int = 3,
    inner: int = 50,
    rel_tol: float = 1e-9,
) -> list[ClaimResult]:
    """Claim 2 (EM lemma): exact EM never decreases ``log p(Y)``.

    Instances: ``n`` in 1..3, ``m`` in 1..2, ``T`` in 3..6; a random augmented model (full
    ``So_k``); ``sequences`` observation sequences ``Y`` drawn from the model under a random
    *generating* policy; EM starts from a different random policy.  Each iteration: E-step
    ``estep.smooth``, M-step ``mstep.maximize(..., objective="exact")`` with a covariance floor
    ``1e-3 I`` (feasible for every iterate) and at most ``inner`` inner iterations
    (``MStepConfig.exact_max_iter``; each inner step is itself an EM step in the action and does
    not decrease the exact objective, so the capped M-step is a generalized-EM step and the
    lemma still applies).  Row 2b repeats this with the paper's surrogate
    M-step and a covariance floor ``0.1 I`` (an informative row: the surrogate is a Jensen lower
    bound of the exact objective, so monotonicity is not guaranteed).
    """
    rng = child_rng(seed, 2)
    ms = mstep_module()
    if ms is None or not hasattr(ms, "maximize"):
        return [ClaimResult("2a exact EM monotone in log p(Y)", "mstep.maximize not available", 0, 0,
                            float("nan"), "", None, "soc_opt.mstep missing: check skipped")]
    results = {label: {"worst": np.inf, "held": 0, "ce": None, "gain": [], "errors": 0}
               for label, _, _ in _CLAIM2_VARIANTS}
    for _ in range(instances):
        n = int(rng.integers(1, 4))
        m = int(rng.integers(1, 3))
        T = int(rng.integers(3, 7))
        model = random_augmented_model(rng, n, m, T)
        gen = random_policy(rng, T, n, m)
        mu0, P0 = random_initial_state(rng, n)
        require_standing_hypotheses(model, mu0, P0)
        Y = np.stack([sample_model_trajectory(rng, model, gen, mu0, P0)[1] for _ in range(sequences)])
        start = random_policy(rng, T, n, m)
        for label, objective, floor in _CLAIM2_VARIANTS:
            _claim2_accumulate(results[label], model, start, Y, mu0, P0, objective=objective, floor=floor,
                               iterations=iterations, inner=inner, rel_tol=rel_tol)
    return _claim2_rows(results, instances, iterations=iterations, sequences=sequences, inner=inner,
                        rel_tol=rel_tol)


def _claim2_accumulate(r: dict, model, start, Y, mu0, P0, *, objective: str, floor, iterations: int, inner: int,
                       rel_tol: float) -> None:
    """Run EM on one instance and fold the outcome into the accumulator ``r`` (in place)."""
    n, m, T = model.n, model.m, model.T
    cons = _cov_floor_constraints(floor)
    try:
        lls, pols = _em_run(model, start, Y, mu0, P0, objective=objective, constraints=cons,
                            iterations=iterations, inner=inner)
    except Exception as exc:  # an M-step failure is reported as a failed instance
        r["errors"] += 1
        if r["ce"] is None:
            r["ce"] = {"n": n, "m": m, "T": T, "error": f"{type(exc).__name__}: {exc}"}
        return
    lls = np.asarray(lls)
    inc = np.diff(lls) / np.maximum(1.0, np.abs(lls[:-1]))
    worst = float(inc.min())
    r["worst"] = min(r["worst"], worst)
    r["gain"].append(lls[-1] - lls[0])
    if worst >= -rel_tol:
        r["held"] += 1
    elif r["ce"] is None:
        i = int(np.argmin(inc))
        r["ce"] = tolist({
            "n": n, "m": m, "T": T, "iteration": i, "loglik_before": lls[i], "loglik_after": lls[i + 1],
            "loglik_trace": lls, "Ao": model.Ao, "co": model.co, "So": model.So, "mu0": mu0, "P0": P0,
            "Y": Y, "policy_before": pols[i].to_dict(), "policy_after": pols[i + 1].to_dict(),
        })


def _claim2_rows(results: dict, instances: int, *, iterations: int, sequences: int, inner: int,
                 rel_tol: float) -> list[ClaimResult]:
    out = []
    for label, name, desc, note in (
        ("exact", "2a exact EM monotone in log p(Y)",
         f"exact EM (estep.smooth + mstep.maximize(objective='exact'), cov floor 1e-3 I) never decreases "
         f"log p(Y) over {iterations} iterations",
         f"the EM lemma; M-step inner iterations capped at {inner} (generalized EM)"),
        ("surrogate", "2b surrogate EM in log p(Y) (informative)",
         "the paper's surrogate M-step (objective='surrogate', cov floor 0.1 I), same instances: is log p(Y) "
         "monotone too? Not implied by the EM lemma; not a failure of claim 2",
         "the surrogate is a Jensen lower bound of the exact objective"),
    ):
        r = results[label]
        g = np.asarray(r["gain"])
        gain = f"median total gain in log p(Y) {np.median(g):.3g}" if len(g) else "no completed runs"
        err = f"; {r['errors']} runs raised" if r["errors"] else ""
        out.append(ClaimResult(
            name, desc, instances, r["held"], float(r["worst"]) if np.isfinite(r["worst"]) else float("nan"),
            f"most negative increment (l_(i+1) - l_i)/max(1,|l_i|) over iterations (held if >= -{rel_tol:g})",
            r["ce"], f"{note}; {sequences} sequences per instance; {gain}{err}",
        ))
    return out


# ---------------------------------------------------------------------------
# Claim 3: surrogate increase => expected cost decrease (Theorem IV.1 of the earlier paper)
# ---------------------------------------------------------------------------

_CLAIM3_VARIANTS = (("floor", "model"), ("fixed", "model"), ("optimistic", "optimistic"))


def expected_stage_costs(smoothed: Smoothed, policy: LinearGaussianPolicy, Qs, s_star, Qa, a_star) -> np.ndarray:
    """``E[Y_k(s_k, a_k)]``, ``k = 0..T-1``, with ``s_k ~ N(s_hat_k, P_k)`` (smoothed) and ``a_k ~ policy(.|s_k)``.

    ``Y_k = (s - s*)^T Qs (s - s*) + (a - a*)^T Qa (a - a*)`` (docs/math.md §0); closed form
    ``tr(Qs P) + (s_hat - s*)^T Qs (s_hat - s*) + tr(Qa (K P K^T + Sigma)) + (K s_hat + k - a*)^T Qa (K s_hat + k - a*)``.
    """
    T = policy.T
    mean = np.asarray(smoothed.mean)[:T]
    P = np.asarray(smoothed.cov)[:T]
    ds = mean - s_star
    state = np.einsum("tij,ji->t", P, Qs) + np.einsum("ti,ij,tj->t", ds, Qs, ds)
    am = np.einsum("tmn,tn->tm", policy.K, mean) + policy.k - a_star
    acov = np.einsum("tmi,tij,tnj->tmn", policy.K, P, policy.K) + policy.cov
    action = np.einsum("tij,ji->t", acov, Qa) + np.einsum("ti,ij,tj->t", am, Qa, am)
    return state + action


def ls_augmented(s: np.ndarray, a: np.ndarray, y: np.ndarray, ridge: float = 1e-6, jitter: float = 1e-6) -> AugmentedModel:
    """Per-step least-squares fit of ``(s_{k+1}, y_k)`` on ``(s_k, a_k, 1)`` from ``M`` rollouts.

    ``So_k`` is the residual covariance with ``1/(M - (n+m+1))`` normalisation plus ``jitter I``.
    """
    M, T1, n = s.shape
    T, m = a.shape[1], a.shape[2]
    Ao = np.zeros((T, n + 1, n + m))
    co = np.zeros((T, n + 1))
    So = np.zeros((T, n + 1, n + 1))
    for k in range(T):
        X = np.concatenate([s[:, k], a[:, k], np.ones((M, 1))], axis=1)
        Z = np.concatenate([s[:, k + 1], y[:, k, None]], axis=1)
        G = X.T @ X + ridge * np.eye(X.shape[1])
        W = np.linalg.solve(G, X.T @ Z)  # (n+m+1, n+1)
        R = Z - X @ W
        Ao[k] = W[: n + m].T
        co[k] = W[n + m]
        So[k] = symmetrize(R.T @ R / max(1, M - X.shape[1])) + jitter * np.eye(n + 1)
    return AugmentedModel(Ao, co, So, n)


def claim3_instance(rng: np.random.Generator, M: int):
    """A random stable linear system with quadratic costs, a policy ``phi^i`` and ``M`` rollouts under it."""
    n = int(rng.integers(1, 4))
    m = int(rng.integers(1, 3))
    T = int(rng.integers(1, 7))
    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = 0.95 * Qo
    B = rng.standard_normal((n, m)) / np.sqrt(n)
    c = 0.1 * rng.standard_normal(n)
    W = random_spd_spectrum(rng, n, 0.01, 0.05)
    Qs = random_spd_spectrum(rng, n, 0.05, 0.3) / n
    Qa = random_spd_spectrum(rng, m, 0.05, 0.3)
    s_star = rng.standard_normal(n)
    a_star = np.zeros(m)
    policy = random_policy(rng, T, n, m)
    # one covariance for all steps, so that "Sigma >= Sigma^i" is a single matrix floor (row 3b)
    policy = policy.with_cov(np.broadcast_to(random_spd_spectrum(rng, m, 0.2, 1.0), (T, m, m)).copy())
    mu0 = 0.5 * rng.standard_normal(n)
    P0 = random_spd_spectrum(rng, n, 0.02, 0.1)
    # rollouts of the true system under phi^i
    s = np.zeros((M, T + 1, n))
    a = np.zeros((M, T, m))
    s[:, 0] = mu0 + rng.standard_normal((M, n)) @ np.linalg.cholesky(P0).T
    Lw = np.linalg.cholesky(W)
    for k in range(T):
        a[:, k] = policy.sample_action(k, s[:, k], rng)
        s[:, k + 1] = s[:, k] @ A.T + a[:, k] @ B.T + c + rng.standard_normal((M, n)) @ Lw.T
    ds = s[:, :T] - s_star
    da = a - a_star
    Ycost = np.einsum("mti,ij,mtj->mt", ds, Qs, ds) + np.einsum("mti,ij,mtj->mt", da, Qa, da)
    y = np.exp(-Ycost)
    system = {"A": A, "B": B, "c": c, "W": W, "Qs": Qs, "Qa": Qa, "s_star": s_star, "a_star": a_star,
              "mu0": mu0, "P0": P0}
    return n, m, T, system, policy, s, a, y


def claim3_cost_decrease(seed: int = 0, instances: int = 20, *, rollouts: int = 40, cov_floor: float = 0.1,
                         rel_tol: float = 1e-9) -> list[ClaimResult]:
    """Claim 3: if ``L(phi^{i+1}) >= L(phi^i)`` then ``E[V_{phi^{i+1}}|Y] <= E[V_{phi^i}|Y]``.

    Per instance: a random stable linear system ``s_{k+1} = A s + B a + c + w`` (``A = 0.95 x``
    orthogonal, ``w ~ N(0, W)``), quadratic stage cost ``Y_k`` (docs/math.md §0, ``a* = 0``), a random
    policy ``phi^i``, ``rollouts`` rollouts under ``phi^i`` with ``y_k = exp(-Y_k)`` (costs scaled
    so that ``Y_k = O(1)``), an augmented model fitted by per-step least squares
    (:func:`ls_augmented`), one ``Y`` sampled from the fitted model under ``phi^i`` (the paper's
    Step 2), ``estep.smooth`` under ``phi^i``, and ``mstep.maximize`` (surrogate, time-varying)
    giving ``phi^{i+1}``.  ``L`` is ``sum_k mstep.surrogate`` with the same smoothed moments;
    ``E[V_phi|Y] = sum_k expected_stage_costs`` under the same smoothing distribution.

    Rows: (3a) covariance floor ``cov_floor I`` (``Sigma^{i+1} = cov_floor I``); (3b) covariance
    floor ``Sigma^i`` itself (``phi^i`` has one covariance for all steps), so only ``[K k]``
    change (isolates the feedback/offset update); (3c) as 3a with ``Y = 1`` (docs/math.md §3 mode
    ``optimistic``) instead of the model-sampled ``Y``.
    """
    rng = child_rng(seed, 3)
    ms = mstep_module()
    if ms is None or not hasattr(ms, "maximize"):
        return [ClaimResult("3 surrogate up => E[V|Y] down", "mstep.maximize not available", 0, 0,
                            float("nan"), "", None, "soc_opt.mstep missing: check skipped")]
    acc = {lab: {"tried": 0, "held": 0, "worst": -np.inf, "ce": None, "not_increased": 0, "errors": 0,
                 "dV": []} for lab, _ in _CLAIM3_VARIANTS}
    for _ in range(instances):
        n, m, T, system, phi, s, a, y = claim3_instance(rng, rollouts)
        model = ls_augmented(s, a, y)
        require_standing_hypotheses(model, system["mu0"], system["P0"])
        _, Y_model = sample_model_trajectory(rng, model, phi, system["mu0"], system["P0"])
        cache = {}
        for lab, y_mode in _CLAIM3_VARIANTS:
            if y_mode not in cache:
                cache[y_mode] = _claim3_baseline(ms, model, phi, system, Y_model if y_mode == "model" else np.ones(T))
            floor = phi.cov[0] if lab == "fixed" else cov_floor
            _claim3_accumulate(acc[lab], ms, model, phi, system, cache[y_mode], floor, rel_tol)
    return _claim3_rows(acc, rollouts=rollouts, cov_floor=cov_floor, rel_tol=rel_tol)


def _claim3_baseline(ms, model, phi, system: dict, Y):
    """``(Y, smoothed, E[V_phi|Y], L(phi))`` under the current policy ``phi``."""
    sm = smooth(model, phi, Y, system["mu0"], system["P0"])
    V_old = float(expected_stage_costs(sm, phi, system["Qs"], system["s_star"], system["Qa"],
                                       system["a_star"]).sum())
    L_old = float(np.sum(ms.surrogate(model, sm, Y, phi)))
    return Y, sm, V_old, L_old


def _claim3_accumulate(r: dict, ms, model, phi, system: dict, baseline, floor, rel_tol: float) -> None:
    """One surrogate M-step from ``phi`` under ``floor``; fold the outcome into ``r`` (in place)."""
    n, m, T = model.n, model.m, model.T
    Y, sm, V_old, L_old = baseline
    try:
        new = ms.maximize(model, moments(sm, Y), constraints=_cov_floor_constraints(floor), method="closed_form",
                          variant="time_varying", objective="surrogate", previous=phi, min_norm=False).policy
    except Exception as exc:
        r["errors"] += 1
        if r["ce"] is None:
            r["ce"] = {"error": f"{type(exc).__name__}: {exc}", "n": n, "m": m, "T": T}
        return
    L_new = float(np.sum(ms.surrogate(model, sm, Y, new)))
    if L_new < L_old - rel_tol * max(1.0, abs(L_old)):
        r["not_increased"] += 1
        return
    V_new = float(expected_stage_costs(sm, new, system["Qs"], system["s_star"], system["Qa"], system["a_star"]).sum())
    dV = V_new - V_old
    r["tried"] += 1
    r["dV"].append(dV / max(1e-300, abs(V_old)))
    r["worst"] = max(r["worst"], dV)
    if dV <= rel_tol * max(1.0, abs(V_old)):
        r["held"] += 1
    elif r["ce"] is None or ("error" not in r["ce"] and r["ce"]["n"] * r["ce"]["T"] * r["ce"]["m"] > n * T * m):
        # keep the smallest counterexample (fewest numbers)
        r["ce"] = tolist({
            "n": n, "m": m, "T": T, **system,
            "phi_i": phi.to_dict(), "phi_i+1": new.to_dict(),
            "Y": Y, "s_hat": sm.mean, "P": sm.cov,
            "model_Ao": model.Ao, "model_co": model.co, "model_So": model.So,
            "L_old": L_old, "L_new": L_new, "EV_old": V_old, "EV_new": V_new,
        })


def _claim3_rows(acc: dict, *, rollouts: int, cov_floor: float, rel_tol: float) -> list[ClaimResult]:
    out = []
    for lab, name, desc in (
        ("floor", "3a surrogate up => E[V|Y] down (cov floor)",
         f"Theorem IV.1: on instances where the surrogate M-step (cov floor {cov_floor:g} I) increased "
         "L = sum_k Lbar_k, the expected cost under the phi^i smoothing distribution did not increase"),
        ("fixed", "3b same, Sigma held at Sigma^i",
         "as 3a but with the floor Sigma >= Sigma^i, so Sigma^{i+1} = Sigma^i and only [K k] change "
         "(the covariance reduction no longer lowers the cost by itself)"),
        ("optimistic", "3c same, optimistic Y = 1",
         f"as 3a (cov floor {cov_floor:g} I) but conditioning on the 'optimal event' y_k = 1 (docs/math.md §3 "
         "mode 'optimistic') instead of a Y sampled from the fitted model"),
    ):
        r = acc[lab]
        dv = np.asarray(r["dV"])
        med = f"median relative change in E[V|Y] {np.median(dv):+.3g}" if len(dv) else "no comparable instances"
        extra = f"; surrogate did not increase on {r['not_increased']}" if r["not_increased"] else ""
        extra += f"; {r['errors']} M-steps raised" if r["errors"] else ""
        out.append(ClaimResult(
            name, desc, r["tried"], r["held"], float(r["worst"]) if r["tried"] else float("nan"),
            f"max over instances of E[V_new|Y] - E[V_old|Y] (held if <= {rel_tol:g} max(1, E[V_old|Y]))",
            r["ce"], f"{med}{extra}; {rollouts} rollouts per instance, n in 1..3, m in 1..2, T in 1..6",
        ))
    return out
