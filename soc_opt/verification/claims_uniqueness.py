"""Claim 1: uniqueness of the M-step maximiser (Theorem "uniqueness", docs/math.md §5, §9).

With theta_k = [K_k k_k] (m x (n+1)), stilde = (s, 1), Stilde_k = E[stilde stilde^T | Y],
B_k = [B_k; By_k] and H_k = B_k^T So_k^{-1} B_k, the surrogate is
  Lbar_k = -1/2 tr(So^{-1} (Szz - C Szs^T - Szs C^T + C Stilde C^T + B Sigma B^T)) - 1/2 log|So|,
  C = [As_k + B K_k, co_k + B k_k]  (so that C stilde = As s + co + B theta stilde),
whose Hessian in vec(theta) (column-major) is  -(Stilde_k kron H_k).
Stilde_k > 0  <=>  P_k > 0 (Schur complement), so the Hessian is negative definite iff
H_k > 0 (B_k full column rank) and P_k > 0.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..estep import moments, smooth
from ..linalg import schur_pd_margin, unvec
from ..models import AugmentedModel, LinearGaussianPolicy, Smoothed, symmetrize
from ..testing import random_augmented_model, random_initial_state, random_policy, sample_model_trajectory
from .common import ClaimResult, child_rng, logdet, mstep_module, tolist
from .hypotheses import require_standing_hypotheses

__all__ = ["claim1_uniqueness", "surrogate_hessian", "hessian_nd_margin", "step_hessian_nd_margin"]


def _H(model: AugmentedModel, k: int) -> np.ndarray:
    B = model.Bs[k]
    return symmetrize(B.T @ cho_solve(cho_factor(model.So[k], lower=True), B))


def surrogate_hessian(model: AugmentedModel, Sss_k: np.ndarray, k: int) -> np.ndarray:
    """Analytic Hessian of ``Lbar_k`` w.r.t. ``vec([K_k k_k])`` (column-major): ``-(Stilde_k kron H_k)``.

    ``Sss_k`` is ``E[(s_k,1)(s_k,1)^T | Y]`` (``Moments.Sss[k]``).
    """
    return -np.kron(symmetrize(np.asarray(Sss_k, dtype=float)), _H(model, k))


def _lbar(model: AugmentedModel, mom, k: int, K: np.ndarray, kk: np.ndarray, Sigma: np.ndarray) -> float:
    """Independent evaluation of the paper's ``Lbar_k`` (docs/math.md §5) from moments."""
    B = model.Bs[k]
    C = np.concatenate([model.As[k] + B @ K, (model.co[k] + B @ kk)[:, None]], axis=1)
    E = mom.Szz[k] - C @ mom.Szs[k].T - mom.Szs[k] @ C.T + C @ mom.Sss[k] @ C.T + B @ Sigma @ B.T
    F = cho_factor(model.So[k], lower=True)
    return float(-0.5 * np.trace(cho_solve(F, symmetrize(E))) - 0.5 * logdet(model.So[k], "So_k"))


def _theta_unvec(v: np.ndarray, m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``vec([K k])`` (column-major) -> ``(K (m, n), k (m,))``."""
    th = unvec(v, m, n + 1)
    return th[:, :n].copy(), th[:, n].copy()


def hessian_nd_margin(Hs: np.ndarray, m: int, rel_tol: float) -> tuple[float, bool]:
    """Scale-free test that a Hessian in ``vec([K k])`` is negative definite: ``(margin, ok)``.

    ``margin = -schur_pd_margin(-Hs, split at the offset block)``: the offset block (``-H_k`` times
    the corner 1 of ``Stilde``) and its Schur complement (``-(P_k kron H_k)``) are each measured against
    their own largest eigenvalue, so rescaling the state or shifting its mean leaves the verdict alone
    (``lambda_max / ||Hs||`` would shrink like ``1 / |mean|^4``).  ``ok``: ``margin < -rel_tol``.
    """
    M = -symmetrize(np.asarray(Hs, dtype=float))
    margin = -float(schur_pd_margin(M, M.shape[0] - m))
    return margin, bool(margin < -rel_tol)


def step_hessian_nd_margin(model: AugmentedModel, Sss_k: np.ndarray, k: int, rel_tol: float) -> tuple[float, bool]:
    """:func:`hessian_nd_margin` of the per-step Hessian ``-(Stilde_k kron H_k)``, computed from its two factors.

    For a Kronecker product the offset-block ratio is ``r_H = lambda_min/lambda_max(H_k)`` and the
    Schur-complement ratio (``P_k kron H_k``) is ``r_H r_P`` with ``r_P`` the ratio of ``P_k``, so the
    margin is ``r_H * min(1, r_P)``.  Taking it from the factors avoids the rounding of the assembled
    Kronecker product (``eps |mean|^2 ||H_k||``), which would hide a small ``lambda_min(H_k) lambda_min(P_k)``.
    """
    w = np.linalg.eigvalsh(_H(model, k))
    r_h = float(w[0] / max(abs(w).max(), 1e-300))
    r_p = float(schur_pd_margin(np.asarray(Sss_k, dtype=float), model.n))
    margin = -(r_h * r_p if r_h > 0 and r_p > 0 else min(r_h, r_p))
    return margin, bool(margin < -rel_tol)


def _claim1_instance(rng: np.random.Generator, *, b_rank_deficient: bool = False):
    n = int(rng.integers(1, 5))
    if b_rank_deficient:
        m = int(rng.integers(2, 4))
    else:
        m = int(rng.integers(1, min(3, n + 1) + 1))
    T = int(rng.integers(2, 6))
    model = random_augmented_model(rng, n, m, T, b_rank=m - 1 if b_rank_deficient else None)
    policy = random_policy(rng, T, n, m)
    mu0, P0 = random_initial_state(rng, n)
    require_standing_hypotheses(model, mu0, P0)
    _, y = sample_model_trajectory(rng, model, policy, mu0, P0)
    return model, policy, mu0, P0, y


def _known_component_smoothed(sm: Smoothed, steps, value: float = 1.0) -> Smoothed:
    """Copy of ``sm`` in which state component 0 is known exactly (= ``value``) at ``steps``.

    Zeroing row/column 0 of ``P_k`` and of the lag-one cross-covariances keeps the joint
    Gaussian of the trajectory valid (it is ``D Sigma D`` with ``D`` a 0/1 diagonal).
    """
    mean, cov, cross = np.array(sm.mean), np.array(sm.cov), np.array(sm.cross)
    for k in steps:
        mean[k, 0] = value
        cov[k, 0, :] = 0.0
        cov[k, :, 0] = 0.0
        if k < len(cross):
            cross[k, :, 0] = 0.0
        if k >= 1:
            cross[k - 1, 0, :] = 0.0
    return Smoothed(mean, cov, cross, sm.loglik)


def _singularity_scan(model, mom, rel_tol: float) -> tuple[float, bool, bool]:
    """Per-step Hessians of an ill-posed instance: ``(largest margin, every step singular,
    time-invariant sum negative definite)``."""
    worst, singular_all, Hsum = -np.inf, True, 0.0
    for k in range(model.T):
        Hk = surrogate_hessian(model, mom.Sss[k], k)
        lam, ok = step_hessian_nd_margin(model, mom.Sss[k], k, rel_tol)
        singular_all &= not ok
        worst = max(worst, lam)
        Hsum = Hsum + Hk
    return worst, singular_all, hessian_nd_margin(Hsum, model.m, rel_tol)[1]


def claim1_uniqueness(seed: int = 0, instances: int = 20, *, fd_instances: int = 5, rel_tol: float = 1e-10) -> list[ClaimResult]:
    """Claim 1 (Theorem "uniqueness"): the M-step Hessian of ``Lbar_k`` in ``vec([K_k k_k])``.

    Well-posed instances (``random_augmented_model`` with ``B_k`` full column rank, smoothed
    ``P_k > 0`` from ``estep.smooth`` on ``y`` drawn from the model): per-step and time-invariant
    (``sum_k``) Hessians must be negative definite.  Ill-posed instances: ``[B_k; By_k]``
    rank ``m-1`` (same null vector at every step), and a state component known exactly
    (``P_k`` singular; smoothed moments edited, see :func:`_known_component_smoothed`): the
    Hessians must be singular (not negative definite), and an explicit pair of distinct
    maximisers with equal surrogate is reported.  Finally the analytic Hessian is compared
    with central finite differences of ``mstep.surrogate`` (and with ``mstep.surrogate_grad_hess``
    where available).

    ``rel_tol``: negative definite means scale-free margin ``< -rel_tol`` (see :func:`hessian_nd_margin`).
    """
    rng = child_rng(seed, 1)
    wellposed_rows, wellposed = _wellposed_rows(rng, instances, rel_tol)
    return [
        *wellposed_rows,
        _rank_deficient_row(rng, instances, rel_tol),
        _singular_p_row(wellposed, rel_tol),
        # finite-difference cross-check of the analytic Hessian against mstep
        _claim1_fd_row(wellposed[: max(0, min(fd_instances, instances))]),
    ]


def _wellposed_rows(rng: np.random.Generator, instances: int, rel_tol: float):
    """Rows 1a (per-step) and 1b (time-invariant), and the instances ``(model, policy, sm, y, mom)``."""
    pk_worst, pk_held, pk_ce = -np.inf, 0, None
    ti_worst, ti_held, ti_ce = -np.inf, 0, None
    wellposed = []
    for _ in range(instances):
        model, policy, mu0, P0, y = _claim1_instance(rng)
        sm = smooth(model, policy, y, mu0, P0)
        mom = moments(sm, y)
        wellposed.append((model, policy, sm, y, mom))
        worst_k, ok_all, Hsum = -np.inf, True, 0.0
        for k in range(model.T):
            Hk = surrogate_hessian(model, mom.Sss[k], k)
            lam, ok = step_hessian_nd_margin(model, mom.Sss[k], k, rel_tol)
            Hsum = Hsum + Hk
            if lam > worst_k:
                worst_k, k_worst = lam, k
            ok_all &= ok
        pk_worst = max(pk_worst, worst_k)
        small = tolist({"n": model.n, "m": model.m, "T": model.T, "step": k_worst, "margin": worst_k,
                        "B": model.Bs[k_worst], "So": model.So[k_worst], "P_k": sm.cov[k_worst]})
        if ok_all:
            pk_held += 1
        elif pk_ce is None:
            pk_ce = small
        lam, ok = hessian_nd_margin(Hsum, model.m, rel_tol)
        ti_worst = max(ti_worst, lam)
        if ok:
            ti_held += 1
        elif ti_ce is None:
            ti_ce = small
    rows = [ClaimResult(
        "1a uniqueness: well-posed, per-step",
        "B_k = [B_k; By_k] full column rank and smoothed P_k > 0: every per-step Hessian of Lbar_k "
        "w.r.t. vec([K_k k_k]) is negative definite (unique maximiser)",
        instances, pk_held, pk_worst,
        f"max over instances and steps of the scale-free margin -min(lambda_min/lambda_max of H_k-block, of its Schur complement) "
        f"of the Hessian (held if < -{rel_tol:g})",
        pk_ce, "Hessian = -(Stilde_k kron H_k), Stilde_k = E[(s,1)(s,1)^T|Y], H_k = B_k^T So_k^-1 B_k; "
        "n in 1..4, m in 1..min(3, n+1), T in 2..5",
    ), ClaimResult(
        "1b uniqueness: well-posed, time-invariant",
        "same instances: the time-invariant Hessian sum_k Hess_k (one [K k] shared by all steps) is negative definite",
        instances, ti_held, ti_worst,
        f"max over instances of the scale-free margin of sum_k Hessian_k (held if < -{rel_tol:g})",
        ti_ce, "",
    )]
    return rows, wellposed


def _rank_deficient_row(rng: np.random.Generator, instances: int, rel_tol: float) -> ClaimResult:
    """Row 1c: ``[B_k; By_k]`` of rank ``m-1`` on fresh instances."""
    bd_worst, bd_held, bd_ti_held, bd_ce, bd_raised = -np.inf, 0, 0, None, 0
    for _ in range(instances):
        model, policy, mu0, P0, y = _claim1_instance(rng, b_rank_deficient=True)
        sm = smooth(model, policy, y, mu0, P0)
        mom = moments(sm, y)
        lam, singular_all, ok_ti = _singularity_scan(model, mom, rel_tol)
        bd_worst = max(bd_worst, lam)
        if singular_all:
            bd_held += 1
        if not ok_ti:
            bd_ti_held += 1
        if bd_ce is None and singular_all:
            bd_ce = _nonuniqueness_example(model, policy, sm, y, mom, kind="rank_deficient_B")
        bd_raised += _mstep_rejects(model, sm, y)
    return ClaimResult(
        "1c ill-posed: rank-deficient B (counterexample)",
        "[B_k; By_k] of rank m-1: the Hessian is singular (NOT negative definite) at every step and the "
        "maximiser is not unique; 'held' counts instances where this was detected",
        instances, bd_held, bd_worst,
        f"largest scale-free margin seen over instances and steps (held if >= -{rel_tol:g}, i.e. ~0)",
        bd_ce, f"time-invariant sum also singular on {bd_ti_held}/{instances} (shared null vector of B); "
        "counterexample: two distinct maximisers [K k] with equal surrogate; mstep.maximize raised "
        f"NonUniqueMaximizerError on {bd_raised}/{instances}",
    )


def _singular_p_row(wellposed, rel_tol: float) -> ClaimResult:
    """Row 1d: the well-posed instances with state component 0 known exactly (``P_k`` singular)."""
    instances = len(wellposed)
    sp_worst, sp_held, sp_ti_held, sp_ce, sp_raised = -np.inf, 0, 0, None, 0
    one_step_ti_nd = 0
    for model, policy, sm, y, _ in wellposed:
        sm_all = _known_component_smoothed(sm, range(model.T + 1))
        mom = moments(sm_all, y)
        lam, singular_all, ok_ti = _singularity_scan(model, mom, rel_tol)
        sp_worst = max(sp_worst, lam)
        if singular_all:
            sp_held += 1
        if not ok_ti:
            sp_ti_held += 1
        if sp_ce is None and singular_all:
            sp_ce = _nonuniqueness_example(model, policy, sm_all, y, mom, kind="known_state_component")
        sp_raised += _mstep_rejects(model, sm_all, y)
        # singular at step 0 only: the time-invariant sum stays negative definite
        mom1 = moments(_known_component_smoothed(sm, [0], value=float(sm.mean[0, 0])), y)
        H1 = sum(surrogate_hessian(model, mom1.Sss[k], k) for k in range(model.T))
        if hessian_nd_margin(H1, model.m, rel_tol)[1]:
            one_step_ti_nd += 1
    return ClaimResult(
        "1d ill-posed: singular P_k (counterexample)",
        "state component 0 known exactly (= 1) at every step, so P_k is singular: the per-step and "
        "time-invariant Hessians are singular and [K k] is not unique ('held' counts detections)",
        instances, sp_held, sp_worst,
        f"largest scale-free margin seen (held if >= -{rel_tol:g}, i.e. ~0)",
        sp_ce, f"time-invariant sum singular on {sp_ti_held}/{instances}; with P singular at step 0 only, "
        f"the time-invariant Hessian is still negative definite on {one_step_ti_nd}/{instances} "
        "(the time-invariant condition is weaker than per-step P_k > 0); mstep.maximize raised "
        f"NonUniqueMaximizerError on {sp_raised}/{instances}",
    )


def _nonuniqueness_example(model, policy, sm, y, mom, *, kind: str) -> dict:
    """Two distinct maximisers of Lbar_0 with equal value (step 0), as a small dict."""
    k = 0
    n, m = model.n, model.m
    Hk = surrogate_hessian(model, mom.Sss[k], k)
    w, V = np.linalg.eigh(symmetrize(Hk))
    v = V[:, -1]  # direction of the (near) zero eigenvalue
    # minimum-norm stationary point: -Hess theta = B^T So^-1 E[(zeta - As s - co) stilde^T]
    So_f = cho_factor(model.So[k], lower=True)
    B = model.Bs[k]
    R = mom.Szs[k] - np.concatenate([model.As[k], model.co[k][:, None]], axis=1) @ mom.Sss[k]
    rhs = (B.T @ cho_solve(So_f, R)).ravel(order="F")
    theta1 = np.linalg.lstsq(-Hk, rhs, rcond=1e-10)[0]
    theta2 = theta1 + v * max(1.0, np.linalg.norm(theta1))
    Sig = policy.cov[k]
    K1, k1 = _theta_unvec(theta1, m, n)
    K2, k2 = _theta_unvec(theta2, m, n)
    out = {
        "kind": kind, "n": n, "m": m, "step": k,
        "B": B, "So": model.So[k], "P_k": sm.cov[k], "s_hat_k": sm.mean[k],
        "hessian_eigenvalues": w,
        "null_direction_vec_Kk": v,
        "K1": K1, "k1": k1, "K2": K2, "k2": k2,
        "Lbar_at_1": _lbar(model, mom, k, K1, k1, Sig),
        "Lbar_at_2": _lbar(model, mom, k, K2, k2, Sig),
    }
    out.update(_mstep_surrogate_pair(model, policy, sm, y, k, ((K1, k1), (K2, k2))))
    return tolist(out)


def _mstep_surrogate_pair(model, policy, sm, y, k: int, thetas) -> dict:
    """``mstep.surrogate`` at step ``k`` for the two maximisers ``thetas`` (an error is reported, not raised)."""
    ms = mstep_module()
    if ms is None or not hasattr(ms, "surrogate"):
        return {}
    out = {}
    try:
        pol = []
        for KK, kkk in thetas:
            Kall = np.array(policy.K)
            kall = np.array(policy.k)
            Kall[k], kall[k] = KK, kkk
            pol.append(LinearGaussianPolicy(Kall, kall, policy.cov))
        out["mstep_surrogate_at_1"] = float(ms.surrogate(model, sm, y, pol[0])[k])
        out["mstep_surrogate_at_2"] = float(ms.surrogate(model, sm, y, pol[1])[k])
    except Exception as exc:  # report, do not fail the row
        out["mstep_surrogate_error"] = f"{type(exc).__name__}: {exc}"
    return out


def _mstep_rejects(model, sm, y) -> int:
    """1 if ``mstep.maximize`` (closed form, cov floor 0.1 I) raises ``NonUniqueMaximizerError``, else 0."""
    ms = mstep_module()
    if ms is None or not hasattr(ms, "NonUniqueMaximizerError"):
        return 0
    try:
        ms.maximize(model, moments(sm, y), constraints=ms.MStepConstraints(cov_floor=0.1), min_norm=False)
    except ms.NonUniqueMaximizerError:
        return 1
    return 0


def fd_hessian_vec(f, d: int, h: float) -> np.ndarray:
    """Central second differences at 0 of a vector-valued ``f: R^d -> R^T``: returns ``(T, d, d)``.

    Exact for quadratics up to rounding.
    """
    E = np.eye(d) * h
    f0 = f(np.zeros(d))
    Hs = np.zeros((len(f0), d, d))
    for i in range(d):
        Hs[:, i, i] = (f(E[i]) - 2 * f0 + f(-E[i])) / h**2
        for j in range(i + 1, d):
            Hs[:, i, j] = Hs[:, j, i] = (f(E[i] + E[j]) - f(E[i] - E[j]) - f(E[j] - E[i]) + f(-E[i] - E[j])) / (4 * h**2)
    return Hs


def _claim1_fd_row(cases) -> ClaimResult:
    """Row 1e: analytic Hessian vs central second differences of ``mstep.surrogate``."""
    ms = mstep_module()
    tol = 1e-6
    if ms is None or not hasattr(ms, "surrogate"):
        return ClaimResult(
            "1e Hessian vs finite differences", "mstep.surrogate not available", 0, 0, float("nan"),
            "max relative error", None, "soc_opt.mstep missing: cross-check skipped",
        )
    worst, held, ce, tried = 0.0, 0, None, 0
    own_worst = 0.0
    gh_worst, gh_note = 0.0, "mstep.surrogate_grad_hess not available"
    for model, policy, sm, y, mom in cases:
        n, m, T = model.n, model.m, model.T
        # Lbar_k depends on phi_k only, so one perturbation of every step's [K_k k_k] along the
        # same coordinate gives the T second differences at once.
        F0 = np.concatenate([policy.K, policy.k[:, :, None]], axis=2)  # (T, m, n+1)

        def f(v):
            F = F0 + v.reshape((m, n + 1), order="F")[None]
            return np.asarray(ms.surrogate(model, sm, y, LinearGaussianPolicy(F[..., :n], F[..., n], policy.cov)))

        Hfd = fd_hessian_vec(f, m * (n + 1), 1e-2)  # (T, d, d)
        ok_case = True
        vals0 = f(np.zeros(m * (n + 1)))
        for k in range(T):
            Han = surrogate_hessian(model, mom.Sss[k], k)
            err = float(np.abs(Hfd[k] - Han).max() / np.abs(Han).max())
            worst = max(worst, err)
            if err > tol:
                ok_case = False
                if ce is None:
                    ce = tolist({"n": n, "m": m, "step": k, "analytic": Han, "finite_difference": Hfd[k], "rel_err": err})
            own = _lbar(model, mom, k, policy.K[k], policy.k[k], policy.cov[k])
            own_worst = max(own_worst, abs(own - vals0[k]) / max(1.0, abs(own)))
            if hasattr(ms, "surrogate_grad_hess"):
                try:
                    Hm = np.asarray(ms.surrogate_grad_hess(model, mom, k, policy).hess, dtype=float)
                    gh_worst = max(gh_worst, float(np.abs(Hm - Han).max() / np.abs(Han).max()))
                    gh_note = f"mstep.surrogate_grad_hess Hessian vs analytic: max rel. error {gh_worst:.1e}"
                except Exception as exc:  # report only
                    gh_note = f"mstep.surrogate_grad_hess failed: {type(exc).__name__}: {exc}"
        tried += 1
        held += ok_case
    return ClaimResult(
        "1e Hessian vs finite differences",
        "analytic Hessian -(Stilde_k kron H_k) agrees with central second differences (step 1e-2) of "
        "mstep.surrogate in vec([K_k k_k]) at every step",
        tried, held, worst,
        f"max relative error max|H_fd - H|/max|H| (held if <= {tol:g})",
        ce, f"own Lbar_k vs mstep.surrogate values: max rel. difference {own_worst:.1e}; {gh_note}",
    )
