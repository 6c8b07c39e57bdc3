"""M-step (SPEC §5).  Intermediate state: the module moved to :mod:`soc_opt.mstep.maximize`
(a rename, so that its history follows); the next commit splits it into modules by concept."""

from .maximize import *  # noqa: F401,F403
from .maximize import _CACHE, _sigma_exact, __all__  # noqa: F401
