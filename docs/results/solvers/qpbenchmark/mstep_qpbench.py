"""The M-step QPs of soc_opt (docs/math.md section 5) as a qpbenchmark test set.

Written by soc_opt.bench.qp_bench_report.export_qpbenchmark: one .npz per problem in
problems/ (P, q, G, h), minimise 1/2 x^T P x + q^T x subject to G x <= h.  Families:
well_conditioned, ill_conditioned, degenerate, active.  Run: qpbenchmark mstep_qpbench.py run --results-path results/mstep_qpbench.csv
"""

from pathlib import Path

import numpy as np
import qpbenchmark


class MstepQpbench(qpbenchmark.TestSet):
    """soc_opt M-step problems (one time step each), unwhitened."""

    @property
    def description(self) -> str:
        return "soc_opt M-step QPs: P = Stilde kron H, q = -vec R from the smoother's moments."

    @property
    def title(self) -> str:
        return "soc_opt M-step test set"

    @property
    def sparse_only(self) -> bool:
        return False

    def __iter__(self):
        for path in sorted((Path(__file__).parent / "problems").glob("*.npz")):
            d = np.load(path)
            G = d["G"] if d["G"].size else None
            h = d["h"] if d["h"].size else None
            yield qpbenchmark.Problem(d["P"], d["q"], G, h, None, None, None, None, name=path.stem)
