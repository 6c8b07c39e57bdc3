"""One DPSOC-EM recursion by hand on linear2d (docs/math.md §2–§5).

rollouts -> fit augmented model -> Y -> E-step (RTS smoother) -> DP M-step -> new policy.
Run: .venv/bin/python examples/em_iteration_by_hand.py
"""

import numpy as np

from soc_opt import estep, mstep
from soc_opt.learning import fit
from soc_opt.tasks import load_task

rng = np.random.default_rng(0)
task = load_task("linear2d")
policy = task.initial_policy(1.0)

# 1. sample M rollouts of the current policy (measured states s, actions a, costs Y, y = exp(-Y))
ro = task.rollouts(policy, 20, rng)
print(f"rollouts: s {ro.s.shape}, a {ro.a.shape}, y {ro.y.shape}; mean total cost {ro.total_cost().mean():.1f}")

# 2. augmented model of (s_{k+1}, y_k) given (s_k, a_k) with a variational-Bayes mixture prior
cfg = fit.FitConfig()
prior = fit.update_prior(None, ro, cfg, rng)
model = fit.fit_augmented(ro, cfg, prior)
print(f"augmented model: Ao {model.Ao.shape}, So {model.So.shape}")

# 3. cost observations Y (the paper's "model" mode: sampled from the fitted model)
Y = fit.cost_observations("model", ro, model, policy, task.mu0, task.P0, rng)

# 4. E-step: Kalman filter + RTS smoother of the closed loop (correlated s/y noise handled)
sm = estep.smooth(model, policy, Y, task.mu0, task.P0)
print(f"E-step: log p(Y) = {np.mean(sm.loglik):.3f} (mean over {Y.shape[0]} sequences)")

# 5. M-step: the DP sweep of the Proposition, closed form, covariance floor at half the current one
cons = mstep.MStepConstraints(cov_floor=(0.5 * np.asarray(policy.cov)).tolist())
new = mstep.maximize(model, estep.moments(sm, Y), constraints=cons, method="closed_form", min_norm=True).policy
before = mstep.surrogate(model, sm, Y, policy).sum()
after = mstep.surrogate(model, sm, Y, new).sum()
print(f"M-step: surrogate sum_k Lbar_k {before:.3f} -> {after:.3f}")

# the same M-step by CVXPY (Clarabel) agrees with the closed form
new_cvx = mstep.maximize(model, estep.moments(sm, Y), constraints=cons, method="cvxpy", min_norm=True).policy
print(f"closed form vs CVXPY: max |K diff| = {np.abs(new.K - new_cvx.K).max():.2e}")

# 6. evaluate: sample the EM policy
ro_new = task.rollouts(new, 20, rng)
print(f"mean total cost (true state): before {task.true_cost(ro).sum(-1).mean():.1f}, "
      f"after {task.true_cost(ro_new).sum(-1).mean():.1f}")
