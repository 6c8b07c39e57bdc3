"""The optimisation methods (docs/math.md §7) and the one registry the drivers read.

- :mod:`.base`: the :class:`~soc_opt.methods.base.Method` protocol, its check, the flags check and the
  generic run loop;
- :mod:`.config`: the run configuration (:class:`DPSOCConfig` and its shared sections);
- :mod:`.state`: history rows and best policy (every method), the sample-based methods' run state;
- one folder per method: :mod:`.lqr_flm` (settings, step acceptance, the iteration), :mod:`.dpsoc_em`
  (settings, the EM phase plugged into that iteration), :mod:`.ilqg` (settings, state, iteration);
- :mod:`.registry`: one line per method, filling :data:`soc_opt.plugins.METHODS` (name -> method).

The registry is imported explicitly (``from soc_opt.methods.registry import METHODS``) so that a
method module can import the base and state modules of this package without a cycle; the core
(configuration, state files, run directories) reads :data:`soc_opt.plugins.METHODS`, which imports the
registry on first use.
"""
