"""The paper's claims as data (docs/math.md §9): label, statement as written, hypotheses, the
statement that does hold, the expected verdict and the check that decides the verdict.

A verdict is ``holds`` (the statement as written held on every instance), ``holds under corrected
statement`` (it failed, the corrected statement held on the same instances) or ``fails``.  When the
corrected statement is about another quantity than the claim (``Claim.corrected_is_about``, e.g. the
cost claim, whose corrected statement is about log p(Y)), the verdict stays ``fails`` and
``ClaimVerdict.what_holds`` says separately what the other statement is about and whether it held.  A
claim whose verdict differs from its expected verdict makes ``soc-opt verify`` exit non-zero.
Failing statements point to a certificate: the minimal counterexample found by
:mod:`soc_opt.verification.certificates`, re-checked by ``soc-opt verify --replay FILE``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import checks, checks_ecm, checks_kl
from .common import child_rng
from .hypotheses import STANDING

__all__ = ["Claim", "ClaimVerdict", "CLAIMS", "HOLDS", "CORRECTED", "FAILS", "run_claims", "verdicts_json",
           "format_verdicts", "CERT_DIR"]

HOLDS, CORRECTED, FAILS = "holds", "holds under corrected statement", "fails"
#: where the committed certificates live (relative to the repository root)
CERT_DIR = "docs/results/verification"


@dataclass(frozen=True)
class Claim:
    """One claim of the paper.  ``check(rng, instances, full) -> (as_written, corrected | None)``."""

    key: str
    label: str
    cite: str
    statement: str
    hypotheses: str
    corrected: str | None
    expected: str
    certificate: str | None
    check: Callable
    #: set when the corrected statement is about another quantity than the claim (e.g. log p(Y) instead
    #: of cost): it is then reported on its own line and cannot turn the verdict into "holds under
    #: corrected statement"
    corrected_is_about: str | None = None
    #: hypotheses the check's statements rely on that the paper leaves implicit (docs/math.md §9.1): for the
    #: rows that use P_j|T > 0, "P0 > 0 and So_k > 0" (hypotheses.STANDING); every instance is checked against
    #: them up front (hypotheses.require_standing_hypotheses)
    standing: str | None = None


@dataclass(frozen=True)
class ClaimVerdict:
    """The outcome of one claim: its verdict and both tallies (``checks.Outcome``)."""

    claim: Claim
    verdict: str
    as_written: checks.Outcome
    corrected: checks.Outcome | None
    seconds: float

    @property
    def as_expected(self) -> bool:
        """The verdict is the expected one and, for a claim with ``corrected_is_about``, the other
        statement (reported by :attr:`what_holds`) held too."""
        if self.claim.corrected_is_about is not None and not (self.corrected is not None and self.corrected.holds):
            return False
        return self.verdict == self.claim.expected

    @property
    def what_holds(self) -> str | None:
        """For a claim whose corrected statement is about another quantity: what that statement is about
        and whether it held (the claim's own verdict stays ``fails``)."""
        c, co = self.claim, self.corrected
        if c.corrected_is_about is None or co is None:
            return None
        return (f"the claim fails; a different statement, about {c.corrected_is_about}, "
                f"{'holds' if co.holds else 'does not hold'} ({co.held}/{co.instances}): {c.corrected}")


def _verdict(aw: checks.Outcome, co: checks.Outcome | None, corrected_is_about: str | None = None) -> str:
    if aw.holds:
        return HOLDS
    if co is not None and co.holds and corrected_is_about is None:
        return CORRECTED
    return FAILS


# --------------------------------------------------------------------------- wrappers of the older rows


def _from_rows(rows, meaning: str) -> checks.Outcome:
    out = checks.Outcome(meaning)
    for r in rows:
        out.instances += r.instances
        out.held += r.held
        if out.example is None and r.held < r.instances:
            out.example = {"row": r.claim, "counterexample": r.counterexample}
        out.notes.append(f"{r.claim}: {r.held}/{r.instances}, worst margin {r.worst_margin:.3g}")
    out.worst = float(max(r.worst_margin for r in rows)) if rows else float("nan")
    return out


def _em_lemma(rng, instances: int, full: bool):
    from .claims_em import claim2_em_monotone

    seed = int(rng.integers(2**31))
    # exact EM dominates the run time: the full run caps it at 30 instances of 12 iterations
    rows = claim2_em_monotone(seed, min(instances, 30), iterations=12 if full else 6, sequences=2,
                              inner=50 if full else 20)
    return _from_rows([r for r in rows if r.claim.startswith("2a")],
                      "most negative (l_(i+1) - l_i)/max(1,|l_i|) over exact-EM iterations (held if >= -1e-9)"), None


def _free_energy(rng, instances: int, full: bool):
    from .free_energy import claim4_free_energy

    seed = int(rng.integers(2**31))
    rows = claim4_free_energy(seed, instances, mc_samples=100_000 if full else 20_000, n_other=40 if full else 12)
    by = {r.claim[:2]: r for r in rows}
    aw = _from_rows([by["4b"], by["4d"]], "as written: sup for both signs of rho (rows 4b, 4d)")
    co = _from_rows([by["4a"], by["4b"], by["4c"], by["4e"]],
                    "sup for rho > 0, inf for rho < 0, equality at Q*, Monte Carlo (rows 4a, 4b, 4c, 4e)")
    return aw, co


def _hessian_impl(rng, instances: int, full: bool):
    from .claims_uniqueness import claim1_uniqueness

    seed = int(rng.integers(2**31))
    rows = claim1_uniqueness(seed, min(instances, 40), fd_instances=min(instances, 40))
    return _from_rows([r for r in rows if r.claim.startswith("1e")],
                      "max |H_fd - H|/max|H|, mstep.surrogate by finite differences (held if <= 1e-6)"), None


# --------------------------------------------------------------------------- the table


CLAIMS: tuple[Claim, ...] = (
    Claim("uniqueness", "Theorem uniqueness ([F_j e_j])", "docs/math.md §5, §9.1",
          "the per-step M-step maximiser [F_j e_j] of Lbar_j is unique",
          "as written: none stated (the rank condition appears only in the proof); the corrected statement: the "
          "stacked B_j = [B^d_j; B^y_j] of full column rank (H_j > 0) and the standing hypotheses",
          "the [F_j e_j] equation has a unique solution iff H_j = B_j^T (So_j)^-1 B_j > 0 with the stacked "
          "B_j = [B^d_j; B^y_j] (so m <= n+1); P_j|T > 0 is automatic under the model given P0 > 0 and So_k > 0",
          CORRECTED, f"{CERT_DIR}/uniqueness_n1_m2_T1.json", checks.uniqueness_gain, standing=STANDING),
    Claim("uniqueness_sigma", "Theorem uniqueness (Sigma_j)", "docs/math.md §5",
          "the maximiser in Sigma_j is the unique stationary point of Lbar_j",
          "none stated",
          "Lbar_j is linear with gradient -H_j/2 in Sigma_j, so there is no stationary point in the PD cone; on "
          "{Sigma >= Sigma_min} the maximiser is Sigma_min (a boundary point), unique iff H_j > 0",
          CORRECTED, f"{CERT_DIR}/uniqueness_sigma_n1_m1_T1.json", checks.uniqueness_sigma),
    Claim("ltv", "Lemma LTV", "docs/math.md §5",
          "L = log p(s_1) + sum_k Lbar_k, and an M-step that raises L raises log p(Y) at least as much "
          "(dlog p(Y) >= dL)",
          "smoothed moments under the current policy; Sigma free in the M-step (cov floor)",
          "the EM inequality dlog p(Y) >= dQ with Q = sum_k E[log N(zeta_k; M_k s_k + m_k, S_k)] (action integrated "
          "out) for every move",
          CORRECTED, f"{CERT_DIR}/ltv_n1_m1_T1.json", checks.lemma_ltv),
    Claim("dpsoc", "Proposition DPSOC", "docs/math.md §5",
          "the backward sweep j = T-1..0, phi_j = argmax Lbar_j with the future fixed, maximises sum_k Lbar_k",
          "smoothed moments fixed; B_j full column rank; feasible set {Sigma >= Sigma_min}",
          None, HOLDS, None, checks.proposition_dpsoc, standing=STANDING),
    Claim("em_lemma", "EM lemma", "docs/math.md §5, §9.2",
          "exact EM never decreases log p(Y)",
          "exact M-step (action integrated out), capped inner iterations (generalized EM)",
          None, HOLDS, None, _em_lemma),
    Claim("cost_decrease", "Theorem IV.1 of the reference (cost decrease)", "docs/math.md §9.3",
          "if the surrogate M-step raises L, then E[V_{phi^{i+1}}|Y] <= E[V_{phi^i}|Y]",
          "quadratic cost, y = exp(-Y) modelled linearly, Sigma held at Sigma^i",
          "the EM inequality: dlog p(Y) >= dQ for the same move, and exact EM does not lower log p(Y)",
          FAILS, f"{CERT_DIR}/cost_decrease_n1_m1_T1.json", checks.theorem_cost_decrease,
          corrected_is_about="log p(Y) (the EM inequality), not the cost E[V|Y]"),
    Claim("free_energy", "Lemma radon (free energy)", "docs/math.md §9.4",
          "(1/rho) log E_P[exp(rho J)] = sup_Q (E_Q J - KL(Q||P)/rho), attained by Q* ∝ P exp(rho J)",
          "rho != 0, E_P[exp(rho J)] finite",
          "sup for rho > 0, inf for rho < 0 (dividing by rho < 0 reverses the inequality)",
          CORRECTED, f"{CERT_DIR}/free_energy_rho_neg_d1.json", _free_energy),
    Claim("hessian_impl", "Implementation: analytic M-step Hessian", "docs/math.md §5",
          "-(Stilde_j kron H_j) is the Hessian of mstep.surrogate in vec([K_j k_j])",
          "well-posed instances", None, HOLDS, None, _hessian_impl),
    Claim("ecm", "ECM step (Sigma fixed)", "docs/math.md §5, §9.2",
          "with Sigma held at Sigma^i, the surrogate M-step's maximiser over [K_j k_j] equals the maximiser of the "
          "exact expected complete-data log-likelihood Q (Woodbury: B^T S^-1 = (I + H Sigma)^-1 B^T So^-1), so the "
          "step is an ECM step and log p(Y) does not decrease",
          "Sigma^(i+1) = Sigma^i (M-step floor = Sigma^i); H_j > 0 (stacked B_j of full column rank); smoothed "
          "moments of the current policy",
          None, HOLDS, None, checks_ecm.ecm_step, standing=STANDING),
    Claim("smoother", "Implementation: E-step smoother = dense conditioning", "docs/math.md §4",
          "estep.smooth's means, P_t|T, P_(t+1,t)|T and log p(Y) equal those of conditioning the joint Gaussian of "
          "(s_0..s_T, y_0..y_(T-1)) on Y with dense linear algebra",
          "small T (dense oracle)", None, HOLDS, None, checks_ecm.smoother_oracle, standing=STANDING),
    Claim("kl_step", "Implementation: KL-constrained LQG step", "docs/math.md §6",
          "lqg.kl_step (closed form: the dual over the multipliers, one backward pass per trial multiplier) solves "
          "min sum_k E[l_k] s.t. KL_k <= nu_k (or sum_k KL_k <= nu): every KL_k (by lqg.kl_divergence) meets its "
          "budget, with equality where eta_k > 10 eta_min; the policy minimises the Lagrangian sum_k E[l_k] + "
          "sum_k eta_k KL_k (finite differences of lqg.expected_cost and lqg.kl_divergence); the dual value equals "
          "the cost, and the dual function (lqg.dual.dual_function) at other multipliers stays below it",
          "convex stage costs (positive definite action block), positive definite reference covariances, finite "
          "budgets in [0.05, 0.5] per step; n <= 3, m <= 2, T <= 4",
          None, HOLDS, None, checks_kl.kl_step_kkt),
)

_TAGS = {c.key: i + 10 for i, c in enumerate(CLAIMS)}


def run_claims(seed: int = 0, *, full: bool = False, instances: int | None = None,
               only: tuple[str, ...] | None = None) -> list[ClaimVerdict]:
    """Run every claim's check (quick: 20 instances each; ``full``: 100 and the literal
    CVXPY sweep).  Each claim draws from ``Generator(PCG64([seed, tag]))`` of its own."""
    n = instances if instances is not None else (100 if full else 20)
    if n < 1:
        raise ValueError(f"instances must be >= 1, got {n}")
    out = []
    for c in CLAIMS:
        if only is not None and c.key not in only:
            continue
        t0 = time.perf_counter()
        aw, co = c.check(child_rng(seed, _TAGS[c.key]), n, full)
        out.append(ClaimVerdict(c, _verdict(aw, co, c.corrected_is_about), aw, co, time.perf_counter() - t0))
    return out


def _outcome_json(o: checks.Outcome | None):
    from .table import json_safe

    if o is None:
        return None
    return json_safe({"instances": o.instances, "held": o.held, "worst_margin": o.worst,
                       "margin_meaning": o.margin_meaning, "notes": o.notes, "first_failure": o.example})


def verdicts_json(results: list[ClaimVerdict]) -> dict:
    """``{"ok": bool, "claims": [...]}`` with ``expected``, ``verdict`` and ``certificate`` per claim."""
    rows = []
    for r in results:
        c = r.claim
        rows.append({"key": c.key, "label": c.label, "cite": c.cite, "statement": c.statement,
                     "hypotheses": c.hypotheses, "standing_hypotheses": c.standing, "corrected_statement": c.corrected,
                     "expected": c.expected,
                     "verdict": r.verdict, "as_expected": r.as_expected, "what_holds": r.what_holds,
                     "certificate": c.certificate if r.verdict != HOLDS else None,
                     "as_written": _outcome_json(r.as_written), "corrected": _outcome_json(r.corrected),
                     "seconds": round(r.seconds, 3)})
    return {"ok": all(r.as_expected for r in results), "claims": rows}


def format_verdicts(results: list[ClaimVerdict]) -> str:
    """Plain-text claims table."""
    head = ("claim", "as written", "corrected", "verdict", "expected", "")
    rows = []
    for r in results:
        co = "-" if r.corrected is None else f"{r.corrected.held}/{r.corrected.instances}"
        rows.append((r.claim.label, f"{r.as_written.held}/{r.as_written.instances}", co, r.verdict,
                     r.claim.expected, "ok" if r.as_expected else "UNEXPECTED"))
    w = [max(len(h), *(len(x[i]) for x in rows)) for i, h in enumerate(head)]
    lines = ["  ".join(c.ljust(w[i]) for i, c in enumerate(x)).rstrip() for x in (head, tuple("-" * k for k in w), *rows)]
    for r in results:
        if r.verdict != HOLDS and r.claim.certificate:
            lines.append(f"{r.claim.label}: counterexample {r.claim.certificate}")
        if r.what_holds:
            lines.append(f"  [{r.claim.key}] {r.what_holds}")
        if r.claim.standing:
            lines.append(f"  [{r.claim.key}] standing hypotheses: {r.claim.standing}")
        for note in r.as_written.notes + (r.corrected.notes if r.corrected else []):
            lines.append(f"  [{r.claim.key}] {note}")
    return "\n".join(lines)


def total_seconds(results: list[ClaimVerdict]) -> float:
    return float(np.sum([r.seconds for r in results]))
