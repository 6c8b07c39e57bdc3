"""Tests for soc_opt/costs.py: analytic derivatives against finite differences, ramps, expansion."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from soc_opt.costs import (
    RAMPS,
    CostSum,
    PointCost,
    QuadraticStateActionCost,
    StateCost,
    TorqueCost,
    ramp,
)
from soc_opt.models import QuadraticCost, ShapeError
from soc_opt.testing import random_trajectory

N, M_, T = 7, 3, 6


def _traj(seed=0):
    return random_trajectory(np.random.default_rng(seed), N, M_, T)


def _terms(r="constant"):
    rng = np.random.default_rng(1)
    kw = dict(ramp=r, final_multiplier=3.0, weight=1.7)
    return {
        "point_l1_l2": PointCost(N, M_, [0, 1, 2, 4, 5, 6], target=rng.normal(size=6), wp=[1.0, 2.0, 0.5],
                                 l1=0.3, l2=2.0, alpha=0.05, **kw),
        "point_l2_only": PointCost(N, M_, [1, 2, 3], target=[0.1, -0.2, 0.3], wp=1.5, l1=0.0, l2=4.0, **kw),
        "point_l1_only": PointCost(N, M_, [0, 3, 6], target=[0.5, 0.0, -0.5], l1=1.0, l2=0.0, alpha=0.01, **kw),
        "point_moving_target": PointCost(N, M_, [0, 1, 2], target_idx=[3, 4, 5], wp=[1.0, 1.0, 3.0], l1=0.2, l2=1.0,
                                         alpha=0.1, **kw),
        "point_moving_target_offset": PointCost(N, M_, [0, 1, 2], target_idx=[3, 4, 5], target_offset=[0.3, -0.1, 0.2],
                                                wp=[1.0, 1.0, 3.0], l1=0.2, l2=1.0, alpha=0.1, **kw),
        "torque": TorqueCost(N, M_, wu=[1.0, 0.1, 2.0], **kw),
        "state": StateCost(N, M_, idx=[1, 4, 6], target=[0.3, -1.0, 2.0], weights=[1.0, 5.0, 0.2], **kw),
        "state_full": StateCost(N, M_, target=0.5, weights=2.0, **kw),
        "quadratic": QuadraticStateActionCost(
            N, M_, Qs=(lambda A: A @ A.T)(rng.normal(size=(N, N))), Qa=[1e-2, 1.0, 3.0],
            target=rng.normal(size=N), action_target=[0.1, 0.2, 0.3], **kw),
    }


def _fd_grad(f, z, h=1e-6):
    g = np.zeros_like(z)
    for i in range(z.size):
        e = np.zeros_like(z)
        e[i] = h
        g[i] = (f(z + e) - f(z - e)) / (2 * h)
    return g


def _check_term(term, s, a, rtol=1e-6):
    d = term.derivatives(s, a)
    np.testing.assert_allclose(d.l, term(s, a), rtol=1e-12, atol=1e-12)
    for k in range(T):
        def val(z, k=k):
            ss, aa = s.copy(), a.copy()
            ss[k], aa[k] = z[:N], z[N:]
            return term(ss, aa)[k]

        def grad(z, k=k):
            ss, aa = s.copy(), a.copy()
            ss[k], aa[k] = z[:N], z[N:]
            dd = term.derivatives(ss, aa)
            return np.r_[dd.lx[k], dd.lu[k]]

        z = np.r_[s[k], a[k]]
        g_fd = _fd_grad(val, z)
        scale = max(1.0, np.abs(g_fd).max())
        np.testing.assert_allclose(np.r_[d.lx[k], d.lu[k]], g_fd, atol=rtol * scale, err_msg=f"gradient, step {k}")
        H_fd = np.array([_fd_grad(lambda zz, i=i: grad(zz)[i], z) for i in range(N + M_)])
        H = np.block([[d.lxx[k], d.lux[k].T], [d.lux[k], d.luu[k]]])
        scale = max(1.0, np.abs(H_fd).max())
        np.testing.assert_allclose(H, H_fd, atol=rtol * scale, err_msg=f"Hessian, step {k}")
        # other steps do not depend on (s_k, a_k): derivative rows of other k are independent
    assert d.lx.shape == (T, N) and d.lu.shape == (T, M_)
    assert d.lxx.shape == (T, N, N) and d.luu.shape == (T, M_, M_) and d.lux.shape == (T, M_, N)


@pytest.mark.parametrize("r", RAMPS)
@pytest.mark.parametrize("name", list(_terms()))
def test_term_derivatives_match_finite_differences(name, r):
    term = _terms(r)[name]
    s, a = _traj()
    _check_term(term, s, a)


def test_ramp_definitions():
    T4 = 4
    np.testing.assert_allclose(ramp("constant", T4), [1, 1, 1, 1])
    np.testing.assert_allclose(ramp("linear", T4), [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(ramp("quadratic", T4), [0.0625, 0.25, 0.5625, 1.0])
    np.testing.assert_allclose(ramp("final_only", T4), [0, 0, 0, 1])
    np.testing.assert_allclose(ramp("linear", T4, final_multiplier=10.0), [0.25, 0.5, 0.75, 10.0])
    with pytest.raises(ValueError, match="unknown ramp 'cubic'"):
        ramp("cubic", 3)


def test_point_cost_value_matches_formula():
    rng = np.random.default_rng(3)
    s, a = _traj(3)
    target = rng.normal(size=3)
    wp = np.array([1.0, 2.0, 0.5])
    term = PointCost(N, M_, [2, 3, 4], target=target, wp=wp, l1=0.7, l2=3.0, alpha=0.2, ramp="linear", weight=2.0)
    d2 = ((s[:T, 2:5] - target) ** 2 * wp).sum(axis=1)
    expected = 2.0 * (np.arange(1, T + 1) / T) * (0.5 * 3.0 * d2 + 0.7 * np.sqrt(0.2 + d2))
    np.testing.assert_allclose(term(s, a), expected, rtol=1e-13)


def test_point_cost_moving_target_is_distance_between_state_points():
    s, a = _traj(4)
    term = PointCost(N, M_, [0, 1, 2], target_idx=[4, 5, 6], l2=2.0)
    np.testing.assert_allclose(term(s, a), ((s[:T, 0:3] - s[:T, 4:7]) ** 2).sum(axis=1), rtol=1e-13)


def test_point_cost_offset_target_is_the_distance_to_the_shifted_state_point():
    s, a = _traj(4)
    off = np.array([0.08, -0.05, 0.0])
    term = PointCost(N, M_, [0, 1, 2], target_idx=[4, 5, 6], target_offset=off, l2=2.0)
    np.testing.assert_allclose(term(s, a), ((s[:T, 0:3] - s[:T, 4:7] - off) ** 2).sum(axis=1), rtol=1e-13)
    with pytest.raises(ValueError, match="target_offset needs target_idx"):
        PointCost(N, M_, [0, 1, 2], target=[0.0, 0.0, 0.0], target_offset=off)


def test_quadratic_cost_is_spec_formula():
    rng = np.random.default_rng(5)
    s, a = _traj(5)
    Qs = np.diag(rng.uniform(0.5, 2, N))
    Qa = 1e-5 * np.eye(M_)
    st_ = rng.normal(size=N)
    term = QuadraticStateActionCost(N, M_, Qs=Qs, Qa=Qa, target=st_)
    e = s[:T] - st_
    expected = np.einsum("ti,ij,tj->t", e, Qs, e) + np.einsum("ti,ij,tj->t", a, Qa, a)
    np.testing.assert_allclose(term(s, a), expected, rtol=1e-13)


def test_batched_evaluation_equals_per_sample():
    rng = np.random.default_rng(6)
    cs = CostSum(list(_terms("quadratic").values()), N, M_)
    S = rng.normal(size=(4, 2, T + 1, N))
    A = rng.normal(size=(4, 2, T, M_))
    out = cs(S, A)
    assert out.shape == (4, 2, T)
    for i in range(4):
        for j in range(2):
            np.testing.assert_allclose(out[i, j], cs(S[i, j], A[i, j]), rtol=1e-13)
    # the last state s_T is not charged
    S2 = S.copy()
    S2[..., T, :] += 100.0
    np.testing.assert_allclose(cs(S2, A), out)


def test_cost_sum_derivatives_are_sums_of_terms():
    terms = list(_terms("linear").values())
    cs = CostSum(terms, N, M_)
    s, a = _traj(7)
    d = cs.derivatives(s, a)
    for f in ("l", "lx", "lu", "lxx", "luu", "lux"):
        np.testing.assert_allclose(getattr(d, f), sum(getattr(t.derivatives(s, a), f) for t in terms), rtol=1e-12)


@pytest.mark.parametrize("r", RAMPS)
def test_expand_reproduces_cost_to_second_order(r):
    cs = CostSum(list(_terms(r).values()), N, M_)
    s, a = _traj(8)
    q = cs.expand(s, a)
    assert isinstance(q, QuadraticCost) and q.n == N and q.C.shape == (T, N + M_, N + M_)
    # exact at the expansion point
    np.testing.assert_allclose(q(s, a), cs(s, a), rtol=1e-10, atol=1e-10)
    rng = np.random.default_rng(9)
    ds, da = rng.normal(size=s.shape), rng.normal(size=a.shape)
    errs = []
    for eps in (1e-2, 5e-3):
        errs.append(np.abs(q(s + eps * ds, a + eps * da) - cs(s + eps * ds, a + eps * da)))
    # third-order remainder: halving the step divides the error by ~8 wherever it is not round-off
    big = errs[0] > 1e-9
    assert big.any() or r == "final_only"
    ratio = errs[0][big] / errs[1][big]
    assert np.all((ratio > 6.0) & (ratio < 10.0)), ratio


def test_expand_is_exact_for_quadratic_terms():
    terms = [t for k, t in _terms("quadratic").items() if k in ("torque", "state", "state_full", "quadratic", "point_l2_only")]
    cs = CostSum(terms, N, M_)
    s, a = _traj(10)
    q = cs.expand(s, a)
    rng = np.random.default_rng(11)
    s2, a2 = rng.normal(size=s.shape) * 3, rng.normal(size=a.shape) * 3
    np.testing.assert_allclose(q(s2, a2), cs(s2, a2), rtol=1e-10)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    l1=st.floats(0.0, 2.0),
    l2=st.floats(0.0, 5.0),
    alpha=st.floats(1e-3, 1.0),
)
def test_point_cost_derivatives_random(seed, l1, l2, alpha):
    rng = np.random.default_rng(seed)
    term = PointCost(N, M_, rng.permutation(N)[:3], target=rng.normal(size=3), wp=rng.uniform(0.1, 3, 3),
                     l1=l1, l2=l2, alpha=alpha, ramp=RAMPS[seed % 4])
    s, a = _traj(seed % 1000)
    _check_term(term, s, a, rtol=2e-5)


def test_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown ramp"):
        TorqueCost(N, M_, ramp="exp")
    with pytest.raises(ShapeError, match="torque cost wu"):
        TorqueCost(N, M_, wu=[1.0, 2.0])
    with pytest.raises(ValueError, match="out of range"):
        PointCost(N, M_, [5, 6, 7], target=[0, 0, 0])
    with pytest.raises(ValueError, match="exactly one of target"):
        PointCost(N, M_, [0, 1, 2])
    with pytest.raises(ShapeError, match="states must have shape"):
        TorqueCost(N, M_)(np.zeros((T + 1, N + 1)), np.zeros((T, M_)))
    with pytest.raises(ShapeError, match="expected \\(n=7, m=3\\)"):
        CostSum([TorqueCost(N, 2)], N, M_)


@pytest.mark.parametrize("r", RAMPS)
def test_one_stage_cost_equals_the_batched_cost_bit_for_bit(r):
    """``CostTerm.stage`` / ``CostSum.stage`` (one stage, O(1); docs/gym.md "Reward") give exactly
    the ``k``-th entry of the batched evaluation, for every term, ramp, horizon and scale."""
    terms = _terms(r)
    cs = CostSum(list(terms.values()), N, M_)
    rng = np.random.default_rng(12)
    for T_ in (1, 2, 7, 100):
        for scale in (1e-3, 1.0, 1e3):
            S = rng.normal(size=(3, T_ + 1, N)) * scale
            A = rng.normal(size=(3, T_, M_)) * scale
            full = {name: t(S, A) for name, t in terms.items()}
            total = cs(S, A)
            for i in range(3):
                for k in range(T_):
                    for name, t in terms.items():
                        assert np.array_equal(t.stage(S[i, k], A[i, k], k, T_), full[name][i, k]), (name, T_, k)
                    assert np.array_equal(cs.stage(S[i, k], A[i, k], k, T_), total[i, k]), (T_, k)


def test_one_stage_cost_rejects_a_trajectory_or_a_stage_outside_the_horizon():
    term = _terms()["torque"]
    s, a = _traj()
    with pytest.raises(ShapeError, match="one stage"):
        term.stage(s, a, 0, T)
    with pytest.raises(ValueError, match="stage 6 outside 0..5"):
        term.stage(s[0], a[0], T, T)


@pytest.mark.parametrize("window", [(0.0, 0.5), (0.3, 1.0), (0.25, 0.75)])
def test_window_keeps_a_term_on_its_stages_only(window):
    """A windowed term equals the unwindowed one on stages ``ceil(w0 T) <= k < ceil(w1 T)`` and is
    zero elsewhere, in value and every derivative, batched and one stage at a time."""
    T_ = 20
    rng = np.random.default_rng(3)
    s, a = rng.standard_normal((T_ + 1, N)), rng.standard_normal((T_, M_))
    kw = dict(target=rng.normal(size=3), l1=0.3, l2=2.0, ramp="linear", final_multiplier=2.0)
    full = PointCost(N, M_, [0, 1, 2], **kw)
    win = PointCost(N, M_, [0, 1, 2], window=window, **kw)
    on = (np.arange(T_) >= np.ceil(window[0] * T_)) & (np.arange(T_) < np.ceil(window[1] * T_))
    assert 0 < on.sum() < T_
    np.testing.assert_array_equal(win(s, a), np.where(on, full(s, a), 0.0))
    d_full, d_win = full.derivatives(s, a), win.derivatives(s, a)
    for f in ("l", "lx", "lu", "lxx", "luu", "lux"):
        x_full, x_win = getattr(d_full, f), getattr(d_win, f)
        mask = on.reshape((T_,) + (1,) * (x_full.ndim - 1))
        np.testing.assert_array_equal(x_win, np.where(mask, x_full, 0.0))
    batched = win(s, a)
    for k in range(T_):
        assert np.array_equal(win.stage(s[k], a[k], k, T_), batched[k])


def test_window_must_be_an_increasing_pair_of_fractions():
    for bad in [(0.5, 0.5), (0.6, 0.2), (-0.1, 0.5), (0.0, 1.5), (0.1, 0.2, 0.3)]:
        with pytest.raises(ValueError, match="window must be two fractions"):
            TorqueCost(N, M_, window=bad)
