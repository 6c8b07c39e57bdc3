"""Tests for soc_opt/testing.py: the shared instances are well posed (the properties their users rely on)."""

import numpy as np

from soc_opt import lqg, mstep
from soc_opt.testing import make_kl_instance, random_ltv_system, random_mstep_instance, simulate_linear


def test_kl_instance_has_a_convex_cost_and_a_positive_definite_reference(kl_instance):
    dyn, cost, ref, mu0, P0 = kl_instance
    assert np.all(np.linalg.eigvalsh(cost.C) > 0)
    assert np.all(np.linalg.eigvalsh(ref.cov) > 0)
    res = lqg.kl_step(dyn, cost, ref, 0.5, mu0, P0)
    np.testing.assert_allclose(np.sum(res.kl), 0.5, rtol=1e-6)


def test_kl_instance_draws_are_reproducible_from_the_generator():
    a = make_kl_instance(3, 1, 4, np.random.default_rng(5))
    b = make_kl_instance(3, 1, 4, np.random.default_rng(5))
    np.testing.assert_array_equal(a[0].A, b[0].A)
    np.testing.assert_array_equal(a[2].K, b[2].K)


def test_mstep_instance_has_a_unique_closed_form_maximiser(mstep_instance):
    model, mom = mstep_instance
    cons = mstep.MStepConstraints(cov_floor=0.1)
    cf = mstep.maximize(model, mom, constraints=cons, min_norm=False).policy
    cv = mstep.maximize(model, mom, constraints=cons, method="cvxpy", min_norm=False).policy
    np.testing.assert_allclose(cf.K, cv.K, rtol=1e-5, atol=1e-6)
    assert random_mstep_instance(3, 2, 5, np.random.default_rng(0))[0].T == 5


def test_simulate_linear_without_noise_follows_the_system_exactly():
    rng = np.random.default_rng(1)
    system = random_ltv_system(rng, 2, 1, 5)
    system = {**system, "W": np.broadcast_to(1e-300 * np.eye(2), (5, 2, 2)).copy() + 1e-12 * np.eye(2)}
    ro = simulate_linear(system, 3, rng)
    pred = np.einsum("tij,mtj->mti", system["A"], ro.x[:, :-1]) + np.einsum("tij,mtj->mti", system["B"], ro.a) + system["c"]
    np.testing.assert_allclose(ro.x[:, 1:], pred, atol=1e-4)
    np.testing.assert_array_equal(ro.s, ro.x)
