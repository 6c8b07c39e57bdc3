"""The compiled kernels (soc_opt.compiled) against the numpy reference path and the oracles the Gaussian
core is tested on: brute-force conditioning of the joint Gaussian (tests/test_lgssm.py), the dense
posterior of the §11 smoother's linearised model, the extended-Kalman update of the kinematic filter,
and (with the peers installed) dynamax and pykalman.  The compiled tests skip without numba."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_lgssm import CASES, _brute_force, _instance, _seq

from soc_opt import compiled, lgssm
from soc_opt.models import NotPositiveDefiniteError

needs_numba = pytest.mark.skipif(not compiled.available(), reason="compiled kernels: pip install 'soc_opt[fast]'")


def _per_sequence(params: lgssm.Params, M: int) -> lgssm.Params:
    """The same model with the initial covariance given per sequence (covariances per sequence)."""
    P0 = np.asarray(params.initial.cov)
    if P0.ndim == 3:
        return params
    return params._replace(initial=lgssm.Initial(params.initial.mean, np.broadcast_to(P0, (M,) + P0.shape)))


def _close(a, b, rtol=1e-11):
    """Rounding-level agreement: every entry within ``rtol`` of the array's largest magnitude."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(1.0, float(np.abs(b).max())))


# ------------------------------------------------------------------ which path runs (no numba needed)


def test_the_path_follows_the_environment_variable_and_numba_being_installed(monkeypatch):
    monkeypatch.delenv(compiled.ENV, raising=False)
    assert compiled.backend() == ("numba" if compiled.available() else "numpy")
    monkeypatch.setenv(compiled.ENV, "numpy")
    assert compiled.backend() == "numpy" and compiled.describe().startswith("numpy")
    assert compiled.backend("numba" if compiled.available() else "numpy") in ("numba", "numpy")
    monkeypatch.setenv(compiled.ENV, "fortran")
    with pytest.raises(ValueError, match="fortran"):
        compiled.backend()
    assert compiled.describe().startswith("error:")
    monkeypatch.setattr(compiled, "available", lambda: False)
    monkeypatch.setenv(compiled.ENV, "numba")
    with pytest.raises(ImportError, match=r"soc_opt\[fast\]"):
        compiled.backend()
    monkeypatch.delenv(compiled.ENV)
    assert compiled.backend() == "numpy" and compiled.describe() == "numpy"


def test_the_cache_directory_is_the_users_not_the_source_tree(monkeypatch, tmp_path):
    monkeypatch.delenv("SOC_OPT_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compiled.cache_dir() == tmp_path / "soc_opt" / "numba"
    monkeypatch.setenv("SOC_OPT_CACHE_DIR", str(tmp_path / "own"))
    assert compiled.cache_dir() == tmp_path / "own"


@needs_numba
def test_compiled_kernels_are_cached_outside_the_package():
    from soc_opt.compiled import kinematic_kernels, lgssm_kernels

    src = Path(compiled.__file__).resolve().parents[1]
    for fn in (lgssm_kernels.smooth, lgssm_kernels.forward, lgssm_kernels.smoother, kinematic_kernels.online_update):
        where = Path(fn._cache._cache_path).resolve()
        assert src not in where.parents, where
        assert where == (compiled.cache_dir() / f"kernels-{compiled.source_hash()[:20]}").resolve()
    assert not list(src.rglob("*.nbi"))  # nothing cached in the source tree


# ------------------------------------------------------------------ the Gaussian core


@needs_numba
@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_compiled_smoother_matches_brute_force_conditioning_and_the_numpy_path(case):
    """Every case of the core's brute-force test, with covariances per sequence (an initial covariance
    per sequence where the case shares them): the compiled smoother and filter equal the conditioned
    joint Gaussian to 1e-9 (the core's own tolerance) and the numpy path to rounding."""
    rng = np.random.default_rng(7)
    M, T = 3, 4
    K = T if case["K"] == "T" else T + 1
    params, y = _instance(rng, M=M, T=T, n=3, p=case["p"], K=K, correlated=case["correlated"],
                          per_sequence=case["per_sequence"])
    params = _per_sequence(params, M)
    post = lgssm.rts_smoother(params, y, kernels="numba")
    ref = lgssm.rts_smoother(params, y, kernels="numpy")
    filt = lgssm.kalman_filter(params, y, kernels="numba")
    for i in range(M):
        mean, cov, cross, ll = _brute_force(_seq(params, i, M), y[i])
        np.testing.assert_allclose(post.smoothed_means[i], mean, atol=1e-9)
        np.testing.assert_allclose(post.smoothed_covariances[i], cov, atol=1e-9)
        np.testing.assert_allclose(post.smoothed_cross_covariances[i], cross, atol=1e-9)
        np.testing.assert_allclose(post.marginal_loglik[i], ll, atol=1e-9)
        np.testing.assert_allclose(filt.marginal_loglik[i], ll, atol=1e-9)
        np.testing.assert_allclose(lgssm.log_likelihood(params, y, kernels="numba")[i], ll, atol=1e-9)
    for got, want in zip(post, ref):
        _close(got, want)
    for got, want in zip(filt, lgssm.kalman_filter(params, y, kernels="numpy")):
        _close(got, want)


@needs_numba
@pytest.mark.parametrize("n, p, correlated", [(6, 1, True), (5, 3, False), (4, 9, False)])
def test_compiled_path_equals_the_numpy_path_to_rounding_over_a_long_horizon(n, p, correlated):
    """60 steps, 5 sequences with their own emissions: covariance form (``p <= n``, correlated noise
    removed by the shared preparation) and information form (``p > n``)."""
    rng = np.random.default_rng(11)
    params, y = _instance(rng, M=5, T=60, n=n, p=p, K=61, correlated=correlated, per_sequence=True)
    for got, want in zip(lgssm.rts_smoother(params, y, kernels="numba"), lgssm.rts_smoother(params, y, kernels="numpy")):
        _close(got, want, 1e-10)


@needs_numba
@pytest.mark.parametrize("p", [2, 4])
def test_compiled_extended_filter_linearises_at_the_predictions_and_equals_the_numpy_path(p):
    rng = np.random.default_rng(5)
    M, T = 3, 6
    params, y = _instance(rng, M=M, T=T, n=3, p=p, K=T + 1, correlated=False)
    H, d = params.emissions.weights, params.emissions.bias
    seen = {"numba": [], "numpy": []}

    def hook(kind):
        def linearize(k, m):
            seen[kind].append(m.copy())
            return np.broadcast_to(H[k], (M,) + H[k].shape) + 0.01 * np.sin(m)[:, :1, None], \
                np.broadcast_to(d[k], (M,) + d[k].shape)
        return linearize

    got = lgssm.rts_smoother(params, y, linearize=hook("numba"), kernels="numba")
    want = lgssm.rts_smoother(params, y, linearize=hook("numpy"), kernels="numpy")
    for a, b in zip(got, want):
        _close(a, b)
    _close(np.stack(seen["numba"]), np.stack(seen["numpy"]))
    filt = lgssm.kalman_filter(params, y, linearize=hook("numba"), kernels="numba")
    _close(np.stack(seen["numba"][-(T + 1):], 1), filt.predicted_means[:, :T + 1])


@needs_numba
def test_compiled_path_raises_what_the_numpy_path_raises():
    rng = np.random.default_rng(2)
    M, T = 2, 5
    params, y = _instance(rng, M=M, T=T, n=3, p=2, K=T + 1, correlated=False, per_sequence=True)
    bad_R = params._replace(emissions=params.emissions._replace(cov=-np.asarray(params.emissions.cov)))
    for kernels in ("numpy", "numba"):
        with pytest.raises(NotPositiveDefiniteError, match=r"innovation covariance S\[0\]"):
            lgssm.rts_smoother(bad_R, y, kernels=kernels)
    # a predicted covariance that is not positive definite from step 3 on (a negative process noise there),
    # the innovation covariances kept positive definite by a large measurement noise
    Q = np.array(params.dynamics.cov)
    Q[2:] = -50.0 * np.eye(3)
    bad_Q = params._replace(dynamics=params.dynamics._replace(cov=Q), emissions=params.emissions._replace(
        cov=np.broadcast_to(1e4 * np.eye(2), np.shape(params.emissions.cov))))
    msgs = []
    for kernels in ("numpy", "numba"):
        with pytest.raises(NotPositiveDefiniteError, match=r"predicted covariance P\[3\]") as e:
            lgssm.rts_smoother(bad_Q, y, kernels=kernels)
        msgs.append(str(e.value))
    assert msgs[0] == msgs[1]


@needs_numba
def test_shared_covariances_keep_the_numpy_path_bit_for_bit():
    """The compiled path serves covariances per sequence only: with every matrix shared (the E-step) the
    numpy recursion runs whichever path is chosen, so its results do not depend on it."""
    rng = np.random.default_rng(8)
    params, y = _instance(rng, M=4, T=7, n=3, p=1, correlated=True)
    for a, b in zip(lgssm.rts_smoother(params, y, kernels="numba"), lgssm.rts_smoother(params, y, kernels="numpy")):
        np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------ the kinematic estimator


@pytest.fixture(scope="module")
def peg_batch():
    from soc_opt.noise.kinematic.model import KinematicModel
    from soc_opt.tasks import load_task

    task = load_task("peg")
    ro = task.rollouts(task.initial_policy(1.0), 3, np.random.default_rng(3))
    return task, KinematicModel(task), ro


@needs_numba
def test_compiled_kinematic_smoother_equals_the_numpy_path_and_the_dense_posterior(peg_batch, monkeypatch):
    """The §11.2 smoother's three kinds of pass (the extended filter's, a Gauss-Newton pass, a pass at a
    fixed linearisation) on peg rollouts: the two paths agree to rounding; the dense posterior of the
    linearised model is tests/test_kinematic_smoother.py's oracle, which the compiled path meets too."""
    from soc_opt.noise.kinematic import em
    from soc_opt.noise.kinematic.config import KinematicConfig
    from soc_opt.noise.kinematic.smoother import smooth

    task, km, ro = peg_batch
    cfg = KinematicConfig()
    R = task.rho2 * np.eye(km.n)
    lg = em.z_model(km, em.initial_map(km, ro.s, task.rho2, cfg.s_floor), cfg)
    out = {}
    for kernels in ("numpy", "numba"):
        monkeypatch.setenv(compiled.ENV, kernels)
        ekf = smooth(km, lg, ro.s, ro.a, R)
        gn = smooth(km, lg, ro.s, ro.a, R, ekf.mean)
        fixed = smooth(km, lg, ro.s, ro.a, R, gn.z_lin, gn.lin)
        out[kernels] = (ekf, gn, fixed)
    for got, want in zip(out["numba"], out["numpy"]):
        for name in ("mean", "cov", "cross", "loglik", "z_lin"):
            _close(getattr(got, name), getattr(want, name), 1e-9)
    monkeypatch.setenv(compiled.ENV, "numba")
    from test_kinematic_smoother import test_equals_dense_gaussian_posterior_of_the_linearised_model

    test_equals_dense_gaussian_posterior_of_the_linearised_model((task, km, ro))


@needs_numba
def test_compiled_online_update_equals_the_numpy_update_and_steps_each_row_alone():
    from soc_opt.noise.kinematic.filter import _online_update

    rng = np.random.default_rng(4)
    B, n, nz = 6, 26, 14
    X = rng.standard_normal((nz, nz))
    Lm = X @ X.T + nz * np.eye(nz)
    H, s, hx = rng.standard_normal((B, n, nz)), rng.standard_normal((B, n)), rng.standard_normal((B, n))
    got = _online_update(s, hx, H, Lm, 0.1, kernels="numba")
    _close(got, _online_update(s, hx, H, Lm, 0.1, kernels="numpy"), 1e-12)
    for b in range(B):
        np.testing.assert_array_equal(_online_update(s[b], hx[b], H[b], Lm, 0.1, kernels="numba"), got[b])
    with pytest.raises(np.linalg.LinAlgError):
        _online_update(s, hx, np.zeros((B, n, nz)), np.zeros((nz, nz)), 0.1, kernels="numba")


# ------------------------------------------------------------------ the peers' smoothers


@needs_numba
def test_per_sequence_compiled_core_agrees_with_dynamax_and_pykalman():
    """The peers' like-for-like row (covariances per sequence, docs/results/peers/) on the compiled path:
    the same posterior as dynamax without its diagonal boost and as pykalman, to 1e-10."""
    pytest.importorskip("dynamax", reason="dynamax: pip install -e '.[peers]'")
    pytest.importorskip("pykalman", reason="pykalman: pip install -e '.[peers]'")
    from dynamax.utils import utils as dxu

    from soc_opt.peers import smoothers as psm

    defaults = dxu.psd_solve.__defaults__
    dxu.psd_solve.__defaults__ = (0.0,)
    try:
        row = psm.compare(np.random.default_rng(4), 4, T=10, M=3, m=2, repeats=1)
    finally:
        dxu.psd_solve.__defaults__ = defaults
    assert row["kernels"].startswith("numba")
    for peer in ("dynamax", "pykalman"):
        for what in ("dmean", "dcov", "dloglik"):
            assert row[f"{peer}_max_{what}"] < 1e-10
    assert row["per_seq_max_dmean"] < 1e-10 and row["per_seq_max_dcov"] < 1e-10
