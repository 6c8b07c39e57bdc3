"""The optimisation methods (docs/math.md §7) and the one registry the drivers read.

- :mod:`.base`: the :class:`~soc_opt.methods.base.Method` protocol and the generic run loop;
- :mod:`.config`: the run configuration (:class:`DPSOCConfig` and its sections);
- :mod:`.state`: run state, iteration records, best policy (what checkpoints hold);
- :mod:`.lqr_flm`, :mod:`.dpsoc_em`: the sample-based methods; iLQG is :mod:`soc_opt.methods.ilqg`;
- :mod:`.registry`: one line per method, filling :data:`soc_opt.plugins.METHODS` (name -> method).

The registry is imported explicitly (``from soc_opt.methods.registry import METHODS``) so that a
method module can import the base and state modules of this package without a cycle; the core
(configuration, state files, run directories) reads :data:`soc_opt.plugins.METHODS`, which imports the
registry on first use.
"""
