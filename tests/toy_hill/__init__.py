"""A toy method written from docs/architecture.md ("How to add", a method) alone: its own folder
(settings, state, method) and one registration line, ``soc_opt.plugins.METHODS.register(HILL)``.

"Hill": random search on the feed-forward term.  Each iteration samples ``[hill] samples`` rollouts of
the current policy and of the policy with its feed-forward moved by a random direction of length
``[hill] radius``; it keeps the move when its batch is cheaper.  It reads its ``[hill]`` table and the
flag ``--iterations``; it has no KL step, so its history rows have no ``kl``, ``nu``, ``mult`` columns.
"""

from .method import HILL, Hill

__all__ = ["HILL", "Hill"]
