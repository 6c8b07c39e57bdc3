"""State files (soc_opt.experiments.statefile): exact round trips of every run state, layouts included, and
refusal of anything outside the schema (issue 18 items 1 and 2)."""

from __future__ import annotations

import io
import json
import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from soc_opt.experiments.run import run_experiment
from soc_opt.experiments.statefile import StateFileError, decode_state, encode_state, peek_state
from soc_opt.lqg.moments import expected_cost
from soc_opt.methods.config import DPSOCConfig, EMConfig, LQRFLMConfig
from soc_opt.noise.aware import NoiseConfig
from soc_opt.tasks import load_task

BASE = LQRFLMConfig(iterations=3, samples=6, kl_budget=1.0)
CONFIGS = {
    "lqr-flm": ("lqr-flm", DPSOCConfig(i_switch=1, baseline=BASE)),
    "dpsoc-em": ("dpsoc-em", DPSOCConfig(i_switch=1, baseline=BASE, em=EMConfig(n_em=1))),
    "dpsoc-em-kalman": ("dpsoc-em", DPSOCConfig(i_switch=1, em=EMConfig(n_em=1), baseline=BASE.replace(
        noise=NoiseConfig(estimator="kalman", fit_correction="ssm_em", prior_data="smoothed")))),
    "ilqg": ("ilqg", DPSOCConfig().replace(ilqg=DPSOCConfig().ilqg.replace(iterations=2))),
}


@pytest.fixture(scope="module")
def states():
    task = load_task("linear2d", overrides={"T": 12})
    out = {}
    for name, (method, cfg) in CONFIGS.items():
        got = []
        run_experiment(task, method, cfg, 0, None, on_iteration=got.append)
        out[name] = got
    return out


def _arrays(obj, path="state", out=None) -> dict:
    """Every array reachable from ``obj``, by path."""
    out = {} if out is None else out
    if isinstance(obj, np.ndarray):
        out[path] = obj
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _arrays(v, f"{path}[{i}]", out)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _arrays(v, f"{path}.{k}", out)
    elif hasattr(obj, "__dict__"):
        for k, v in vars(obj).items():
            _arrays(v, f"{path}.{k}", out)
    return out


@pytest.mark.parametrize("name", list(CONFIGS))
def test_every_state_round_trips_with_equal_values_types_strides_and_flags(states, name):
    for state in states[name]:
        data = encode_state(state)
        back = decode_state(data)
        assert type(back) is type(state)
        a, b = _arrays(state), _arrays(back)
        assert a.keys() == b.keys()
        for k in a:
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
            assert a[k].strides == b[k].strides, k  # the layout, not only the values
            assert a[k].flags.writeable == b[k].flags.writeable, k
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        assert encode_state(back) == data  # scalars, strings, dicts, tuples: all equal


def test_the_run_state_holds_non_contiguous_arrays_that_pickle_would_make_contiguous(states):
    """Why layouts are stored: the previous step's model and reference hold transposed / sliced
    views, and a product on them rounds differently from the same product on a C-ordered copy
    (the cross-process resume drift of issue 18)."""
    state = states["lqr-flm"][-1]
    views = {k: a for k, a in _arrays(state.prev).items() if not a.flags.c_contiguous}
    assert views, "expected non-contiguous arrays in RunState.prev"
    pickled = pickle.loads(pickle.dumps(state.prev))
    assert all(_arrays(pickled)[k].flags.c_contiguous for k in views)
    kept = decode_state(encode_state(state)).prev
    assert all(_arrays(kept)[k].strides == a.strides for k, a in views.items())
    # the numbers depend on the layout: the step-size adaptation's expected cost, over the run
    diff = 0
    for s in states["lqr-flm"] + states["dpsoc-em"]:
        p, q, r = s.prev, pickle.loads(pickle.dumps(s.prev)), decode_state(encode_state(s)).prev
        if p is None:
            continue
        j = expected_cost(p.model.dynamics, p.model.cost, p.reference, p.model.mu0, p.model.P0)
        jr = expected_cost(r.model.dynamics, r.model.cost, r.reference, r.model.mu0, r.model.P0)
        np.testing.assert_array_equal(j, jr)  # the state file: bit for bit
        jq = expected_cost(q.model.dynamics, q.model.cost, q.reference, q.model.mu0, q.model.P0)
        diff += not np.array_equal(j, jq)
    print(f"pickled copies changed the expected cost in {diff} states")


arrays_st = st.sampled_from([np.float64, np.int64, np.bool_, np.float32, np.complex128]).flatmap(
    lambda dt: st.tuples(st.integers(0, 4), st.integers(0, 5), st.integers(0, 3)).map(
        lambda s: np.arange(int(np.prod(s)), dtype=np.int64).reshape(s).astype(dt)))


@settings(max_examples=60, deadline=None)
@given(a=arrays_st, perm=st.permutations([0, 1, 2]), step=st.integers(1, 2), ro=st.booleans())
def test_arrays_keep_values_and_strides_for_views_transposes_and_broadcasts(a, perm, step, ro):
    views = [a.transpose(perm), a[::step], a.transpose(perm)[:, ::step], np.broadcast_to(a[:1], a.shape)]
    for v in views:
        if ro:
            v = v.view()
            v.flags.writeable = False
        back = decode_state(encode_state({"v": v, "s": v.dtype.type(1)}))
        assert back["v"].strides == v.strides and back["v"].dtype == v.dtype
        assert back["v"].flags.writeable == v.flags.writeable
        np.testing.assert_array_equal(back["v"], v)
        assert type(back["s"]) is v.dtype.type


def test_json_values_round_trip_exactly_including_non_finite_floats_and_big_ints():
    value = {"f": [0.1, -0.0, float("inf"), float("-inf"), 1e-320], "i": 2**100, "t": (1, "x", None, True),
             "rng": np.random.default_rng(5).bit_generator.state}
    back = decode_state(encode_state(value))
    assert back["f"][:2] == [0.1, -0.0] and str(back["f"][1]) == "-0.0" and back["f"][2:] == value["f"][2:]
    assert back["i"] == 2**100 and back["t"] == (1, "x", None, True) and back["rng"] == value["rng"]
    assert np.isnan(decode_state(encode_state(float("nan"))))


def test_encoding_an_object_outside_the_schema_names_it():
    class Foo:
        pass

    with pytest.raises(TypeError, match=r"state\.x.*Foo.*schema"):
        encode_state({"x": Foo()})
    with pytest.raises(TypeError, match="dtype object"):
        encode_state({"x": np.array([None])})


# ----------------------------------------------------------------- refusal


def _file(tree_state, arrays=None, *, version=2, checksum=True) -> bytes:
    """A state file with the given structure, checksummed as the writer does."""
    from soc_opt.experiments import statefile

    arrays = arrays or {}
    tree = json.dumps({"format": statefile.FORMAT, "version": version, "state": tree_state}).encode()
    digest = statefile._digest(tree, arrays) if checksum else "0" * 64
    buf = io.BytesIO()
    np.savez(buf, **arrays, __tree__=np.frombuffer(tree, np.uint8), __sha256__=np.frombuffer(digest.encode(), np.uint8))
    return buf.getvalue()


class Payload:
    """Unpickling it creates ``path`` (a stand-in for running any command)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _object_array_npz(marker) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, a0=np.array([Payload(marker)], dtype=object), __tree__=np.zeros(1, np.uint8),
             __sha256__=np.zeros(1, np.uint8))
    return buf.getvalue()


def bad_files(marker) -> dict[str, bytes]:
    """Crafted state files: pickles with a payload, object arrays, JSON with unexpected types."""
    arr = {"a0": np.zeros(4)}
    return {
        "pickle": pickle.dumps(Payload(marker)),
        "pickle with the old header": b"soc_opt checkpoint v1\n" + b"0" * 64 + b"\n" + pickle.dumps(Payload(marker)),
        "npz with an object array": _object_array_npz(marker),
        "unknown type": _file({"$": "object", "type": "posix.system", "fields": {"command": f"touch {marker}"}}),
        "unknown node": _file({"$": "reduce", "callable": "os.system", "args": [f"touch {marker}"]}),
        "a list where a node is expected": _file([1, 2, 3]),
        "field of no class": _file({"$": "object", "type": "RunState", "fields": {"__class__": 1}}),
        "layout outside its buffer": _file({"$": "array", "key": "a0", "shape": [100], "strides": [8]}, arr),
        "negative stride": _file({"$": "array", "key": "a0", "shape": [2], "strides": [-8]}, arr),
        "missing array": _file({"$": "array", "key": "a7", "shape": [1], "strides": [8]}, arr),
        "wrong checksum": _file({"$": "tuple", "items": []}, checksum=False),
        "other version": _file({"$": "tuple", "items": []}, version=1),
        "incomplete object": _file({"$": "object", "type": "BestPolicy",
                                "fields": {"mean_cost": 1.0, "policy": {"$": "list", "items": []}}}),
        "empty": b"",
        "garbage": b"PK\x03\x04 not really a zip",
    }


@pytest.mark.parametrize("kind", list(bad_files("m")))
def test_every_crafted_state_file_is_refused_and_runs_nothing(tmp_path, kind):
    marker = tmp_path / "marker"
    data = bad_files(marker)[kind]
    with pytest.raises(StateFileError) as err:
        decode_state(data, "checkpoint.npz")
    assert "checkpoint.npz" in str(err.value)
    assert not marker.exists()


def test_peek_reads_the_iteration_without_building_the_state(states):
    state = states["lqr-flm"][1]
    assert peek_state(encode_state(state))["iteration"] == state.iteration
