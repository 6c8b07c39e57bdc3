"""Compare the closed forms with the general-purpose solvers (docs/math.md §5, §6).

M-step: closed form vs CVXPY/Clarabel vs CVXPY/SCS.
KL-constrained LQG step: closed form (LQR backward pass + dual) vs CasADi/IPOPT.
Run: .venv/bin/python examples/compare_solvers.py   (the same tables as `soc-opt solvers --quick`)
"""

from soc_opt.bench import lqg as bench_lqg
from soc_opt.bench import mstep as bench_mstep
from soc_opt.experiments.report import format_table

print("M-step (n=6, m=2, T=5)")
print(format_table(bench_mstep.run(sizes=((6, 2),), T=5)))
print("\nKL step (n=4, m=2, T=20)")
print(format_table(bench_lqg.run(sizes=((4, 2, 20),))))
