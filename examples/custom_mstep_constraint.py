"""Solve one M-step with a constraint soc_opt does not ship (docs/math.md §5), in CVXPY.

The surrogate Lbar_k is an exact quadratic in f = vec([K_k k_k]) (column-major) plus a linear
term in Sigma_k, so its value, gradient and Hessian at any policy define it completely:

    Lbar_k(f, Sigma) = Lbar_k(f0, Sigma0) + g^T (f - f0) + 1/2 (f - f0)^T Hs (f - f0)
                       + <G_Sigma, Sigma - Sigma0>,      Hs = -(Stilde kron H) <= 0.

Here we add a custom constraint — the offsets of all joints sum to zero and every feedback
gain on the velocity states is bounded by 0.05 — and check, first, that without it the same
CVXPY problem reproduces soc_opt's closed form.
Run: .venv/bin/python examples/custom_mstep_constraint.py
"""

import cvxpy as cp
import numpy as np

from soc_opt import estep, lqg, mstep
from soc_opt.learning import fit
from soc_opt.tasks import load_task

rng = np.random.default_rng(0)
task = load_task("linear2d")
# a non-trivial current policy: LQR on the known model, with exploration noise
T, n_, m_ = task.T, task.n, task.m
lq = lqg.lqr(task.linearize(), task.cost_expansion(np.zeros((T + 1, n_)), np.zeros((T, m_))), task.mu0, task.P0)
policy = lq.with_cov(np.broadcast_to(4.0 * np.eye(m_), (T, m_, m_)).copy())
ro = task.rollouts(policy, 20, rng)
model = fit.fit_augmented(ro, fit.FitConfig(prior="none"))
Y = fit.cost_observations("measured", ro, model, policy, task.mu0, task.P0, rng)
sm = estep.smooth(model, policy, Y, task.mu0, task.P0)
mom = estep.moments(sm, Y)

k = 10  # one time step
n, m = task.n, task.m
Sigma_min = 0.5 * np.asarray(policy.cov[k])
d = mstep.surrogate_grad_hess(model, mom, k, policy)
f0 = np.concatenate([policy.K[k], policy.k[k][:, None]], axis=1).reshape(-1, order="F")
value0 = mstep.surrogate_from_moments(model, mom, policy)[k]

f = cp.Variable(m * (n + 1))
Sigma = cp.Variable((m, m), PSD=True)
Hneg = -0.5 * (d.hess + d.hess.T)  # PSD
objective = (value0 + d.grad @ (f - f0) - 0.5 * cp.quad_form(f - f0, cp.psd_wrap(Hneg))
             + cp.trace(d.grad_sigma @ (Sigma - policy.cov[k])))
base = [Sigma >> Sigma_min]

# 1. without the custom constraint: same maximiser as the closed form
cp.Problem(cp.Maximize(objective), base).solve(solver=cp.CLARABEL)
closed = mstep.maximize(model, mom, constraints=mstep.MStepConstraints(cov_floor=Sigma_min.tolist()),
                                min_norm=True).policy
F_closed = np.concatenate([closed.K[k], closed.k[k][:, None]], axis=1).reshape(-1, order="F")
print(f"closed-form gains: max |[K k]| = {np.abs(F_closed).max():.3f}")
print(f"no custom constraint: |f - f_closed|_max = {np.abs(f.value - F_closed).max():.2e}, "
      f"|Sigma - Sigma_closed|_max = {np.abs(Sigma.value - closed.cov[k]).max():.2e}")

# 2. with it: offsets sum to zero, |K[:, velocities]| <= 0.05
F = cp.reshape(f, (m, n + 1), order="F")
velocity = [2, 3]
custom = [cp.sum(F[:, n]) == 0, cp.abs(F[:, velocity]) <= 0.05]
prob = cp.Problem(cp.Maximize(objective), base + custom)
prob.solve(solver=cp.CLARABEL)
Fv = np.asarray(F.value)
print(f"custom constraint: status {prob.status}, Lbar_k {value0:.4f} -> {prob.value:.4f}, "
      f"sum of offsets {Fv[:, n].sum():.1e}, max |K_velocity| {np.abs(Fv[:, velocity]).max():.4f}")
