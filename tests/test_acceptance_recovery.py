"""Step sizes that recover (issue 47 item 2; soc_opt/methods/lqr_flm/acceptance.py, docs/math.md §12.2).

``[baseline.acceptance] recover = true``: a rejection remembers the multiplier the run had before it
(``RunState.mult_recover``); a later accepted step whose actual improvement is at least ``recover_ratio``
times a positive predicted one gives it back (at most ``mult_max``) and lifts the ceiling.  Off (the
default) the multiplier follows the rule of §6 and §12.2 exactly as before.  A rejection is forced as in
tests/test_lqr_flm.py: one KL step is made to return a wrecked policy.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_lqr_flm import _damage_call  # a KL step that returns a wrecked policy

from soc_opt.config import ConfigError
from soc_opt.experiments.overrides import apply_config_sets, split_sets
from soc_opt.experiments.run import load_run_config, run_experiment
from soc_opt.experiments.statefile import decode_state, encode_state, peek_state
from soc_opt.lqg.step_size import StepSizeConfig
from soc_opt.methods.base import run_method
from soc_opt.methods.config import AS_WRITTEN, AcceptanceConfig
from soc_opt.methods.lqr_flm.acceptance import NextMultiplier, Verdict, next_multiplier
from soc_opt.methods.registry import get_method
from soc_opt.methods.state import AcceptedPolicy
from soc_opt.tasks import load_task

STEP = StepSizeConfig()


@pytest.fixture(scope="module")
def task():
    return load_task("linear2d")


def _accepted(cost_mean: float, cost_se: float, mult: float = 1.0) -> AcceptedPolicy:
    """An accepted policy carrying only what :func:`next_multiplier` reads (its test cost and error)."""
    return AcceptedPolicy(None, cost_mean, cost_se, 0, None, None, mult)


def _documented_rule(step, cfg, verdict, mult, ceiling, improvements, accepted, adapt):
    """docs/math.md §6 and §12.2 as written there, without recovery: the reference of the rule."""
    if not verdict.accept:
        new = max(mult * cfg.shrink, step.mult_min)
        if cfg.ceiling < 1.0:
            ceiling = cfg.ceiling * mult if ceiling is None else min(ceiling, cfg.ceiling * mult)
        return new, ceiling
    new = mult
    if adapt and improvements is not None:
        predicted, actual = improvements
        if cfg.actual == "samples" and accepted is not None:
            actual = accepted.cost_mean - verdict.cost
        factor = predicted / (2.0 * max(step.min_gap, predicted - actual))
        factor = min(max(factor, step.factor_min), step.factor_max)
        new = min(max(factor * mult, step.mult_min), step.mult_max)
        clear = accepted is not None and verdict.cost < accepted.cost_mean - cfg.kappa * math.hypot(verdict.se,
                                                                                                    accepted.cost_se)
        if cfg.hold_when_improved and clear:
            new = max(new, mult)
    if ceiling is not None:
        if mult >= ceiling * (1.0 - 1e-12):
            ceiling = None
        else:
            new = min(new, ceiling)
    return new, ceiling


positive = st.floats(1e-3, 1e3)
improvement = st.floats(-1e4, 1e4)


@settings(max_examples=300, deadline=None)
@given(accept=st.booleans(), mult=st.floats(1e-4, 1e4), ceiling=st.one_of(st.none(), positive),
       improvements=st.one_of(st.none(), st.tuples(improvement, improvement)),
       has_accepted=st.booleans(), c_a=improvement, se_a=st.floats(0, 10), cost=improvement, se=st.floats(0, 10),
       shrink=st.floats(0.01, 0.99), cap=st.floats(0.05, 1.0), actual=st.sampled_from(["laplace", "samples"]),
       hold=st.booleans(), adapt=st.booleans(), recover_to=st.one_of(st.none(), positive))
def test_recover_off_gives_exactly_the_documented_multiplier_and_ceiling(accept, mult, ceiling, improvements,
                                                                         has_accepted, c_a, se_a, cost, se, shrink,
                                                                         cap, actual, hold, adapt, recover_to):
    cfg = AcceptanceConfig(shrink=shrink, ceiling=cap, actual=actual, hold_when_improved=hold)
    assert cfg.recover is False  # the default
    verdict = Verdict(accept, True, cost, se, 0.0)
    accepted = _accepted(c_a, se_a) if has_accepted else None
    got = next_multiplier(STEP, cfg, verdict, mult, ceiling, improvements, accepted, adapt, recover_to)
    assert isinstance(got, NextMultiplier)
    assert (got.mult, got.ceiling) == _documented_rule(STEP, cfg, verdict, mult, ceiling, improvements, accepted, adapt)
    assert got.recover_to is None  # nothing is remembered with recover off
    # the call without the new argument is the same call
    assert next_multiplier(STEP, cfg, verdict, mult, ceiling, improvements, accepted, adapt) == got


def test_as_written_keeps_recover_off():
    assert AS_WRITTEN.recover is False and AS_WRITTEN.enabled is False
    assert AcceptanceConfig().recover is False and AcceptanceConfig().recover_ratio == 0.5


ON = AcceptanceConfig(recover=True)
ACCEPT, REJECT = Verdict(True, True, 10.0, 1.0, 20.0), Verdict(False, True, 30.0, 1.0, 20.0)


def test_an_accepted_step_predicting_well_after_a_rejection_restores_the_pre_rejection_multiplier_and_lifts_the_ceiling():
    acc = _accepted(10.0, 1.0, mult=2.0)
    rej = next_multiplier(STEP, ON, REJECT, 2.0, None, (5.0, -50.0), acc)
    assert rej == NextMultiplier(2.0 * ON.shrink, ON.ceiling * 2.0, 2.0)  # shrunk, capped, remembered
    # a second rejection in a row remembers the larger, first multiplier
    rej2 = next_multiplier(STEP, ON, REJECT, rej.mult, rej.ceiling, (5.0, -50.0), acc, recover_to=rej.recover_to)
    assert rej2.recover_to == 2.0 and rej2.mult == pytest.approx(2.0 * ON.shrink ** 2)
    for ratio in (ON.recover_ratio, 0.8, 1.0, 3.0):  # actual / predicted at or above recover_ratio
        got = next_multiplier(STEP, ON, ACCEPT, rej2.mult, rej2.ceiling, (100.0, ratio * 100.0), acc,
                              recover_to=rej2.recover_to)
        assert got == NextMultiplier(2.0, None, None), ratio
    # without the GPS rule (adapt_multiplier = false) the same prediction gives the multiplier back too
    got = next_multiplier(STEP, ON, ACCEPT, rej2.mult, rej2.ceiling, (100.0, 60.0), acc, False, rej2.recover_to)
    assert got == NextMultiplier(2.0, None, None)
    # the rule's own value wins when it is the larger one
    big = next_multiplier(STEP, ON, ACCEPT, 1.5, None, (100.0, 100.0), acc, recover_to=2.0)
    assert big == NextMultiplier(1.5 * STEP.factor_max, None, None)


def test_recover_fraction_gives_back_that_fraction_of_the_remembered_multiplier():
    """``recover_fraction = 0.5``: the step that failed at 10 is not retried at 10 at once, but at 5; the
    rule's own value still wins when larger, and the default 1.0 is the full multiplier."""
    half = AcceptanceConfig(recover=True, recover_fraction=0.5)
    acc = _accepted(10.0, 1.0, mult=10.0)
    rej = next_multiplier(STEP, half, REJECT, 10.0, None, (5.0, -50.0), acc)
    assert rej.recover_to == 10.0
    got = next_multiplier(STEP, half, ACCEPT, rej.mult, rej.ceiling, (100.0, 80.0), acc, recover_to=rej.recover_to)
    assert got == NextMultiplier(5.0, None, None)
    full = next_multiplier(STEP, ON, ACCEPT, rej.mult, rej.ceiling, (100.0, 80.0), acc, recover_to=rej.recover_to)
    assert full == NextMultiplier(10.0, None, None) and AcceptanceConfig().recover_fraction == 1.0
    big = next_multiplier(STEP, half, ACCEPT, 4.0, None, (100.0, 100.0), acc, recover_to=10.0)
    assert big == NextMultiplier(4.0 * STEP.factor_max, None, None)
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(ConfigError, match="recover_fraction: must be in"):
            AcceptanceConfig(recover_fraction=bad)


def test_an_accepted_step_below_the_recover_ratio_does_not_restore_the_multiplier():
    acc = _accepted(10.0, 1.0, mult=2.0)
    rej = next_multiplier(STEP, ON, REJECT, 2.0, None, None, acc)
    off = AcceptanceConfig()
    for predicted, actual in ((100.0, 49.0), (100.0, 0.0), (100.0, -10.0), (0.0, 0.0), (-5.0, -1.0)):
        got = next_multiplier(STEP, ON, ACCEPT, rej.mult, rej.ceiling, (predicted, actual), acc, recover_to=rej.recover_to)
        plain = next_multiplier(STEP, off, ACCEPT, rej.mult, rej.ceiling, (predicted, actual), acc)
        assert (got.mult, got.ceiling) == (plain.mult, plain.ceiling), (predicted, actual)  # the ordinary rule
        assert got.recover_to == 2.0 and got.mult < 2.0  # still remembered, not given back
    # no improvements at all (the first step after the EM phase): nothing to judge the model by
    got = next_multiplier(STEP, ON, ACCEPT, rej.mult, rej.ceiling, None, acc, recover_to=rej.recover_to)
    assert got == NextMultiplier(rej.mult, rej.ceiling, 2.0)
    # a stricter ratio: 0.6 of the prediction is not enough for recover_ratio = 0.7
    strict = AcceptanceConfig(recover=True, recover_ratio=0.7)
    got = next_multiplier(STEP, strict, ACCEPT, rej.mult, rej.ceiling, (100.0, 60.0), acc, recover_to=2.0)
    assert got.recover_to == 2.0 and got.mult < 2.0


@settings(max_examples=200, deadline=None)
@given(mult=st.floats(1e-4, 1e6), recover_to=st.one_of(st.none(), st.floats(1e-4, 1e6)),
       mult_max=st.floats(1e-3, 1e4), ratio=st.floats(0.0, 1.0), actual=st.floats(0.0, 2.0))
def test_recover_to_never_exceeds_mult_max(mult, recover_to, mult_max, ratio, actual):
    """Even from a multiplier or a remembered value above ``mult_max`` (a run starts at 1 whatever
    ``mult_max`` is), what is remembered and what is given back stay at most ``mult_max``."""
    step = StepSizeConfig(mult_min=min(1e-4, mult_max), mult_max=mult_max)
    cfg = AcceptanceConfig(recover=True, recover_ratio=ratio)
    rej = next_multiplier(step, cfg, REJECT, mult, None, None, None, recover_to=recover_to)
    assert rej.recover_to == min(mult if recover_to is None else max(mult, recover_to), mult_max)
    held = next_multiplier(step, cfg, ACCEPT, rej.mult, rej.ceiling, None, None, recover_to=recover_to)
    assert held.recover_to is None or held.recover_to <= mult_max
    got = next_multiplier(step, cfg, ACCEPT, min(rej.mult, mult_max), rej.ceiling, (1.0, actual), None,
                          recover_to=rej.recover_to)
    assert got.mult <= mult_max and (got.recover_to is None or got.recover_to <= mult_max)
    if actual >= ratio:  # the model predicts well: given back, at most mult_max
        assert got.recover_to is None and got.ceiling is None
        assert got.mult == max(min(rej.recover_to, mult_max), got.mult) and got.mult >= rej.recover_to


def _cfg(method: str, recover: bool, iterations: int = 5, samples: int = 5, i_switch: int = 3):
    cfg = load_run_config("linear2d", method=method, overrides={"iterations": iterations, "samples": samples})
    acc = cfg.baseline.acceptance.replace(enabled=True, recover=recover)
    return cfg.replace(i_switch=i_switch, baseline=cfg.baseline.replace(acceptance=acc))


def test_run_state_mult_recover_round_trips_through_the_checkpoint(task, tmp_path, monkeypatch):
    """``RunState.mult_recover`` is in the state file (a float and None alike), and a run stopped while a
    multiplier is remembered and resumed from its checkpoint ends with the same numbers."""
    cfg = _cfg("lqr-flm", True)
    _damage_call(monkeypatch, {1})
    full = run_method(get_method("lqr-flm"), task, cfg, 0)
    states = []
    _damage_call(monkeypatch, {1})
    run_experiment(task, "lqr-flm", cfg, 0, None, on_iteration=states.append)
    pending = [s for s in states if s.mult_recover is not None]
    assert pending, "the wrecked step should leave a multiplier to give back"
    for s in (pending[0], states[-1]):
        data = encode_state(s)
        back = decode_state(data)
        assert back.mult_recover == s.mult_recover and back.mult_ceiling == s.mult_ceiling and back.mult == s.mult
        assert encode_state(back) == data
        assert peek_state(data)["mult_recover"] == s.mult_recover
    stop_at = pending[0].iteration

    class Stop(Exception):
        pass

    def stop_after(s):
        if s.iteration == stop_at:
            raise Stop

    _damage_call(monkeypatch, {1})
    with pytest.raises(Stop):
        run_experiment(task, "lqr-flm", cfg, 0, tmp_path / "run", on_iteration=stop_after)
    resumed = run_experiment(task, "lqr-flm", cfg, 0, tmp_path / "run")
    assert [r.mult for r in resumed.history] == [r.mult for r in full.history]
    for a, b in zip(resumed.history, full.history):
        np.testing.assert_array_equal(a.cost, b.cost)
    assert (resumed.mult, resumed.mult_ceiling, resumed.mult_recover) == (full.mult, full.mult_ceiling,
                                                                          full.mult_recover)


@pytest.mark.parametrize("method", ["lqr-flm", "dpsoc-em"])
def test_linear2d_multiplier_rises_back_after_a_rejection_with_recover_and_not_without(task, monkeypatch, method):
    """The step producing p_2 is wrecked and rejected; once an accepted step's actual improvement is at
    least half its prediction, the run with ``recover`` is back at the multiplier of the rejected step,
    the run without stays below the ceiling the rejection left."""
    runs = {}
    for recover in (False, True):
        _damage_call(monkeypatch, {1})
        state = run_method(get_method(method), task, _cfg(method, recover), 0)
        runs[recover] = [r for r in state.history if r.phase == "baseline"]
    off, on = runs[False], runs[True]
    assert off[2].extra["accepted"] == on[2].extra["accepted"] == 0.0  # p_2 rejected in both runs
    before = off[1].mult  # the multiplier of the step that produced the rejected p_2
    assert on[1].mult == before and on[2].mult == off[2].mult == pytest.approx(before * 0.1)
    assert on[2].extra["mult_recover"] == before and "mult_recover" not in off[2].extra

    def good(r):
        return r.extra["accepted"] == 1.0 and r.extra["predicted_improvement"] > 0 and (
            r.extra["actual_improvement"] >= 0.5 * r.extra["predicted_improvement"])

    back = [i for i in range(3, len(on)) if good(on[i])]
    assert back, "an accepted step after the rejection should predict well on linear2d"
    i = back[0]
    for j in range(3, i):  # before it the two runs take the same steps
        assert on[j].mult == off[j].mult and np.isclose(on[j].extra["mult_recover"], before)
    assert on[i].mult == before and np.isnan(on[i].extra["mult_recover"])  # given back, nothing remembered
    assert all(r.mult < 0.5 * before for r in off[2:i + 1])  # without it: below the ceiling (half of before)
    assert on[i].mult > 2 * off[i].mult


def test_recover_loads_from_toml_and_set_and_a_bad_recover_ratio_names_the_key(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("[baseline.acceptance]\nrecover = true\nrecover_ratio = 0.3\n")
    cfg = load_run_config("linear2d", good, method="lqr-flm")
    assert cfg.baseline.acceptance.recover is True and cfg.baseline.acceptance.recover_ratio == 0.3
    assert cfg.baseline.acceptance.enabled is True  # the rest of the table keeps its defaults
    assert load_run_config("linear2d", method="lqr-flm").baseline.acceptance.recover is False
    # --set baseline.acceptance.recover=true
    base = load_run_config("linear2d", method="lqr-flm")
    sets = split_sets(["baseline.acceptance.recover=true", "baseline.acceptance.recover_ratio=1"])[1]
    got = apply_config_sets(base, sets, "lqr-flm").baseline.acceptance
    assert got.recover is True and got.recover_ratio == 1.0
    for bad in ("1.5", "-1"):
        path = tmp_path / "bad.toml"
        path.write_text(f"[baseline.acceptance]\nrecover = true\nrecover_ratio = {bad}\n")
        with pytest.raises(ConfigError, match=r"baseline\.acceptance\.recover_ratio: must be in \[0, 1\]"):
            load_run_config("linear2d", path, method="lqr-flm")
        with pytest.raises(ConfigError, match=r"recover_ratio"):
            apply_config_sets(base, split_sets([f"baseline.acceptance.recover_ratio={bad}"])[1], "lqr-flm")
    with pytest.raises(ConfigError, match="recover_ratio: must be in"):
        AcceptanceConfig(recover_ratio=float("-1"))
    with pytest.raises(ConfigError, match="recover: expected true/false"):
        apply_config_sets(base, split_sets(["baseline.acceptance.recover=maybe"])[1], "lqr-flm")


def test_a_record_without_recover_resumes_as_recover_off():
    """Run directories recorded before the option existed ran without it (``IMPLIED_WHEN_ABSENT``)."""
    from soc_opt.experiments.rundir import differences

    new = {"baseline": {"acceptance": AcceptanceConfig().to_dict()}}
    old = {"baseline": {"acceptance": {k: v for k, v in new["baseline"]["acceptance"].items()
                                       if k not in ("recover", "recover_ratio")}}}
    assert differences(old, new) == []
    on = {"baseline": {"acceptance": AcceptanceConfig(recover=True).to_dict()}}
    assert differences(old, on) == ["baseline.acceptance.recover: (unset: false when recorded) -> true"]
