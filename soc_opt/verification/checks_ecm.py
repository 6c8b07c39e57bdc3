"""Two rows of the claims table about the E-step and the M-step with ``Sigma`` held fixed (docs/math.md §4,
§5, §9.2), checked through the library's code path like the rows of :mod:`soc_opt.verification.checks`.

``ecm`` — with ``Sigma`` held fixed, the surrogate M-step's ``[K k]`` is the maximiser of the exact expected
complete-data log-likelihood ``Q``, so that step is an ECM step (a conditional maximisation of ``Q``) and
``log p(Y)`` does not decrease under it.  Why: per step ``Lbar`` and ``Q`` are concave quadratics in
``F = [K k]`` whose normal equations are ``H F Stilde = R`` and ``H_S F Stilde = R_S`` with
``H = B^T So^-1 B``, ``R = B^T So^-1 (Szs - Atil Stilde)`` and the same with ``S = So + B Sigma B^T`` in place of
``So``.  Woodbury gives ``B^T S^-1 = (I + H Sigma)^-1 B^T So^-1``, so ``H_S = (I + H Sigma)^-1 H`` and
``R_S = (I + H Sigma)^-1 R``: the two equations differ by the invertible factor ``(I + H Sigma)^-1`` and have
the same solutions.  The EM inequality then gives ``dlog p(Y) >= dQ >= 0``.

``smoother`` — an implementation row: ``estep.smooth``'s means, covariances ``P_t|T``, cross-covariances
``P_{t+1,t|T}`` and ``log p(Y)`` equal dense conditioning of the joint Gaussian (the project's oracle,
:mod:`soc_opt.verification.oracle`).  No claim row sees a wrong covariance in the smoother (the other rows
use the smoothed moments consistently on both sides of their comparisons); this one does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import estep, mstep
from ..models import symmetrize
from .checks import INEQ_TOL, CaseResult, Instance, Outcome, draw_instance, em_inequality_gap, policy_F, rescale_instance
from .oracle import dense_posterior, smoother_errors

__all__ = ["AGREE_TOL", "SMOOTHER_TOL", "exact_maximiser_F", "metric_distance", "EcmCase", "ecm_case", "ecm_step",
           "smoother_case", "smoother_oracle"]

#: relative tolerance of "the two maximisers agree" (in the metric of Q's Hessian; measured: ~1e-12-1e-10)
AGREE_TOL = 1e-7
#: tolerance of the smoother against dense conditioning (whitened by the posterior covariance; docs/math.md §4: 1e-8)
SMOOTHER_TOL = 1e-8


def exact_maximiser_F(model, mom, Sigma: np.ndarray) -> np.ndarray:
    """(T, m, n+1) the maximiser in ``[K k]`` of ``Q_k = E log N(zeta_k; (Atil + B F) stilde, S_k)`` with
    ``Sigma`` fixed, ``S_k = So_k + B Sigma_k B^T``: ``F = H_S^-1 R_S Stilde^-1`` (docs/math.md §5, exact EM).
    Plain numpy from the model and the moments, independent of ``soc_opt.mstep``."""
    Sigma = np.asarray(Sigma, dtype=float)
    out = []
    for k in range(model.T):
        B = np.asarray(model.Bs[k])
        Atil = np.concatenate([model.As[k], model.co[k][:, None]], axis=1)
        S = symmetrize(model.So[k] + B @ Sigma[k] @ B.T)
        SiB = np.linalg.solve(S, B)
        HS = symmetrize(B.T @ SiB)
        RS = SiB.T @ (mom.Szs[k] - Atil @ mom.Sss[k])
        out.append(np.linalg.solve(symmetrize(mom.Sss[k]), np.linalg.solve(HS, RS).T).T)
    return np.stack(out)


def metric_distance(model, mom, Sigma: np.ndarray, F1: np.ndarray, F2: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(T,) ``||L_H^T (F1 - F2) L_S||_F / ||L_H^T ref L_S||_F`` with ``H_S = L_H L_H^T`` (Q's curvature in the
    action) and ``Stilde = L_S L_S^T``: ``1/2 ||L_H^T dF L_S||^2`` is what ``Q`` loses at ``F + dF``, so the
    distance is free of the units of the state and the action."""
    Sigma = np.asarray(Sigma, dtype=float)
    out = []
    for k in range(model.T):
        B = np.asarray(model.Bs[k])
        S = symmetrize(model.So[k] + B @ Sigma[k] @ B.T)
        LH = np.linalg.cholesky(symmetrize(B.T @ np.linalg.solve(S, B)))
        LS = np.linalg.cholesky(symmetrize(mom.Sss[k]))
        w = lambda F: np.linalg.norm(LH.T @ F @ LS)  # noqa: E731
        out.append(w(F1[k] - F2[k]) / max(w(ref[k]), np.finfo(float).tiny))
    return np.array(out)


# --------------------------------------------------------------------------- ECM


@dataclass(frozen=True)
class EcmCase:
    """An instance of :func:`ecm_step`: one ``Sigma`` shared by the steps, held by the M-step's floor."""

    inst: Instance

    def rescaled(self, cs: float, ca: float) -> EcmCase:
        return EcmCase(rescale_instance(self.inst, cs, ca))


def ecm_case(case: EcmCase) -> CaseResult:
    """One instance of :func:`ecm_step`.  ``info``: the agreement in the metric of ``Q`` and plainly
    (``max|dF| / max|F_Q|``), the relative change of ``Sigma``, ``dlog p(Y)`` and ``dQ`` over ``max(1, |log p|)``."""
    inst = case.inst
    model, sm, y, old = inst.model, inst.sm, inst.y, inst.policy
    n, m, T = model.n, model.m, model.T
    Sig = np.asarray(old.cov)
    new = mstep.maximize(model, estep.moments(sm, y), constraints=mstep.MStepConstraints(cov_floor=Sig[0].tolist()), min_norm=False).policy
    sig_rel = float(np.abs(np.asarray(new.cov) - Sig).max() / np.abs(Sig).max())
    mom = estep.moments(sm, y)
    FQ = exact_maximiser_F(model, mom, Sig)
    F_new, F_old = policy_F(new), policy_F(old)
    ref = np.where(np.linalg.norm(FQ, axis=(1, 2))[:, None, None] > 0, FQ, F_old)
    agree = float(metric_distance(model, mom, Sig, F_new, FQ, ref).max())
    plain = float(np.abs(F_new - FQ).max() / max(np.abs(FQ).max(), np.finfo(float).tiny))
    g = em_inequality_gap(model, y, inst.mu0, inst.P0, old, sm, new)
    scale = max(1.0, abs(g["logp_old"]))
    dlogp, dQ = g["dlogp"] / scale, g["dQ"] / scale
    ok = agree <= AGREE_TOL and sig_rel <= AGREE_TOL and dlogp >= -INEQ_TOL and dQ >= -INEQ_TOL
    info = {"agree": agree, "plain": plain, "sigma_change": sig_rel, "dlogp": dlogp, "dQ": dQ}
    return CaseResult(ok, agree, {"n": n, "m": m, "T": T, **info, **g}, info=info)


def ecm_step(rng, instances: int, full: bool = False):
    """ECM (docs/math.md §5, §9.2): with ``Sigma`` held at ``Sigma^i`` (``mstep.maximize`` with
    ``cov_floor = Sigma^i``), the surrogate M-step's ``[K k]`` equals the maximiser of the exact ``Q`` in
    ``[K k]`` (:func:`exact_maximiser_F`, plain numpy), so the step is an ECM step and ``log p(Y)``
    (``estep.smooth``) does not decrease; ``dQ`` (``mstep.exact_objective``) is ``>= 0`` too.
    Instances: ``n`` in 1..4, ``m`` in 1..min(n+1, 3) (so the stacked ``B`` has full column rank),
    ``T`` in 1..4, one random ``Sigma`` shared by all steps.
    """
    out = Outcome("max over steps of ||L_H^T (F_surrogate - F_Q) L_S|| / ||L_H^T F_Q L_S|| (Q's metric; held if <= "
                  f"{AGREE_TOL:g}, Sigma unchanged to {AGREE_TOL:g}, dlog p(Y) and dQ >= -{INEQ_TOL:g} max(1,|log p|))")
    infos = []
    for _ in range(instances):
        n = int(rng.integers(1, 5))
        m = int(rng.integers(1, min(n + 1, 3) + 1))
        T = int(rng.integers(1, 5))
        r = ecm_case(EcmCase(draw_instance(rng, n, m, T, shared_cov=True)))
        r.add_to(out)
        infos.append(r.info)
    if infos:
        dec = sum(i["dlogp"] < 0 for i in infos)
        out.notes.append(
            f"max plain relative difference max|dF|/max|F_Q| {max(i['plain'] for i in infos):.2g}; max Sigma change "
            f"{max(i['sigma_change'] for i in infos):.2g}; log p(Y) decreased on {dec}/{len(infos)} (any decrease, before the tolerance); "
            f"min dlog p(Y)/max(1,|log p|) {min(i['dlogp'] for i in infos):.3g}, min dQ {min(i['dQ'] for i in infos):.3g}")
    return out, None


# --------------------------------------------------------------------------- the smoother against its oracle


def smoother_case(inst: Instance) -> CaseResult:
    """One instance of :func:`smoother_oracle`; ``info`` holds the four errors."""
    e = smoother_errors(inst.sm, dense_posterior(inst.model, inst.policy, inst.y, inst.mu0, inst.P0))
    info = {"mean": e.mean, "cov": e.cov, "cross": e.cross, "loglik": e.loglik}
    return CaseResult(e.worst <= SMOOTHER_TOL, e.worst,
                      {"n": inst.model.n, "m": inst.model.m, "T": inst.model.T, **info}, info=info)


def smoother_oracle(rng, instances: int, full: bool = False):
    """Implementation (docs/math.md §4): ``estep.smooth`` agrees with dense conditioning of the joint
    Gaussian of ``(s_0..s_T, y_0..y_{T-1})`` on ``Y`` — means, ``P_t|T``, ``P_{t+1,t|T}`` whitened by the
    oracle's ``P_t|T`` and ``log p(Y)`` relative to ``max(1, |log p|)``, all to ``SMOOTHER_TOL``.
    Instances: ``n`` in 1..3, ``m`` in 1..2, ``T`` in 1..5, ``Y`` drawn from the model.
    """
    out = Outcome(f"max of the whitened errors of the means, P_t|T, P_(t+1,t)|T and the relative error of log p(Y) "
                  f"(held if <= {SMOOTHER_TOL:g})")
    worst = {"mean": 0.0, "cov": 0.0, "cross": 0.0, "loglik": 0.0}
    for _ in range(instances):
        n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(1, 6))
        r = smoother_case(draw_instance(rng, n, m, T))
        r.add_to(out)
        worst = {k: max(v, r.info[k]) for k, v in worst.items()}
    out.notes.append("worst errors: " + ", ".join(f"{k} {v:.2g}" for k, v in worst.items()))
    return out, None
