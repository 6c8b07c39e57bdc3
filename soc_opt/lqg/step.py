"""The KL-constrained LQG step (docs/math.md §6): the entries :func:`kl_step` (the model's pieces as
arguments) and :func:`kl_step_local` (the same step on a :class:`~soc_opt.lqg.problem.LocalModel`),
and the closed-form path.

``method="closed_form"`` solves the dual over the multipliers (:mod:`.dual`) with one backward
pass per trial multiplier (:mod:`.backward`); ``method="casadi"`` solves the primal NLP with
IPOPT (:mod:`.casadi_nlp`), ``method="fatrop"`` its multiple-shooting form with fatrop
(:mod:`.fatrop_nlp`).
"""

from __future__ import annotations

import math

import numpy as np

from ..linalg import single_thread_blas_cached
from ..models import LinearGaussianDynamics, LinearGaussianPolicy, QuadraticCost
from .casadi_nlp import kl_step_casadi
from .dual import dual_objective, solve_scalar, solve_vector
from .fatrop_nlp import kl_step_fatrop
from .problem import KLProblem, KLStepConfig, KLStepResult, LocalModel, check_dims, check_init, check_nu, policy_from


def kl_step(dynamics: LinearGaussianDynamics, cost: QuadraticCost, reference: LinearGaussianPolicy, nu, mu0, P0,
            *, method: str = "closed_form", config: KLStepConfig | None = None, eta0=None) -> KLStepResult:
    """KL-constrained LQG step (docs/math.md §6): ``min sum_k E[l_k]  s.t.  KL_k <= nu_k`` (or ``sum KL <= nu``).

    Args:
        dynamics, cost: the local linear-Gaussian model and quadratic cost expansion.
        reference: ``phat`` (covariances must be positive definite).
        nu: scalar (one total budget, one multiplier: the GPS form) or ``(T,)`` per-step
            budgets; ``inf`` entries are unconstrained (``eta = 0``, deterministic step),
            ``0`` entries pin the step to the reference (``eta = inf``).
        mu0, P0: initial state distribution.
        method: a name in :data:`KL_METHODS`: ``"closed_form"`` (backward passes + dual solve),
            ``"casadi"`` (IPOPT NLP) or ``"fatrop"`` (multiple-shooting optimal control NLP solved
            by fatrop).
        config: :class:`KLStepConfig`.
        eta0: optional warm start of the multiplier(s) (closed form only).
    Returns a :class:`KLStepResult`.
    """
    config = KLStepConfig() if config is None else config
    if not isinstance(config, KLStepConfig):
        raise TypeError(f"config must be a KLStepConfig, got {type(config).__name__}")
    T, n, m = check_dims(dynamics, cost=cost, reference=reference)
    mu0, P0 = check_init(mu0, P0, n)
    nu_arr, scalar = check_nu(nu, T)
    nu_out = float(nu_arr[0]) if scalar else nu_arr.copy()
    solve = KL_METHODS.get(method)
    if solve is None:
        raise ValueError(f"unknown method {method!r}; use one of {', '.join(map(repr, KL_METHODS))}")
    return solve(KLProblem(dynamics, cost, reference, mu0, P0), nu_arr, scalar, nu_out, config, eta0)


def kl_step_local(model: LocalModel, reference: LinearGaussianPolicy, nu, *, method: str = "closed_form",
                  config: KLStepConfig | None = None, eta0=None) -> KLStepResult:
    """:func:`kl_step` on a fitted :class:`~soc_opt.lqg.problem.LocalModel` (dynamics, cost expansion,
    ``mu0``, ``P0``): ``kl_step(model.dynamics, model.cost, reference, nu, model.mu0, model.P0, ...)``,
    the same arithmetic and the same :class:`KLStepResult`.  The form the loop uses (the model it
    solved on is also what :func:`~soc_opt.lqg.step_size.laplace_improvements` reads)."""
    if not isinstance(model, LocalModel):
        raise TypeError(f"model must be a LocalModel (dynamics, cost, mu0, P0), got {type(model).__name__}")
    return kl_step(model.dynamics, model.cost, reference, nu, model.mu0, model.P0, method=method, config=config,
                   eta0=eta0)


def _closed_form(prob: KLProblem, nu, scalar, nu_out, config, eta0) -> KLStepResult:
    # many small matrix products: threaded BLAS gains nothing there, and on a loaded machine
    # its spinning threads made the dual solve several times slower
    with single_thread_blas_cached():
        return _kl_step_closed(prob, nu, scalar, nu_out, config, eta0)


def _casadi(prob: KLProblem, nu, scalar, nu_out, config, eta0) -> KLStepResult:
    return kl_step_casadi(prob, nu, scalar, nu_out, config)


def _fatrop(prob: KLProblem, nu, scalar, nu_out, config, eta0) -> KLStepResult:
    return kl_step_fatrop(prob, nu, scalar, nu_out, config)


#: The KL-step solvers: ``method`` name -> ``solve(problem, nu, scalar, nu_out, config, eta0)``.
#: A new solver is one module returning a :class:`KLStepResult` plus one entry here; the run
#: configuration's ``kl_method`` accepts every name in this table.
KL_METHODS = {"closed_form": _closed_form, "casadi": _casadi, "fatrop": _fatrop}


def _kl_step_closed(prob: KLProblem, nu: np.ndarray, scalar: bool, nu_out, config, eta0) -> KLStepResult:
    T = prob.T
    if scalar:
        v = float(nu[0])
        if math.isinf(v) or v == 0.0:
            eta_fixed = np.full(T, 0.0 if math.isinf(v) else math.inf)
            r, nb, it, status = solve_vector(prob, np.full(T, v), config, None)
            status = "unconstrained (nu = inf): LQR" if math.isinf(v) else "nu = 0: reference policy"
            eta = eta_fixed
            dual = float(r.cost.sum())
        else:
            r, nb, it, status = solve_scalar(prob, v, config, eta0)
            eta = r.bw.eta.copy()
            dual = float(r.cost.sum() + eta[0] * (r.kl.sum() - v))
    else:
        r, nb, it, status = solve_vector(prob, nu, config, eta0)
        eta = r.bw.eta.copy()
        dual = dual_objective(r, eta, nu)
    bw = r.bw
    return KLStepResult(
        policy=policy_from(bw.K, bw.k, bw.S, eta),
        eta=eta,
        kl=r.kl.copy(),
        expected_cost=float(r.cost.sum()),
        n_backward=nb,
        scalar_eta=scalar,
        nu=nu_out,
        dual_value=dual,
        method="closed_form",
        n_iter=it,
        status=status,
        marginals=r.marg,
    )
