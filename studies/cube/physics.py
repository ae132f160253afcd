r"""Rigid-body simulators as the cube study's physics reference: MuJoCo's and Drake's cube with its
known geometry, from the first state of each toss to its end.

Not a learned model: the box of the tosses (side 0.1048 m, mass 0.37 kg) falling on a plane, with
the nominal parameters of dair_pll's cube (``assets/contactnets_cube.urdf``: inertia
0.00081 kg m² about each axis, Coulomb friction 0.15) or with friction, contact stiffness and
inertia chosen on the validation tosses (:func:`tune`). It tells how far the study's whole-toss
metric is from a model that has the geometry and the rigid-body equations exactly, on the same
tosses (dair_pll's "Drake, nominal parameters" ran on its own split).

- **MuJoCo** (``engine="mujoco"``): ``substeps`` steps per recorded period, soft contact with a
  critically damped time constant, a pyramidal cone;
- **Drake** (``engine="drake"``): dair_pll's simulator — a discrete ``MultibodyPlant`` at the
  recorded period (one step per sample, as dair_pll ran it), point contact between the box and a
  half space, TAMSI (the discrete contact solver of the Drake dair_pll used). Nominal: dair_pll's
  setup, the cube's 0.15 against the ground's 1.0 (Drake combines them to ``2ab/(a+b) = 0.26``)
  and Drake's default point stiffness and dissipation; tuned: one friction for both surfaces,
  stiffness and Hunt–Crossley dissipation.

- :func:`floor_height`: the plane's height, from the resting heights of the training tosses
  (``median(p_z at the end) - side / 2``);
- :func:`simulate`: the whole-toss rollouts of either engine;
- :func:`tune`: the grid point with the lowest whole-toss rotation error on the validation tosses.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from lcs_cvx.datasets import CUBE_DT

from .metrics import whole_toss_errors

__all__ = ["Physics", "NOMINAL", "NOMINAL_DRAKE", "GRIDS", "floor_height", "simulate", "errors", "tune"]

_XML = """<mujoco><option timestep="{ts}" integrator="implicitfast" cone="pyramidal"/>
<worldbody><geom type="plane" size="5 5 .1" pos="0 0 {floor}" friction="{mu} 0.005 0.0001" solref="{tc} 1"/>
<body name="cube"><freejoint/><inertial pos="0 0 0" mass="{mass}" diaginertia="{I} {I} {I}"/>
<geom type="box" size="{a} {a} {a}" friction="{mu} 0.005 0.0001" solref="{tc} 1"/></body></worldbody></mujoco>"""


@dataclass(frozen=True)
class Physics:
    """The simulated cube: the engine (``"mujoco"`` or ``"drake"``), friction coefficient (the
    box's; the plane's is ``ground_friction``, ``None``: the same), moment of inertia (kg m²),
    mass (kg), side (m), floor height (m); MuJoCo's contact time constant (s, ``solref``,
    critically damped); Drake's point stiffness (N/m) and Hunt–Crossley dissipation (s/m),
    ``None``: Drake's defaults."""

    engine: str = "mujoco"
    friction: float = 0.15
    ground_friction: float | None = None
    time_constant: float = 0.005
    stiffness: float | None = None
    dissipation: float | None = None
    inertia: float = 0.00081
    mass: float = 0.37
    side: float = 0.1048
    floor: float = 0.0


#: dair_pll's nominal cube (its URDF) in MuJoCo, with a stiff contact.
NOMINAL = Physics()
#: dair_pll's nominal cube in Drake, as dair_pll simulates it (the ground's friction 1.0).
NOMINAL_DRAKE = Physics(engine="drake", ground_friction=1.0)
_INERTIA = (0.00081, 0.37 * 0.1048**2 / 6)  # the URDF's, a solid box's
#: The grids :func:`tune` searches, by engine.
GRIDS = {"mujoco": {"friction": (0.1, 0.15, 0.2, 0.3, 0.5), "time_constant": (0.002, 0.005, 0.01, 0.02, 0.04),
                    "inertia": _INERTIA},
         "drake": {"friction": (0.1, 0.15, 0.2, 0.3), "stiffness": (1e3, 1e4, 1e5),
                   "dissipation": (0.5, 2.0, 10.0, 50.0), "inertia": _INERTIA}}


def floor_height(xs: Sequence[torch.Tensor], side: float = NOMINAL.side) -> float:
    """The plane's height: the median final height of the tosses ``xs`` (at rest) less half the side."""
    return float(np.median([float(x[-1, 6]) for x in xs])) - side / 2


def simulate(physics: Physics, xs: Sequence[torch.Tensor], substeps: int = 10) -> list[torch.Tensor]:
    """For each toss ``x`` ``(T, 13)`` (:data:`lcs_cvx.datasets.CUBE_COLUMNS`), the ``(T, 13)``
    simulated trajectory from ``x[0]`` (``substeps``: MuJoCo's steps per recorded period; Drake
    takes one)."""
    if physics.engine == "drake":
        return _simulate_drake(physics, xs)
    if physics.engine != "mujoco":
        raise ValueError(f"physics.engine: expected 'mujoco' or 'drake', got {physics.engine!r}")
    import mujoco

    p = physics
    model = mujoco.MjModel.from_xml_string(_XML.format(
        ts=CUBE_DT / substeps, floor=p.floor, mu=p.friction, tc=p.time_constant, mass=p.mass, I=p.inertia,
        a=p.side / 2))
    data = mujoco.MjData(model)
    out = []
    for x in xs:
        x0 = x[0].numpy()
        # MuJoCo's free joint takes the position, the quaternion, the world linear velocity and
        # the body angular velocity as the tosses record them
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


def _simulate_drake(p: Physics, xs: Sequence[torch.Tensor]) -> list[torch.Tensor]:
    """:func:`simulate` in Drake: the free body's state is (quaternion, position) and (world
    angular velocity, world linear velocity); the quaternion of each step is given the sign of the
    previous one (Drake's poses fix ``w ≥ 0``), so the rollout is continuous as the tosses are."""
    from pydrake.common.eigen_geometry import Quaternion
    from pydrake.geometry import AddContactMaterial, Box, HalfSpace, ProximityProperties
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.math import SpatialVelocity
    from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlantConfig
    from pydrake.multibody.tree import SpatialInertia, UnitInertia
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=CUBE_DT, contact_model="point",
                                                      discrete_contact_approximation="tamsi"), builder)
    k = p.inertia / p.mass
    body = plant.AddRigidBody("cube", SpatialInertia(p.mass, np.zeros(3), UnitInertia(k, k, k)))
    for frame, pose, shape, mu in ((body, RigidTransform(), Box(p.side, p.side, p.side), p.friction),
                                   (plant.world_body(), RigidTransform([0.0, 0.0, p.floor]), HalfSpace(),
                                    p.friction if p.ground_friction is None else p.ground_friction)):
        props = ProximityProperties()
        AddContactMaterial(dissipation=p.dissipation, point_stiffness=p.stiffness,
                           friction=CoulombFriction(mu, mu), properties=props)
        plant.RegisterCollisionGeometry(frame, pose, shape, f"{frame.name()} collision", props)
    plant.Finalize()
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    out = []
    for x in xs:
        x0 = x[0].numpy()
        R = RotationMatrix(Quaternion(x0[:4] / np.linalg.norm(x0[:4])))
        context.SetTime(0.0)
        plant.SetFreeBodyPose(plant_context, body, RigidTransform(R, x0[4:7]))
        plant.SetFreeBodySpatialVelocity(plant_context, body, SpatialVelocity(R.matrix() @ x0[7:10], x0[10:13]))
        simulator = Simulator(diagram, context)
        simulator.Initialize()
        traj = [x0]
        for step in range(1, x.shape[0]):
            simulator.AdvanceTo(step * CUBE_DT)
            q, v = plant.GetPositions(plant_context), plant.GetVelocities(plant_context)
            quat = q[:4] if np.dot(q[:4], traj[-1][:4]) >= 0 else -q[:4]
            R = RotationMatrix(Quaternion(q[:4] / np.linalg.norm(q[:4]))).matrix()
            traj.append(np.concatenate([quat, q[4:7], R.T @ v[:3], v[3:6]]))
        out.append(torch.tensor(np.array(traj), dtype=torch.float64))
    return out


def errors(physics: Physics, xs: Sequence[torch.Tensor]) -> dict[str, float]:
    """dair_pll's whole-toss errors (:func:`studies.cube.metrics.whole_toss_errors`) of the
    simulated tosses."""
    return whole_toss_errors(simulate(physics, xs), xs)


def tune(val: Sequence[torch.Tensor], floor: float, engine: str = "mujoco"
         ) -> tuple[Physics, list[dict[str, float]]]:
    """The point of ``GRIDS[engine]`` with the lowest whole-toss rotation error on the validation
    tosses ``val`` (dair_pll's metric), and every point's errors."""
    grid = GRIDS[engine]
    rows = []
    for values in itertools.product(*grid.values()):
        point = dict(zip(grid, values, strict=True))
        rows.append({**point, **errors(Physics(engine=engine, floor=floor, **point), val)})
    best = min(rows, key=lambda r: r["rot"])
    return Physics(engine=engine, floor=floor, **{k: best[k] for k in grid}), rows
