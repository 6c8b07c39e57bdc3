"""Model-based iLQG (docs/math.md §7): the documented import path; the code is :mod:`soc_opt.methods.ilqg`."""

from .methods.ilqg import *  # noqa: F401,F403
from .methods.ilqg import __all__  # noqa: F401
