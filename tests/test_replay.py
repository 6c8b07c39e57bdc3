"""Tests for soc_opt.verification.replay: the certificates are decided in exact arithmetic
(docs/verification.md "Counterexamples"; docs/math.md §5, §9).

Every committed certificate replays to its recorded verdict; moving one datum that the argument needs
*exactly* (a column that must stay proportional, a point that must be a maximiser, a covariance
that must be held, the tilted Q*) by one ulp, in either direction, makes the replay reject it; and a
certificate whose data are binary floats that only approximate what the claim needs is rejected.
"""

from __future__ import annotations

import copy
import json
import math
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from flint import fmpq, fmpq_mat

from soc_opt import estep
from soc_opt.testing import random_augmented_model, random_initial_state, random_policy, sample_model_trajectory
from soc_opt.verification import registry
from soc_opt.verification.certificates import exact_text
from soc_opt.verification.replay import (
    col,
    dense_smoother,
    gradient,
    logp,
    mat,
    maximiser,
    moments,
    null_vector,
    num,
    replay,
    replay_file,
)

ROOT = Path(__file__).resolve().parents[1]
CERTS = sorted((ROOT / registry.CERT_DIR).glob("*.json"))
OLD_FLOAT_UNIQUENESS = ROOT / "tests" / "data" / "uniqueness_v1_float_certificate.json"


def _load(name: str) -> dict:
    return json.loads((ROOT / registry.CERT_DIR / name).read_text())


def _get(d, path):
    for p in path:
        d = d[p]
    return d


def _set(d, path, value):
    _get(d, path[:-1])[path[-1]] = value


def _one_ulp(text: str, direction: int) -> str:
    """The datum moved by one ulp: to the adjacent double when it is a double, else by 2^-52 of itself
    (2^-1074 when it is 0), as exact text."""
    q = Fraction(text)
    x = float(q)
    if Fraction(x) == q:
        return exact_text(math.nextafter(x, direction * math.inf))
    step = abs(q) * Fraction(1, 2**52) if q else Fraction(1, 2**1074)
    return str(q + direction * step)


def _datum_paths(data, prefix=()):
    if isinstance(data, dict):
        for k, v in data.items():
            yield from _datum_paths(v, prefix + (k,))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield from _datum_paths(v, prefix + (i,))
    else:
        yield prefix, data


# --------------------------------------------------------------------------- the committed certificates


@pytest.mark.parametrize("path", CERTS, ids=[p.name for p in CERTS])
def test_committed_certificate_replays_to_its_verdict_in_exact_arithmetic(path):
    ok, lines = replay_file(path)
    assert ok, "\n".join(lines)
    assert "statement as written: FAILS (reproduced); corrected statement: holds" in lines[-1]
    assert not any("[NO]" in ln or "undecided" in ln for ln in lines)


@pytest.mark.parametrize("path", CERTS, ids=[p.name for p in CERTS])
def test_committed_certificate_states_every_datum_as_exact_text(path):
    cert = json.loads(path.read_text())
    assert cert["format"] == "soc_opt certificate v2"
    for where, v in _datum_paths(cert["data"]):
        if where[-1] in ("n", "step", "d"):
            assert isinstance(v, int)
            continue
        assert isinstance(v, str), (where, v)
        Fraction(v)  # "p/q" or a decimal, read exactly


def test_uniqueness_certificate_has_exactly_proportional_columns_and_singular_H():
    d = _load("uniqueness_n1_m2_T1.json")["data"]
    n = d["model"]["n"]
    B = mat(d["model"]["Ao"][0])
    B = fmpq_mat([[B[i, j] for j in range(n, B.ncols())] for i in range(B.nrows())])
    So = mat(d["model"]["So"][0])
    assert B.rank() == B.ncols() - 1
    assert (B.transpose() * So.solve(B)).det() == 0
    v = null_vector(B)
    assert v is not None and all(x == 0 for x in (B * v).entries())


# --------------------------------------------------------------------------- one ulp breaks a certificate

# the data each certificate needs exactly: (file, path into "data")
HINGES = [
    ("uniqueness_n1_m2_T1.json", ("model", "Ao", 0, 0, 2)),  # proportional columns of the stacked B
    ("uniqueness_n1_m2_T1.json", ("model", "Ao", 0, 1, 1)),
    ("uniqueness_n1_m2_T1.json", ("F1", 0, 1)),  # a maximiser
    ("uniqueness_n1_m2_T1.json", ("F2", 1, 0)),  # the other maximiser
    ("uniqueness_sigma_n1_m1_T1.json", ("F", 0, 0)),  # the maximiser in [K k]
    ("uniqueness_sigma_n1_m1_T1.json", ("F", 0, 1)),
    ("ltv_n1_m1_T1.json", ("new", "K", 0, 0, 0)),  # the M-step's [K k]
    ("ltv_n1_m1_T1.json", ("new", "k", 0, 0)),
    ("ltv_n1_m1_T1.json", ("new", "cov", 0, 0, 0)),  # the M-step's Sigma = the floor
    ("cost_decrease_n1_m1_T1.json", ("new", "K", 0, 0, 0)),
    ("cost_decrease_n1_m1_T1.json", ("new", "k", 0, 0)),
    ("cost_decrease_n1_m1_T1.json", ("new", "cov", 0, 0, 0)),  # Sigma held at Sigma^i
    ("free_energy_rho_neg_d1.json", ("Qstar", "cov", 0, 0)),  # the tilted Q* attains the lhs
    ("free_energy_rho_neg_d1.json", ("Qstar", "mean", 0)),
]


def test_every_committed_certificate_has_a_hinge_test():
    assert {name for name, _ in HINGES} == {p.name for p in CERTS}


@pytest.mark.parametrize("direction", [1, -1], ids=["up", "down"])
@pytest.mark.parametrize("name,where", HINGES, ids=[f"{n.split('_n')[0].split('_rho')[0]}:{'.'.join(map(str, w))}"
                                                    for n, w in HINGES])
def test_one_ulp_perturbation_of_an_exact_datum_makes_the_replay_reject(name, where, direction):
    cert = _load(name)
    assert replay(cert)[0]
    bad = copy.deepcopy(cert)
    old = _get(bad["data"], where)
    _set(bad["data"], where, _one_ulp(old, direction))
    assert Fraction(_get(bad["data"], where)) != Fraction(old)
    ok, lines = replay(bad)
    assert not ok, "\n".join(lines)
    assert any("[NO]" in ln for ln in lines)


def test_one_ulp_is_one_ulp():
    assert Fraction(_one_ulp("0.5", 1)) - Fraction(1, 2) == Fraction(1, 2**53)
    assert Fraction(_one_ulp("1/3", -1)) == Fraction(1, 3) * (1 - Fraction(1, 2**52))
    assert Fraction(_one_ulp("0", 1)) == Fraction(1, 2**1074)


# --------------------------------------------------------------------------- floats that only approximate


def _as_floats(cert: dict) -> dict:
    out = copy.deepcopy(cert)
    for where, v in _datum_paths(cert["data"]):
        if where[-1] not in ("n", "step", "d"):
            _set(out["data"], where, float(Fraction(v)))
    return out


@pytest.mark.parametrize("name", ["uniqueness_n1_m2_T1.json", "uniqueness_sigma_n1_m1_T1.json", "ltv_n1_m1_T1.json",
                                  "cost_decrease_n1_m1_T1.json"])
def test_certificate_rounded_to_binary_floats_is_rejected(name, tmp_path):
    """Its maximisers are rationals with odd denominators: the nearest doubles are not maximisers."""
    fl = _as_floats(_load(name))
    ok, lines = replay(fl)  # Python floats: their exact binary values
    assert not ok and any("gradient" in ln and "[NO]" in ln for ln in lines), "\n".join(lines)
    p = tmp_path / name
    p.write_text(json.dumps(fl))  # JSON numbers: the decimals they spell
    assert not replay_file(p)[0]


def test_free_energy_certificate_in_floats_still_replays_because_its_data_are_dyadic():
    """The rejection above is about the values, not their type: 1/2, -1, 0 are doubles exactly."""
    assert replay(_as_floats(_load("free_energy_rho_neg_d1.json")))[0]


def test_the_old_float_uniqueness_certificate_is_not_a_counterexample_in_exact_arithmetic():
    """v1 built its 'proportional' columns from an SVD null vector: read exactly, the stacked B has full
    rank, H is nonsingular, the maximiser is unique and neither stored point is one."""
    ok, lines = replay_file(OLD_FLOAT_UNIQUENESS)
    text = "\n".join(lines)
    assert not ok
    assert "rank 2 of m = 2" in text
    assert "[NO] gradient exactly 0 at F1 and at F2" in text
    assert "[NO] corrected statement: H_0 = B^T So^-1 B is exactly singular" in text
    assert "statement as written: not refuted" in lines[-1]


# --------------------------------------------------------------------------- the exact pieces


def test_num_reads_data_exactly_and_rejects_what_is_not_a_number():
    assert num("1/3") == fmpq(1, 3)
    assert num("0.1") == fmpq(1, 10)  # a decimal string is that decimal
    assert num("-1.5e-3") == fmpq(-3, 2000)
    assert num(0.1) == fmpq(3602879701896397, 36028797018963968)  # a float is its binary value
    assert num(Fraction("0.1")) == fmpq(1, 10)  # a JSON number as read by replay_file
    for bad in ("nan", "inf", "1/0", "x", True, None, [1], float("nan")):
        with pytest.raises(ValueError):
            num(bad)


def test_malformed_certificate_data_is_rejected_not_crashed():
    cert = _load("ltv_n1_m1_T1.json")
    cert["data"]["y"] = ["not a number"]
    ok, lines = replay(cert)
    assert not ok and "malformed" in lines[-2]


def test_maximiser_has_an_exactly_zero_gradient_for_singular_and_regular_H():
    for name, key in (("uniqueness_n1_m2_T1.json", "policy"), ("ltv_n1_m1_T1.json", "old")):
        d = _load(name)["data"]
        n = d["model"]["n"]
        Ao, co, So = mat(d["model"]["Ao"][0]), col(d["model"]["co"][0]), mat(d["model"]["So"][0])
        step = (fmpq_mat([[Ao[i, j] for j in range(n)] for i in range(n + 1)]),
                fmpq_mat([[Ao[i, j] for j in range(n, Ao.ncols())] for i in range(n + 1)]), co, So)
        mean, C, _ = dense_smoother(d["model"], d[key], d["y"], d["mu0"], d["P0"])
        mom = moments(mean, C, d["y"], 0)
        assert all(x == 0 for x in gradient(step, maximiser(step, mom), mom).entries())


@pytest.mark.parametrize("n,m,T", [(1, 1, 1), (2, 1, 3), (3, 2, 4)])
def test_exact_dense_smoother_matches_the_library_smoother(n, m, T):
    rng = np.random.default_rng(n * 100 + m * 10 + T)
    model = random_augmented_model(rng, n, m, T)
    pol = random_policy(rng, T, n, m)
    mu0, P0 = random_initial_state(rng, n)
    _, y = sample_model_trajectory(rng, model, pol, mu0, P0)
    sm = estep.smooth(model, pol, y, mu0, P0)
    md = {"Ao": model.Ao.tolist(), "co": model.co.tolist(), "So": model.So.tolist(), "n": n}
    mean, C, lp = dense_smoother(md, {"K": pol.K.tolist(), "k": pol.k.tolist(), "cov": pol.cov.tolist()},
                                 y.tolist(), mu0.tolist(), P0.tolist())
    Cf = np.array([[float(v) for v in row] for row in C.tolist()]).reshape(T + 1, n, T + 1, n)
    np.testing.assert_allclose(np.array([[float(v) for v in mk.entries()] for mk in mean]), sm.mean, atol=1e-9)
    np.testing.assert_allclose(np.stack([Cf[k, :, k, :] for k in range(T + 1)]), sm.cov, atol=1e-9)
    np.testing.assert_allclose(np.stack([Cf[k + 1, :, k, :] for k in range(T)]), sm.cross, atol=1e-9)
    assert float(logp(lp).mid()) == pytest.approx(sm.loglik, abs=1e-9)


def test_replay_of_a_missing_or_malformed_file_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        replay_file(tmp_path / "nope.json")
    p = tmp_path / "x.json"
    p.write_text("{\"kind\": 1}")
    with pytest.raises(ValueError, match="x.json"):
        replay_file(p)


def test_replay_rejects_a_cost_certificate_whose_new_policy_is_the_old_one():
    cert = _load("cost_decrease_n1_m1_T1.json")
    cert["data"]["new"] = cert["data"]["old"]
    assert not replay(cert)[0]
