"""Re-check a certificate (:mod:`soc_opt.verification.certificates`) in exact arithmetic.

Nothing of the library is imported.  Every datum is read as an exact rational (a string ``"p/q"``, a
decimal string such as ``"0.125"`` or ``"-1.5e-3"``, an integer; a JSON number means the decimal it
spells, a Python ``float`` its exact binary value), and every quantity the verdict depends on is
computed from the definitions in exact rational arithmetic (python-flint ``fmpq``/``fmpq_mat``):
the smoothed moments by conditioning the dense joint Gaussian of ``(s_0..s_T, y_0..y_{T-1})``
under the closed loop (docs/math.md §4), the surrogate's rational part, its gradient, the expected
cost (§5, §9).  The only irrational numbers are logarithms (``log det``, ``log 2 pi`` in ``log p(Y)``,
the exact objective ``Q`` and the free energy); they are evaluated as ``arb`` balls at
:data:`PREC` bits, and an inequality is decided only when the ball excludes the boundary.  An
equality is decided exactly: between rationals by comparison, between ``r + c log g`` forms by
comparing ``r`` and ``g`` (``log`` of a positive rational other than 1 is irrational).  An
undecided comparison counts as a failed check, so no rounding can flip a verdict.

:func:`replay` returns ``(ok, lines)``: ``ok`` is True when the statement as written fails on the
certificate *and* the corrected statement holds on it (docs/math.md §9; docs/verification.md).
"""

from __future__ import annotations

import json
import math
from fractions import Fraction

from flint import arb, ctx, fmpq, fmpq_mat

from ..config import MAX_DEPTH, ConfigError, check_depth, shorten
from ..reading import RefusedFile, read_regular

__all__ = ["PREC", "num", "mat", "col", "dense_smoother", "moments", "gradient", "lbar_rational", "lbar",
           "exact_q", "logp", "maximiser", "null_vector", "replay", "replay_file"]

#: working precision (bits) of the interval evaluations of logarithms
PREC = 300


# --------------------------------------------------------------------------- exact data


def num(x) -> fmpq:
    """One datum as an exact rational: ``"p/q"``, a decimal string, an int, a Fraction, or a float
    (its exact binary value).  Anything else (bool, NaN, inf, None, a list) is a clear error."""
    if isinstance(x, fmpq):
        return x
    if isinstance(x, bool) or x is None:
        raise ValueError(f"certificate datum {x!r} is not a number")
    if isinstance(x, int):
        return fmpq(x)
    if isinstance(x, float) and not math.isfinite(x):
        raise ValueError(f"certificate datum {x!r} is not finite")
    if isinstance(x, (float, str, Fraction)):
        try:
            fr = Fraction(x.strip() if isinstance(x, str) else x)
        except (ValueError, ZeroDivisionError):
            raise ValueError(f"certificate datum {x!r} is not an exact rational ('p/q' or a decimal)") from None
        return fmpq(fr.numerator, fr.denominator)
    raise ValueError(f"certificate datum {x!r} is not a number")


def mat(rows) -> fmpq_mat:
    """A 2-D list of data as an exact matrix."""
    rows = list(rows)
    if not rows or not isinstance(rows[0], (list, tuple)):
        raise ValueError(f"expected a matrix (list of rows), got {rows!r}")
    return fmpq_mat([[num(v) for v in r] for r in rows])


def col(v) -> fmpq_mat:
    """A 1-D list of data as an exact column vector."""
    return fmpq_mat([[num(x)] for x in v])


def _eye(d: int) -> fmpq_mat:
    M = fmpq_mat(d, d)
    for i in range(d):
        M[i, i] = 1
    return M


def _block(M: fmpq_mat, r0: int, r1: int, c0: int, c1: int) -> fmpq_mat:
    return fmpq_mat([[M[i, j] for j in range(c0, c1)] for i in range(r0, r1)])


def _hcat(*Ms: fmpq_mat) -> fmpq_mat:
    return fmpq_mat([sum((M.tolist()[i] for M in Ms), []) for i in range(Ms[0].nrows())])


def _vcat(*Ms: fmpq_mat) -> fmpq_mat:
    return fmpq_mat(sum((M.tolist() for M in Ms), []))


def _tr(M: fmpq_mat) -> fmpq:
    return sum((M[i, i] for i in range(M.nrows())), fmpq(0))


def _scalar(M: fmpq_mat) -> fmpq:
    return M[0, 0]


def _is_zero(M: fmpq_mat) -> bool:
    return all(v == 0 for v in M.entries())


def _pos_def(M: fmpq_mat) -> bool:
    """Exactly symmetric with every leading principal minor > 0 (Sylvester's criterion)."""
    d = M.nrows()
    return M == M.transpose() and all(_block(M, 0, i, 0, i).det() > 0 for i in range(1, d + 1))


def _f(x) -> float:
    """A float for display only (never used in a decision)."""
    return float(x.mid()) if isinstance(x, arb) else float(x)


def _qtext(x: fmpq) -> str:
    """A rational for display: exact when short, else its float (marked nonzero when it is)."""
    t = str(x)
    return t if len(t) <= 40 else f"{float(x):.3g} (exact rational, {'nonzero' if x != 0 else 'zero'})"


def _show(M: fmpq_mat, digits: int = 6) -> list:
    return [[round(float(v), digits) for v in row] for row in M.tolist()]


# --------------------------------------------------------------------------- model and policy


def exact_model(d):
    """Per step ``(A_k, B_k, c_k, So_k)`` with the *stacked* ``B_k = [B^d_k; B^y_k]`` (``(n+1) x m``)."""
    n = int(d["n"])
    out = []
    for Ao, co, So in zip(d["Ao"], d["co"], d["So"], strict=True):
        Aok = mat(Ao)
        out.append((_block(Aok, 0, n + 1, 0, n), _block(Aok, 0, n + 1, n, Aok.ncols()), col(co), mat(So)))
    return out, n


def _policy(d):
    return [mat(K) for K in d["K"]], [col(k) for k in d["k"]], [mat(S) for S in d["cov"]]


def _F(policy: dict, k: int) -> fmpq_mat:
    K, kk, _ = _policy(policy)
    return _hcat(K[k], kk[k])


# --------------------------------------------------------------------------- smoother, moments, objectives


def dense_smoother(model: dict, policy: dict, y, mu0, P0):
    """Exact posterior of the states given ``Y`` (docs/math.md §4), by conditioning the joint Gaussian.

    Returns ``(mean, C, lp)``: ``mean[k]`` the column ``E[s_k | Y]``, ``C`` the joint covariance of
    ``(s_0..s_T)`` given ``Y`` (``(T+1) n`` square; block ``(k, j)`` is ``Cov(s_k, s_j | Y)``) and
    ``lp = (r, det Cyy, T)`` with ``log p(Y) = r - 1/2 log det Cyy - T/2 log 2 pi`` (see :func:`logp`).
    """
    steps, n = exact_model(model)
    K, kk, cov = _policy(policy)
    y = [num(v) for v in y]
    T = len(y)
    if len(steps) != T or len(K) != T:
        raise ValueError(f"model has {len(steps)} steps, policy {len(K)}, y {T}: they must agree")
    dim = n + T * (n + 1)  # w = (s_0, e_0, .., e_{T-1}), independent blocks
    Cw = fmpq_mat(dim, dim)
    P0m = mat(P0)
    for i in range(n):
        for j in range(n):
            Cw[i, j] = P0m[i, j]
    mw = _vcat(col(mu0), fmpq_mat(dim - n, 1))
    Gs = [_hcat(_eye(n), fmpq_mat(n, dim - n))]  # s_k = Gs[k] w + gs[k]
    gs = [fmpq_mat(n, 1)]
    Gy, gy = [], []
    for k, (A, B, c, So) in enumerate(steps):
        M = A + B * K[k]
        mk = B * kk[k] + c
        S = So + B * cov[k] * B.transpose()
        off = n + k * (n + 1)
        for i in range(n + 1):
            for j in range(n + 1):
                Cw[off + i, off + j] = S[i, j]
        E = fmpq_mat(n + 1, dim)
        for i in range(n + 1):
            E[i, off + i] = 1
        Z = M * Gs[k] + E
        z = M * gs[k] + mk
        Gs.append(_block(Z, 0, n, 0, dim))
        gs.append(_block(z, 0, n, 0, 1))
        Gy.append(_block(Z, n, n + 1, 0, dim))
        gy.append(_block(z, n, n + 1, 0, 1))
    Gs_, gs_, Gy_, gy_ = _vcat(*Gs), _vcat(*gs), _vcat(*Gy), _vcat(*gy)
    mu_s, mu_y = Gs_ * mw + gs_, Gy_ * mw + gy_
    Css, Csy, Cyy = Gs_ * Cw * Gs_.transpose(), Gs_ * Cw * Gy_.transpose(), Gy_ * Cw * Gy_.transpose()
    Kg = Cyy.solve(Csy.transpose()).transpose()
    r = fmpq_mat([[v] for v in y]) - mu_y
    mean_all = mu_s + Kg * r
    C = Css - Kg * Csy.transpose()
    mean = [_block(mean_all, k * n, (k + 1) * n, 0, 1) for k in range(T + 1)]
    quad = _scalar(r.transpose() * Cyy.solve(r))
    return mean, C, (-quad / 2, Cyy.det(), T)


def logp(lp) -> arb:
    """``log p(Y)`` as an arb ball from :func:`dense_smoother`'s exact parts (call inside ``ctx.workprec``)."""
    r, det, T = lp
    return arb(r) - arb(det).log() / 2 - T * (2 * arb.pi()).log() / 2


def _cov_block(C: fmpq_mat, n: int, k: int, j: int) -> fmpq_mat:
    return _block(C, k * n, (k + 1) * n, j * n, (j + 1) * n)


def moments(mean, C, y, k: int):
    """``(Szz, Szs, Sss)`` at step ``k``: second moments of ``zeta = (s_{k+1}, y_k)`` and ``stilde = (s_k, 1)``."""
    n = mean[0].nrows()
    zm = _vcat(mean[k + 1], fmpq_mat([[num(y[k])]]))
    sm = _vcat(mean[k], fmpq_mat([[1]]))

    def pad(B):
        return _vcat(_hcat(B, fmpq_mat(n, 1)), fmpq_mat(1, n + 1))

    return (pad(_cov_block(C, n, k + 1, k + 1)) + zm * zm.transpose(),
            pad(_cov_block(C, n, k + 1, k)) + zm * sm.transpose(),
            pad(_cov_block(C, n, k, k)) + sm * sm.transpose())


def _resid(step, F, mom):
    A, B, c, _ = step
    Szz, Szs, Sss = mom
    Cm = _hcat(A, c) + B * F
    return Szz - Cm * Szs.transpose() - Szs * Cm.transpose() + Cm * Sss * Cm.transpose()


def lbar_rational(step, F, Sigma, mom) -> fmpq:
    """``Lbar_k + 1/2 log det So_k``: the part of the paper's surrogate that depends on the policy
    (docs/math.md §5), exactly.  Differences of ``Lbar`` between policies are differences of this."""
    _, B, _, So = step
    E = _resid(step, F, mom) + B * Sigma * B.transpose()
    return -_tr(So.solve(E)) / 2


def lbar(step, F, Sigma, mom) -> arb:
    """The surrogate ``Lbar_k`` itself (an arb ball)."""
    return arb(lbar_rational(step, F, Sigma, mom)) - arb(step[3].det()).log() / 2


def exact_q(step, F, Sigma, mom) -> arb:
    """``E[log N(zeta_k; (Atil + B F) stilde, So + B Sigma B^T)]`` (the action integrated out; §5), an arb ball."""
    _, B, _, So = step
    S = So + B * Sigma * B.transpose()
    d = S.nrows()
    return (-d * (2 * arb.pi()).log() / 2 - arb(S.det()).log() / 2
            - arb(_tr(S.solve(_resid(step, F, mom)))) / 2)


def _H(step) -> fmpq_mat:
    _, B, _, So = step
    return B.transpose() * So.solve(B)


def gradient(step, F, mom) -> fmpq_mat:
    """Gradient of ``Lbar_k`` in ``F = [K_k k_k]``: ``B^T So^-1 (Szs - Atil Sss) - H F Sss`` (exact)."""
    A, B, c, So = step
    _, Szs, Sss = mom
    return B.transpose() * So.solve(Szs - _hcat(A, c) * Sss) - _H(step) * F * Sss


def null_vector(M: fmpq_mat) -> fmpq_mat | None:
    """An exact nonzero ``v`` with ``M v = 0`` (from the reduced row echelon form), or None."""
    R, rank = M.rref()
    d = M.ncols()
    pivots = []
    for i in range(rank):
        pivots.append(next(j for j in range(d) if R[i, j] != 0))
    free = [j for j in range(d) if j not in pivots]
    if not free:
        return None
    v = fmpq_mat(d, 1)
    v[free[0], 0] = 1
    for i, p in enumerate(pivots):
        v[p, 0] = -R[i, free[0]]
    return v


def maximiser(step, mom) -> fmpq_mat:
    """The minimum-norm ``F`` with zero :func:`gradient` (every maximiser of the concave ``Lbar_k`` in ``F``
    when ``H`` is singular; the unique one when ``H > 0``), exactly.  With ``B = C D`` a rank
    factorisation, ``F = D^T (D D^T)^-1 (C^T So^-1 C)^-1 C^T So^-1 (Szs - Atil Sss) Sss^-1``."""
    A, B, c, So = step
    _, Szs, Sss = mom
    R, rank = B.rref()
    pivots = [next(j for j in range(B.ncols()) if R[i, j] != 0) for i in range(rank)]
    Cf = _hcat(*[_block(B, 0, B.nrows(), j, j + 1) for j in pivots])
    D = _block(R, 0, rank, 0, B.ncols())
    X = Sss.transpose().solve((Cf.transpose() * So.solve(Szs - _hcat(A, c) * Sss)).transpose()).transpose()
    G = (Cf.transpose() * So.solve(Cf)).solve(X)
    return D.transpose() * (D * D.transpose()).solve(G)


# --------------------------------------------------------------------------- decisions


def _sign(x) -> int | None:
    """Sign of an exact rational, or of an arb ball when it excludes 0 (else None: undecided)."""
    if isinstance(x, fmpq):
        return (x > 0) - (x < 0)
    if x > 0:
        return 1
    if x < 0:
        return -1
    return 0 if (x.is_exact() and x.is_zero()) else None


def _check(lines, ok, text):
    lines.append(f"  [{'ok' if ok else 'NO'}] {text}")
    return bool(ok)


def _positive(lines, x, text):
    s = _sign(x)
    return _check(lines, s == 1, text + ("" if s is not None else " (undecided at the working precision)"))


def _nonnegative(lines, x, text):
    s = _sign(x)
    return _check(lines, s in (0, 1), text + ("" if s is not None else " (undecided at the working precision)"))


def _is_maximiser(lines, steps, mean, C, y, policy, label):
    """Zero exact gradient of ``Lbar_k`` in ``[K_k k_k]`` at every step (``Lbar_k`` is concave in it)."""
    ok = all(_is_zero(gradient(steps[k], _F(policy, k), moments(mean, C, y, k))) for k in range(len(steps)))
    return _check(lines, ok, f"{label}: gradient of Lbar in [K k] is exactly 0 at every step (a maximiser)")


# --------------------------------------------------------------------------- per kind


def _uniqueness_gain(c, lines):
    d = c["data"]
    y = d["y"]
    steps, n = exact_model(d["model"])
    mean, C, _ = dense_smoother(d["model"], d["policy"], y, d["mu0"], d["P0"])
    k = int(d["step"])
    mom = moments(mean, C, y, k)
    F1, F2, Sig = mat(d["F1"]), mat(d["F2"]), mat(d["Sigma"])
    g1, g2 = gradient(steps[k], F1, mom), gradient(steps[k], F2, mom)
    H, B = _H(steps[k]), steps[k][1]
    P = _cov_block(C, n, k, k)
    lines.append(f"  stacked B_{k} = {_show(B)} (rank {B.rank()} of m = {B.ncols()}); det H_{k} = {_qtext(H.det())}; "
                 f"P_{k}|T = {_show(P)}")
    lines.append(f"  F1 = {_show(F1)}, F2 = {_show(F2)}; Lbar(F1) = {_f(lbar(steps[k], F1, Sig, mom)):.12g}, "
                 f"Lbar(F2) - Lbar(F1) = {_qtext(lbar_rational(steps[k], F2, Sig, mom) - lbar_rational(steps[k], F1, Sig, mom))}")
    fails = all([
        _check(lines, _pos_def(steps[k][3]), f"So_{k} > 0 (so Lbar is concave in [K k] and a zero gradient is a maximum)"),
        _check(lines, F1 != F2, "F1 != F2"),
        _check(lines, _is_zero(g1) and _is_zero(g2), "gradient exactly 0 at F1 and at F2: both maximise"),
        _check(lines, lbar_rational(steps[k], F1, Sig, mom) == lbar_rational(steps[k], F2, Sig, mom),
               "Lbar(F1) = Lbar(F2) exactly"),
    ])
    corrected = all([
        _check(lines, H.det() == 0, f"corrected statement: H_{k} = B^T So^-1 B is exactly singular, so non-uniqueness "
                                    "is what it predicts"),
        _check(lines, _pos_def(P), f"P_{k}|T > 0"),
    ])
    return fails, corrected


def _uniqueness_sigma(c, lines):
    d = c["data"]
    y = d["y"]
    steps, _ = exact_model(d["model"])
    mean, C, _ = dense_smoother(d["model"], d["policy"], y, d["mu0"], d["P0"])
    k = int(d["step"])
    mom = moments(mean, C, y, k)
    F, Smin = mat(d["F"]), mat(d["Sigma_min"])
    ts = [num(t) for t in d["t"]]
    vals = [lbar_rational(steps[k], F, Smin * t, mom) for t in ts]
    H = _H(steps[k])
    lines.append(f"  Lbar at Sigma = t Sigma_min, t = {[str(t) for t in ts]}: "
                 f"{[round(_f(lbar(steps[k], F, Smin * t, mom)), 9) for t in ts]}; gradient in Sigma = -H/2 = {_show(H * fmpq(-1, 2), 9)}")
    fails = all([
        _check(lines, not _is_zero(H), "Lbar is affine in Sigma with gradient -H/2 != 0: no stationary point in Sigma"),
        _check(lines, all(b < a for a, b in zip(vals, vals[1:])), "Lbar strictly decreasing in t: the sup is at Sigma = 0, "
                                                                 "not a policy"),
    ])
    corrected = all([
        _check(lines, _pos_def(H), f"H_{k} > 0"),
        _check(lines, _pos_def(Smin), "Sigma_min > 0"),
        _check(lines, _is_zero(gradient(steps[k], F, mom)), "gradient in [K k] exactly 0 at F"),
    ])
    if corrected:
        lines.append("  so, Lbar being affine in Sigma: Lbar(F, Sigma_min + D) - Lbar(F, Sigma_min) = -tr(H D)/2 < 0 for every "
                     "D >= 0, D != 0, and (F, Sigma_min) is the unique maximiser on {Sigma >= Sigma_min}")
    return fails, corrected


def _ltv_like(c, lines):
    d = c["data"]
    y = d["y"]
    steps, _ = exact_model(d["model"])
    mean, C, lp_old = dense_smoother(d["model"], d["old"], y, d["mu0"], d["P0"])
    _, _, lp_new = dense_smoother(d["model"], d["new"], y, d["mu0"], d["P0"])
    T = len(steps)
    dL = sum((lbar_rational(steps[k], _F(d["new"], k), _policy(d["new"])[2][k], moments(mean, C, y, k))
              - lbar_rational(steps[k], _F(d["old"], k), _policy(d["old"])[2][k], moments(mean, C, y, k))
              for k in range(T)), fmpq(0))
    dQ = sum((exact_q(steps[k], _F(d["new"], k), _policy(d["new"])[2][k], moments(mean, C, y, k))
              - exact_q(steps[k], _F(d["old"], k), _policy(d["old"])[2][k], moments(mean, C, y, k))
              for k in range(T)), arb(0))
    dlogp = logp(lp_new) - logp(lp_old)
    lines.append(f"  log p(Y): {_f(logp(lp_old)):.9g} -> {_f(logp(lp_new)):.9g} (dlog p = {_f(dlogp):.6g}); "
                 f"dL = {_f(dL):.6g}; dQ = {_f(dQ):.6g}")
    return dict(steps=steps, mean=mean, C=C, y=y, lp_old=lp_old, dL=dL, dQ=dQ, dlogp=dlogp)


def _ltv(c, lines):
    d = c["data"]
    r = _ltv_like(c, lines)
    floor = mat(d["cov_floor"])
    covs = _policy(d["new"])[2]
    fails = all([
        _check(lines, all(S == floor for S in covs), "new Sigma = the floor at every step (the M-step's Sigma)"),
        _check(lines, all(_pos_def(_H(s)) for s in r["steps"]), "H_k > 0 at every step (the M-step is unique)"),
        _is_maximiser(lines, r["steps"], r["mean"], r["C"], r["y"], d["new"], "new policy"),
        _positive(lines, r["dL"], "the M-step raised L (dL > 0)"),
        _positive(lines, r["dL"] - r["dlogp"], "as written fails: dlog p(Y) < dL"),
    ])
    corrected = _nonnegative(lines, r["dlogp"] - r["dQ"], "corrected (EM inequality): dlog p(Y) >= dQ")
    return fails, corrected


def _expected_cost(mean, C, policy, cost, T) -> fmpq:
    K, kk, cov = _policy(policy)
    Qs, ss, Qa, aa = mat(cost["Qs"]), col(cost["s_star"]), mat(cost["Qa"]), col(cost["a_star"])
    n = mean[0].nrows()
    tot = fmpq(0)
    for k in range(T):
        P, m = _cov_block(C, n, k, k), mean[k]
        am = K[k] * m + kk[k] - aa
        tot += (_tr(Qs * P) + _scalar((m - ss).transpose() * Qs * (m - ss))
                + _tr(Qa * (K[k] * P * K[k].transpose() + cov[k])) + _scalar(am.transpose() * Qa * am))
    return tot


def _cost_decrease(c, lines):
    d = c["data"]
    r = _ltv_like(c, lines)
    T = len(r["steps"])
    V_old = _expected_cost(r["mean"], r["C"], d["old"], d["cost"], T)
    V_new = _expected_cost(r["mean"], r["C"], d["new"], d["cost"], T)
    _, _, lp_ex = dense_smoother(d["model"], d["exact_em"], r["y"], d["mu0"], d["P0"])
    ex = _policy(d["exact_em"])
    old = _policy(d["old"])
    dQ_ex = sum((exact_q(r["steps"][k], _F(d["exact_em"], k), ex[2][k], moments(r["mean"], r["C"], r["y"], k))
                 - exact_q(r["steps"][k], _F(d["old"], k), old[2][k], moments(r["mean"], r["C"], r["y"], k))
                 for k in range(T)), arb(0))
    dlogp_ex = logp(lp_ex) - logp(r["lp_old"])
    lines.append(f"  E[V|Y]: {_f(V_old):.9g} -> {_f(V_new):.9g}; observed y = {[_f(num(v)) for v in r['y']]}; "
                 f"exact-EM step: dQ = {_f(dQ_ex):.6g}, dlog p(Y) = {_f(dlogp_ex):.6g}")
    fails = all([
        _check(lines, _policy(d["new"])[2] == old[2], "Sigma held at Sigma^i exactly"),
        _is_maximiser(lines, r["steps"], r["mean"], r["C"], r["y"], d["new"], "new policy (the surrogate M-step in [K k])"),
        _positive(lines, r["dL"], "the surrogate increased (dL > 0)"),
        _positive(lines, r["dQ"], "the exact objective increased (dQ > 0)"),
        _check(lines, V_new > V_old, "as written fails: E[V|Y] increased (exact)"),
    ])
    corrected = all([
        _nonnegative(lines, r["dlogp"] - r["dQ"], "corrected (EM inequality): dlog p(Y) >= dQ"),
        _positive(lines, dQ_ex, "the exact-EM step raised Q (a generalised EM step)"),
        _nonnegative(lines, dlogp_ex - dQ_ex, "so it raised log p(Y) at least as much"),
    ])
    return fails, corrected


def _free_energy(c, lines):
    """``F(Q) = E_Q J - KL(Q||P)/rho`` and the left side ``(1/rho) log E_P[exp(rho J)]`` both have the form
    ``r + (-1/(2 rho)) log g`` with rational ``r, g`` (Gaussian ``P``, ``Q``; quadratic ``J``)."""
    d = c["data"]
    rho, mu, S, A, b, cc = num(d["rho"]), col(d["mu"]), mat(d["S"]), mat(d["A"]), col(d["b"]), num(d["c"])
    dim = mu.nrows()
    Si = S.inv()
    N = Si - A * rho  # E_P[exp(rho J)] < inf iff N > 0

    def EJ(m, Cq):
        return _tr(A * Cq) / 2 + _scalar(m.transpose() * A * m) / 2 + _scalar(b.transpose() * m) + cc

    def F(m, Cq):  # (r, g) with F = r - log(g) / (2 rho)
        dm = m - mu
        r = EJ(m, Cq) - (_tr(Si * Cq) + _scalar(dm.transpose() * Si * dm) - dim) / (2 * rho)
        return r, S.det() / Cq.det()

    mq = N.solve(Si * mu + b * rho)
    lhs = ((_scalar(mq.transpose() * N * mq) - _scalar(mu.transpose() * Si * mu)) / 2 + rho * cc) / rho, (S * N).det()

    def val(rg):
        return arb(rg[0]) - arb(rg[1]).log() / (2 * arb(rho))

    Qm, QC = col(d["Qstar"]["mean"]), mat(d["Qstar"]["cov"])
    FQ = F(Qm, QC)
    ts = [num(t) for t in d["t"]]
    Ft = [F(mu + col([t] * dim), S) for t in ts]  # Q_t = N(mu + t 1, S): g = 1, F rational
    lines.append(f"  rho = {rho}, lhs (1/rho) log E_P[exp(rho J)] = {_f(val(lhs)):.12g}; Q* = N({_show(Qm)}, {_show(QC)}), "
                 f"F(Q*) = {_f(val(FQ)):.12g}; F(N(mu + t, S)) for t = {[str(t) for t in ts]}: {[str(f[0]) for f in Ft]}")
    fails = all([
        _check(lines, rho < 0, "rho < 0"),
        _check(lines, _pos_def(N), "N = S^-1 - rho A > 0, so E_P[exp(rho J)] is finite"),
        _check(lines, all(b[0] > a[0] for a, b in zip(Ft, Ft[1:])), "F(Q_t) strictly increasing in t (exact)"),
        _positive(lines, val(Ft[-1]) - val(lhs) - 100, "as written fails: F(Q_t) > lhs + 100, so sup_Q F != lhs"),
    ])
    corrected = all([
        _check(lines, _pos_def(QC), "Q* has a positive definite covariance"),
        _check(lines, FQ[0] == lhs[0] and FQ[1] == lhs[1], "F(Q*) = lhs exactly (equal rational parts and log arguments)"),
        _check(lines, all(_sign(val(f) - val(lhs)) == 1 for f in Ft),
               "corrected: every F(Q_t) > lhs (an inf, attained at Q*)"),
    ])
    return fails, corrected


_KINDS = {"uniqueness_gain": _uniqueness_gain, "uniqueness_sigma": _uniqueness_sigma, "ltv": _ltv,
          "cost_decrease": _cost_decrease, "free_energy": _free_energy}


def replay(cert: dict) -> tuple[bool, list[str]]:
    """Re-check a certificate dict in exact / interval arithmetic; ``(ok, lines)``."""
    kind = cert.get("kind")
    if kind not in _KINDS:
        raise ValueError(f"certificate kind {kind!r} is not one of {sorted(_KINDS)}")
    lines = [f"certificate {kind} (claim {cert.get('claim')}), n={cert.get('n')} m={cert.get('m')} T={cert.get('T')}"]
    with ctx.workprec(PREC):
        try:
            fails, corrected = _KINDS[kind](cert, lines)
        except (KeyError, ValueError, ZeroDivisionError, TypeError) as e:
            lines.append(f"  [NO] malformed or degenerate certificate data: {type(e).__name__}: {e}")
            fails = corrected = False
    lines.append(f"statement as written: {'FAILS (reproduced)' if fails else 'not refuted'}; "
                 f"corrected statement: {'holds' if corrected else 'does NOT hold'} "
                 f"(exact rationals; logarithms as {PREC}-bit balls)")
    return bool(fails and corrected), lines


#: Largest certificate file read: 64 MiB (the committed ones are a few kB).
MAX_CERTIFICATE_BYTES = 64 << 20


def replay_file(path) -> tuple[bool, list[str]]:
    """:func:`replay` on a JSON file (numbers read exactly as the decimals they spell); a clear error
    names a missing or malformed file."""
    try:  # a regular file, read without blocking, at most MAX_CERTIFICATE_BYTES
        cert = check_depth(json.loads(read_regular(path, MAX_CERTIFICATE_BYTES, what="certificate", follow=True),
                                      parse_float=Fraction), f"certificate file {path}")
    except FileNotFoundError:
        raise FileNotFoundError(f"certificate file {path} does not exist") from None
    except RefusedFile as e:
        raise ConfigError(f"certificate file {e}") from None
    except ConfigError:
        raise
    except RecursionError:
        raise ConfigError(f"certificate file {path}: nested more than {MAX_DEPTH} levels deep") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"certificate file {path} is not valid JSON ({shorten(str(e))})") from None
    if not isinstance(cert, dict) or "data" not in cert:
        raise ValueError(f"certificate file {path} has no 'data' key (not a soc_opt certificate)")
    return replay(cert)
