"""LQR and the KL-constrained LQG step (docs/math.md §6).

Problem.  Dynamics ``s_{k+1} ~ N(A_k s_k + B_k a_k + c_k, W_k)`` (``k = 0..T-1``), stage
costs ``l_k(z) = 1/2 z^T C_k z + z^T c_k + c0_k`` on ``z = (s_k, a_k)`` (no terminal cost:
``s_T`` is not charged), ``s_0 ~ N(mu0, P0)``, a reference policy
``phat(a|s) = N(Kh_k s + kh_k, Sh_k)`` with ``Sh_k > 0`` and KL budgets ``nu``::

    min_p  sum_k E_p[l_k]   s.t.   KL_k = E_{p(s_k)} KL(p(.|s_k) || phat(.|s_k)) <= nu_k

``nu`` is either a ``(T,)`` array (per-step budgets, multipliers ``eta_k``) or a scalar (one
total budget ``sum_k KL_k <= nu`` with one multiplier ``eta``, the GPS form).

Lagrangian and sign convention.  ``L(p, eta) = sum_k E[l_k] + sum_k eta_k (KL_k - nu_k)`` with
``eta_k >= 0``; the dual ``g(eta) = min_p L(p, eta)`` is concave with gradient
``dg/deta_k = KL_k - nu_k`` (envelope theorem).  CasADi/IPOPT use the Lagrangian
``f + lam_g^T g``; for ``g_k = KL_k <= ubg_k = nu_k`` an active upper bound has
``lam_g_k >= 0`` and ``lam_g_k = eta_k`` (no sign flip; checked by the tests).

Modules (each imports only from those below it):

* :mod:`.step`: the entries :func:`kl_step` and :func:`kl_step_local` (on a :class:`LocalModel`) and
  the closed-form path (``method="closed_form"``).
* :mod:`.casadi_nlp`: ``method="casadi"``, the NLP solved by IPOPT in its ``"symbolic"``
  formulation, and the IPOPT driver; :mod:`.structured_nlp`: the ``"structured"`` formulation.
* :mod:`.dual`: the scalar and vector dual solvers over the multipliers ``eta``.
* :mod:`.backward`: the backward pass for fixed ``eta`` (closed form, Quu repair rule) and
  :func:`lqr`.
* :mod:`.step_size`: the step-size rule (GPS): :class:`StepSizeConfig`, :func:`laplace_improvements`,
  :func:`adapt_multiplier`.
* :mod:`.moments`: forward pass, expected cost and KL in closed form.
* :mod:`.problem`: shared types (:class:`LocalModel`, the step's model; :class:`KLStepConfig`,
  :class:`KLStepResult`, :class:`Marginals`, :class:`SolverError`, :class:`BudgetUnreachable`), input
  validation and the per-step problem arrays.

Both the closed form and the CasADi/IPOPT NLP agree to about 1e-10 in policy and multipliers
on the tested instances.

Speed (closed form, one core of the development machine, ``n=26, m=7, T=100``): scalar budget
about 40 ms / 8 backward passes, per-step budgets about 80 ms / 16 passes
(``python -m soc_opt.bench.lqg``).
"""

from .backward import lqr
from .moments import expected_cost, forward, kl_divergence
from .problem import BudgetUnreachable, KLStepConfig, KLStepResult, LocalModel, Marginals, SolverError
from .step import KL_METHODS, kl_step, kl_step_local
from .step_size import StepSizeConfig, adapt_multiplier, laplace_improvements

__all__ = [
    "SolverError",
    "BudgetUnreachable",
    "Marginals",
    "KLStepConfig",
    "KLStepResult",
    "LocalModel",
    "forward",
    "expected_cost",
    "kl_divergence",
    "lqr",
    "kl_step",
    "kl_step_local",
    "KL_METHODS",
    "StepSizeConfig",
    "adapt_multiplier",
    "laplace_improvements",
]
