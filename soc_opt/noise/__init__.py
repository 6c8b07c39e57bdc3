"""Control under measurement noise (docs/math.md §10): beyond the paper, chosen by ``[baseline.noise]``.

- :mod:`.estimator`: the Kalman filter in the loop, filtered policies, the innovation form (§10.2);
- :mod:`.noisefit`: bias-corrected and SSM-EM fits as library functions (§10.1);
- :mod:`.aware`: the loop's noise-aware pieces and :class:`~soc_opt.noise.aware.NoiseConfig`
  (with one table per estimator that has its own options);
- :mod:`.strategy`: one :class:`~soc_opt.noise.strategy.NoiseStrategy` per run (what the loop calls);
- :mod:`.registry`: one line per estimator, filling :data:`soc_opt.plugins.ESTIMATORS`;
- :mod:`.lqg_reference`: exact LQG on a known linear system (§10.3);
- :mod:`.kinematic` and :mod:`.kinematic_strategy`: the structured estimator that knows the
  robot's kinematics (§11) and its strategy, ``estimator = "kinematic"``.
"""
