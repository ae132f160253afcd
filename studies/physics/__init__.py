"""Learning an LCS of a simulated contact system (data from MuJoCo, not from an LCS).

- :mod:`studies.physics.cartpole_walls` -- the cart-pole with two soft walls (MJCF model, data
  generator) and the study that learns it (``run_study``, a ``kind = "module"`` config).
- :mod:`studies.physics.models` -- the models compared: learned LCSs (violation and prediction
  loss, in normalised coordinates, exported in physical units) and the baselines (affine least
  squares, a small MLP, the affine model per true contact mode).
- :mod:`studies.physics.evaluation` -- one-step and open-loop rollout errors, contact agreement,
  the table and the figures.
- :mod:`studies.physics.mpc_example` -- a short-horizon MPC on a learned LCS, run in MuJoCo.
"""
