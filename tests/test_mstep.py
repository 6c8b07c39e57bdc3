"""Tests of the M-step (docs/math.md §5, §9 claims 1-2).

Instances are built directly (no smoother): a random augmented model with PD ``So`` and a
random joint Gaussian over ``(s_0, ..., s_T)`` whose blocks give the smoothed means,
covariances and lag-one cross-covariances, so the moments are those of a valid distribution.
Oracles: exact Gaussian expectations written out in the test from the definitions, finite
differences, CVXPY with Clarabel/SCS, KKT conditions from CVXPY duals, random perturbations,
``numpy.linalg.lstsq`` for minimum-norm solutions.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.stats import multivariate_normal

from soc_opt import errors as soc_errors
from soc_opt.config import ConfigError
from soc_opt.estep import moments
from soc_opt.models import AugmentedModel, LinearGaussianPolicy, ShapeError
from soc_opt.mstep import (
    ClosedFormUnavailableError,
    InfeasibleConstraintsError,
    MStepConfig,
    MStepConstraints,
    NonUniqueMaximizerError,
    SolverError,
    exact_objective,
    exact_objective_from_moments,
    maximize,
    surrogate,
    surrogate_from_moments,
    surrogate_grad_hess,
)
from soc_opt.mstep.cvx import CACHE
from soc_opt.mstep.exact_em import sigma_exact
from soc_opt.testing import random_smoothed, random_spd

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
LOG2PI = np.log(2 * np.pi)


# --------------------------------------------------------------------------- instances


def random_model(rng, n, m, T, *, deficient_step=None):
    """Random augmented model; at ``deficient_step`` the action columns are rank 1."""
    Ao = rng.normal(size=(T, n + 1, n + m)) / np.sqrt(n + m)
    if deficient_step is not None and m > 1:
        Ao[deficient_step, :, n + 1 :] = Ao[deficient_step, :, n : n + 1] * rng.normal(size=m - 1)
    co = rng.normal(size=(T, n + 1))
    So = np.stack([random_spd(rng, n + 1, floor=0.2) for _ in range(T)])
    return AugmentedModel(Ao, co, So, n)


def random_policy(rng, T, n, m, var=0.5):
    K = 0.3 * rng.normal(size=(T, m, n))
    k = rng.normal(size=(T, m))
    cov = np.stack([random_spd(rng, m, floor=0.05) * var for _ in range(T)])
    return LinearGaussianPolicy(K, k, cov)


def instance(seed, n=3, m=2, T=4, **kw):
    rng = np.random.default_rng(seed)
    model = random_model(rng, n, m, T, deficient_step=kw.pop("deficient_step", None))
    sm = random_smoothed(rng, n, T, **kw)
    y = rng.uniform(0.05, 1.0, size=sm.mean.shape[:-2] + (T,))
    return model, sm, y, moments(sm, y), rng


def quad_terms(model, mom):
    """Test-side ``H_k``, ``R_k``, ``Stilde_k`` written from docs/math.md §5."""
    B = model.Bs
    Atil = np.concatenate([model.As, model.co[..., None]], axis=-1)
    Soi = np.linalg.inv(model.So)
    H = np.einsum("tia,tij,tjb->tab", B, Soi, B)
    R = np.einsum("tia,tij,tjc->tac", B, Soi, mom.Szs - Atil @ mom.Sss)
    return H, R, mom.Sss


def F_of(policy):
    return np.concatenate([policy.K, policy.k[..., None]], axis=-1)


def policy_from(F, cov, allow_singular=False):
    n = F.shape[-1] - 1
    return LinearGaussianPolicy(F[..., :n], F[..., n], cov, allow_singular=allow_singular)


def rel_err(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


# --------------------------------------------------------------------------- objectives vs oracles


def _joint_pair(sm, k):
    """Mean and covariance of ``(s_k, s_{k+1})`` for one (unbatched) smoothed sequence."""
    mu = np.concatenate([sm.mean[k], sm.mean[k + 1]])
    n = sm.n
    C = np.zeros((2 * n, 2 * n))
    C[:n, :n], C[n:, n:] = sm.cov[k], sm.cov[k + 1]
    C[n:, :n] = sm.cross[k]
    C[:n, n:] = sm.cross[k].T
    return mu, C


@SETTINGS
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3))
def test_surrogate_equals_gaussian_expectation_of_its_definition(seed, n, m):
    model, sm, y, mom, rng = instance(seed, n, m, T=3)
    pol = random_policy(rng, 3, n, m)
    got = surrogate(model, sm, y, pol)
    for k in range(3):
        # e = zeta - Ao z - co is affine in v = (s_k, s_{k+1}, w): e = D v + d
        mu, C = _joint_pair(sm, k)
        Lw = np.linalg.cholesky(pol.cov[k])
        As, B = model.As[k], model.Bs[k]
        D = np.zeros((n + 1, 2 * n + m))
        D[:n, n : 2 * n] = np.eye(n)
        D[:, :n] = -As - B @ pol.K[k]
        D[:, 2 * n :] = -B @ Lw
        d = -model.co[k] - B @ pol.k[k]
        d[n] += y[k]
        muv = np.concatenate([mu, np.zeros(m)])
        Cv = np.zeros((2 * n + m, 2 * n + m))
        Cv[: 2 * n, : 2 * n], Cv[2 * n :, 2 * n :] = C, np.eye(m)
        Soi = np.linalg.inv(model.So[k])
        me = D @ muv + d
        quad = np.trace(Soi @ D @ Cv @ D.T) + me @ Soi @ me
        want = -0.5 * quad - 0.5 * np.linalg.slogdet(model.So[k])[1]
        assert got[k] == pytest.approx(want, rel=1e-10, abs=1e-10)


@SETTINGS
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3))
def test_exact_objective_equals_expected_log_density(seed, n, m):
    model, sm, y, mom, rng = instance(seed, n, m, T=3)
    pol = random_policy(rng, 3, n, m)
    got = exact_objective(model, sm, y, pol)
    for k in range(3):
        mu, C = _joint_pair(sm, k)
        B = model.Bs[k]
        Mk = model.As[k] + B @ pol.K[k]
        S = model.So[k] + B @ pol.cov[k] @ B.T
        # residual r = zeta - M s_k - m_k, affine in (s_k, s_{k+1})
        D = np.zeros((n + 1, 2 * n))
        D[:n, n:] = np.eye(n)
        D[:, :n] = -Mk
        d = -(B @ pol.k[k] + model.co[k])
        d[n] += y[k]
        mr, Cr = D @ mu + d, D @ C @ D.T
        want = multivariate_normal(np.zeros(n + 1), S).logpdf(mr) - 0.5 * np.trace(np.linalg.solve(S, Cr))
        assert got[k] == pytest.approx(want, rel=1e-10, abs=1e-10)


@SETTINGS
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3), M=st.sampled_from([None, 3]))
def test_surrogate_is_jensen_lower_bound_of_exact_objective(seed, n, m, M):
    model, sm, y, mom, rng = instance(seed, n, m, T=4, M=M)
    for var in (0.01, 1.0, 10.0):
        pol = random_policy(rng, 4, n, m, var=var)
        lower = surrogate_from_moments(model, mom, pol) - 0.5 * (n + 1) * LOG2PI
        exact = exact_objective_from_moments(model, mom, pol)
        assert np.all(lower <= exact + 1e-10 * np.abs(exact))
        assert np.allclose(lower, surrogate_from_moments(model, mom, pol, include_constant=True))


# --------------------------------------------------------------------------- derivatives (claim 1)


@settings(max_examples=10, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3))
def test_grad_hess_match_finite_differences(seed, n, m):
    T = 3
    model, sm, y, mom, rng = instance(seed, n, m, T=T)
    pol = random_policy(rng, T, n, m)
    k = int(rng.integers(T))
    gh = surrogate_grad_hess(model, mom, k, pol)
    F0 = F_of(pol)
    d = m * (n + 1)

    def L(v, cov=None):
        F = F0.copy()
        F[k] = v.reshape((m, n + 1), order="F")
        c = pol.cov if cov is None else cov
        return surrogate_from_moments(model, mom, policy_from(F, c))[k]

    v0, h = F0[k].reshape(-1, order="F"), 1e-3
    E = np.eye(d)
    g_fd = np.array([(L(v0 + h * E[i]) - L(v0 - h * E[i])) / (2 * h) for i in range(d)])
    H_fd = np.empty((d, d))
    for i in range(d):
        for j in range(d):
            H_fd[i, j] = (L(v0 + h * (E[i] + E[j])) - L(v0 + h * (E[i] - E[j]))
                          - L(v0 - h * (E[i] - E[j])) + L(v0 - h * (E[i] + E[j]))) / (4 * h * h)
    scale = max(1.0, abs(L(v0)))
    assert np.abs(g_fd - gh.grad).max() <= 1e-7 * scale
    assert np.abs(H_fd - gh.hess).max() <= 1e-5 * scale
    # Sigma: directional derivative along a symmetric direction
    Ed = rng.normal(size=(m, m))
    Ed = Ed + Ed.T
    cp_, cm_ = np.array(pol.cov), np.array(pol.cov)
    cp_[k] += h * Ed
    cm_[k] -= h * Ed
    dir_fd = (L(v0, cp_) - L(v0, cm_)) / (2 * h)
    assert dir_fd == pytest.approx(np.sum(gh.grad_sigma * Ed), rel=1e-7, abs=1e-9)


@SETTINGS
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3))
def test_hessian_negative_definite_for_full_rank_B_and_pd_P(seed, n, m):
    assume(m <= n + 1)  # B is (n+1) x m: full column rank needs m <= n+1
    model, sm, y, mom, rng = instance(seed, n, m, T=3)
    pol = random_policy(rng, 3, n, m)
    for k in range(3):
        ev = np.linalg.eigvalsh(surrogate_grad_hess(model, mom, k, pol).hess)
        assert ev[-1] < 0


def test_hessian_singular_for_rank_deficient_B():
    model, sm, y, mom, rng = instance(1, 3, 2, T=3, deficient_step=1)
    assert np.linalg.matrix_rank(model.Bs[1]) == 1
    pol = random_policy(rng, 3, 3, 2)
    ev = np.linalg.eigvalsh(surrogate_grad_hess(model, mom, 1, pol).hess)
    assert ev[-1] >= -1e-12 * np.abs(ev).max()  # not negative definite: a zero eigenvalue
    assert np.linalg.eigvalsh(surrogate_grad_hess(model, mom, 0, pol).hess)[-1] < 0


def test_hessian_singular_for_singular_P():
    model, sm, y, mom, rng = instance(2, 3, 2, T=3, singular_step=2)
    assert np.abs(sm.cov[2]).max() == 0.0
    pol = random_policy(rng, 3, 3, 2)
    ev = np.linalg.eigvalsh(surrogate_grad_hess(model, mom, 2, pol).hess)
    assert ev[-1] >= -1e-12 * np.abs(ev).max()
    assert np.linalg.eigvalsh(surrogate_grad_hess(model, mom, 1, pol).hess)[-1] < 0


# --------------------------------------------------------------------------- closed form


@SETTINGS
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3),
       cons=st.sampled_from(["floor_scalar", "floor_matrix", "entropy"]))
def test_closed_form_is_a_maximum_under_random_perturbations(seed, n, m, cons):
    assume(m <= n + 1)  # B is (n+1) x m: full column rank needs m <= n+1
    T = 3
    model, sm, y, mom, rng = instance(seed, n, m, T=T)
    Smin = random_spd(rng, m, floor=0.05)
    c = float(rng.normal())
    C = {"floor_scalar": MStepConstraints(cov_floor=0.2), "floor_matrix": MStepConstraints(cov_floor=Smin),
         "entropy": MStepConstraints(entropy_floor=c)}[cons]
    pol = maximize(model, moments(sm, y), constraints=C, min_norm=False).policy
    best = surrogate(model, sm, y, pol)
    H, R, S = quad_terms(model, mom)
    # first-order condition, test-side formula
    G = R - H @ F_of(pol) @ S
    assert np.abs(G).max() <= 1e-9 * max(1.0, np.abs(R).max())
    if cons == "entropy":
        assert np.allclose(np.linalg.slogdet(pol.cov)[1], c, atol=1e-10)
    for _ in range(20):
        F = F_of(pol) + 10.0 ** rng.uniform(-4, 0) * rng.normal(size=(T, m, n + 1))
        X = rng.normal(size=(T, m, m)) * 10.0 ** rng.uniform(-4, 0)
        X = X @ np.swapaxes(X, 1, 2)
        if cons == "entropy":  # any feasible Sigma on the constraint surface log det = c
            cov = pol.cov + X + 1e-3 * np.eye(m)
            cov = cov * np.exp((c - np.linalg.slogdet(cov)[1]) / m)[:, None, None]
        else:  # any Sigma above the floor
            cov = pol.cov + X
        val = surrogate(model, sm, y, policy_from(F, cov))
        assert np.all(val <= best + 1e-10 * np.abs(best))


def test_time_invariant_closed_form_satisfies_summed_normal_equations():
    model, sm, y, mom, rng = instance(5, 3, 2, T=5)
    pol = maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=0.3), variant="time_invariant", min_norm=False).policy
    assert np.allclose(pol.K, pol.K[0]) and np.allclose(pol.cov, pol.cov[0])
    H, R, S = quad_terms(model, mom)
    F = F_of(pol)[0]
    G = sum(R[k] - H[k] @ F @ S[k] for k in range(5))
    assert np.abs(G).max() <= 1e-9 * np.abs(R).sum(0).max()
    Hs = H.sum(0)  # entropy floor with H = sum_k H_k
    alpha = np.exp((0.3 + np.linalg.slogdet(Hs)[1]) / 2)
    assert rel_err(pol.cov[0], alpha * np.linalg.inv(Hs)) <= 1e-10


def test_time_varying_steps_decouple():
    """With moments fixed, phi_j depends only on step j's data (the sweep is separable)."""
    model, sm, y, mom, rng = instance(6, 3, 2, T=4)
    C = MStepConstraints(cov_floor=0.1)
    p1 = maximize(model, mom, constraints=C, min_norm=False).policy
    Szz, Szs = np.array(mom.Szz), np.array(mom.Szs)
    Szs[1] += 0.3
    mom2 = type(mom)(Szz, Szs, mom.Sss, mom.count)
    p2 = maximize(model, mom2, constraints=C, min_norm=False).policy
    same = [0, 2, 3]
    assert np.array_equal(p1.K[same], p2.K[same]) and not np.allclose(p1.K[1], p2.K[1])


def test_batched_moments_from_several_sequences():
    model, sm, y, mom, rng = instance(8, 2, 2, T=3, M=4)
    assert mom.count == 4
    pol = maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=0.1), min_norm=False).policy
    H, R, S = quad_terms(model, mom)
    assert np.abs(R - H @ F_of(pol) @ S).max() <= 1e-9 * np.abs(R).max()


# --------------------------------------------------------------------------- CVXPY vs closed form

CLOSED_FORM_SETS = {
    "floor": lambda rng, m: MStepConstraints(cov_floor=random_spd(rng, m, floor=0.05)),
    "floor_scalar": lambda rng, m: MStepConstraints(cov_floor=0.3),
    "entropy": lambda rng, m: MStepConstraints(entropy_floor=float(rng.normal())),
    # relaxation rule: the floor's optimum satisfies a loose ceiling
    "floor_ceiling": lambda rng, m: MStepConstraints(cov_floor=0.1, cov_ceiling=50.0),
}


def _compare(seed, n, m, T, cons, variant, solver, tol):
    model, sm, y, mom, rng = instance(seed, n, m, T=T)
    C = CLOSED_FORM_SETS[cons](rng, m)
    cf = maximize(model, mom, constraints=C, variant=variant, min_norm=False)
    cv = maximize(model, mom, constraints=C, method="cvxpy", solver=solver, variant=variant, min_norm=False)
    # optimal value reported by the solver (plus the constants it omits) vs closed form
    want = cf.objective if variant == "time_varying" else np.array([cf.objective.sum()])
    assert rel_err(cv.solver_value, want) <= tol
    # the maximised objective evaluated at the CVXPY maximiser (time-invariant: the sum over steps)
    got = cv.objective if variant == "time_varying" else np.array([cv.objective.sum()])
    assert rel_err(got, want) <= tol
    assert rel_err(F_of(cv.policy), F_of(cf.policy)) <= tol
    return cf, cv


@SETTINGS
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3),
       cons=st.sampled_from(["floor", "floor_scalar", "entropy", "floor_ceiling"]),
       variant=st.sampled_from(["time_varying", "time_invariant"]))
def test_cvxpy_clarabel_matches_closed_form(seed, n, m, cons, variant):
    assume(m <= n + 1)  # B is (n+1) x m: full column rank needs m <= n+1
    cf, cv = _compare(seed, n, m, 3, cons, variant, "CLARABEL", 1e-6)
    assert rel_err(cv.policy.cov, cf.policy.cov) <= 1e-6  # the maximiser, Sigma included (docs/math.md §5)
    assert all(s == "optimal" for s in cv.status)


@pytest.mark.parametrize("n,m", [(3, 2), (6, 2), (26, 7)])
@pytest.mark.parametrize("variant", ["time_varying", "time_invariant"])
def test_cvxpy_clarabel_entropy_floor_covariance(variant, n, m):
    """The entropy-floor maximiser alpha H^-1 lies on the curved boundary log det Sigma = c, where
    the value is flat to first order; Clarabel must still return Sigma to 1e-6 (docs/math.md §5), with
    the default MStepConfig tolerances and per-step entropy floors."""
    T = 4
    model, sm, y, mom, rng = instance(11, n, m, T=T)
    C = MStepConstraints(entropy_floor=(1.5 * rng.normal(size=T)).tolist())
    cf = maximize(model, mom, constraints=C, variant=variant, min_norm=False).policy
    cv = maximize(model, mom, constraints=C, method="cvxpy", variant=variant, min_norm=False)
    assert all(s == "optimal" for s in cv.status)
    assert rel_err(cv.policy.cov, cf.cov) <= 1e-6


def test_cvxpy_entropy_floor_uses_no_exponential_cones():
    """The entropy floor is an SDP + geometric-mean (SOC) construction, not CVXPY's log_det, and is
    DPP; its reported dual is that of log det Sigma >= c (checked against a cp.log_det reference
    solved by SCS)."""
    import cvxpy as cp

    model, sm, y, mom, rng = instance(16, 3, 2, T=2)
    C = MStepConstraints(entropy_floor=[-0.4, 0.7])
    res = maximize(model, mom, constraints=C, method="cvxpy", min_norm=False)
    prob = CACHE[("factored", 3, 2, (False, True, False), False, 0)]
    assert prob.problem.is_dpp()
    data = prob.problem.get_problem_data(cp.CLARABEL)[0]
    assert data["dims"].exp == 0 and len(data["dims"].psd) > 0
    H, R, S = quad_terms(model, mom)
    for k, c in enumerate([-0.4, 0.7]):
        Sig = cp.Variable((2, 2), PSD=True)
        ref = cp.Problem(cp.Minimize(0.5 * cp.trace(H[k] @ Sig)), [cp.log_det(Sig) >= c])
        ref.solve(solver="SCS", eps_abs=1e-10, eps_rel=1e-10, max_iters=200_000)
        nu = float(res.duals[k]["entropy_floor"])
        assert abs(nu - float(ref.constraints[0].dual_value)) <= 1e-5 * nu
        # stationarity in Sigma: -H/2 + nu Sigma^-1 = 0
        assert np.abs(-0.5 * H[k] + nu * np.linalg.inv(res.policy.cov[k])).max() <= 1e-6 * np.abs(H[k]).max()


@settings(max_examples=15, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3),
       cons=st.sampled_from(["floor", "entropy"]),
       variant=st.sampled_from(["time_varying", "time_invariant"]))
def test_cvxpy_scs_matches_closed_form(seed, n, m, cons, variant):
    assume(m <= n + 1)  # B is (n+1) x m: full column rank needs m <= n+1
    cf, cv = _compare(seed, n, m, 3, cons, variant, "SCS", 1e-4)
    assert rel_err(cv.policy.cov, cf.policy.cov) <= 1e-4


def test_relaxation_rule_for_combined_covariance_constraints():
    """Floor + entropy floor: whichever single-constraint optimum is feasible for both is returned,
    and CVXPY (which knows nothing of the rule) agrees on the value."""
    model, sm, y, mom, rng = instance(14, 3, 2, T=3)
    H, R, S = quad_terms(model, mom)
    cases = {
        "entropy inactive": (MStepConstraints(cov_floor=0.3, entropy_floor=-20.0), lambda k: 0.3 * np.eye(2)),
        "floor inactive": (MStepConstraints(cov_floor=1e-8, entropy_floor=0.5),
                           lambda k: np.exp((0.5 + np.linalg.slogdet(H[k])[1]) / 2) * np.linalg.inv(H[k])),
    }
    for name, (C, want) in cases.items():
        cf = maximize(model, mom, constraints=C, min_norm=False)
        for k in range(3):
            assert rel_err(cf.policy.cov[k], want(k)) <= 1e-10, name
        cv = maximize(model, mom, constraints=C, method="cvxpy", min_norm=False)
        assert rel_err(cv.solver_value, cf.objective) <= 1e-6, name


def test_per_step_covariance_constraints():
    """Per-step floors (as built from the previous policy's covariances) act step by step."""
    T, m = 4, 2
    model, sm, y, mom, rng = instance(15, 3, m, T=T)
    prev = random_policy(rng, T, 3, m)
    ent = np.linalg.slogdet(prev.cov)[1]
    pol = maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=ent.tolist()), min_norm=False).policy
    assert np.allclose(np.linalg.slogdet(pol.cov)[1], ent, atol=1e-10)
    cv = maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=ent.tolist()), method="cvxpy", min_norm=False).policy
    assert np.allclose(np.linalg.slogdet(cv.cov)[1], ent, atol=1e-6)
    floors = 0.5 * np.asarray(prev.cov)
    pol = maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=floors.tolist()), min_norm=False).policy
    assert np.array_equal(pol.cov, floors)
    cv = maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=floors.tolist()), method="cvxpy",
                  min_norm=False).policy
    assert rel_err(cv.cov, floors) <= 1e-6
    # time-invariant: max_k c_k, and a dominating floor
    ti = maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=ent.tolist()), variant="time_invariant",
                  min_norm=False).policy
    assert np.allclose(np.linalg.slogdet(ti.cov)[1], ent.max(), atol=1e-10)
    nested = np.stack([(1.0 + j) * np.eye(m) for j in range(T)])
    ti = maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=nested.tolist()), variant="time_invariant",
                  min_norm=False).policy
    assert np.allclose(ti.cov, T * np.eye(m))
    with pytest.raises(ValueError, match="dominates"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=floors.tolist()), variant="time_invariant", min_norm=False)
    with pytest.raises(ShapeError, match="entropy_floor"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=ent[:2].tolist()), min_norm=False)
    with pytest.raises(ShapeError, match="cov_floor"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=floors[:2].tolist()), min_norm=False)
    with pytest.raises(InfeasibleConstraintsError, match="step 2"):
        bad = np.array(floors)
        bad[2] = 10 * np.eye(m)
        MStepConstraints(cov_floor=bad.tolist(), cov_ceiling=np.eye(m).tolist())
    # per-step floors in the exact-EM step
    res = maximize(model, mom, constraints=MStepConstraints(cov_floor=floors.tolist()), objective="exact",
                                  previous=prev, config=MStepConfig(exact_max_iter=20), min_norm=False)
    assert all(np.linalg.eigvalsh(res.policy.cov[k] - floors[k])[0] >= -1e-10 for k in range(T))


def test_cvxpy_problem_is_built_once_and_dpp():
    model, sm, y, mom, rng = instance(12, 2, 2, T=3)
    C = MStepConstraints(cov_floor=0.2, offset_bound=0.1)
    maximize(model, mom, constraints=C, method="cvxpy", min_norm=False)
    keys = set(CACHE)
    built = {k: id(v.problem) for k, v in CACHE.items()}
    model2, sm2, y2, mom2, _ = instance(13, 2, 2, T=5)
    maximize(model2, mom2, constraints=C, method="cvxpy", min_norm=False)
    assert set(CACHE) == keys
    assert all(id(CACHE[k].problem) == built[k] for k in keys)
    assert all(v.problem.is_dpp() for v in CACHE.values())


# --------------------------------------------------------------------------- KKT (no closed form)


def _kkt_scale(R):
    return max(1.0, np.abs(R).max())


@pytest.mark.parametrize("variant", ["time_varying", "time_invariant"])
def test_offset_bound_kkt(variant):
    model, sm, y, mom, rng = instance(21, 3, 2, T=4)
    free = maximize(model, mom, constraints=MStepConstraints(cov_floor=0.1), variant=variant, min_norm=False).policy
    b = 0.5 * np.abs(free.k).min()  # binds every component
    res = maximize(model, mom, constraints=MStepConstraints(cov_floor=0.1, offset_bound=b), method="cvxpy",
                                  variant=variant, min_norm=False)
    H, R, S = quad_terms(model, mom)
    F = F_of(res.policy)
    n = 3
    assert np.all(np.abs(F[..., n]) <= b * (1 + 1e-8))  # primal feasibility
    if variant == "time_varying":
        G = R - H @ F @ S
        lam_u = np.stack([d["offset_upper"] for d in res.duals])
        lam_l = np.stack([d["offset_lower"] for d in res.duals])
    else:
        G = sum(R[k] - H[k] @ F[0] @ S[k] for k in range(4))[None]
        lam_u, lam_l = res.duals[0]["offset_upper"][None], res.duals[0]["offset_lower"][None]
        F = F[:1]
    tol = 1e-6 * _kkt_scale(R)
    assert np.all(lam_u >= -tol) and np.all(lam_l >= -tol)  # dual feasibility
    assert np.abs(G[..., :n]).max() <= tol  # stationarity (K free)
    assert np.abs(G[..., n] - (lam_u - lam_l)).max() <= tol  # stationarity (k bounded)
    assert np.abs(lam_u * (b - F[..., n])).max() <= tol  # complementary slackness
    assert np.abs(lam_l * (b + F[..., n])).max() <= tol
    assert np.all(lam_u + lam_l > 1e-6)  # the bound is active: a genuinely constrained case
    # the constrained value cannot exceed the unconstrained one
    assert res.objective.sum() <= surrogate_from_moments(model, mom, free).sum() + 1e-9


def _norm(X):
    return float(np.abs(X).max())


def _assert_trust_region_kkt(res, prev, H, R, S, delta, variant):
    """KKT conditions of the trust-region M-step (``cov_floor`` + ``trust_region``) from the CVXPY duals.

    Stationarity ``G = sum_j mu_j (F - Fp_j)/||F - Fp_j||`` with a normwise backward-error scale:
    each term's size bound (``|R| + |H||F||S| + sum_j mu_j |F|/||F - Fp_j||``).  Returns the
    multipliers (time-varying: one per step; time-invariant: one per centre)."""
    T = R.shape[0]
    F, Fp = F_of(res.policy), F_of(prev)
    if variant == "time_varying":
        mus = []
        for k in range(T):
            G = R[k] - H[k] @ F[k] @ S[k]
            D = F[k] - Fp[k]
            mu = float(res.duals[k]["trust"][0])
            nrm = np.linalg.norm(D)
            scale = _norm(R[k]) + _norm(H[k]) * _norm(F[k]) * _norm(S[k]) + mu * _norm(F[k]) / nrm
            assert nrm <= delta * (1 + 1e-7)  # primal feasibility
            assert mu >= -1e-9 * scale  # dual feasibility
            assert _norm(G - mu * D / nrm) <= 1e-6 * scale  # stationarity
            assert abs(mu * (delta - nrm)) <= 1e-6 * scale * delta  # complementary slackness
            mus.append(mu)
        return np.array(mus)
    Fk = F[0]
    G = sum(R[k] - H[k] @ Fk @ S[k] for k in range(T))
    mu = res.duals[0]["trust"]
    assert mu.shape == (T,)
    D = Fk - Fp
    nrm = np.linalg.norm(D, axis=(1, 2))
    scale = (_norm(R.sum(0)) + sum(_norm(H[k]) * _norm(S[k]) for k in range(T)) * _norm(Fk)
             + float(np.sum(np.abs(mu) / nrm)) * _norm(Fk))
    assert np.all(nrm <= delta * (1 + 1e-7)) and np.all(mu >= -1e-9 * scale)
    assert _norm(G - np.einsum("t,tij->ij", mu, D / nrm[:, None, None])) <= 1e-6 * scale
    assert np.abs(mu * (delta - nrm)).max() <= 1e-6 * scale * delta
    return mu


@pytest.mark.parametrize("variant", ["time_varying", "time_invariant"])
def test_trust_region_kkt(variant):
    T = 4
    model, sm, y, mom, rng = instance(22, 3, 2, T=T)
    prev = random_policy(rng, T, 3, 2)
    delta = 0.05
    if variant == "time_invariant":  # centres within delta/2 of a common point: a nonempty intersection
        F0 = F_of(prev)[0]
        Fp = F0 + rng.normal(size=(T, 2, 4)) * 0.2 * delta / 4
        prev = policy_from(Fp, prev.cov)
    res = maximize(model, mom, constraints=MStepConstraints(cov_floor=0.1, trust_region=delta), method="cvxpy",
                                  variant=variant, previous=prev, min_norm=False)
    H, R, S = quad_terms(model, mom)
    mu = _assert_trust_region_kkt(res, prev, H, R, S, delta, variant)
    if variant == "time_varying":
        assert np.all(mu > 1e-3)  # active at every step: a genuinely constrained case
    else:
        assert mu.max() > 1e-3


def test_trust_region_matches_secular_equation_oracle():
    """Time-varying trust region vs the More-Sorensen characterisation: ``(S kron H + mu I) vec F =
    vec R + mu vec F_prev`` with ``mu >= 0`` chosen by root finding so that ``||F - F_prev|| = delta``."""
    from scipy.optimize import brentq

    T, n, m = 3, 3, 2
    model, sm, y, mom, rng = instance(25, n, m, T=T)
    prev = random_policy(rng, T, n, m)
    delta = 0.05
    res = maximize(model, mom, constraints=MStepConstraints(cov_floor=0.1, trust_region=delta), method="cvxpy",
                                  previous=prev, min_norm=False)
    H, R, S = quad_terms(model, mom)
    for k in range(T):
        Q = np.kron(S[k], H[k])
        r, fp = R[k].reshape(-1, order="F"), F_of(prev)[k].reshape(-1, order="F")
        d = len(r)

        def F_of_mu(mu):
            return np.linalg.solve(Q + mu * np.eye(d), r + mu * fp)

        assert np.linalg.norm(F_of_mu(0.0) - fp) > delta  # the unconstrained optimum is outside
        mu = brentq(lambda mu: np.linalg.norm(F_of_mu(mu) - fp) - delta, 0.0, 1e8, xtol=1e-14, rtol=1e-15)
        want = F_of_mu(mu).reshape((m, n + 1), order="F")
        assert rel_err(F_of(res.policy)[k], want) <= 1e-6
        assert float(res.duals[k]["trust"][0]) == pytest.approx(mu * delta, rel=1e-5)


def _trust_region_instance(seed, n, m, variant, T=4):
    """A random well-posed ``cov_floor + trust_region`` M-step: ``delta`` log-uniform in [0.01, 1];
    time-invariant centres within about ``0.2 delta`` of a common point (a nonempty intersection)."""
    model, sm, y, mom, rng = instance(seed, n, m, T=T)
    prev = random_policy(rng, T, n, m)
    delta = float(10.0 ** rng.uniform(-2, 0))
    if variant == "time_invariant":
        F0 = F_of(prev)[0]
        prev = policy_from(F0 + rng.normal(size=(T, m, n + 1)) * 0.2 * delta / np.sqrt(m * (n + 1)), prev.cov)
    return model, mom, prev, delta


@pytest.mark.parametrize("variant", ["time_varying", "time_invariant"])
def test_trust_region_clarabel_solves_random_instances(variant):
    """Regression: with Clarabel the trust-region M-step used to end as ``optimal_inaccurate`` (raised
    as SolverError) on roughly a quarter to a half of such instances, whenever the trust region is
    active with a multiplier comparable to the curvature of the objective (``mu/delta`` not large
    against the eigenvalues of ``Stilde kron H``).  Every instance must now solve with status
    ``optimal`` at the default tolerances and satisfy the KKT conditions; the reported optimal value
    (spectral form plus the constants it omits) must match the surrogate at the maximiser."""
    sizes = [(3, 2), (6, 2), (26, 7)]
    hard = 0
    for i in range(30):
        n, m = sizes[i % 3]
        model, mom, prev, delta = _trust_region_instance(700 + i, n, m, variant)
        res = maximize(model, mom, constraints=MStepConstraints(cov_floor=0.1, trust_region=delta), method="cvxpy",
                                      variant=variant, previous=prev, min_norm=False)
        assert all(s == "optimal" for s in res.status), (i, n, m, res.status)
        H, R, S = quad_terms(model, mom)
        mu = _assert_trust_region_kkt(res, prev, H, R, S, delta, variant)
        got = res.objective if variant == "time_varying" else np.array([res.objective.sum()])
        assert rel_err(res.solver_value, got) <= 1e-8
        # how many solves are in the regime where the default Clarabel settings failed: an active
        # trust region whose multiplier (mu/delta for 1/2 ||F - Fp||^2) is below 10 lambda_max
        lam_max = (np.linalg.eigvalsh(H)[:, -1] * np.linalg.eigvalsh(S)[:, -1])
        if variant == "time_varying":
            hard += int(np.sum((mu > 0) & (mu / delta < 10 * lam_max)))
        else:
            hard += int(0 < mu.sum() / delta < 10 * lam_max.sum())
    assert hard >= 10, hard  # the instances do exercise that regime


def test_trust_region_solution_does_not_depend_on_earlier_solves():
    """The cached DPP problem is re-solved with a fresh Clarabel solver: updating the cached solver in
    place (CVXPY's warm_start) would reuse the equilibration computed for an earlier instance, so
    the result of a solve depended on what had been solved before."""
    def C(d):
        return MStepConstraints(cov_floor=0.1, trust_region=d)

    model, mom, prev, delta = _trust_region_instance(801, 6, 2, "time_varying")
    first = maximize(model, mom, constraints=C(delta), method="cvxpy", previous=prev, min_norm=False)
    model2, mom2, prev2, delta2 = _trust_region_instance(802, 6, 2, "time_varying")
    maximize(model2, mom2, constraints=C(delta2), method="cvxpy", previous=prev2, min_norm=False)
    again = maximize(model, mom, constraints=C(delta), method="cvxpy", previous=prev, min_norm=False)
    assert np.array_equal(F_of(first.policy), F_of(again.policy))
    assert np.array_equal(np.stack([d["trust"] for d in first.duals]), np.stack([d["trust"] for d in again.duals]))


def test_offset_bound_and_trust_region_kkt():
    """Both F constraints at once (the spectral form maps the offset column through the eigenbasis)."""
    T, n, m = 3, 3, 2
    model, sm, y, mom, rng = instance(28, n, m, T=T)
    prev = random_policy(rng, T, n, m)
    b = 0.1
    prev = LinearGaussianPolicy(prev.K, np.clip(prev.k, -b, b), prev.cov)  # a feasible centre
    delta = 0.3
    res = maximize(model, mom, constraints=MStepConstraints(cov_floor=0.1, offset_bound=b, trust_region=delta),
                                  method="cvxpy", previous=prev, min_norm=False)
    assert all(s == "optimal" for s in res.status)
    H, R, S = quad_terms(model, mom)
    F, Fp = F_of(res.policy), F_of(prev)
    for k in range(T):
        G = R[k] - H[k] @ F[k] @ S[k]
        D = F[k] - Fp[k]
        nrm = np.linalg.norm(D)
        mu = float(res.duals[k]["trust"][0])
        lu, ll = res.duals[k]["offset_upper"], res.duals[k]["offset_lower"]
        scale = _norm(R[k]) + _norm(H[k]) * _norm(F[k]) * _norm(S[k]) + mu * _norm(F[k]) / nrm + _norm(lu) + _norm(ll)
        assert nrm <= delta * (1 + 1e-7) and np.all(np.abs(F[k, :, n]) <= b * (1 + 1e-7))
        assert mu >= -1e-9 * scale and np.all(lu >= -1e-9 * scale) and np.all(ll >= -1e-9 * scale)
        W = mu * D / nrm
        W[:, n] += lu - ll
        assert _norm(G - W) <= 1e-6 * scale  # stationarity
        assert abs(mu * (delta - nrm)) <= 1e-6 * scale * delta
        assert np.abs(lu * (b - F[k, :, n])).max() <= 1e-6 * scale * b
        assert np.abs(ll * (b + F[k, :, n])).max() <= 1e-6 * scale * b
    # both constraints active at every step: a genuinely doubly constrained case
    assert all(float(d["trust"][0]) > 1e-3 and np.max(d["offset_upper"] + d["offset_lower"]) > 1e-3
               for d in res.duals)


def test_floor_and_ceiling_kkt():
    model, sm, y, mom, rng = instance(23, 3, 2, T=3)
    m = 2
    Smin = random_spd(rng, m, floor=0.05)
    Smax = Smin + random_spd(rng, m, floor=0.01)
    res = maximize(model, mom, constraints=MStepConstraints(cov_floor=Smin, cov_ceiling=Smax), method="cvxpy",
                                  min_norm=False)
    H, R, S = quad_terms(model, mom)
    for k in range(3):
        Sig = res.policy.cov[k]
        Z1, Z2 = res.duals[k]["cov_floor"], res.duals[k]["cov_ceiling"]
        tol = 1e-6 * max(1.0, np.abs(H[k]).max())
        # primal feasibility
        assert np.linalg.eigvalsh(Sig - Smin)[0] >= -1e-8 and np.linalg.eigvalsh(Smax - Sig)[0] >= -1e-8
        # dual feasibility
        assert np.linalg.eigvalsh(Z1)[0] >= -tol and np.linalg.eigvalsh(Z2)[0] >= -tol
        # stationarity in Sigma: -H/2 + Z1 - Z2 = 0
        assert np.abs(-0.5 * H[k] + Z1 - Z2).max() <= tol
        # complementary slackness
        assert abs(np.trace(Z1 @ (Sig - Smin))) <= tol and abs(np.trace(Z2 @ (Smax - Sig))) <= tol
        assert np.abs(R[k] - H[k] @ F_of(res.policy)[k] @ S[k]).max() <= 1e-6 * _kkt_scale(R)
    # and it is the relaxation optimum Sigma_min
    assert rel_err(res.policy.cov, np.broadcast_to(Smin, (3, m, m))) <= 1e-6


def test_entropy_floor_and_ceiling_kkt_scs():
    """Both active: no closed form.  KKT with SCS (accurate on the log-det boundary)."""
    model, sm, y, mom, rng = instance(24, 2, 2, T=2)
    H, R, S = quad_terms(model, mom)
    # a ceiling that cuts alpha H^-1 but leaves room for log det >= c
    Smax = 0.5 * np.eye(2)
    c = float(np.linalg.slogdet(Smax)[1]) - 0.3
    C = MStepConstraints(entropy_floor=c, cov_ceiling=Smax)
    with pytest.raises(ClosedFormUnavailableError, match="cvxpy"):
        maximize(model, mom, constraints=C, min_norm=False)
    res = maximize(model, mom, constraints=C, method="cvxpy", solver="SCS", min_norm=False)
    for k in range(2):
        Sig = res.policy.cov[k]
        nu, Z2 = float(res.duals[k]["entropy_floor"]), res.duals[k]["cov_ceiling"]
        tol = 1e-5 * max(1.0, np.abs(H[k]).max())
        assert np.linalg.slogdet(Sig)[1] >= c - 1e-6 and np.linalg.eigvalsh(Smax - Sig)[0] >= -1e-6
        assert nu >= -tol and np.linalg.eigvalsh(Z2)[0] >= -tol
        assert np.abs(-0.5 * H[k] + nu * np.linalg.inv(Sig) - Z2).max() <= tol
        assert abs(nu * (np.linalg.slogdet(Sig)[1] - c)) <= tol and abs(np.trace(Z2 @ (Smax - Sig))) <= tol
        assert nu > 1e-4 and np.abs(Z2).max() > 1e-4  # both active


# --------------------------------------------------------------------------- exact EM (claim 2)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 4), m=st.integers(1, 3),
       cons=st.sampled_from(["none", "floor", "entropy", "ceiling"]),
       variant=st.sampled_from(["time_varying", "time_invariant"]))
def test_exact_em_inner_iterations_never_decrease_exact_objective(seed, n, m, cons, variant):
    T = 3
    model, sm, y, mom, rng = instance(seed, n, m, T=T)
    C = {"none": MStepConstraints(), "floor": MStepConstraints(cov_floor=0.05),
         "entropy": MStepConstraints(entropy_floor=-1.0), "ceiling": MStepConstraints(cov_ceiling=2.0)}[cons]
    start = random_policy(rng, T, n, m, var=0.3)
    if variant == "time_invariant":
        start = LinearGaussianPolicy(*(np.broadcast_to(a[0], a.shape) for a in (start.K, start.k, start.cov)))
    # a feasible start (EM is monotone from a feasible point)
    res0 = maximize(model, mom, constraints=C, objective="exact", previous=start, variant=variant,
                                   config=MStepConfig(exact_max_iter=1), min_norm=False)
    res = maximize(model, mom, constraints=C, objective="exact", previous=res0.policy, variant=variant,
                                  config=MStepConfig(exact_max_iter=60), min_norm=False)
    h = res.history if variant == "time_varying" else res.history.sum(1, keepdims=True)
    assert h.shape[0] == res.iterations + 1 >= 2
    assert np.all(np.diff(h, axis=0) >= -1e-10 * np.abs(h[1:]))
    assert np.allclose(res.history[-1], exact_objective_from_moments(model, mom, res.policy))
    assert np.all(h[-1] >= h[0])


def test_exact_em_with_offset_bound_is_monotone_and_feasible():
    T = 2
    model, sm, y, mom, rng = instance(31, 2, 2, T=T)
    start = random_policy(rng, T, 2, 2, var=0.3)
    b = 0.5 * np.abs(start.k).min()
    start = LinearGaussianPolicy(start.K, np.clip(start.k, -b, b), start.cov)
    C = MStepConstraints(offset_bound=b)
    with pytest.raises(ClosedFormUnavailableError, match="cvxpy"):
        maximize(model, mom, constraints=C, objective="exact", previous=start, min_norm=False)
    res = maximize(model, mom, constraints=C, objective="exact", method="cvxpy", previous=start,
                                  config=MStepConfig(exact_max_iter=15), min_norm=False)
    assert np.all(np.abs(res.policy.k) <= b * (1 + 1e-7))
    h = res.history
    assert np.all(np.diff(h, axis=0) >= -1e-7 * np.abs(h[1:]))  # CVXPY solves to ~1e-9
    assert np.all(h[-1] > h[0])


def test_exact_em_floor_clipping_is_the_constrained_gaussian_mle():
    """Covariance step with a floor: the whitened-eigenvalue clipping beats feasible alternatives."""
    rng = np.random.default_rng(3)
    m = 3
    for _ in range(20):
        W = random_spd(rng, m, floor=0.01)
        Smin = random_spd(rng, m, floor=0.05)
        rc = MStepConstraints(cov_floor=Smin).resolve(m)
        X = sigma_exact(W[None], rc, "closed_form", "CLARABEL", MStepConfig(), ["t"])[0]

        def f(X):
            return -np.linalg.slogdet(X)[1] - np.trace(np.linalg.solve(X, W))

        assert np.linalg.eigvalsh(X - Smin)[0] >= -1e-10
        for _ in range(30):
            Y = rng.normal(size=(m, m)) * 10.0 ** rng.uniform(-3, 0)
            Xp = X + Y @ Y.T  # feasible (still above the floor)
            assert f(Xp) <= f(X) + 1e-10
            D = rng.normal(size=(m, m)) * 1e-3
            Xq = X + D + D.T
            if np.linalg.eigvalsh(Xq - Smin)[0] >= 0:
                assert f(Xq) <= f(X) + 1e-10


@pytest.mark.parametrize("seed", [41, 42, 43])
def test_exact_em_never_decreases_log_likelihood(seed):
    """docs/math.md §9 claim 2 end to end with the smoother: log p(Y) is non-decreasing over 50 exact-EM
    iterations (generalized EM: each M-step runs at most 20 inner iterations, each of which
    cannot decrease the exact objective)."""
    from soc_opt import estep

    rng = np.random.default_rng(seed)
    n, m, T = 3, 2, 6
    model = random_model(rng, n, m, T)
    pol = random_policy(rng, T, n, m, var=0.5)
    mu0, P0 = rng.normal(size=n), random_spd(rng, n, floor=0.3)
    y = rng.normal(size=(4, T))
    cfg = MStepConfig(exact_max_iter=20)
    ll = [float(np.sum(estep.log_likelihood(model, pol, y, mu0, P0)))]
    for _ in range(50):
        sm = estep.smooth(model, pol, y, mu0, P0)
        pol = maximize(model, moments(sm, y), objective="exact", previous=pol, config=cfg, min_norm=False).policy
        ll.append(float(np.sum(estep.log_likelihood(model, pol, y, mu0, P0))))
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:]))
    assert ll[-1] > ll[0]


# --------------------------------------------------------------------------- min-norm solutions


@pytest.mark.parametrize("which", ["B", "P"])
def test_min_norm_solution_for_non_unique_maximiser(which):
    kw = {"deficient_step": 1} if which == "B" else {"singular_step": 1}
    model, sm, y, mom, rng = instance(51, 3, 2, T=3, **kw)
    C = MStepConstraints(cov_floor=0.1)
    with pytest.raises(NonUniqueMaximizerError, match="k=1") as e:
        maximize(model, moments(sm, y), constraints=C, min_norm=False)
    msg = str(e.value)
    if which == "B":
        assert "rank 1 < m=2" in msg
    else:
        assert "P_1" in msg and "smallest eigenvalue" in msg
    with pytest.raises(NonUniqueMaximizerError, match="k=1"):
        maximize(model, moments(sm, y), constraints=C, method="cvxpy", min_norm=False)
    pol = maximize(model, moments(sm, y), constraints=C, min_norm=True).policy
    H, R, S = quad_terms(model, mom)
    Q = np.kron(S[1], H[1])
    v = np.linalg.lstsq(Q, R[1].reshape(-1, order="F"), rcond=1e-10)[0]
    assert rel_err(F_of(pol)[1].reshape(-1, order="F"), v) <= 1e-6
    best = surrogate(model, sm, y, pol)
    for _ in range(20):
        F = F_of(pol) + 0.1 * rng.normal(size=F_of(pol).shape)
        assert np.all(surrogate(model, sm, y, policy_from(F, pol.cov)) <= best + 1e-9 * np.abs(best))


def test_time_invariant_min_norm_and_error():
    model, sm, y, mom, rng = instance(52, 3, 2, T=1, deficient_step=0)
    C = MStepConstraints(cov_floor=0.1)
    with pytest.raises(NonUniqueMaximizerError, match="time-invariant"):
        maximize(model, moments(sm, y), constraints=C, variant="time_invariant", min_norm=False)
    pol = maximize(model, moments(sm, y), constraints=C, variant="time_invariant", min_norm=True).policy
    H, R, S = quad_terms(model, mom)
    v = np.linalg.lstsq(np.kron(S[0], H[0]), R[0].reshape(-1, order="F"), rcond=1e-10)[0]
    assert rel_err(F_of(pol)[0].reshape(-1, order="F"), v) <= 1e-6


def test_entropy_floor_needs_full_rank_B_even_with_min_norm():
    model, sm, y, mom, rng = instance(53, 3, 2, T=3, deficient_step=2)
    with pytest.raises(NonUniqueMaximizerError, match="k=2.*entropy_floor"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=0.0), min_norm=True)


# --------------------------------------------------------------------------- errors


def test_wrong_shapes_raise_shape_error():
    model, sm, y, mom, rng = instance(61, 3, 2, T=4)
    model5 = random_model(rng, 3, 2, 5)
    with pytest.raises(ShapeError, match="moments Szz"):
        maximize(model5, moments(sm, y), constraints=MStepConstraints(cov_floor=0.1), min_norm=False)
    with pytest.raises(ShapeError, match="y"):
        maximize(model, moments(sm, y[:3]), constraints=MStepConstraints(cov_floor=0.1), min_norm=False)
    with pytest.raises(ShapeError, match="policy K"):
        surrogate(model, sm, y, random_policy(rng, 4, 2, 2))
    with pytest.raises(ShapeError, match="cov_floor"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=np.eye(3)), min_norm=False)
    with pytest.raises(ShapeError, match="offset_bound"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=0.1, offset_bound=(1.0, 2.0, 3.0)), method="cvxpy",
                 min_norm=False)
    with pytest.raises(ShapeError, match="previous"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=0.1), previous=random_policy(rng, 3, 3, 2), min_norm=False)


def test_no_covariance_constraint_is_an_error_unless_singular_allowed():
    model, sm, y, mom, rng = instance(62, 3, 2, T=3)
    for C in (MStepConstraints(), MStepConstraints(cov_ceiling=1.0)):
        with pytest.raises(ValueError, match="Sigma_k = 0"):
            maximize(model, moments(sm, y), constraints=C, min_norm=False)
    with pytest.raises(ValueError, match="cov_ceiling alone"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_ceiling=1.0), min_norm=False)
    for C in (MStepConstraints(allow_singular=True), MStepConstraints(cov_ceiling=1.0, allow_singular=True)):
        pol = maximize(model, moments(sm, y), constraints=C, min_norm=False).policy
        assert np.all(pol.cov == 0) and pol.allow_singular
        pol2 = maximize(model, moments(sm, y), constraints=C, method="cvxpy", min_norm=False).policy
        assert np.abs(pol2.cov).max() <= 1e-7 and np.allclose(pol2.K, pol.K, rtol=1e-6, atol=1e-8)


def test_infeasible_constraint_sets_are_named():
    with pytest.raises(InfeasibleConstraintsError, match="cov_floor.*cov_ceiling"):
        MStepConstraints(cov_floor=2.0, cov_ceiling=1.0)
    with pytest.raises(InfeasibleConstraintsError, match="cov_floor.*cov_ceiling"):
        MStepConstraints(cov_floor=np.diag([1.0, 3.0]), cov_ceiling=np.diag([2.0, 2.0]))
    model, sm, y, mom, rng = instance(63, 3, 2, T=3)
    with pytest.raises(InfeasibleConstraintsError, match="entropy_floor.*cov_ceiling"):
        # log det I = 0 < 1
        maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=1.0, cov_ceiling=1.0), min_norm=False)
    with pytest.raises(InfeasibleConstraintsError, match="cov_floor.*cov_ceiling"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=0.5, cov_ceiling=np.diag([1.0, 0.2])), min_norm=False)
    with pytest.raises(ConfigError, match="positive semidefinite"):
        MStepConstraints(cov_floor=-np.eye(2))
    with pytest.raises(ConfigError, match="offset_bound"):
        MStepConstraints(offset_bound=-1.0)


def test_closed_form_unavailable_and_missing_previous():
    model, sm, y, mom, rng = instance(64, 3, 2, T=3)
    for C in (MStepConstraints(cov_floor=0.1, offset_bound=1.0), MStepConstraints(cov_floor=0.1, trust_region=1.0)):
        with pytest.raises(ClosedFormUnavailableError, match="method='cvxpy'"):
            maximize(model, moments(sm, y), constraints=C, previous=random_policy(rng, 3, 3, 2), min_norm=False)
    with pytest.raises(ValueError, match="trust_region needs previous"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=0.1, trust_region=1.0), method="cvxpy", min_norm=False)
    with pytest.raises(ValueError, match="needs previous"):
        maximize(model, moments(sm, y), objective="exact", min_norm=False)
    with pytest.raises(ValueError, match="method"):
        maximize(model, moments(sm, y), constraints=MStepConstraints(cov_floor=0.1), method="newton", min_norm=False)


def test_solver_failure_raises_solver_error():
    model, sm, y, mom, rng = instance(65, 3, 2, T=2)
    cfg = MStepConfig(scs_max_iters=2, scs_eps=1e-12)
    with pytest.raises(SolverError, match="SCS") as e:
        maximize(model, moments(sm, y), constraints=MStepConstraints(entropy_floor=0.0, offset_bound=0.01), method="cvxpy",
                 solver="SCS", config=cfg, min_norm=False)
    assert e.value.status is not None and e.value.step == 1  # the backward sweep starts at T-1
    # one base class for every solver path: soc_opt.errors.SolverError catches it too
    assert isinstance(e.value, soc_errors.SolverError) and isinstance(e.value, RuntimeError)


def test_constraints_and_config_load_from_toml(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text(
        "[mstep.constraints]\ncov_floor = [[0.5, 0.1], [0.1, 0.4]]\nentropy_floor = -2\noffset_bound = [1.0, 2.0]\n"
        "[mstep.config]\nsolver = 'SCS'\nexact_max_iter = 50\n"
    )
    import tomllib

    data = tomllib.loads(p.read_text())["mstep"]
    C = MStepConstraints.from_dict(data["constraints"])
    assert C.cov_floor == ((0.5, 0.1), (0.1, 0.4)) and C.entropy_floor == -2.0 and C.offset_bound == (1.0, 2.0)
    assert MStepConstraints.from_dict(C.to_dict()) == C
    cfg = MStepConfig.from_dict(data["config"])
    assert cfg.solver == "SCS" and cfg.exact_max_iter == 50
    q = tmp_path / "c.toml"
    q.write_text("cov_floor = 0.2\ntrust_region = 0.5\n")
    assert MStepConstraints.from_toml(q) == MStepConstraints(cov_floor=0.2, trust_region=0.5)
    with pytest.raises(ConfigError, match="unknown config key"):
        MStepConstraints.from_dict({"cov_flor": 1.0})
    with pytest.raises(ConfigError, match="solver"):
        MStepConfig.from_dict({"solver": "MOSEK"})
