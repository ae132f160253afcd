"""Recorded data shipped with the package.

:func:`cube_tosses`: 550 real tosses of a cube onto a table, recorded by motion capture at
148 Hz, the data set of ContactNets (Pfrommer, Halm, Posa, CoRL 2020) as published in
DAIRLab/dair_pll (``assets/contactnets_cube``), under the BSD-3-Clause licence of its authors
(``contactnets_cube.LICENSE`` beside the data, copyright the Dynamic Autonomy and Intelligent
Robotics Lab).
"""

from __future__ import annotations

from importlib import resources

import numpy as np

from ..trajectories import Trajectories

__all__ = ["cube_tosses", "CUBE_DT", "CUBE_SIDE", "CUBE_MASS", "CUBE_COLUMNS"]

#: Sampling period of the tosses (s): 148 Hz.
CUBE_DT = 1.0 / 148.0
#: Side of the cube (m) and its mass (kg), from dair_pll's ``contactnets_cube.urdf``.
CUBE_SIDE = 0.1048
CUBE_MASS = 0.37
#: The 13 state columns: unit quaternion (w, x, y, z), centre position (m, world frame), angular
#: velocity (rad/s, body frame), linear velocity (m/s, world frame).
CUBE_COLUMNS = ("qw", "qx", "qy", "qz", "px", "py", "pz", "wx", "wy", "wz", "vx", "vy", "vz")


def cube_tosses() -> Trajectories:
    """The 550 ContactNets cube tosses as :class:`lcs_cvx.Trajectories`, in file order.

    Each toss ``k`` is ``xs[k]`` ``(T_k + 1, 13)`` (85 to 139 samples; columns
    :data:`CUBE_COLUMNS`, sampled every :data:`CUBE_DT` s) with no input (``us[k]`` of shape
    ``(T_k, 0)``). ``Trajectories.split`` splits them by toss; dair_pll splits real data 50 / 25 /
    25 % into training, validation and test tosses.
    """
    with resources.files(__package__).joinpath("contactnets_cube.npz").open("rb") as fh:
        data = np.load(fh)
        states, offsets = data["states"], data["offsets"]
    xs = [states[offsets[k]:offsets[k + 1]] for k in range(len(offsets) - 1)]
    return Trajectories(xs, [np.zeros((len(x) - 1, 0)) for x in xs])
