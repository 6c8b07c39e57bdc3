"""Tests for the claims table and the certificate searches (soc_opt.verification.registry, .checks,
.certificates; docs/math.md §5, §9); the exact replay itself is tested in tests/test_replay.py.

Every claim row is shown to be able to fail: a mutant (a library function replaced by a broken
one: wrong sign, dropped term) makes the row's verdict differ from the expected verdict, and
``soc-opt verify`` then exits non-zero.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from soc_opt import estep, mstep
from soc_opt.cli import main
from soc_opt.lqg import dual as lqg_dual
from soc_opt.lqg import step as lqg_step
from soc_opt.lqg.problem import KLProblem
from soc_opt.models import LinearGaussianPolicy, QuadraticCost
from soc_opt.verification import certificates, registry
from soc_opt.verification import free_energy as fe
from soc_opt.verification.replay import replay

ROOT = Path(__file__).resolve().parents[1]
CERTS = sorted((ROOT / registry.CERT_DIR).glob("*.json"))
KEYS = [c.key for c in registry.CLAIMS]


# --------------------------------------------------------------------------- the table


def test_every_claim_reaches_its_expected_verdict_on_the_quick_run():
    res = registry.run_claims(0, instances=12)
    assert [r.claim.key for r in res] == KEYS
    for r in res:
        assert r.as_expected, (r.claim.key, r.verdict, r.as_written.held, r.as_written.instances)
    doc = registry.verdicts_json(res)
    json.dumps(doc)
    assert doc["ok"] is True
    for row in doc["claims"]:
        assert {"expected", "verdict", "certificate", "statement", "hypotheses"} <= set(row)
        if row["verdict"] != registry.HOLDS:
            assert (ROOT / row["certificate"]).is_file()


def test_claims_that_fail_as_written_all_have_a_committed_certificate():
    failing = [c for c in registry.CLAIMS if c.expected != registry.HOLDS]
    assert {c.certificate for c in failing} == {str(p.relative_to(ROOT)) for p in CERTS}


# --------------------------------------------------------------------------- certificates and replay


def test_searches_find_the_minimal_sizes_and_their_certificates_replay():
    got = {}
    for name, search in certificates.SEARCHES.items():
        cert = search()
        ok, lines = replay(json.loads(json.dumps(cert)))
        assert ok, "\n".join(lines)
        got[name] = (cert["n"], cert["m"], cert["T"])
    assert got["uniqueness_n1_m2_T1.json"] == (1, 2, 1)  # m = 1 with a nonzero B is always unique
    assert got["ltv_n1_m1_T1.json"] == (1, 1, 1)
    assert got["cost_decrease_n1_m1_T1.json"] == (1, 1, 1)
    assert got["uniqueness_sigma_n1_m1_T1.json"] == (1, 1, 1)
    assert got["free_energy_rho_neg_d1.json"][0] == 1


# --------------------------------------------------------------------------- command line


def test_verify_replay_command_exit_status(tmp_path, capsys):
    assert main(["verify", "--replay", *map(str, CERTS)]) == 0
    assert "FAILS (reproduced)" in capsys.readouterr().out
    cert = json.loads(CERTS[0].read_text())
    cert["data"]["new" if "new" in cert["data"] else "F2"] = cert["data"].get("old", cert["data"].get("F1"))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(cert))
    assert main(["verify", "--replay", str(bad)]) == 1


def test_verify_unknown_only_key_is_a_clear_error(capsys):
    assert main(["verify", "--only", "dpsoc,nonsense"]) == 2
    assert "nonsense" in capsys.readouterr().err


# --------------------------------------------------------------------------- mutants


def _drop_offset(monkeypatch):
    """Mutant: the surrogate ignores the offset k (a dropped term)."""
    orig = mstep.objectives.surrogate_from_moments

    def broken(model, mom, policy, include_constant=False):
        p = LinearGaussianPolicy(policy.K, np.zeros_like(policy.k), policy.cov, allow_singular=True)
        return orig(model, mom, p, include_constant)

    monkeypatch.setattr(mstep.objectives, "surrogate_from_moments", broken)


def _sigma_wrong_sign(monkeypatch):
    """Mutant: +1/2 tr(H Sigma) instead of -1/2 tr(H Sigma) in the surrogate."""
    orig = mstep.objectives.surrogate_from_moments

    def broken(model, mom, policy, include_constant=False):
        p0 = LinearGaussianPolicy(policy.K, policy.k, np.zeros_like(policy.cov), allow_singular=True)
        v0 = orig(model, mom, p0, include_constant)
        return 2 * v0 - orig(model, mom, policy, include_constant)

    monkeypatch.setattr(mstep.objectives, "surrogate_from_moments", broken)


def _exact_without_action_noise(monkeypatch):
    """Mutant: the exact objective drops B Sigma B^T from its covariance (it becomes the surrogate)."""
    monkeypatch.setattr(mstep, "exact_objective",
                        lambda model, sm, y, p: mstep.surrogate(model, sm, y, p, include_constant=True))


def _maximize_wrong_offset_sign(monkeypatch):
    """Mutant: the M-step returns -k (wrong sign of the offset)."""
    orig = mstep.maximize

    def broken(*a, **kw):
        r = orig(*a, **kw)
        p = r.policy
        return dataclasses.replace(r, policy=LinearGaussianPolicy(p.K, -p.k - 0.5, p.cov))

    monkeypatch.setattr(mstep, "maximize", broken)


def _log_partition_drops_logdet(monkeypatch):
    """Mutant: log E_P[exp(rho J)] without its -1/2 log|N| term."""
    orig = fe.log_partition

    def broken(mu, S, A, b, c, rho):
        _, N, _, _ = fe._tilt_parts(*fe._quad_checked(mu, S, A, b, c)[:4], rho)
        return orig(mu, S, A, b, c, rho) + 0.5 * np.linalg.slogdet(N)[1]

    monkeypatch.setattr(fe, "log_partition", broken)


def _maximize_perturbed_gains(monkeypatch):
    """Mutant: the M-step's [K k] off by 1% (1.01 [K k]); Sigma untouched."""
    orig = mstep.maximize

    def broken(*a, **kw):
        r = orig(*a, **kw)
        p = r.policy
        return dataclasses.replace(r, policy=LinearGaussianPolicy(1.01 * p.K, 1.01 * p.k, p.cov))

    monkeypatch.setattr(mstep, "maximize", broken)


def _smoother_cov_times_1_1(monkeypatch):
    """Mutant: the smoother's covariances P_t|T 10% too large (tests/test_verification_rows.py has the
    cross-covariance and log p(Y) mutants too)."""
    orig = estep.smooth

    def broken(*a, **kw):
        sm = orig(*a, **kw)
        return dataclasses.replace(sm, cov=1.1 * np.asarray(sm.cov))

    monkeypatch.setattr(estep, "smooth", broken)


def _kl_covariance_term_wrong_sign(monkeypatch):
    """Mutant: the dual's KL_k with its covariance term subtracted (``1/2 (quad - cov)`` instead of
    ``1/2 (quad + cov)``, ``cov = sum_i log1p(mu_i/eta) - mu_i/(mu_i + eta)``): the solver meets the budgets on
    a wrong KL."""
    orig = lqg_dual.evaluate_eta

    def broken(prob, bw):
        ev = orig(prob, bw)
        pos = np.isfinite(bw.eta) & (bw.eta > 0)
        mu, e = ev.mu_eig[pos], bw.eta[pos][:, None]
        cov = np.zeros(bw.eta.shape)
        cov[pos] = (np.log1p(mu / e) - mu / (mu + e)).sum(axis=1)
        return ev._replace(kl=ev.kl - cov)

    monkeypatch.setattr(lqg_dual, "evaluate_eta", broken)


def _kl_backward_off_by_one(monkeypatch):
    """Mutant: the backward pass reads step t+1's cost at step t (an off-by-one in its time index)."""
    orig = lqg_dual.backward_pass

    def broken(prob, eta, **kw):
        C = prob.cost
        shifted = QuadraticCost(np.concatenate([C.C[1:], C.C[-1:]]), np.concatenate([C.c[1:], C.c[-1:]]), C.n)
        return orig(KLProblem(prob.dynamics, shifted, prob.reference, prob.mu0, prob.P0), eta, **kw)

    monkeypatch.setattr(lqg_dual, "backward_pass", broken)


def _dual_objective_sign_flip(monkeypatch):
    """Mutant: ``dual_objective`` returns ``cost - eta (KL - nu)`` (its multiplier term with the wrong sign)."""

    def broken(ev, eta, nu):
        use = np.isfinite(eta) & (eta > 0)
        return float(ev.cost.sum() - eta[use] @ (ev.kl[use] - nu[use]))

    monkeypatch.setattr(lqg_dual, "dual_objective", broken)
    monkeypatch.setattr(lqg_step, "dual_objective", broken)


KL_MUTANTS = {"kl_covariance_sign": _kl_covariance_term_wrong_sign, "backward_off_by_one": _kl_backward_off_by_one,
              "dual_objective_sign": _dual_objective_sign_flip}


MUTANTS = {
    "uniqueness": _drop_offset,
    "uniqueness_sigma": _sigma_wrong_sign,
    "ltv": _exact_without_action_noise,
    "dpsoc": _maximize_wrong_offset_sign,
    "em_lemma": _maximize_wrong_offset_sign,
    "cost_decrease": _exact_without_action_noise,
    "free_energy": _log_partition_drops_logdet,
    "hessian_impl": _drop_offset,
    "ecm": _maximize_perturbed_gains,
    "smoother": _smoother_cov_times_1_1,
    "kl_step": _kl_backward_off_by_one,
}


def test_every_claim_has_a_mutant():
    assert set(MUTANTS) == set(KEYS)


@pytest.mark.parametrize("key", KEYS)
def test_mutant_makes_the_claim_row_fail(key, monkeypatch):
    (ok,) = registry.run_claims(0, instances=6, only=(key,))
    assert ok.as_expected
    MUTANTS[key](monkeypatch)
    (bad,) = registry.run_claims(0, instances=6, only=(key,))
    assert not bad.as_expected, (key, bad.verdict)
    assert bad.verdict == registry.FAILS


@pytest.mark.parametrize("mutant", list(KL_MUTANTS))
def test_verify_catches_each_kl_step_mutant(mutant, monkeypatch, capsys):
    """``soc-opt verify`` exits 1 with the KL step's dual KL, backward pass or dual objective broken."""
    assert main(["verify", "--only", "kl_step", "--instances", "6"]) == 0
    capsys.readouterr()
    KL_MUTANTS[mutant](monkeypatch)
    assert main(["verify", "--only", "kl_step", "--instances", "6", "--json"]) == 1
    row = json.loads(capsys.readouterr().out)["claims"][0]
    assert row["key"] == "kl_step" and row["expected"] == "holds" and row["verdict"] == "fails"


def test_verify_exits_nonzero_when_a_claim_expected_to_hold_breaks(monkeypatch, capsys):
    assert main(["verify", "--only", "dpsoc,ltv", "--instances", "4"]) == 0
    capsys.readouterr()
    _maximize_wrong_offset_sign(monkeypatch)
    assert main(["verify", "--only", "dpsoc,ltv", "--instances", "4", "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    row = {r["key"]: r for r in doc["claims"]}["dpsoc"]
    assert row["expected"] == "holds" and row["verdict"] == "fails" and doc["ok"] is False
