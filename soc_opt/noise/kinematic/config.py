"""Parameters of the kinematic estimator (``[baseline.noise.kinematic]``, ``docs/math.md §11``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ...config import Config, Interval, Options, config_error

__all__ = ["KinematicConfig"]


@dataclass(frozen=True)
class KinematicConfig(Config):
    """The structured estimator of ``estimator = "kinematic"`` (``docs/math.md §11``; ``docs/noise.md`` §11).

    It uses the robot's kinematics (MuJoCo forward kinematics and site Jacobians), not its
    masses, inertia or damping (unless ``start_map = "rigid_body"``); the acceleration map
    ``u = B a + D z + c + w`` is learned.

    relin:          Gauss-Newton passes of the iterated smoother (relinearising ``h`` at the
                    smoothed mean) after the first extended-Kalman pass.
    em_iters:       EM iterations per learner iteration (E-step with the linearisation fixed,
                    so the likelihood of the linearised model never decreases).
    segments:       the acceleration map is constant over this many equal time segments
                    (``T``: one map per step).
    prior_strength: pseudo-count of the prior on each segment's map: the time-pooled moments of
                    the same E-step (``0``: none, plain maximum likelihood per segment).
    q_noise:        standard deviation (rad, or m for slide joints) per control step of the
                    process noise on the joint-angle rows (residual of the kinematic rows).
    s_floor:        eigenvalue floor of the acceleration noise ``S`` ((rad/s^2)^2).
    p0:             variance of the start state ``z_0`` around ``z(x_0)`` (times ``I``); a task with a start
                    range (``[process_noise] start``, docs/math.md §8.1) adds its covariance (``r^2 / 3`` on
                    the angles of ``state.joints``).
    warm_start:     start EM from the acceleration map of the sampling policy's filter (the
                    previous iteration's) instead of the batch's own initial map (``B = D = c = 0``,
                    ``S`` from the measured velocities' second differences).
    restart_from_data: with ``warm_start``, also run EM from the batch's own initial map and keep
                    the run whose final ``log p(s | a)`` (each at its own linearisation of ``h``) is
                    higher: EM from the previous map can stay in a poor local optimum near the plan
                    of the last KL step, whose smoothed states then confirm the plan (measured on
                    peg: the warm start's likelihood 5,000 lower, a 3 cm bias of the peg position
                    while it rests on the table, the learner's cost 22 against a true 33).  Doubles
                    the estimator's work (see ``parallel_starts``).
    parallel_starts: run the second EM start in a forked child process while this one runs the
                    first (:func:`soc_opt.noise.kinematic.em.fit_starts`), when ``fork`` exists, more
                    than one CPU is available and one is idle (:func:`soc_opt.parallel.spare_cpu`);
                    else in turn.  Results are identical either way (each start's arithmetic is
                    unchanged); only the wall time differs.
    start_select:   how the two EM starts of ``restart_from_data`` are compared: ``"previous"`` (the
                    likelihood each final map gives the previous batch, which the sampling policy's
                    filter was learned from and which was drawn under other gains: held out, one
                    extended-Kalman pass per map, docs/math.md §11.2) or ``"batch"`` (the final
                    likelihood of this batch, the default).  In-sample, the batch's own
                    start can win with a map that explains this batch through the state feedback
                    ``D`` the sampler's gains tie to its actions, and predict badly once the gains
                    change (the hypothesis; measured, ``"previous"`` is worse on peg and no better
                    on the door, so it is not the default).  Without a previous
                    batch (the first iteration) ``"batch"`` is used.  ``"data"``: always the batch's
                    own start (for the learner; with ``filter_start = "sampler"`` the filter still
                    follows the sampler's line; measured worse on both tasks, off).
    filter_start:   the EM run the online filter (what the next policy acts on) is built from:
                    ``"kept"`` (the run ``start_select`` kept, which the learner also learns from) or
                    ``"sampler"`` (the default: the run started from the sampling policy's filter's
                    map, so the filter's map follows its own line of warm starts, while the learner
                    still gets the kept run's smoothed states).  The batch's own
                    start ends with a larger acceleration noise ``S`` (EM shrinks it slowly from its
                    broad start): the smoother then follows the measurements more, which removes the
                    bias the learner needs removed, and the filter follows them more too: under
                    high-gain feedback that drove the door's closed loop off, although the same
                    filter estimated the batch itself better.  Without a sampler's map (the first iteration), or with
                    a single EM start, the filter is the kept run's.
    kl_model:       the LQR-FLM KL step's model: ``"plain"`` (the fit on the smoothed states as if
                    the state were known) or ``"innovation"`` (its innovation form with the
                    Kalman filter of that fit and ``R``, as in ``docs/noise.md`` §5: filter-error
                    cost term and innovation noise; the policy still acts on the kinematic filter).
    filter:         what the policy acts on: ``"kinematic"`` (the extended Kalman filter of the
                    structured model, docs/math.md §11.3) or ``"fit"`` (the Kalman filter of the
                    local dynamics fitted on the smoothed states, docs/math.md §10.2: the KL step
                    and the EM phase then run on that filter's innovation form, as with
                    ``estimator = "kalman"``, and ``kl_model`` is not used).  With ``"fit"`` the
                    sampling policy carries no acceleration map, so EM is not warm-started.
    gains:          the online filter's update: ``"online"`` (relinearised at each rollout's own
                    prediction, the extended Kalman update with the nominal prior covariance;
                    docs/math.md §11.3) or ``"nominal"`` (gains computed once along the mean
                    smoothed trajectory).  Used with
                    ``filter = "kinematic"``.
    dynamics:       the local dynamics of the KL step and the EM phase: ``"fit"`` (the §2 regression
                    on the smoothed states) or ``"structured"`` (the estimator's own transition in ``z``,
                    kinematic rows and acceleration map, carried into the task's state through ``h``
                    linearised along the batch's mean smoothed trajectory; docs/math.md §11.3 (a):
                    the model the policy's filter predicts with).  With ``filter = "kinematic"`` only.
    fit_moments:    the statistics of the §2 fit on the smoothed states: ``"means"`` (the smoothed means
                    as if they were the states) or ``"posterior"`` (plus the smoother's posterior
                    covariances ``H P H^T`` and cross-covariances of consecutive states, in task
                    coordinates, averaged over rollouts and weighted as data against the NIW prior:
                    the expected sufficient statistics of the EM M-step, docs/math.md §11.3; the
                    default).  Used with
                    ``learn_on = "smoothed"`` and ``rho^2 > 0`` (otherwise the states are exact or
                    filtered, and the fit takes them as they are).
    structured_prior: pseudo-count of the structured transition (the one ``dynamics = "structured"``
                    uses) as a conjugate prior on the per-step fit of ``dynamics = "fit"``: the fit's
                    joint moments pooled with ``structured_prior`` pseudo-tuples drawn from that
                    transition at the data's ``(x_k, a_k)`` moments, against ``M + n0`` for the batch
                    (docs/math.md §11.3).  ``0`` (default): the fit on the data alone.  With
                    ``filter = "kinematic"`` and ``dynamics = "fit"`` only.
    w_floor:        with ``dynamics = "structured"`` or ``structured_prior > 0``: variance added to every diagonal entry of the
                    process noise in task coordinates (the transition's noise has rank ``nz`` there).
    start_map:      the batch's own EM start's map: ``"zero"`` (``B = D = c = 0``: kinematics only) or
                    ``"rigid_body"`` (the robot's contact-free rigid-body acceleration, MuJoCo's
                    ``qacc_smooth``, linearised along the batch's mean measured trajectory; assumes
                    the robot's masses, inertia, damping and gravity known, not its contacts;
                    :mod:`soc_opt.noise.kinematic.rigid`).  The first iteration has only this start.
    learn_on:       the states the learner (prior, fit, cost expansion, EM phase) sees: ``"smoothed"``
                    (``h(E[z_k | s_0..s_T, a])``) or ``"filtered"`` (the estimates the new policy will
                    act on: this batch re-filtered with the batch's new filter, ``E[z_k | s_0..s_k]``
                    in the filter's model, so the fitted dynamics are those of the filter's estimate
                    under the actions, estimation error included).
    """

    relin: int = 1
    em_iters: int = 2
    segments: int = 50
    prior_strength: float = 20.0
    q_noise: float = 0.007
    s_floor: float = 1e-4
    p0: float = 1e-6
    warm_start: bool = True
    restart_from_data: bool = True
    parallel_starts: bool = True
    start_select: Literal["previous", "batch", "data"] = "batch"
    filter_start: Literal["kept", "sampler"] = "sampler"
    kl_model: Literal["plain", "innovation"] = "plain"
    filter: Literal["kinematic", "fit"] = "kinematic"
    learn_on: Literal["smoothed", "filtered"] = "smoothed"
    gains: Literal["nominal", "online"] = "online"
    dynamics: Literal["fit", "structured"] = "fit"
    fit_moments: Literal["means", "posterior"] = "posterior"
    structured_prior: float = 0.0
    w_floor: float = 1e-6
    start_map: Literal["zero", "rigid_body"] = "zero"

    # runs of the kinematic estimator recorded before these fields existed used fixed gains and the means fit
    _implied_when_absent = {"kinematic.gains": ("nominal", {"estimator": "kinematic"}),
                            "kinematic.fit_moments": ("means", {"estimator": "kinematic"}),
                            "kinematic.restart_from_data": (False, {"estimator": "kinematic"}),
                            "kinematic.start_select": ("batch", {"estimator": "kinematic"}),
                            "kinematic.filter_start": ("kept", {"estimator": "kinematic"})}

    _constraints = {
        "relin": [Interval(0)],
        "em_iters": [Interval(0)],
        "segments": [Interval(1)],
        "prior_strength": [Interval(0.0)],
        "q_noise": [Interval(0.0)],
        "s_floor": [Interval(0.0, None, "neither")],
        "p0": [Interval(0.0, None, "neither")],
        "kl_model": [Options(("plain", "innovation"))],
        "start_select": [Options(("previous", "batch", "data"))],
        "filter_start": [Options(("kept", "sampler"))],
        "filter": [Options(("kinematic", "fit"))],
        "learn_on": [Options(("smoothed", "filtered"))],
        "gains": [Options(("nominal", "online"))],
        "dynamics": [Options(("fit", "structured"))],
        "fit_moments": [Options(("means", "posterior"))],
        "w_floor": [Interval(0.0, None, "neither")],
        "structured_prior": [Interval(0.0)],
        "start_map": [Options(("zero", "rigid_body"))],
    }

    def __post_init__(self):
        if self.dynamics == "structured" and self.filter != "kinematic":
            raise config_error("dynamics", "'structured' is the transition of the kinematic filter; it needs "
                               f"filter = 'kinematic' (got {self.filter!r})")
        if self.structured_prior > 0 and (self.dynamics != "fit" or self.filter != "kinematic"):
            raise config_error("structured_prior", "the structured prior is a prior on the fit of dynamics = 'fit' "
                               "with filter = 'kinematic' (got dynamics = "
                               f"{self.dynamics!r}, filter = {self.filter!r})")
