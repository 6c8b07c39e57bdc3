"""Re-check a certificate (:mod:`soc_opt.verification.certificates`) with plain numpy.

Nothing of the library is imported: the smoothed moments and ``log p(Y)`` come from conditioning
the dense joint Gaussian of ``(s_0..s_T, y_0..y_{T-1})`` under the closed loop (docs/math.md §4),
the surrogate, the exact objective and the expected cost from their definitions (docs/math.md §5,
§9).  :func:`replay` returns ``(ok, lines)``: ``ok`` is True when the statement as written fails on
the certificate *and* the corrected statement holds on it, with the numbers in ``lines``.
"""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["replay", "replay_file", "dense_smoother"]

_TOL = 1e-8


def _A(x):
    return np.asarray(x, dtype=float)


def _model(d):
    Ao, co, So, n = _A(d["Ao"]), _A(d["co"]), _A(d["So"]), int(d["n"])
    return Ao[:, :, :n], Ao[:, :, n:], co, So, n


def _policy(d):
    return _A(d["K"]), _A(d["k"]), _A(d["cov"])


def dense_smoother(model: dict, policy: dict, y, mu0, P0):
    """Posterior mean ``(T+1, n)`` and joint covariance ``(T+1, n, T+1, n)`` of the states given ``Y``,
    and ``log p(Y)``, by conditioning the joint Gaussian of states and observations (dense)."""
    As, Bs, co, So, n = _model(model)
    K, kk, cov = _policy(policy)
    y = _A(y)
    T = len(y)
    dim = n + T * (n + 1)  # w = (s_0, e_0, .., e_{T-1}), independent blocks
    Cw = np.zeros((dim, dim))
    Cw[:n, :n] = _A(P0)
    mw = np.zeros(dim)
    mw[:n] = _A(mu0)
    Gs = [np.eye(n, dim)]  # s_k = Gs[k] w + gs[k]
    gs = [np.zeros(n)]
    Gy, gy = [], []
    for k in range(T):
        M = As[k] + Bs[k] @ K[k]
        mk = Bs[k] @ kk[k] + co[k]
        S = So[k] + Bs[k] @ cov[k] @ Bs[k].T
        off = n + k * (n + 1)
        Cw[off:off + n + 1, off:off + n + 1] = S
        E = np.zeros((n + 1, dim))
        E[:, off:off + n + 1] = np.eye(n + 1)
        Z = M @ Gs[k] + E
        z = M @ gs[k] + mk
        Gs.append(Z[:n])
        gs.append(z[:n])
        Gy.append(Z[n])
        gy.append(z[n])
    Gs_, gs_ = np.concatenate(Gs), np.concatenate(gs)
    Gy_, gy_ = np.array(Gy), np.array(gy)
    mu_s, mu_y = Gs_ @ mw + gs_, Gy_ @ mw + gy_
    Css, Csy, Cyy = Gs_ @ Cw @ Gs_.T, Gs_ @ Cw @ Gy_.T, Gy_ @ Cw @ Gy_.T
    Kg = np.linalg.solve(Cyy, Csy.T).T
    mean = mu_s + Kg @ (y - mu_y)
    C = Css - Kg @ Csy.T
    r = y - mu_y
    logp = -0.5 * (T * math.log(2 * math.pi) + np.linalg.slogdet(Cyy)[1] + r @ np.linalg.solve(Cyy, r))
    return mean.reshape(T + 1, n), 0.5 * (C + C.T).reshape(T + 1, n, T + 1, n), float(logp)


def _moments(mean, C, y, k):
    """``Szz, Szs, Sss`` at step ``k``: second moments of ``zeta = (s_{k+1}, y_k)`` and ``(s_k, 1)``."""
    n = mean.shape[1]
    zm = np.append(mean[k + 1], y[k])
    sm = np.append(mean[k], 1.0)
    Czz = np.zeros((n + 1, n + 1))
    Czz[:n, :n] = C[k + 1, :, k + 1, :]
    Czs = np.zeros((n + 1, n + 1))
    Czs[:n, :n] = C[k + 1, :, k, :]
    Css = np.zeros((n + 1, n + 1))
    Css[:n, :n] = C[k, :, k, :]
    return Czz + np.outer(zm, zm), Czs + np.outer(zm, sm), Css + np.outer(sm, sm)


def _resid(model, k, F, mom):
    As, Bs, co, So, n = _model(model)
    Szz, Szs, Sss = mom
    Cm = np.concatenate([As[k], co[k][:, None]], axis=1) + Bs[k] @ F
    return Szz - Cm @ Szs.T - Szs @ Cm.T + Cm @ Sss @ Cm.T


def lbar(model, k, F, Sigma, mom) -> float:
    """The paper's surrogate ``Lbar_k`` at ``[K k] = F``, ``Sigma`` (docs/math.md §5)."""
    _, Bs, _, So, _ = _model(model)
    E = _resid(model, k, F, mom) + Bs[k] @ Sigma @ Bs[k].T
    return float(-0.5 * np.trace(np.linalg.solve(So[k], E)) - 0.5 * np.linalg.slogdet(So[k])[1])


def exact_q(model, k, F, Sigma, mom) -> float:
    """``E[log N(zeta_k; (Atil + B F) stilde, So + B Sigma B^T)]`` (action integrated out)."""
    _, Bs, _, So, n = _model(model)
    S = So[k] + Bs[k] @ Sigma @ Bs[k].T
    E = _resid(model, k, F, mom)
    return float(-0.5 * (n + 1) * math.log(2 * math.pi) - 0.5 * np.linalg.slogdet(S)[1]
                 - 0.5 * np.trace(np.linalg.solve(S, E)))


def _grad(model, k, F, mom) -> np.ndarray:
    """Gradient of ``Lbar_k`` in ``F``: ``B^T So^-1 (Szs - Atil Sss) - H F Sss``."""
    As, Bs, co, So, n = _model(model)
    Szz, Szs, Sss = mom
    Atil = np.concatenate([As[k], co[k][:, None]], axis=1)
    SoiB = np.linalg.solve(So[k], Bs[k])
    return SoiB.T @ (Szs - Atil @ Sss) - (Bs[k].T @ SoiB) @ F @ Sss


def _F(policy, k):
    K, kk, _ = _policy(policy)
    return np.concatenate([K[k], kk[k][:, None]], axis=1)


def _totals(model, y, mean, C, policy, which):
    T = len(y)
    f = lbar if which == "L" else exact_q
    _, _, cov = _policy(policy)
    return sum(f(model, k, _F(policy, k), cov[k], _moments(mean, C, y, k)) for k in range(T))


def _check(lines, ok, text):
    lines.append(f"  [{'ok' if ok else 'NO'}] {text}")
    return ok


# --------------------------------------------------------------------------- per kind


def _uniqueness_gain(c, lines):
    d = c["data"]
    y = _A(d["y"])
    mean, C, _ = dense_smoother(d["model"], d["policy"], y, d["mu0"], d["P0"])
    k = int(d["step"])
    mom = _moments(mean, C, y, k)
    F1, F2, Sig = _A(d["F1"]), _A(d["F2"]), _A(d["Sigma"])
    L1, L2 = lbar(d["model"], k, F1, Sig, mom), lbar(d["model"], k, F2, Sig, mom)
    g1, g2 = _grad(d["model"], k, F1, mom), _grad(d["model"], k, F2, mom)
    _, Bs, _, So, _ = _model(d["model"])
    H = Bs[k].T @ np.linalg.solve(So[k], Bs[k])
    hev, pev = np.linalg.eigvalsh(H), np.linalg.eigvalsh(C[k, :, k, :])
    scale = max(1.0, abs(L1))
    lines.append(f"  stacked B_{k} = {np.round(Bs[k], 6).tolist()}; eig H = {hev.tolist()}; eig P_{k}|T = {pev.tolist()}")
    lines.append(f"  F1 = {np.round(F1, 6).tolist()}, F2 = {np.round(F2, 6).tolist()}")
    lines.append(f"  Lbar(F1) = {L1:.12g}, Lbar(F2) = {L2:.12g}; |grad(F1)| = {np.abs(g1).max():.2e}, "
                 f"|grad(F2)| = {np.abs(g2).max():.2e}")
    fails = all([
        _check(lines, np.abs(F1 - F2).max() > 0.1, "F1 and F2 differ"),
        _check(lines, max(np.abs(g1).max(), np.abs(g2).max()) <= _TOL * scale, "zero gradient at both (Lbar concave: both maximise)"),
        _check(lines, abs(L1 - L2) <= 1e-9 * scale, "equal surrogate value"),
    ])
    corrected = all([
        _check(lines, hev[0] <= 1e-10 * max(1.0, hev[-1]), "corrected statement: H_j is singular, so non-uniqueness is predicted"),
        _check(lines, pev[0] > 0, "P_j|T > 0 (automatic)"),
    ])
    return fails, corrected


def _uniqueness_sigma(c, lines):
    d = c["data"]
    y = _A(d["y"])
    mean, C, _ = dense_smoother(d["model"], d["policy"], y, d["mu0"], d["P0"])
    k = int(d["step"])
    mom = _moments(mean, C, y, k)
    F, Smin = _A(d["F"]), _A(d["Sigma_min"])
    vals = [lbar(d["model"], k, F, t * Smin, mom) for t in d["t"]]
    _, Bs, _, So, _ = _model(d["model"])
    H = Bs[k].T @ np.linalg.solve(So[k], Bs[k])
    lines.append(f"  Lbar at Sigma = t Sigma_min, t = {d['t']}: {[round(v, 9) for v in vals]}; gradient in Sigma = -H/2 = "
                 f"{np.round(-0.5 * H, 9).tolist()}")
    fails = all([
        _check(lines, np.abs(H).max() > 1e-8, "gradient -H/2 is nonzero: no stationary point"),
        _check(lines, bool(np.all(np.diff(vals) < 0)), "Lbar strictly decreasing in t: the sup is at Sigma = 0, not a policy"),
    ])
    R = np.eye(len(Smin))
    corrected = all([
        _check(lines, np.linalg.eigvalsh(H)[0] > 0, "H_j > 0"),
        _check(lines, lbar(d["model"], k, F, Smin + 0.1 * R, mom) < lbar(d["model"], k, F, Smin, mom),
               "corrected: on {Sigma >= Sigma_min} the feasible move Sigma_min + 0.1 I lowers Lbar (maximiser Sigma_min)"),
    ])
    return fails, corrected


def _ltv_like(c, lines):
    d = c["data"]
    y = _A(d["y"])
    mean, C, lp_old = dense_smoother(d["model"], d["old"], y, d["mu0"], d["P0"])
    _, _, lp_new = dense_smoother(d["model"], d["new"], y, d["mu0"], d["P0"])
    dL = _totals(d["model"], y, mean, C, d["new"], "L") - _totals(d["model"], y, mean, C, d["old"], "L")
    dQ = _totals(d["model"], y, mean, C, d["new"], "Q") - _totals(d["model"], y, mean, C, d["old"], "Q")
    lines.append(f"  log p(Y): {lp_old:.9g} -> {lp_new:.9g} (dlog p = {lp_new - lp_old:.6g}); dL = {dL:.6g}; dQ = {dQ:.6g}")
    return lp_old, lp_new, dL, dQ, mean, C, y


def _ltv(c, lines):
    lp_old, lp_new, dL, dQ, *_ = _ltv_like(c, lines)
    fails = all([_check(lines, dL > 0, "the M-step raised L"),
                 _check(lines, lp_new - lp_old < dL - 1e-9, "as written fails: dlog p(Y) < dL")])
    corrected = _check(lines, lp_new - lp_old >= dQ - 1e-9, "corrected (EM inequality): dlog p(Y) >= dQ")
    return fails, corrected


def _expected_cost(mean, C, policy, cost, T):
    K, kk, cov = _policy(policy)
    Qs, ss, Qa, aa = _A(cost["Qs"]), _A(cost["s_star"]), _A(cost["Qa"]), _A(cost["a_star"])
    tot = 0.0
    for k in range(T):
        P, m = C[k, :, k, :], mean[k]
        am = K[k] @ m + kk[k] - aa
        tot += (np.trace(Qs @ P) + (m - ss) @ Qs @ (m - ss) + np.trace(Qa @ (K[k] @ P @ K[k].T + cov[k]))
                + am @ Qa @ am)
    return float(tot)


def _cost_decrease(c, lines):
    lp_old, lp_new, dL, dQ, mean, C, y = _ltv_like(c, lines)
    d = c["data"]
    T = len(y)
    V_old = _expected_cost(mean, C, d["old"], d["cost"], T)
    V_new = _expected_cost(mean, C, d["new"], d["cost"], T)
    _, _, lp_ex = dense_smoother(d["model"], d["exact_em"], y, d["mu0"], d["P0"])
    lines.append(f"  E[V|Y]: {V_old:.9g} -> {V_new:.9g}; observed y = {y.tolist()}; exact-EM step log p(Y) = {lp_ex:.9g}")
    fails = all([_check(lines, dL > 0 and dQ > 0, "surrogate and exact objective both increased"),
                 _check(lines, V_new > V_old, "as written fails: E[V|Y] increased")])
    corrected = all([_check(lines, lp_new - lp_old >= dQ - 1e-9, "corrected (EM inequality): dlog p(Y) >= dQ"),
                     _check(lines, lp_ex >= lp_old - 1e-9, "exact-EM step does not lower log p(Y)")])
    return fails, corrected


def _kl(m1, S1, m0, S0):
    d = len(m0)
    r = m1 - m0
    return 0.5 * (np.trace(np.linalg.solve(S0, S1)) + r @ np.linalg.solve(S0, r) - d
                  + np.linalg.slogdet(S0)[1] - np.linalg.slogdet(S1)[1])


def _free_energy(c, lines):
    d = c["data"]
    rho, mu, S, A, b, cc = float(d["rho"]), _A(d["mu"]), _A(d["S"]), _A(d["A"]), _A(d["b"]), float(d["c"])
    EJ = lambda m, C: 0.5 * np.trace(A @ C) + 0.5 * m @ A @ m + b @ m + cc  # noqa: E731
    Fq = lambda m, C: EJ(m, C) - _kl(m, C, mu, S) / rho  # noqa: E731
    # the left side by quadrature of the 1-D (per-axis) integral when A, S are diagonal, else closed form
    Si, N = np.linalg.inv(S), np.linalg.inv(S) - rho * A
    Cq = np.linalg.inv(N)
    mq = Cq @ (Si @ mu + rho * b)
    x = np.linspace(-40, 40, 400001)
    if len(mu) == 1:
        w = np.exp(-0.5 * (x - mu[0]) ** 2 / S[0, 0] + rho * (0.5 * A[0, 0] * x * x + b[0] * x + cc))
        Z = np.trapezoid(w, x) / math.sqrt(2 * math.pi * S[0, 0])
        lhs = math.log(Z) / rho
    else:
        lhs = (-0.5 * np.linalg.slogdet(S @ N)[1] + 0.5 * mq @ N @ mq - 0.5 * mu @ Si @ mu + rho * cc) / rho
    Fs = [Fq(t * np.ones(len(mu)), S) for t in d["t"]]
    lines.append(f"  rho = {rho}, lhs (1/rho) log E_P[exp(rho J)] = {lhs:.12g}; F(Q*) = {Fq(mq, Cq):.12g}; "
                 f"F(N(t, S)) for t = {d['t']}: {[round(float(v), 6) for v in Fs]}")
    fails = all([_check(lines, rho < 0, "rho < 0"),
                 _check(lines, Fs[-1] > lhs + 100 and bool(np.all(np.diff(Fs) > 0)),
                        "as written fails: F(Q_t) grows without bound, so sup_Q F = +inf != lhs")])
    corrected = all([_check(lines, abs(Fq(mq, Cq) - lhs) <= 1e-7 * max(1, abs(lhs)), "F(Q*) = lhs"),
                     _check(lines, min(Fs) >= lhs - 1e-9, "corrected: every F(Q_t) >= lhs (an inf, attained at Q*)")])
    return fails, corrected


_KINDS = {"uniqueness_gain": _uniqueness_gain, "uniqueness_sigma": _uniqueness_sigma, "ltv": _ltv,
          "cost_decrease": _cost_decrease, "free_energy": _free_energy}


def replay(cert: dict) -> tuple[bool, list[str]]:
    """Re-check a certificate dict; ``(ok, lines)``."""
    kind = cert.get("kind")
    if kind not in _KINDS:
        raise ValueError(f"certificate kind {kind!r} is not one of {sorted(_KINDS)}")
    lines = [f"certificate {kind} (claim {cert.get('claim')}), n={cert.get('n')} m={cert.get('m')} T={cert.get('T')}"]
    fails, corrected = _KINDS[kind](cert, lines)
    lines.append(f"statement as written: {'FAILS (reproduced)' if fails else 'not refuted'}; "
                 f"corrected statement: {'holds' if corrected else 'does NOT hold'}")
    return bool(fails and corrected), lines


def replay_file(path) -> tuple[bool, list[str]]:
    """:func:`replay` on a JSON file; a clear error names a missing or malformed file."""
    try:
        with open(path) as f:
            cert = json.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"certificate file {path} does not exist") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"certificate file {path} is not valid JSON ({e})") from None
    if not isinstance(cert, dict) or "data" not in cert:
        raise ValueError(f"certificate file {path} has no 'data' key (not a soc_opt certificate)")
    return replay(cert)
