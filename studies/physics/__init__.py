"""Learning an LCS of a simulated contact system (data from MuJoCo, not from an LCS).

- :mod:`studies.physics.plant` -- the cart-pole with two soft walls (MJCF model, simulation at
  the control rate, data generator).
- :mod:`studies.physics.study` -- the study that learns it (``run_study``, a ``kind = "module"``
  config): data, training jobs, selection, evaluation, ``metrics.json``.
- :mod:`studies.physics.jobs` -- the training jobs, run on :mod:`lcs_cvx.study.executors` and
  stored in the study database as they finish (a second run resumes).
- :mod:`studies.physics.report` -- the markdown report.
- :mod:`studies.physics.cartpole_walls` -- the command line (``python -m``), re-exporting the
  names above.
- :mod:`studies.physics.models` -- the models compared: learned LCSs (violation and prediction
  loss, in normalised coordinates, exported in physical units) and the baselines (affine least
  squares, a small MLP, the affine model per true contact mode).
- :mod:`studies.physics.evaluation` -- one-step and open-loop rollout errors, contact agreement,
  the table and the figures.
- :mod:`studies.physics.mpc_example` -- a short-horizon MPC on a learned LCS, run in MuJoCo.
"""
