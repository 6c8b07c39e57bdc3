"""Tests for the ECM row, the smoother row, the standing hypotheses and the scale invariance of the claim
checks (soc_opt.verification.checks_ecm, .oracle, .hypotheses, .checks; docs/math.md §4, §5, §9;
docs/verification.md).

Mutants that a row must catch are injected as in tests/test_verification_claims.py: a library function
(here ``estep.smooth`` or ``mstep.maximize``) is replaced by a broken one and the row's verdict must flip.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from soc_opt import estep, mstep
from soc_opt import testing as G
from soc_opt.models import AugmentedModel, LinearGaussianPolicy
from soc_opt.verification import checks, checks_ecm, claims_em, claims_uniqueness, registry
from soc_opt.verification.hypotheses import HypothesisError, require_standing_hypotheses, scaled_pd_margin
from soc_opt.verification.oracle import dense_posterior, smoother_errors


def _run(key, instances=12):
    (r,) = registry.run_claims(0, instances=instances, only=(key,))
    return r


# --------------------------------------------------------------------------- ECM


def test_woodbury_makes_the_exact_normal_equations_a_left_multiple_of_the_surrogate_ones():
    """B^T S^-1 B = (I + H Sigma)^-1 H and B^T S^-1 = (I + H Sigma)^-1 B^T So^-1 with S = So + B Sigma B^T
    (docs/math.md §5): the two maximisers in [K k] solve the same equation."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        n, m = int(rng.integers(1, 5)), int(rng.integers(1, 3))
        B = rng.standard_normal((n + 1, m))
        So = G.random_spd_spectrum(rng, n + 1, 0.05, 0.5)
        Sig = G.random_spd_spectrum(rng, m, 0.2, 1.0)
        H = B.T @ np.linalg.solve(So, B)
        S = So + B @ Sig @ B.T
        left = np.linalg.inv(np.eye(m) + H @ Sig)
        np.testing.assert_allclose(B.T @ np.linalg.solve(S, B), left @ H, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.linalg.solve(S, B).T, left @ np.linalg.solve(So, B).T, rtol=1e-10, atol=1e-12)


def test_with_sigma_fixed_the_surrogate_mstep_is_an_ecm_step_and_log_p_never_decreases():
    """100 random well-posed instances: the surrogate M-step's [K k] (mstep.maximize, Sigma held) equals the
    maximiser of the exact Q in Q's metric to 1e-7 relative, and log p(Y) and Q do not decrease."""
    r = _run("ecm", instances=100)
    assert r.verdict == registry.HOLDS and r.as_written.held == 100, r.as_written.example
    assert r.as_written.worst < 1e-9
    assert "log p(Y) decreased on 0/100" in r.as_written.notes[0]


def test_ecm_row_catches_a_perturbed_gain_update(monkeypatch):
    """A 1% error in the M-step's [K k] (mstep.maximize returns 1.01 [K k]) flips the ECM row."""
    assert _run("ecm").as_expected
    orig = mstep.maximize

    def broken(*a, **kw):
        r = orig(*a, **kw)
        p = r.policy
        return dataclasses.replace(r, policy=LinearGaussianPolicy(1.01 * p.K, 1.01 * p.k, p.cov))

    monkeypatch.setattr(mstep, "maximize", broken)
    r = _run("ecm")
    assert r.verdict == registry.FAILS and r.as_written.held == 0


# --------------------------------------------------------------------------- the smoother's mutants


def _smoother_mutant(monkeypatch, field, f):
    """``estep.smooth`` with ``field`` of its output replaced by ``f(field)``, everywhere the checks call it."""
    orig = estep.smooth

    def broken(*a, **kw):
        sm = orig(*a, **kw)
        return dataclasses.replace(sm, **{field: f(getattr(sm, field))})

    for mod in (estep, claims_em, claims_uniqueness):
        monkeypatch.setattr(mod, "smooth", broken)


SMOOTHER_MUTANTS = {
    "P_t|T x 1.1": ("cov", lambda x: 1.1 * np.asarray(x)),
    "P_(t+1,t)|T x 1.1": ("cross", lambda x: 1.1 * np.asarray(x)),
    "log p(Y) + 7": ("loglik", lambda x: x + 7.0),
}


@pytest.mark.parametrize("name", list(SMOOTHER_MUTANTS))
def test_smoother_row_catches_each_smoother_mutant(name, monkeypatch):
    """A 10% error in P_t|T or in P_(t+1,t)|T, or log p(Y) off by a constant: the smoother row (dense
    conditioning, the project's oracle) fails on every instance."""
    assert _run("smoother").as_expected
    _smoother_mutant(monkeypatch, *SMOOTHER_MUTANTS[name])
    r = _run("smoother")
    assert r.verdict == registry.FAILS and r.as_written.held == 0, name


def test_covariance_mutants_are_also_seen_by_the_em_inequality_rows(monkeypatch):
    """P_(t+1,t)|T x 1.1 also breaks the EM inequality of ltv (its corrected statement); P_t|T x 1.1 breaks
    cost_decrease's (docs/verification.md, mutant table): the smoother row is not the only witness."""
    _smoother_mutant(monkeypatch, *SMOOTHER_MUTANTS["P_(t+1,t)|T x 1.1"])
    assert not _run("ltv").as_expected
    monkeypatch.undo()
    _smoother_mutant(monkeypatch, *SMOOTHER_MUTANTS["P_t|T x 1.1"])
    assert not _run("cost_decrease").as_expected


@pytest.mark.parametrize("key", ["ecm", "em_lemma", "ltv"])
def test_monotonicity_rows_are_invariant_to_log_p_plus_a_constant(key, monkeypatch):
    """log p(Y) + c is harmless to the claims about changes of log p(Y) (ECM, the EM lemma, Lemma LTV and the
    EM inequality compare differences): same verdict, same tallies.  The smoother row is the one that sees it."""
    base = _run(key)
    _smoother_mutant(monkeypatch, *SMOOTHER_MUTANTS["log p(Y) + 7"])
    shifted = _run(key)
    assert shifted.verdict == base.verdict and shifted.as_expected
    assert shifted.as_written.held == base.as_written.held
    assert (shifted.corrected is None) == (base.corrected is None)
    if base.corrected is not None:
        assert shifted.corrected.held == base.corrected.held


def test_dense_oracle_matches_the_smoother_on_batched_and_single_sequences():
    rng = np.random.default_rng(4)
    model, policy, mu0, P0 = G.random_estep_instance(rng, 3, 2, 4)
    Y = np.stack([G.sample_model_trajectory(rng, model, policy, mu0, P0)[1] for _ in range(2)])
    sm = estep.smooth(model, policy, Y, mu0, P0)
    for i in range(2):
        one = estep.smooth(model, policy, Y[i], mu0, P0)
        e = smoother_errors(one, dense_posterior(model, policy, Y[i], mu0, P0))
        assert e.worst < 1e-8, e
        np.testing.assert_allclose(sm.mean[i], one.mean, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- standing hypotheses


def _instance(seed=0, n=2, m=1, T=3):
    rng = np.random.default_rng(seed)
    model = G.random_augmented_model(rng, n, m, T)
    policy = G.random_policy(rng, T, n, m)
    mu0, P0 = G.random_initial_state(rng, n)
    _, y = G.sample_model_trajectory(rng, model, policy, mu0, P0)
    return model, policy, mu0, P0, y


def test_library_accepts_a_negligible_P0_and_fails_later_without_naming_it():
    """Today's behaviour, unchanged (estep.py and mstep/ are not touched): P0 = 1e-14 I passes the E-step's
    check (smallest eigenvalue > 0) and the M-step then reports P_0 = Cov(s_0 | Y), not the input P0."""
    model, policy, mu0, _, y = _instance()
    sm = estep.smooth(model, policy, y, mu0, 1e-14 * np.eye(2))
    with pytest.raises(mstep.NonUniqueMaximizerError, match=r"P_0 = Cov\(s_0 \| Y\)"):
        mstep.maximize(model, estep.moments(sm, y), constraints=mstep.MStepConstraints(cov_floor=0.1), min_norm=False)


@pytest.mark.parametrize("P0", [1e-14 * np.eye(2), np.diag([1.0, 1e-14]), np.diag([1.0, 0.0])])
def test_verification_names_a_non_positive_definite_P0_up_front(P0):
    model, _, mu0, _, _ = _instance()
    with pytest.raises(HypothesisError, match=r"^P0 \(the initial state covariance\)"):
        require_standing_hypotheses(model, mu0, P0)


def test_verification_names_a_singular_observation_noise_covariance():
    model, _, mu0, P0, _ = _instance()
    So = np.array(model.So)
    v = np.ones(3) / np.sqrt(3)
    So[1] = So[1] - (v @ np.linalg.solve(So[1], v)) ** -1 * np.outer(v, v) * (1 - 1e-12)  # nearly singular along one direction
    bad = AugmentedModel(model.Ao, model.co, So, model.n)
    with pytest.raises(HypothesisError, match=r"^So_1 \(the observation-noise covariance of step 1\)"):
        require_standing_hypotheses(bad, mu0, P0)


def test_standing_hypotheses_test_is_scale_free_and_passed_by_every_verification_instance():
    """The margin does not move when a coordinate is rescaled, and the rows' instances all pass it (every
    drawer calls it, so a failing instance would stop run_claims)."""
    model, _, mu0, P0, _ = _instance()
    C = np.diag([1e4, 1e-3])
    assert scaled_pd_margin(C @ P0 @ C, C @ (P0 + np.outer(mu0, mu0)) @ C) == pytest.approx(
        scaled_pd_margin(P0, P0 + np.outer(mu0, mu0)), rel=1e-9)
    res = registry.run_claims(0, instances=3)
    assert all(r.as_expected for r in res)
    doc = registry.verdicts_json(res)
    standing = {row["key"]: row["standing_hypotheses"] for row in doc["claims"]}
    for key in ("uniqueness", "dpsoc", "ecm", "smoother"):
        assert "P0 > 0" in standing[key] and "So_k > 0" in standing[key]
    assert "P0 > 0 and So_k > 0" in registry.CLAIMS[0].corrected


# --------------------------------------------------------------------------- scale invariance

SCALES = (1.0, 30.0, 300.0, 1e4)


def _units(i: int, c: float) -> tuple[float, float]:
    """(state scale, action scale): the state, the action, or both, in turn."""
    return ((c, 1.0), (1.0, c), (c, c))[i % 3]


def test_claim_checks_have_no_false_failure_on_rescaled_instances():
    """Issue 32: 100 well-posed random instances, each rescaled (state, action, or both) by 1, 30, 300, 1e4
    (checks.rescale_instance: the same problem in other units, smoothed again): every per-instance check of
    the rows uniqueness, uniqueness_sigma, ltv, dpsoc, ecm and smoother gives the verdict it gives at
    scale 1 (rows expected to hold: held; corrected statements: held; statements as written that fail:
    still fail).  Their tolerances are relative to the problem's own quantities."""
    rng = np.random.default_rng(320)
    wrong = []
    for i in range(100):
        n = int(rng.integers(1, 5))
        m = int(rng.integers(1, min(n + 1, 3) + 1))
        T = int(rng.integers(2, 5))
        inst = checks.draw_instance(rng, n, m, T, shared_cov=True)
        sig = checks.SigmaCase(inst, G.random_spd_spectrum(rng, m, 0.05, 0.3),
                               np.stack([rng.standard_normal((m, m)) for _ in range(5)]))
        ltv = checks.LtvCase(inst, rng.standard_normal((T, m, n + 1)), float(rng.uniform(0.3, 3.0)))
        dp = checks.DpsocCase(inst, int(rng.integers(0, T)), rng.standard_normal((m, n + 1)),
                              tuple((rng.standard_normal((T, m, m)), rng.standard_normal((T, m, n + 1)))
                                    for _ in range(2)))
        ecm = checks_ecm.EcmCase(inst)
        base = {}
        for c in SCALES:
            cs, ca = _units(i, c)
            r_inst = checks.rescale_instance(inst, cs, ca)
            got = {
                "uniqueness": checks.uniqueness_case(r_inst),
                "uniqueness_sigma": checks.uniqueness_sigma_case(sig.rescaled(cs, ca)),
                "ltv": checks.ltv_case(ltv.rescaled(cs, ca)),
                "dpsoc": checks.dpsoc_case(dp.rescaled(cs, ca)),
                "ecm": checks_ecm.ecm_case(ecm.rescaled(cs, ca)),
                "smoother": checks_ecm.smoother_case(r_inst),
            }
            flags = {k: (r.ok, r.co_ok) for k, r in got.items()}
            if c == 1.0:
                base = flags
                expect = {"uniqueness": (True, True), "uniqueness_sigma": (False, True), "dpsoc": (True, None),
                          "ecm": (True, None), "smoother": (True, None)}
                bad = {k: v for k, v in expect.items() if flags[k] != v} | (
                    {} if flags["ltv"][1] else {"ltv": flags["ltv"]})
                if bad:
                    wrong.append((i, "scale 1", bad))
            elif flags != base:
                wrong.append((i, (cs, ca), {k: (base[k], v) for k, v in flags.items() if v != base[k]}))
    assert not wrong, f"{len(wrong)} verdict changes, first {wrong[:5]}"
