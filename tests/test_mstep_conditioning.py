"""Singular, ill-conditioned and well-conditioned M-steps (soc_opt/mstep/conditioning.py, exact.py;
docs/math.md §5, "Conditioning").

The oracle is exact rational arithmetic (python-flint) written here from the definition of ``Lbar``
(docs/math.md §5): the gradient in ``F = [K k]`` is ``B^T So^-1 (Szs - (Atil + B F) Stilde)`` with the
quadratic term through the symmetric part of ``Stilde``, so the maximiser solves the Kronecker normal
equations ``(sym(Stilde) kron H) vec F = vec(R)``, solved exactly here (the library solves ``H F S = R``
by two matrix solves instead).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from flint import fmpq, fmpq_mat

from soc_opt.models import AugmentedModel
from soc_opt.mstep import (
    IllConditionedMaximizerError,
    MinNormWarning,
    MStepConfig,
    MStepConstraints,
    NonUniqueMaximizerError,
    maximize,
)
from soc_opt.mstep.objectives import surrogate_from_moments
from soc_opt.testing import random_mstep_instance

COV = MStepConstraints(cov_floor=0.1)


def q(a) -> fmpq_mat:
    return fmpq_mat([[fmpq(*float(v).as_integer_ratio()) for v in row] for row in np.atleast_2d(a)])


def exact_maximiser(model, mom, k=0):
    """The unique maximiser of ``Lbar_k`` as a rational matrix, from the Kronecker normal equations."""
    n, m = model.n, model.m
    B, So = q(model.Bs[k]), q(model.So[k])
    Atil = q(np.concatenate([model.As[k], model.co[k][:, None]], axis=1))
    Szs, Sraw = q(mom.Szs[k]), q(mom.Sss[k])
    S = (Sraw + Sraw.transpose()) / 2
    SoiB = So.solve(B)
    H = B.transpose() * SoiB
    R = SoiB.transpose() * (Szs - Atil * Sraw)
    d = m * (n + 1)
    Q = fmpq_mat(d, d)
    for a in range(n + 1):  # column-major vec: (S^T kron H)[(a, i), (b, j)] = S[b, a] H[i, j]
        for b in range(n + 1):
            for i in range(m):
                for j in range(m):
                    Q[a * m + i, b * m + j] = S[b, a] * H[i, j]
    r = fmpq_mat(d, 1, [R[i, a] for a in range(n + 1) for i in range(m)])
    v = Q.solve(r)
    return fmpq_mat(m, n + 1, [v[a * m + i, 0] for i in range(m) for a in range(n + 1)])


def rounded(F) -> np.ndarray:
    return np.array([[int(F[i, j].p) / int(F[i, j].q) for j in range(F.ncols())] for i in range(F.nrows())])


def near_parallel(delta_exp: int = 19, seed: int = 7):
    """``n = m = 2, T = 1``: the second action column is the first plus ``2^-delta_exp`` times another dyadic
    column, so ``[B; By]`` has full rank exactly (dyadic data) but ``H_0`` has relative smallest eigenvalue
    about ``1e-11`` (``delta_exp = 19``): below ``eig_tol = 1e-10``, above ``sing_tol``."""
    rng = np.random.default_rng(seed)
    model, mom = random_mstep_instance(2, 2, 1, rng)
    Ao = model.Ao.copy()
    b = np.round(Ao[0, :, 2] * 1024) / 1024
    v = np.round(rng.standard_normal(3) * 1024) / 1024
    Ao[0, :, 2] = b
    Ao[0, :, 3] = b + 2.0**-delta_exp * v
    return AugmentedModel(Ao, model.co, model.So, 2), mom


def F_of(policy):
    return np.concatenate([policy.K, policy.k[..., None]], axis=-1)


def test_near_parallel_actuators_return_the_unique_maximiser_not_a_truncation():
    model, mom = near_parallel()
    Fstar = rounded(exact_maximiser(model, mom))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no MinNormWarning: nothing is truncated
        res = maximize(model, mom, constraints=COV)
    F = F_of(res.policy)[0]
    assert res.exact_steps == (0,) and res.min_norm_steps == ()
    assert np.max(np.abs(F - Fstar) / np.abs(Fstar)) <= 4 * np.finfo(float).eps  # correctly rounded, up to ulps
    assert np.linalg.norm(Fstar) > 1e5  # the unique maximiser is large: a truncation would be far from it
    strict = maximize(model, mom, constraints=COV, min_norm=False).policy  # unique: no error either
    assert np.array_equal(F_of(strict)[0], F)
    # the minimum-norm truncation (what the closed form used to return) loses most of the objective
    Ft = F_of(res.policy).copy()
    Ft[0] = np.linalg.pinv(np.kron(mom.Sss[0].T, _H(model)), rcond=1e-10).dot(_R(model, mom).ravel(order="F")) \
        .reshape(model.n + 1, model.m).T
    trunc = res.policy.__class__(Ft[..., :2], Ft[..., 2], res.policy.cov)
    assert surrogate_from_moments(model, mom, res.policy)[0] > surrogate_from_moments(model, mom, trunc)[0] + 1.0


def _H(model):
    B, So = model.Bs[0], model.So[0]
    return B.T @ np.linalg.solve(So, B)


def _R(model, mom):
    B, So = model.Bs[0], model.So[0]
    Atil = np.concatenate([model.As[0], model.co[0][:, None]], axis=1)
    return B.T @ np.linalg.solve(So, mom.Szs[0] - Atil @ mom.Sss[0])


def test_ill_conditioned_step_is_refused_by_cvxpy_naming_the_threshold_and_the_condition_number():
    model, mom = near_parallel()
    with pytest.raises(IllConditionedMaximizerError) as e:
        maximize(model, mom, constraints=COV, method="cvxpy", min_norm=False)
    msg = str(e.value)
    assert "k=0" in msg and "eig_tol = 1e-10" in msg and "condition number 9.67" in msg


def test_exactly_parallel_actuators_are_singular_with_a_consistent_rank_message():
    model, mom = near_parallel()
    Ao = model.Ao.copy()
    Ao[0, :, 3] = Ao[0, :, 2]  # identical columns: rank 1 exactly
    model = AugmentedModel(Ao, model.co, model.So, 2)
    with pytest.raises(NonUniqueMaximizerError) as e:
        maximize(model, mom, constraints=COV, min_norm=False)
    msg = str(e.value)
    assert "numerical rank 1 < m=2" in msg and "sing_tol" in msg and "rank 2 < m=2" not in msg
    with pytest.warns(MinNormWarning, match=r"time steps \[0\].*minimum-norm"):
        res = maximize(model, mom, constraints=COV)
    assert res.min_norm_steps == (0,) and res.exact_steps == ()


def test_ill_conditioned_P_is_solved_exactly_and_not_called_non_positive_definite():
    """``P_0`` positive definite but below ``eig_tol`` relative to ``Stilde_0`` (the solver benchmark's
    ill-conditioned m = 1 problems, where P_0 is positive definite): the unique maximiser, not an error."""
    rng = np.random.default_rng(3)
    model, mom = random_mstep_instance(2, 1, 1, rng)
    c = 2.0**18  # a state coordinate measured in units 2^20 times larger: P_0 and Stilde_0 scale apart
    D = np.diag([c, 1.0, 1.0])
    mom = dataclasses.replace(mom, Sss=D @ mom.Sss @ D, Szs=mom.Szs @ D)
    Ao = model.Ao.copy()
    Ao[:, :, 0] /= c
    model = AugmentedModel(Ao, model.co, model.So, 2)
    P = mom.Sss[0][:2, :2] - np.outer(mom.Sss[0][:2, 2], mom.Sss[0][2, :2]) / mom.Sss[0][2, 2]
    assert np.linalg.eigvalsh(P)[0] > 0
    res = maximize(model, mom, constraints=COV, min_norm=False)
    assert res.exact_steps == (0,)
    Fstar = rounded(exact_maximiser(model, mom))
    assert np.max(np.abs(F_of(res.policy)[0] - Fstar) / np.abs(Fstar)) <= 4 * np.finfo(float).eps


def test_sing_tol_must_be_below_eig_tol():
    with pytest.raises(ValueError, match="sing_tol: must be below eig_tol"):
        MStepConfig(eig_tol=1e-12, sing_tol=1e-11)


def test_more_actions_than_outputs_is_singular():
    """``m > n+1``: the stacked ``[B; By]`` has at most ``n+1`` independent columns, so ``H_k`` is singular
    whatever its entries (the whitened ``B`` has only ``n+1`` singular values to measure)."""
    model, mom = random_mstep_instance(1, 3, 2, np.random.default_rng(5))
    with pytest.raises(NonUniqueMaximizerError, match="numerical rank 2 < m=3"):
        maximize(model, mom, constraints=COV, min_norm=False)


def test_time_invariant_ill_conditioned_step_is_solved_exactly_up_to_its_size_limit():
    """With ``T = 1`` the time-invariant maximiser is the per-step one: exact below ``EXACT_TI_MAX`` unknowns."""
    model, mom = near_parallel()
    Fstar = rounded(exact_maximiser(model, mom))
    res = maximize(model, mom, constraints=COV, variant="time_invariant", min_norm=False)
    assert res.exact_steps == (0,)
    assert np.max(np.abs(F_of(res.policy)[0] - Fstar) / np.abs(Fstar)) <= 4 * np.finfo(float).eps
    with pytest.raises(IllConditionedMaximizerError, match="eig_tol = 1e-10.*no exact solve"):
        maximize(model, mom, constraints=COV, variant="time_invariant", method="cvxpy", min_norm=False)
