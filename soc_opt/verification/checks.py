"""The checks behind the claims table (docs/math.md §5, §9): each computes its quantity through the
library's own code path (``soc_opt.estep.smooth``, ``soc_opt.mstep.surrogate`` /
``exact_objective`` / ``maximize``) on random instances, never from inputs built to satisfy it.

Every check takes ``(rng, instances, full)`` and returns ``(as_written, corrected)``, two
:class:`Outcome` tallies on the *same* instances: the statement as the paper writes it and the
statement that does hold (``None`` when the claim holds as written).  The library is reached
through module attributes (``estep.smooth``, ``mstep.surrogate``) at call time, so a test can
replace one of them by a broken implementation (a mutant) and see the row fail.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import estep, mstep
from ..linalg import schur_pd_margin
from ..models import LinearGaussianPolicy, symmetrize
from ..testing import (
    random_augmented_model,
    random_initial_state,
    random_policy,
    random_spd_spectrum,
    sample_model_trajectory,
)
from .claims_uniqueness import fd_hessian_vec

__all__ = ["Outcome", "uniqueness_gain", "uniqueness_sigma", "lemma_ltv", "proposition_dpsoc",
           "theorem_cost_decrease", "em_inequality_gap"]

#: relative threshold: a Hessian is negative definite when its scale-free margin (_rel_lambda_max) is < -ND_TOL
ND_TOL = 1e-7
#: relative tolerance of the inequalities between log-likelihoods and objectives
INEQ_TOL = 1e-9


@dataclass
class Outcome:
    """Tally of one statement over instances: how many held, the worst margin and a first failure."""

    margin_meaning: str
    instances: int = 0
    held: int = 0
    worst: float = float("nan")
    example: dict | None = None
    notes: list[str] = field(default_factory=list)
    larger_is_worse: bool = True

    def add(self, ok: bool, margin: float, example: dict | None = None) -> None:
        self.instances += 1
        self.held += bool(ok)
        if np.isnan(self.worst) or (margin > self.worst if self.larger_is_worse else margin < self.worst):
            self.worst = float(margin)
        if not ok and self.example is None:
            self.example = example

    @property
    def holds(self) -> bool:
        return self.instances > 0 and self.held == self.instances


# --------------------------------------------------------------------------- instances


@dataclass(frozen=True)
class Instance:
    """A random augmented model, a policy, initial state, one ``Y`` and its smoothing under the policy."""

    model: object
    policy: LinearGaussianPolicy
    mu0: np.ndarray
    P0: np.ndarray
    y: np.ndarray
    sm: object


def draw_instance(rng, n: int, m: int, T: int, *, proportional: bool = False, shared_cov: bool = False) -> Instance:
    """Model from :func:`soc_opt.testing.random_augmented_model` (``proportional``: stacked ``[B; By]``
    of rank ``m-1`` with nonzero columns), ``Y`` drawn from it under another random policy,
    smoothed by ``estep.smooth`` under ``policy``."""
    model = random_augmented_model(rng, n, m, T, b_rank=m - 1 if proportional else None)
    policy = random_policy(rng, T, n, m)
    if shared_cov:
        policy = policy.with_cov(np.broadcast_to(random_spd_spectrum(rng, m, 0.2, 1.0), (T, m, m)).copy())
    mu0, P0 = random_initial_state(rng, n)
    _, y = sample_model_trajectory(rng, model, random_policy(rng, T, n, m), mu0, P0)
    return Instance(model, policy, mu0, P0, y, estep.smooth(model, policy, y, mu0, P0))


def with_F(policy: LinearGaussianPolicy, F: np.ndarray, cov: np.ndarray | None = None) -> LinearGaussianPolicy:
    """``policy`` with gains ``F = [K k]`` (T, m, n+1) and optionally another covariance."""
    n = policy.n
    return LinearGaussianPolicy(F[..., :n], F[..., n], policy.cov if cov is None else cov)


def policy_F(policy: LinearGaussianPolicy) -> np.ndarray:
    return np.concatenate([policy.K, policy.k[..., None]], axis=-1)


def stacked_H(model) -> np.ndarray:
    """``H_k = B_k^T (So_k)^-1 B_k`` with the stacked ``B_k = [B; By]`` (plain numpy, not the library)."""
    B = np.asarray(model.Bs)
    return symmetrize(np.swapaxes(B, 1, 2) @ np.linalg.solve(model.So, B))


def library_hessians(inst: Instance) -> np.ndarray:
    """(T, d, d) Hessians of ``mstep.surrogate`` in ``vec([K_k k_k])`` by central second differences
    (exact for a quadratic up to rounding) at the instance's policy."""
    model, pol = inst.model, inst.policy
    n, m = model.n, model.m
    F0 = policy_F(pol)

    def f(v):
        F = F0 + v.reshape((m, n + 1), order="F")[None]
        return np.asarray(mstep.surrogate(model, inst.sm, inst.y, with_F(pol, F)))

    return fd_hessian_vec(f, m * (n + 1), 1e-2)


def _rel_lambda_max(Hs: np.ndarray, m: int) -> float:
    """Scale-free negative-definiteness margin of a Hessian in ``vec([K k])`` (< 0: negative definite):
    the offset block and its Schur complement, each against its own scale (:func:`soc_opt.linalg.schur_pd_margin`)."""
    M = -symmetrize(np.asarray(Hs, dtype=float))
    return -float(schur_pd_margin(M, M.shape[0] - m))


# --------------------------------------------------------------------------- uniqueness


def uniqueness_gain(rng, instances: int, full: bool = False):
    """Theorem "uniqueness", the ``[F_j e_j]`` part (docs/math.md §5, §9 claim 1).

    As written (no hypotheses): every per-step Hessian of ``Lbar_j`` (finite differences of
    ``mstep.surrogate``) is negative definite.  Corrected: it is negative definite iff
    ``H_j = B_j^T (So_j)^-1 B_j > 0`` with the stacked ``B_j`` (plain numpy), and ``P_{j|T} > 0``
    (``estep.smooth``) holds on every instance.  Half the instances have proportional actuators.
    """
    aw = Outcome("max over steps of the scale-free margin of the finite-difference Hessian (offset block and its "
                 "Schur complement, each against its own scale; held if < -1e-7)")
    co = Outcome("steps where 'Hessian negative definite' differs from 'H_j > 0', plus steps with P_j|T not > 0 "
                 "(held if 0)")
    for i in range(instances):
        n = int(rng.integers(1, 4))
        m = int(rng.integers(1, min(n + 2, 3) + 1))
        T = int(rng.integers(1, 4))
        prop = i % 2 == 1  # every other instance: proportional actuators (needs m >= 2)
        m = max(m, 2) if prop else m
        inst = draw_instance(rng, n, m, T, proportional=prop)
        Hfd = library_hessians(inst)
        lam = np.array([_rel_lambda_max(Hfd[k], m) for k in range(T)])
        unique = lam < -ND_TOL
        H = stacked_H(inst.model)
        ev = np.linalg.eigvalsh(H)
        h_pd = ev[:, 0] > ND_TOL * np.abs(ev).max(-1)
        p_pd = np.linalg.eigvalsh(np.asarray(inst.sm.cov))[:, 0] > 0
        small = {"n": n, "m": m, "T": T, "proportional": prop, "lambda_rel": lam, "H_min_eig": ev[:, 0]}
        aw.add(bool(unique.all()), float(lam.max()), small)
        bad = int(np.sum(unique != h_pd) + np.sum(~p_pd))
        co.add(bad == 0, bad, small)
    return aw, co


def _sym_basis(m: int):
    for i in range(m):
        for j in range(i, m):
            E = np.zeros((m, m))
            E[i, j] = E[j, i] = 1.0
            yield i, j, E


def uniqueness_sigma(rng, instances: int, full: bool = False):
    """Theorem "uniqueness", the ``Sigma_j`` part (docs/math.md §5).

    As written: the maximiser in ``Sigma_j`` is a stationary point of ``Lbar_j`` (zero gradient of
    ``mstep.surrogate`` in ``Sigma_j``, by central differences at ``mstep.maximize``'s output).
    Corrected: on ``{Sigma >= Sigma_min}`` the maximiser is ``Sigma_min`` (a boundary point, returned
    by ``mstep.maximize``); the gradient is ``-H_j/2`` and every feasible move ``Sigma_min + D``
    (``D >= 0``, ``D != 0``) strictly lowers ``Lbar_j`` when ``H_j > 0``.
    """
    aw = Outcome("max over steps of ||grad_Sigma Lbar_j||_F at the maximiser (held if <= 1e-8)")
    co = Outcome("max violation: |Sigma_j - Sigma_min|, |grad + H/2|, or a feasible move that does not lower "
                 "Lbar_j (held if <= 1e-7)")
    for _ in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(1, 4))
        inst = draw_instance(rng, n, m, T)
        floor = random_spd_spectrum(rng, m, 0.05, 0.3)
        new = mstep.maximize(inst.model, inst.sm, inst.y, constraints=mstep.MStepConstraints(cov_floor=floor.tolist()), min_norm=False)
        L = lambda cov: np.asarray(mstep.surrogate(inst.model, inst.sm, inst.y, new.with_cov(cov)))  # noqa: E731
        h = 0.25 * float(np.linalg.eigvalsh(floor)[0])
        base = np.array(new.cov)
        G = np.zeros((T, m, m))
        for i, j, E in _sym_basis(m):
            d = (L(base + h * E) - L(base - h * E)) / (2 * h)  # directional derivative along E
            G[:, i, j] = G[:, j, i] = d if i == j else d / 2
        gnorm = np.linalg.norm(G, axis=(1, 2))
        aw.add(bool(np.all(gnorm <= 1e-8)), float(gnorm.max()), {"n": n, "m": m, "T": T, "grad": G})
        H = stacked_H(inst.model)
        scale = max(1.0, float(np.abs(H).max()))
        viol = max(float(np.abs(base - floor).max()), float(np.abs(G + 0.5 * H).max()) / scale)
        L0 = L(base)
        for _ in range(5):
            R = rng.standard_normal((m, m))
            D = R @ R.T
            D /= np.linalg.norm(D)
            drop = L0 - L(base + D[None])
            viol = max(viol, float(np.max(-drop)) + (0.0 if np.all(drop > 0) else 1.0))
        co.add(viol <= 1e-7, viol, {"n": n, "m": m, "T": T, "violation": viol})
    return aw, co


# --------------------------------------------------------------------------- Lemma LTV and the EM inequality


def em_inequality_gap(model, y, mu0, P0, old: LinearGaussianPolicy, sm_old, new: LinearGaussianPolicy,
                      sm_new=None) -> dict:
    """The quantities of Lemma LTV and of the EM inequality for a move ``old -> new``, all through the
    library: ``dlogp`` (``estep.smooth(...).loglik``), ``dL`` (``sum_k mstep.surrogate``) and ``dQ``
    (``sum_k mstep.exact_objective``), both objectives under the smoothing of ``old``."""
    if sm_new is None:
        sm_new = estep.smooth(model, new, y, mu0, P0)
    dL = float(np.sum(mstep.surrogate(model, sm_old, y, new)) - np.sum(mstep.surrogate(model, sm_old, y, old)))
    dQ = float(np.sum(mstep.exact_objective(model, sm_old, y, new)) - np.sum(mstep.exact_objective(model, sm_old, y, old)))
    return {"dlogp": float(sm_new.loglik - sm_old.loglik), "dL": dL, "dQ": dQ,
            "logp_old": float(sm_old.loglik), "logp_new": float(sm_new.loglik)}


def lemma_ltv(rng, instances: int, full: bool = False):
    """Lemma LTV (docs/math.md §5): ``L = log p(s_1) + sum_k Lbar_k``, and an M-step that raises ``L``
    raises ``log p(Y)`` at least as much: ``dlog p(Y) >= dL``.  ``log p(s_1)`` does not depend on
    the policy.  The move is the surrogate M-step with ``cov_floor 0.05 I`` (``Sigma`` changes).
    Corrected (the EM inequality): ``dlog p(Y) >= dQ`` with ``Q = sum_k`` exact objective (action
    integrated out), for the M-step and for a random move of ``[K k]`` and ``Sigma``.
    """
    aw = Outcome("min over instances of (dlog p(Y) - dL)/max(1,|log p|) (held if >= -1e-9)", larger_is_worse=False)
    co = Outcome("min of (dlog p(Y) - dQ)/max(1,|log p|) over the M-step and a random move (held if >= -1e-9)",
                 larger_is_worse=False)
    fixed = [0, 0]
    for _ in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(1, 5))
        inst = draw_instance(rng, n, m, T, shared_cov=True)
        args = (inst.model, inst.y, inst.mu0, inst.P0, inst.policy, inst.sm)
        new = mstep.maximize(inst.model, inst.sm, inst.y, constraints=mstep.MStepConstraints(cov_floor=0.05), min_norm=False)
        g = em_inequality_gap(*args, new)
        scale = max(1.0, abs(g["logp_old"]))
        ok = g["dlogp"] >= g["dL"] - INEQ_TOL * scale
        aw.add(ok, (g["dlogp"] - g["dL"]) / scale, {"n": n, "m": m, "T": T, **g})
        F = policy_F(inst.policy)
        rand = with_F(inst.policy, F + 0.3 * rng.standard_normal(F.shape),
                      inst.policy.cov * float(rng.uniform(0.3, 3.0)))
        g2 = em_inequality_gap(*args, rand)
        margin = min(g["dlogp"] - g["dQ"], g2["dlogp"] - g2["dQ"]) / scale
        co.add(margin >= -INEQ_TOL, margin, {"n": n, "m": m, "T": T, "mstep": g, "random": g2})
        # informative: the same lemma with Sigma held at Sigma^i
        fx = mstep.maximize(inst.model, inst.sm, inst.y,
                            constraints=mstep.MStepConstraints(cov_floor=inst.policy.cov[0].tolist()), min_norm=False)
        g3 = em_inequality_gap(*args, fx)
        fixed[0] += 1
        fixed[1] += g3["dlogp"] >= g3["dL"] - INEQ_TOL * scale
    aw.notes.append(f"with Sigma held at Sigma^i (floor = Sigma^i) dlog p >= dL held on {fixed[1]}/{fixed[0]} "
                    "(not a theorem either: Lbar weights residuals by So^-1, log p by (So + B Sigma B^T)^-1)")
    return aw, co


# --------------------------------------------------------------------------- Proposition DPSOC


def proposition_dpsoc(rng, instances: int, full: bool = False):
    """Proposition DPSOC (docs/math.md §5): the backward sweep ``j = T-1..0``, each
    ``phi_j = argmax Lbar_j`` with the future fixed, maximises ``sum_k Lbar_k`` over time-varying
    policies in ``Phi = {Sigma_k >= Sigma_min}``.  Checked on ``mstep.maximize``'s output: (i)
    ``Lbar_j`` depends on ``phi_j`` only (moving ``phi_j`` leaves the other ``mstep.surrogate``
    entries unchanged), (ii) the central-difference gradient of ``sum_k Lbar_k`` in every
    ``[K_k k_k]`` vanishes, (iii) no random feasible move raises ``sum_k Lbar_k``; with ``full``
    also (iv) the literal backward sweep (``method='cvxpy'``) gives the same policy.
    """
    out = Outcome("max of: cross-step change, |grad|/scale, feasible increase, sweep mismatch (held if <= 1e-6)")
    for _ in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(2, 5))
        inst = draw_instance(rng, n, m, T)
        cons = mstep.MStepConstraints(cov_floor=0.1)
        new = mstep.maximize(inst.model, inst.sm, inst.y, constraints=cons, min_norm=False)
        L = lambda p: np.asarray(mstep.surrogate(inst.model, inst.sm, inst.y, p))  # noqa: E731
        F = policy_F(new)
        L0 = L(new)
        scale = max(1.0, float(np.abs(L0).max()))
        worst = 0.0
        j = int(rng.integers(0, T))
        Fj = F.copy()
        Fj[j] += rng.standard_normal(F[j].shape)
        others = np.delete(L(with_F(new, Fj)) - L0, j)
        worst = max(worst, float(np.abs(others).max(initial=0.0)) / scale)
        h = 1e-3
        for idx in np.ndindex(F.shape[1:]):
            E = np.zeros_like(F)
            E[(slice(None),) + idx] = h
            grad = (L(with_F(new, F + E)) - L(with_F(new, F - E))) / (2 * h)
            worst = max(worst, float(np.abs(grad).max()) / scale)
        for _ in range(5):
            D = rng.standard_normal((T, m, m))
            cov = new.cov + 0.1 * np.einsum("tij,tkj->tik", D, D)
            gain = float(np.sum(L(with_F(new, F + 0.1 * rng.standard_normal(F.shape), cov))) - np.sum(L0))
            worst = max(worst, gain / scale)
        if full:
            cv = mstep.maximize(inst.model, inst.sm, inst.y, constraints=cons, method="cvxpy", min_norm=False)
            worst = max(worst, float(np.abs(policy_F(cv) - F).max()) / max(1.0, float(np.abs(F).max())))
        out.add(worst <= 1e-6, worst, {"n": n, "m": m, "T": T, "worst": worst})
    return out, None


# --------------------------------------------------------------------------- Theorem IV.1 of the earlier paper


def theorem_cost_decrease(rng, instances: int, full: bool = False):
    """Theorem IV.1 of the paper's reference (docs/math.md §9 claim 3) with ``Sigma`` held at
    ``Sigma^i``: if the surrogate M-step raises ``L``, then ``E[V|Y]`` does not rise.  Corrected: the
    EM inequality ``dlog p(Y) >= dQ`` on the same moves, and the exact-EM step
    (``objective='exact'``) does not lower ``log p(Y)``.  Instances: claim 3's linear systems with
    ``y = exp(-Y)`` and a per-step least-squares augmented model.
    """
    from .claims_em import claim3_instance, expected_stage_costs, ls_augmented

    aw = Outcome("max of (E[V_new|Y] - E[V_old|Y])/max(1,E[V_old|Y]) over moves that raised L (held if <= 1e-9)")
    co = Outcome("min of (dlog p - dQ) and of the exact-EM dlog p, / max(1,|log p|) (held if >= -1e-9)",
                 larger_is_worse=False)
    cfg = mstep.MStepConfig(exact_max_iter=50)
    for _ in range(instances):
        n, m, T, system, phi, s, a, yobs = claim3_instance(rng, 40)
        model = ls_augmented(s, a, yobs)
        _, Y = sample_model_trajectory(rng, model, phi, system["mu0"], system["P0"])
        mu0, P0 = system["mu0"], system["P0"]
        sm = estep.smooth(model, phi, Y, mu0, P0)
        cons = mstep.MStepConstraints(cov_floor=phi.cov[0].tolist())
        new = mstep.maximize(model, sm, Y, constraints=cons, min_norm=False)
        g = em_inequality_gap(model, Y, mu0, P0, phi, sm, new)
        cost = lambda p: float(expected_stage_costs(sm, p, system["Qs"], system["s_star"], system["Qa"],  # noqa: E731
                                                    system["a_star"]).sum())
        V_old, V_new = cost(phi), cost(new)
        if g["dL"] >= -INEQ_TOL * max(1.0, abs(g["logp_old"])):
            rel = (V_new - V_old) / max(1.0, abs(V_old))
            aw.add(rel <= INEQ_TOL, rel, {"n": n, "m": m, "T": T, "EV_old": V_old, "EV_new": V_new, **g})
        ex = mstep.maximize(model, sm, Y, constraints=mstep.MStepConstraints(cov_floor=1e-3), objective="exact",
                            previous=phi, config=cfg, min_norm=False)
        lp_ex = float(estep.smooth(model, ex, Y, mu0, P0).loglik)
        scale = max(1.0, abs(g["logp_old"]))
        margin = min(g["dlogp"] - g["dQ"], lp_ex - g["logp_old"]) / scale
        co.add(margin >= -INEQ_TOL, margin, {"n": n, "m": m, "T": T, **g, "logp_exact_em": lp_ex})
    return aw, co
