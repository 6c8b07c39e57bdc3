"""Numerical checks of the paper's claims (docs/math.md §9, claims 1-4).

Each check draws random instances from a ``numpy.random.Generator`` seeded by
the caller, evaluates the claim on every instance against a stated tolerance
and returns one or more :class:`ClaimResult` rows: how many instances were
tried, how many behaved as the claim says, the worst margin (with what it
means) and, when an instance did not, a small counterexample.

Rows whose outcome is *informative* rather than a claim of the paper (the
surrogate M-step's monotonicity in log p(Y), the ill-posed uniqueness
instances, the sign convention of the free-energy lemma) say so in their
description.  ``docs/verification.md`` gives the exact definitions.

The claims table (``registry``: each claim's statement as written, hypotheses, corrected
statement, expected verdict; ``checks``: the checks through the library's code path;
``certificates``: minimal counterexamples; ``replay``: their re-check in exact arithmetic) is what
``soc-opt verify`` runs; ``run_all`` gives the older per-row table (``soc-opt verify --rows``).

Modules: ``claims_uniqueness`` (claim 1), ``claims_em`` (claims 2 and 3),
``free_energy`` (claim 4 and its Gaussian closed forms), ``table`` (rendering),
``common`` (the row type and shared helpers); for the claims table ``checks`` (its rows, per instance
and per row, and ``rescale_instance`` for the scale-invariance test), ``checks_ecm`` (the ECM row and
the smoother-against-oracle row), ``oracle`` (dense conditioning of the joint Gaussian, docs/math.md §4)
and ``hypotheses`` (the standing hypotheses ``P0 > 0``, ``So_k > 0``, checked up front).  The instance generators live in
:mod:`soc_opt.testing` and are re-exported here.

The functions are pure: no printing, no global state; ``format_table`` and
``to_json`` render the rows for the command line.
"""

from __future__ import annotations

from ..testing import random_augmented_model, random_initial_state, random_policy, sample_model_trajectory
from .claims_em import claim2_em_monotone, claim3_cost_decrease, expected_stage_costs
from .claims_uniqueness import claim1_uniqueness, hessian_nd_margin, step_hessian_nd_margin, surrogate_hessian
from .common import ClaimResult
from .free_energy import (
    claim4_free_energy,
    duality_objective,
    gaussian_kl,
    gaussian_quadratic_mean,
    log_partition,
    tilted_gaussian,
)
from .hypotheses import HypothesisError, require_standing_hypotheses
from .registry import CLAIMS, ClaimVerdict, format_verdicts, run_claims, verdicts_json
from .table import format_table, to_json

__all__ = [
    # the claims table (docs/verification.md): claims as data, verdicts, certificates
    "CLAIMS",
    "ClaimVerdict",
    "run_claims",
    "verdicts_json",
    "format_verdicts",
    "HypothesisError",
    "require_standing_hypotheses",
    # the older per-row table
    "ClaimResult",
    "run_all",
    "claim1_uniqueness",
    "claim2_em_monotone",
    "claim3_cost_decrease",
    "claim4_free_energy",
    "format_table",
    "to_json",
    # instance generators (from soc_opt.testing) and closed forms (used by the tests and the docs)
    "random_augmented_model",
    "random_policy",
    "random_initial_state",
    "sample_model_trajectory",
    "surrogate_hessian",
    "hessian_nd_margin",
    "step_hessian_nd_margin",
    "expected_stage_costs",
    "log_partition",
    "tilted_gaussian",
    "gaussian_kl",
    "gaussian_quadratic_mean",
    "duality_objective",
]


def run_all(seed: int = 0, instances: int = 20) -> list[ClaimResult]:
    """Run claims 1-4 with ``instances`` random instances each; rows in claim order.

    Every claim draws from its own stream ``Generator(PCG64([seed, claim]))``, so a claim's
    rows do not depend on which other claims ran.
    """
    if instances < 1:
        raise ValueError(f"instances must be >= 1, got {instances}")
    return [
        *claim1_uniqueness(seed, instances),
        *claim2_em_monotone(seed, instances),
        *claim3_cost_decrease(seed, instances),
        *claim4_free_energy(seed, instances),
    ]
