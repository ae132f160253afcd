r"""A rigid-body simulator as the cube study's physics reference: MuJoCo's cube with its known
geometry, from the first state of each toss to its end.

Not a learned model: the box of the tosses (side 0.1048 m, mass 0.37 kg) falling on a plane, with
the nominal parameters of dair_pll's cube (``assets/contactnets_cube.urdf``: inertia
0.00081 kg m² about each axis, Coulomb friction 0.15) or with friction, contact stiffness and
inertia chosen on the validation tosses (:func:`tune`). It tells how far the study's whole-toss
metric is from a model that has the geometry and the rigid-body equations exactly, on the same
tosses (dair_pll's "Drake, nominal parameters" ran on its own split).

- :func:`floor_height`: the plane's height, from the resting heights of the training tosses
  (``median(p_z at the end) - side / 2``);
- :func:`simulate`: the whole-toss rollouts, ``substeps`` MuJoCo steps per recorded period;
- :func:`tune`: the grid point with the lowest whole-toss rotation error on the validation tosses.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from lcs_cvx.datasets import CUBE_DT

from .metrics import whole_toss_errors

__all__ = ["Physics", "NOMINAL", "GRID", "floor_height", "simulate", "errors", "tune"]

_XML = """<mujoco><option timestep="{ts}" integrator="implicitfast" cone="pyramidal"/>
<worldbody><geom type="plane" size="5 5 .1" pos="0 0 {floor}" friction="{mu} 0.005 0.0001" solref="{tc} 1"/>
<body name="cube"><freejoint/><inertial pos="0 0 0" mass="{mass}" diaginertia="{I} {I} {I}"/>
<geom type="box" size="{a} {a} {a}" friction="{mu} 0.005 0.0001" solref="{tc} 1"/></body></worldbody></mujoco>"""


@dataclass(frozen=True)
class Physics:
    """The simulated cube: friction coefficient, contact time constant (s; MuJoCo's ``solref``,
    critically damped), moment of inertia (kg m²), mass (kg), side (m), floor height (m)."""

    friction: float = 0.15
    time_constant: float = 0.005
    inertia: float = 0.00081
    mass: float = 0.37
    side: float = 0.1048
    floor: float = 0.0


#: dair_pll's nominal cube (its URDF), with a stiff contact.
NOMINAL = Physics()
#: The grid :func:`tune` searches: friction × contact time constant × inertia (URDF's, a solid box's).
GRID = {"friction": (0.1, 0.15, 0.2, 0.3, 0.5), "time_constant": (0.002, 0.005, 0.01, 0.02, 0.04),
        "inertia": (0.00081, 0.37 * 0.1048**2 / 6)}


def floor_height(xs: Sequence[torch.Tensor], side: float = NOMINAL.side) -> float:
    """The plane's height: the median final height of the tosses ``xs`` (at rest) less half the side."""
    return float(np.median([float(x[-1, 6]) for x in xs])) - side / 2


def simulate(physics: Physics, xs: Sequence[torch.Tensor], substeps: int = 10) -> list[torch.Tensor]:
    """For each toss ``x`` ``(T, 13)`` (:data:`lcs_cvx.datasets.CUBE_COLUMNS`), the ``(T, 13)``
    simulated trajectory from ``x[0]``: MuJoCo's free joint takes the position, the quaternion, the
    world linear velocity and the body angular velocity as the tosses record them."""
    import mujoco

    p = physics
    model = mujoco.MjModel.from_xml_string(_XML.format(
        ts=CUBE_DT / substeps, floor=p.floor, mu=p.friction, tc=p.time_constant, mass=p.mass, I=p.inertia,
        a=p.side / 2))
    data = mujoco.MjData(model)
    out = []
    for x in xs:
        x0 = x[0].numpy()
        mujoco.mj_resetData(model, data)
        data.qpos[:3], data.qpos[3:7] = x0[4:7], x0[:4]
        data.qvel[:3], data.qvel[3:6] = x0[10:13], x0[7:10]
        traj = [x0]
        for _ in range(x.shape[0] - 1):
            for _ in range(substeps):
                mujoco.mj_step(model, data)
            traj.append(np.concatenate([data.qpos[3:7], data.qpos[:3], data.qvel[3:6], data.qvel[:3]]))
        out.append(torch.tensor(np.array(traj), dtype=torch.float64))
    return out


def errors(physics: Physics, xs: Sequence[torch.Tensor]) -> dict[str, float]:
    """dair_pll's whole-toss errors (:func:`studies.cube.metrics.whole_toss_errors`) of the
    simulated tosses."""
    return whole_toss_errors(simulate(physics, xs), xs)


def tune(val: Sequence[torch.Tensor], floor: float) -> tuple[Physics, list[dict[str, float]]]:
    """The :data:`GRID` point with the lowest whole-toss rotation error on the validation tosses
    ``val`` (dair_pll's metric), and every point's errors."""
    rows = []
    for mu, tc, inertia in itertools.product(*GRID.values()):
        physics = replace(NOMINAL, friction=mu, time_constant=tc, inertia=inertia, floor=floor)
        rows.append({"friction": mu, "time_constant": tc, "inertia": inertia, **errors(physics, val)})
    best = min(rows, key=lambda r: r["rot"])
    return replace(NOMINAL, friction=best["friction"], time_constant=best["time_constant"],
                   inertia=best["inertia"], floor=floor), rows
