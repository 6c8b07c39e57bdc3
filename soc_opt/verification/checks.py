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
from ..models import AugmentedModel, LinearGaussianPolicy, symmetrize
from ..testing import (
    random_augmented_model,
    random_initial_state,
    random_policy,
    random_spd_spectrum,
    sample_model_trajectory,
)
from .claims_uniqueness import fd_hessian_vec
from .hypotheses import require_standing_hypotheses

__all__ = ["Outcome", "CaseResult", "Instance", "draw_instance", "rescale_instance", "rescale_F", "f_units",
           "uniqueness_gain", "uniqueness_case", "uniqueness_sigma", "SigmaCase", "uniqueness_sigma_case",
           "lemma_ltv", "LtvCase", "ltv_case", "proposition_dpsoc", "DpsocCase", "dpsoc_case",
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
    smoothed by ``estep.smooth`` under ``policy``.  The standing hypotheses ``P0 > 0``, ``So_k > 0``
    are checked up front (:func:`~soc_opt.verification.hypotheses.require_standing_hypotheses`)."""
    model = random_augmented_model(rng, n, m, T, b_rank=m - 1 if proportional else None)
    policy = random_policy(rng, T, n, m)
    if shared_cov:
        policy = policy.with_cov(np.broadcast_to(random_spd_spectrum(rng, m, 0.2, 1.0), (T, m, m)).copy())
    mu0, P0 = random_initial_state(rng, n)
    require_standing_hypotheses(model, mu0, P0)
    _, y = sample_model_trajectory(rng, model, random_policy(rng, T, n, m), mu0, P0)
    return Instance(model, policy, mu0, P0, y, estep.smooth(model, policy, y, mu0, P0))


def rescale_F(F: np.ndarray, n: int, cs: float, ca: float) -> np.ndarray:
    """``[K k]`` in the units of :func:`rescale_instance`: ``K -> (ca/cs) K``, ``k -> ca k``."""
    F = np.array(F, dtype=float)
    F[..., :n] *= ca / cs
    F[..., n] *= ca
    return F


def rescale_instance(inst: Instance, cs: float, ca: float) -> Instance:
    """The same instance in other units (docs/math.md §9, scale invariance): state ``s -> cs s``, action
    ``a -> ca a``, ``y`` unchanged, smoothed again by ``estep.smooth``.  In exact arithmetic the smoothed
    means scale by ``cs``, the covariances by ``cs^2``, ``log p(Y)`` does not change, and every claim's
    verdict must not change either."""
    model, pol = inst.model, inst.policy
    n = model.n
    D = np.ones(n + 1)
    D[:n] = cs
    Ao = np.array(model.Ao) * D[None, :, None]
    Ao[:, :, :n] /= cs
    Ao[:, :, n:] /= ca
    model2 = AugmentedModel(Ao, np.array(model.co) * D, np.array(model.So) * D[:, None] * D[None, :], n)
    pol2 = LinearGaussianPolicy(np.array(pol.K) * (ca / cs), np.array(pol.k) * ca, np.array(pol.cov) * ca**2)
    mu0, P0 = np.asarray(inst.mu0) * cs, np.asarray(inst.P0) * cs**2
    require_standing_hypotheses(model2, mu0, P0)
    return Instance(model2, pol2, mu0, P0, inst.y, estep.smooth(model2, pol2, inst.y, mu0, P0))


def f_units(inst: Instance) -> np.ndarray:
    """(T, m, n+1) the natural size of an entry of ``[K_k k_k]``: the action's standard deviation over the
    RMS of the regressor, ``sqrt(Sigma_k,ii / Stilde_k,jj)`` (``Stilde_k = E[(s_k,1)(s_k,1)^T | Y]``).  Finite
    differences and random moves of ``[K k]`` are taken in these units, so they follow a rescaling of the
    state or the action (:func:`rescale_instance`) instead of being absolute."""
    Sss = np.asarray(estep.moments(inst.sm, inst.y).Sss)
    sd_a = np.sqrt(np.diagonal(np.asarray(inst.policy.cov), axis1=1, axis2=2))
    rms = np.sqrt(np.diagonal(Sss, axis1=1, axis2=2))
    return sd_a[:, :, None] / rms[:, None, :]


@dataclass(frozen=True)
class CaseResult:
    """One instance's outcome: the statement as written (``ok``, ``margin``, ``example``) and, for a claim
    with a corrected statement, the corrected one (``co_*``); ``info`` holds auxiliary numbers."""

    ok: bool
    margin: float
    example: dict
    co_ok: bool | None = None
    co_margin: float | None = None
    co_example: dict | None = None
    info: dict | None = None

    def add_to(self, aw: Outcome, co: Outcome | None = None) -> None:
        aw.add(self.ok, self.margin, self.example)
        if co is not None:
            co.add(bool(self.co_ok), float(self.co_margin), self.co_example)


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
    (exact for a quadratic up to rounding) at the instance's policy.  The coordinates are measured in
    :func:`f_units` (the Hessian is ``D_u Hess D_u`` with ``D_u`` a positive diagonal, so it is negative
    definite exactly when the Hessian in ``[K k]`` is) and the step is ``1e-2`` of those units."""
    model, pol = inst.model, inst.policy
    n, m = model.n, model.m
    F0 = policy_F(pol)
    u = f_units(inst)

    def f(v):
        F = F0 + v.reshape((m, n + 1), order="F")[None] * u
        return np.asarray(mstep.surrogate(model, inst.sm, inst.y, with_F(pol, F)))

    return fd_hessian_vec(f, m * (n + 1), 1e-2)


def _rel_lambda_max(Hs: np.ndarray, m: int) -> float:
    """Scale-free negative-definiteness margin of a Hessian in ``vec([K k])`` (< 0: negative definite):
    the offset block and its Schur complement, each against its own scale (:func:`soc_opt.linalg.schur_pd_margin`)."""
    M = -symmetrize(np.asarray(Hs, dtype=float))
    return -float(schur_pd_margin(M, M.shape[0] - m))


# --------------------------------------------------------------------------- uniqueness


def uniqueness_case(inst: Instance, proportional: bool = False) -> CaseResult:
    """One instance of :func:`uniqueness_gain`: as written, every finite-difference Hessian is negative
    definite; corrected, "negative definite" equals "``H_j > 0``" at every step and every ``P_j|T > 0``."""
    model = inst.model
    n, m, T = model.n, model.m, model.T
    lam = np.array([_rel_lambda_max(Hk, m) for Hk in library_hessians(inst)])
    unique = lam < -ND_TOL
    ev = np.linalg.eigvalsh(stacked_H(model))
    h_pd = ev[:, 0] > ND_TOL * np.abs(ev).max(-1)
    p_pd = np.linalg.eigvalsh(np.asarray(inst.sm.cov))[:, 0] > 0
    small = {"n": n, "m": m, "T": T, "proportional": proportional, "lambda_rel": lam, "H_min_eig": ev[:, 0]}
    bad = int(np.sum(unique != h_pd) + np.sum(~p_pd))
    return CaseResult(bool(unique.all()), float(lam.max()), small, bad == 0, bad, small)


def uniqueness_gain(rng, instances: int, full: bool = False):
    """Theorem "uniqueness", the ``[F_j e_j]`` part (docs/math.md §5, §9 claim 1).

    As written (no hypotheses): every per-step Hessian of ``Lbar_j`` (finite differences of
    ``mstep.surrogate``) is negative definite.  Corrected: it is negative definite iff
    ``H_j = B_j^T (So_j)^-1 B_j > 0`` with the stacked ``B_j`` (plain numpy), and ``P_{j|T} > 0``
    (``estep.smooth``) holds on every instance (given ``P0 > 0``, ``So_k > 0``: the standing
    hypotheses).  Half the instances have proportional actuators.
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
        uniqueness_case(draw_instance(rng, n, m, T, proportional=prop), prop).add_to(aw, co)
    return aw, co


def _sym_basis(m: int):
    for i in range(m):
        for j in range(i, m):
            E = np.zeros((m, m))
            E[i, j] = E[j, i] = 1.0
            yield i, j, E


@dataclass(frozen=True)
class SigmaCase:
    """An instance of :func:`uniqueness_sigma`: the floor ``Sigma_min`` (m, m) and five random ``R`` (m, m)
    whose feasible moves are ``Sigma_min + L R R^T L^T / ||R R^T||`` (``Sigma_min = L L^T``)."""

    inst: Instance
    floor: np.ndarray
    moves: np.ndarray

    def rescaled(self, cs: float, ca: float) -> SigmaCase:
        return SigmaCase(rescale_instance(self.inst, cs, ca), self.floor * ca**2, self.moves)


def uniqueness_sigma_case(case: SigmaCase) -> CaseResult:
    """One instance of :func:`uniqueness_sigma`.  The gradient ``G`` in ``Sigma`` is measured as
    ``L^T G L`` (``Sigma_min = L L^T``): the change of ``Lbar_j`` per relative change of ``Sigma``, free of
    the action's units."""
    inst, floor = case.inst, case.floor
    n, m, T = inst.model.n, inst.model.m, inst.model.T
    new = mstep.maximize(inst.model, estep.moments(inst.sm, inst.y),
                         constraints=mstep.MStepConstraints(cov_floor=floor.tolist()), min_norm=False).policy
    L = lambda cov: np.asarray(mstep.surrogate(inst.model, inst.sm, inst.y, new.with_cov(cov)))  # noqa: E731
    h = 0.25 * float(np.linalg.eigvalsh(floor)[0])
    base = np.array(new.cov)
    G = np.zeros((T, m, m))
    for i, j, E in _sym_basis(m):
        d = (L(base + h * E) - L(base - h * E)) / (2 * h)  # directional derivative along E
        G[:, i, j] = G[:, j, i] = d if i == j else d / 2
    Lf = np.linalg.cholesky(floor)
    Gw = Lf.T @ G @ Lf
    gnorm = np.linalg.norm(Gw, axis=(1, 2))
    Hw = Lf.T @ stacked_H(inst.model) @ Lf
    viol = max(float(np.abs(base - floor).max()) / float(np.abs(floor).max()),
               float(np.abs(Gw + 0.5 * Hw).max()) / max(float(np.abs(Hw).max()), np.finfo(float).tiny))
    L0 = L(base)
    for R in case.moves:
        D = R @ R.T
        D = Lf @ (D / np.linalg.norm(D)) @ Lf.T
        drop = L0 - L(base + D[None])
        viol = max(viol, float(np.max(-drop)) + (0.0 if np.all(drop > 0) else 1.0))
    return CaseResult(bool(np.all(gnorm <= 1e-8)), float(gnorm.max()), {"n": n, "m": m, "T": T, "grad": G},
                      viol <= 1e-7, viol, {"n": n, "m": m, "T": T, "violation": viol})


def uniqueness_sigma(rng, instances: int, full: bool = False):
    """Theorem "uniqueness", the ``Sigma_j`` part (docs/math.md §5).

    As written: the maximiser in ``Sigma_j`` is a stationary point of ``Lbar_j`` (zero gradient of
    ``mstep.surrogate`` in ``Sigma_j``, by central differences at ``mstep.maximize``'s output).
    Corrected: on ``{Sigma >= Sigma_min}`` the maximiser is ``Sigma_min`` (a boundary point, returned
    by ``mstep.maximize``); the gradient is ``-H_j/2`` and every feasible move ``Sigma_min + D``
    (``D >= 0``, ``D != 0``) strictly lowers ``Lbar_j`` when ``H_j > 0``.
    """
    aw = Outcome("max over steps of ||L^T grad_Sigma Lbar_j L||_F at the maximiser, Sigma_min = L L^T (held if <= 1e-8)")
    co = Outcome("max violation: |Sigma_j - Sigma_min|/|Sigma_min|, |grad + H/2| relative to |H| (both in the metric "
                 "of Sigma_min), or a feasible move that does not lower Lbar_j (held if <= 1e-7)")
    for _ in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(1, 4))
        inst = draw_instance(rng, n, m, T)
        floor = random_spd_spectrum(rng, m, 0.05, 0.3)
        moves = np.stack([rng.standard_normal((m, m)) for _ in range(5)])
        uniqueness_sigma_case(SigmaCase(inst, floor, moves)).add_to(aw, co)
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


@dataclass(frozen=True)
class LtvCase:
    """An instance of :func:`lemma_ltv` (one ``Sigma`` shared by the steps): the M-step's covariance floor
    ``floor I``, and a random move ``[K k] + 0.3 dF`` (``dF`` in :func:`f_units`), ``Sigma -> cov_factor Sigma``."""

    inst: Instance
    dF: np.ndarray
    cov_factor: float
    floor: float = 0.05

    def rescaled(self, cs: float, ca: float) -> LtvCase:
        return LtvCase(rescale_instance(self.inst, cs, ca), self.dF, self.cov_factor, self.floor * ca**2)


def ltv_case(case: LtvCase) -> CaseResult:
    """One instance of :func:`lemma_ltv`; ``info["fixed_ok"]``: the lemma with ``Sigma`` held at ``Sigma^i``."""
    inst = case.inst
    n, m, T = inst.model.n, inst.model.m, inst.model.T
    args = (inst.model, inst.y, inst.mu0, inst.P0, inst.policy, inst.sm)
    new = mstep.maximize(inst.model, estep.moments(inst.sm, inst.y),
                         constraints=mstep.MStepConstraints(cov_floor=case.floor), min_norm=False).policy
    g = em_inequality_gap(*args, new)
    scale = max(1.0, abs(g["logp_old"]))
    ok = g["dlogp"] >= g["dL"] - INEQ_TOL * scale
    F = policy_F(inst.policy)
    rand = with_F(inst.policy, F + 0.3 * case.dF * f_units(inst), inst.policy.cov * case.cov_factor)
    g2 = em_inequality_gap(*args, rand)
    margin = min(g["dlogp"] - g["dQ"], g2["dlogp"] - g2["dQ"]) / scale
    # informative: the same lemma with Sigma held at Sigma^i
    fx = mstep.maximize(inst.model, estep.moments(inst.sm, inst.y),
                        constraints=mstep.MStepConstraints(cov_floor=inst.policy.cov[0].tolist()), min_norm=False).policy
    g3 = em_inequality_gap(*args, fx)
    return CaseResult(ok, (g["dlogp"] - g["dL"]) / scale, {"n": n, "m": m, "T": T, **g},
                      margin >= -INEQ_TOL, margin, {"n": n, "m": m, "T": T, "mstep": g, "random": g2},
                      {"fixed_ok": g3["dlogp"] >= g3["dL"] - INEQ_TOL * scale})


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
        dF = rng.standard_normal((T, m, n + 1))
        r = ltv_case(LtvCase(inst, dF, float(rng.uniform(0.3, 3.0))))
        r.add_to(aw, co)
        fixed[0] += 1
        fixed[1] += r.info["fixed_ok"]
    aw.notes.append(f"with Sigma held at Sigma^i (floor = Sigma^i) dlog p >= dL held on {fixed[1]}/{fixed[0]} "
                    "(not a theorem either: Lbar weights residuals by So^-1, log p by (So + B Sigma B^T)^-1)")
    return aw, co


# --------------------------------------------------------------------------- Proposition DPSOC


@dataclass(frozen=True)
class DpsocCase:
    """An instance of :func:`proposition_dpsoc`: the floor ``floor I``, a step ``j`` and its move ``dFj``
    (m, n+1), and five feasible moves ``(D (T, m, m), dF (T, m, n+1))``; ``[K k]`` moves are in :func:`f_units`,
    covariance moves ``Sigma + 0.1 L D D^T L^T`` (``Sigma = L L^T``)."""

    inst: Instance
    j: int
    dFj: np.ndarray
    moves: tuple
    floor: float = 0.1

    def rescaled(self, cs: float, ca: float) -> DpsocCase:
        return DpsocCase(rescale_instance(self.inst, cs, ca), self.j, self.dFj, self.moves, self.floor * ca**2)


def dpsoc_case(case: DpsocCase, full: bool = False) -> CaseResult:
    """One instance of :func:`proposition_dpsoc`.  The gradient is taken per unit of :func:`f_units`
    (steps ``1e-3`` of them), so it does not depend on the units of the state or the action."""
    inst = case.inst
    n, m, T = inst.model.n, inst.model.m, inst.model.T
    cons = mstep.MStepConstraints(cov_floor=case.floor)
    new = mstep.maximize(inst.model, estep.moments(inst.sm, inst.y), constraints=cons, min_norm=False).policy
    L = lambda p: np.asarray(mstep.surrogate(inst.model, inst.sm, inst.y, p))  # noqa: E731
    F = policy_F(new)
    u = f_units(inst)
    L0 = L(new)
    scale = max(1.0, float(np.abs(L0).max()))
    worst = 0.0
    j = case.j
    Fj = F.copy()
    Fj[j] += case.dFj * u[j]
    others = np.delete(L(with_F(new, Fj)) - L0, j)
    worst = max(worst, float(np.abs(others).max(initial=0.0)) / scale)
    h = 1e-3
    for idx in np.ndindex(F.shape[1:]):
        E = np.zeros_like(F)
        E[(slice(None),) + idx] = h * u[(slice(None),) + idx]
        grad = (L(with_F(new, F + E)) - L(with_F(new, F - E))) / (2 * h)
        worst = max(worst, float(np.abs(grad).max()) / scale)
    Lc = np.linalg.cholesky(np.asarray(new.cov))
    for D, dF in case.moves:
        LD = Lc @ D
        cov = new.cov + 0.1 * np.einsum("tij,tkj->tik", LD, LD)
        gain = float(np.sum(L(with_F(new, F + 0.1 * dF * u, cov))) - np.sum(L0))
        worst = max(worst, gain / scale)
    if full:
        cv = mstep.maximize(inst.model, estep.moments(inst.sm, inst.y), constraints=cons, method="cvxpy", min_norm=False).policy
        worst = max(worst, float(np.abs((policy_F(cv) - F) / u).max()) / max(1.0, float(np.abs(F / u).max())))
    return CaseResult(worst <= 1e-6, worst, {"n": n, "m": m, "T": T, "worst": worst})


def proposition_dpsoc(rng, instances: int, full: bool = False):
    """Proposition DPSOC (docs/math.md §5): the backward sweep ``j = T-1..0``, each
    ``phi_j = argmax Lbar_j`` with the future fixed, maximises ``sum_k Lbar_k`` over time-varying
    policies in ``Phi = {Sigma_k >= Sigma_min}``.  Checked on ``mstep.maximize``'s output: (i)
    ``Lbar_j`` depends on ``phi_j`` only (moving ``phi_j`` leaves the other ``mstep.surrogate``
    entries unchanged), (ii) the central-difference gradient of ``sum_k Lbar_k`` in every
    ``[K_k k_k]`` vanishes, (iii) no random feasible move raises ``sum_k Lbar_k``; with ``full``
    also (iv) the literal backward sweep (``method='cvxpy'``) gives the same policy.
    """
    out = Outcome("max of: cross-step change, |grad| per unit of [K k], feasible increase (each / max(1, |Lbar|)), "
                  "sweep mismatch (held if <= 1e-6)")
    for _ in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(2, 5))
        inst = draw_instance(rng, n, m, T)
        j = int(rng.integers(0, T))
        dFj = rng.standard_normal((m, n + 1))
        moves = tuple((rng.standard_normal((T, m, m)), rng.standard_normal((T, m, n + 1))) for _ in range(5))
        dpsoc_case(DpsocCase(inst, j, dFj, moves), full).add_to(out)
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
        require_standing_hypotheses(model, system["mu0"], system["P0"])
        _, Y = sample_model_trajectory(rng, model, phi, system["mu0"], system["P0"])
        mu0, P0 = system["mu0"], system["P0"]
        sm = estep.smooth(model, phi, Y, mu0, P0)
        cons = mstep.MStepConstraints(cov_floor=phi.cov[0].tolist())
        new = mstep.maximize(model, estep.moments(sm, Y), constraints=cons, min_norm=False).policy
        g = em_inequality_gap(model, Y, mu0, P0, phi, sm, new)
        cost = lambda p: float(expected_stage_costs(sm, p, system["Qs"], system["s_star"], system["Qa"],  # noqa: E731
                                                    system["a_star"]).sum())
        V_old, V_new = cost(phi), cost(new)
        if g["dL"] >= -INEQ_TOL * max(1.0, abs(g["logp_old"])):
            rel = (V_new - V_old) / max(1.0, abs(V_old))
            aw.add(rel <= INEQ_TOL, rel, {"n": n, "m": m, "T": T, "EV_old": V_old, "EV_new": V_new, **g})
        ex = mstep.maximize(model, estep.moments(sm, Y), constraints=mstep.MStepConstraints(cov_floor=1e-3), objective="exact",
                            previous=phi, config=cfg, min_norm=False).policy
        lp_ex = float(estep.smooth(model, ex, Y, mu0, P0).loglik)
        scale = max(1.0, abs(g["logp_old"]))
        margin = min(g["dlogp"] - g["dQ"], lp_ex - g["logp_old"]) / scale
        co.add(margin >= -INEQ_TOL, margin, {"n": n, "m": m, "T": T, **g, "logp_exact_em": lp_ex})
    return aw, co
