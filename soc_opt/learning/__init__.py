"""Learning the local models from rollouts (docs/math.md §2–§3): :mod:`.fit` (NIW posterior, cost
observations) and :mod:`.mixture` (the variational-Bayes mixture prior)."""
