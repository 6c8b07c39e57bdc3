"""Structured state estimation: known kinematics, learned actuation (``docs/math.md §11``).

Selected by ``[baseline.noise] estimator = "kinematic"``.  The estimator uses the robot's
kinematics (MuJoCo forward kinematics and site Jacobians), not its masses, inertia or damping,
which the paper's learner does not assume either way: it is prior knowledge beyond the paper.

Modules: :mod:`.model` (latent ``z = (q, qd)``, ``h`` and its Jacobian, the transition),
:mod:`.smoother` (iterated extended RTS smoother over rollouts), :mod:`.em` (the acceleration
map), :mod:`.filter` (the online filter saved with the policy), :mod:`.loop` (one call per
batch of rollouts), :mod:`.config` (``[baseline.noise.kinematic]``).
"""

from .config import KinematicConfig

__all__ = ["KinematicConfig"]
