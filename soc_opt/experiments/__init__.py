"""Experiments on disk: :mod:`.run` (one method in a resumable run directory), :mod:`.rundir` (its
files, contract, lock, checkpoints), :mod:`.compare` (LQR-FLM vs DPSOC-EM, docs/math.md §9.5),
:mod:`.report` (figures, Markdown), :mod:`.progress` (bars and lines), :mod:`.tblog` (TensorBoard)."""
