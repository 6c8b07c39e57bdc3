"""Grids of runs (docs/sweeps.md): :mod:`.spec` (the sweep file and one trial), :mod:`.runner` (Ray),
:mod:`.report` (tables and figures)."""
