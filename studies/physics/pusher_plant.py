r"""The plant of the pusher-slider study: a box pushed across a table by a point finger, with
Coulomb friction at the table and at the finger, simulated with MuJoCo, and the transitions it
generates.

The plant (an MJCF model built by :func:`mjcf`; every number is a field of :class:`Physics`):

- slider: a box of 0.5 kg, 10 cm x 10 cm x 4 cm (half sizes 0.05, 0.05, 0.02 m), on a
  horizontal table (a plane at z = 0), with the planar joints x, y (slides), z (a slide, so that
  the table carries its weight through real contact forces) and a hinge about z; no roll or pitch;
- table contact: MuJoCo's box-plane contact (the four bottom corners) with friction coefficient
  ``mu_table = 0.3`` (``condim = 3``);
- pusher: a sphere of radius 1 cm and 1 kg at the slider's mid-height (z = 0.02 m) on two
  horizontal slides, driven by two velocity servos ``f = kv (u - v)`` with ``kv = 1000 N s/m``
  (time constant m / kv = 1 ms: it follows the commanded velocity, and a push of the ~1.5 N the
  table's friction needs slows it by ~1.5 mm/s); it touches the slider only, never the table;
- pusher contact: friction coefficient ``mu_pusher = 0.3`` along the horizontal tangent and 0
  along the vertical one (``condim = 3``, pair friction ``(0.3, 0)``: MuJoCo's contact frame for
  a horizontal normal has its first tangent horizontal; vertical friction between the fixed-height
  finger and a slider that settles on its four soft corners would only chatter);
- friction cone ``cone="pyramidal"``: MuJoCo replaces the friction disk by the square
  ``|f_1| + |f_2| <= mu f_n`` of the contact frame -- friction is polyhedral, as in an LCS;
- contact softness: MuJoCo's defaults, ``solref = (0.02, 1)`` (time constant 0.02 s, critical
  damping) and ``solimp = (0.9, 0.95, 0.001, 0.5, 2)``; gravity 9.81 m/s^2.

Discrete time: MuJoCo's timestep is 2 ms (``integrator="implicitfast"``, which treats the servos'
damping implicitly), float64; a control period is ``substeps = 25`` of them (0.05 s) with the input
held (zero-order hold).

**The slider's frame.** The pyramidal cone of the table contact is a square aligned with its
contact frame, i.e. with the world's axes; so that friction is a property of the slider (its base
square aligned with its edges) and the dynamics do not depend on the slider's heading, the
simulation is re-expressed in the slider's frame at the start of every control period: the slider
and the pusher are rotated and translated so that the slider sits at the origin with heading 0
(positions, velocities and MuJoCo's warm start alike; an exact change of coordinates of a plant
that is otherwise invariant to planar rigid motions). The world pose ``(X, Y, Theta)`` of the
slider is tracked outside MuJoCo by composing the displacement of each period.

State and input (the learning problem), in the slider's frame at the start of the period:

- ``x = (p_x, p_y, v_x, v_y, omega)``: the pusher's centre relative to the slider's centre
  (cm; ``p_x = -6`` cm is touching the back face ``x = -5`` cm with the 1 cm sphere), the
  slider's velocity (cm/s) and angular velocity (rad/s). Centimetres keep the position, velocity
  and rotation components on similar scales (in metres, the relative error would measure
  ``omega`` alone);
- ``u = (u_x, u_y)``: the pusher's commanded velocity (cm/s), held in the world for the period.

A sample is ``(x_t, u_t, x_{t+1})`` one control period apart. For evaluation only, each sample
also records the mean pusher force on the slider over the period (``force``: normal along +x,
tangential along +y, N), its contact mode (``contact``, one of :data:`MODES`) and the slider's
world pose at its start (``pose``: X, Y in cm, Theta in rad). The mode: ``separated`` if the pusher
touched the slider in no substep; else, from the mean tangential slip velocity of the pusher
relative to the slider's material point under it over the contact substeps, ``sticking`` if
``|slip| <= slip_tol = 0.5 cm/s``, else ``sliding +y`` or ``sliding -y``.

Data (:func:`sample_transitions`): each trajectory starts with the slider at rest and the pusher
at rest behind the back face, at a gap ``U[0, 1]`` cm and a contact offset ``p_y ~ U[-3.5, 3.5]``
cm. Every period draws the command ``u_x ~ U[-2, 10]`` cm/s (biased towards the slider: it
pushes on average, and retreats in a sixth of the periods) and ``u_y = -2 p_y + w`` with
``w ~ U[-4, 4]`` cm/s (random sideways motion with a weak pull towards the face's centre, so
that the pusher stays on the face long enough for 20-step windows). A trajectory ends after 25
periods, or when the pusher leaves the back face (``|p_y| > 4.5`` cm) or is more than 3 cm
behind it (that last transition is kept), and a new one starts. The wide-input test set draws
both commands from ranges ``wide_factor = 1.5`` times wider about the same centres.

Measured data (``sensor``, :mod:`studies.physics.sensor`): by default the samples hold the
simulator's states. ``sensor = "mocap"`` logs them as a motion-capture system would: the
slider's world pose and the pusher's world position read with Gaussian jitter (0.5 mm on each
position coordinate, 0.005 rad on the heading), the state rebuilt from the readings with the
slider's velocities as backward differences over the control period (noise of ~1.4 cm/s and
~0.14 rad/s); ``"differenced"`` does the same without jitter (:func:`sample_measured`). The
inputs are those of the exact data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .sensor import Sensor, difference, noise_rng
from .sensor import sensor as get_sensor
from .transitions import Transitions

__all__ = [
    "Physics",
    "Sampling",
    "PusherTransitions",
    "PusherSlider",
    "mjcf",
    "sample_transitions",
    "sample_measured",
    "MODES",
    "STATE_NAMES",
    "STATE_UNITS",
    "INPUT_NAMES",
]

STATE_NAMES = ("p_x", "p_y", "v_x", "v_y", "omega")
STATE_UNITS = ("cm", "cm", "cm/s", "cm/s", "rad/s")
INPUT_NAMES = ("u_x (cm/s)", "u_y (cm/s)")
#: Contact modes of the pusher, by label (``contact`` of a sample).
MODES = ("separated", "sticking", "sliding +y", "sliding -y")
_CM = 100.0  # state and input in cm, MuJoCo in m


@dataclass(frozen=True)
class Physics:
    """Physical and numerical parameters of the plant (SI units; see the module docstring)."""

    slider_half_size: float = 0.05  # square footprint, half side (m)
    slider_half_height: float = 0.02
    slider_mass: float = 0.5
    pusher_radius: float = 0.01
    pusher_mass: float = 1.0
    pusher_kv: float = 1000.0  # velocity servo gain (N s/m)
    mu_table: float = 0.3
    mu_pusher: float = 0.3
    timestep: float = 0.002
    substeps: int = 25  # control period = substeps * timestep
    slip_tol: float = 0.005  # |mean slip| above this (m/s) is sliding

    @property
    def control_period(self) -> float:
        return self.substeps * self.timestep

    @property
    def touching_x(self) -> float:
        """``p_x`` (cm) of the pusher touching the back face."""
        return -_CM * (self.slider_half_size + self.pusher_radius)


@dataclass(frozen=True)
class Sampling:
    """How transitions are drawn (see :func:`sample_transitions`); lengths in cm, velocities
    in cm/s."""

    ux_range: tuple[float, float] = (-2.0, 10.0)  # u_x ~ U[lo, hi]
    uy_noise: float = 4.0  # u_y = -uy_gain p_y + w, w ~ U[-uy_noise, uy_noise]
    uy_gain: float = 2.0  # (1/s)
    traj_len: int = 25
    gap0_max: float = 1.0  # initial gap ~ U[0, gap0_max]
    offset0_max: float = 3.5  # initial p_y ~ U[-offset0_max, offset0_max]
    face_limit: float = 4.5  # the trajectory ends when |p_y| exceeds this ...
    gap_limit: float = 3.0  # ... or the gap does


def mjcf(p: Physics = Physics()) -> str:
    """The MJCF model of the pusher-slider (a string)."""
    a, h, r = p.slider_half_size, p.slider_half_height, p.pusher_radius
    return f"""<mujoco model="pusher_slider">
  <option timestep="{p.timestep:.17g}" gravity="0 0 -9.81" integrator="implicitfast" cone="pyramidal"/>
  <worldbody>
    <geom name="table" type="plane" size="5 5 0.1" contype="0" conaffinity="0"/>
    <body name="slider" pos="0 0 {h:.17g}">
      <joint name="slider_x" type="slide" axis="1 0 0"/>
      <joint name="slider_y" type="slide" axis="0 1 0"/>
      <joint name="slider_z" type="slide" axis="0 0 1"/>
      <joint name="slider_yaw" type="hinge" axis="0 0 1"/>
      <geom name="slider" type="box" size="{a:.17g} {a:.17g} {h:.17g}" mass="{p.slider_mass:.17g}"
            contype="0" conaffinity="0"/>
    </body>
    <body name="pusher" pos="0 0 {h:.17g}">
      <joint name="pusher_x" type="slide" axis="1 0 0"/>
      <joint name="pusher_y" type="slide" axis="0 1 0"/>
      <geom name="pusher" type="sphere" size="{r:.17g}" mass="{p.pusher_mass:.17g}"
            contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="table" geom2="slider" condim="3" friction="{p.mu_table:.17g} {p.mu_table:.17g} 0.005 0.0001 0.0001"/>
    <pair geom1="pusher" geom2="slider" condim="3" friction="{p.mu_pusher:.17g} 0 0.005 0.0001 0.0001"/>
  </contact>
  <actuator>
    <velocity name="push_x" joint="pusher_x" kv="{p.pusher_kv:.17g}"/>
    <velocity name="push_y" joint="pusher_y" kv="{p.pusher_kv:.17g}"/>
  </actuator>
</mujoco>
"""


def _rotate(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


class PusherSlider:
    """The MuJoCo simulation at the control rate, in the slider's frame: :meth:`reset` puts
    the slider at rest at the origin and the pusher at rest at a position behind it,
    :meth:`step` runs one control period.

    Example:
        >>> sim = PusherSlider()
        >>> sim.reset(p_x=-6.2, p_y=1.0)
        >>> x_next, force, mode = sim.step([10.0, 0.0])
        >>> x_next.shape, force.shape, MODES[mode]
        ((5,), (2,), 'sticking')
    """

    # qpos / qvel layout: slider x, y, z, yaw, pusher x, y
    def __init__(self, physics: Physics = Physics()) -> None:
        import mujoco  # imported here so that the rest of the study imports without it

        self._mj = mujoco
        self.physics = physics
        self.model = mujoco.MjModel.from_xml_string(mjcf(physics))
        self.data = mujoco.MjData(self.model)
        if self.model.opt.timestep != physics.timestep or self.model.opt.cone != mujoco.mjtCone.mjCONE_PYRAMIDAL:
            raise RuntimeError("MuJoCo did not take the timestep or the pyramidal cone")
        gid = lambda name: mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)  # noqa: E731
        self._pair = {gid("pusher"), gid("slider")}
        self._f6 = np.zeros(6)
        # the slider's height resting on the table (its corners sink slightly into the soft contact)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[4] = -1.0  # pusher out of the way
        for _ in range(200):
            mujoco.mj_step(self.model, self.data)
        self._z_rest = float(self.data.qpos[2])
        self._origin = np.zeros(3)  # the world pose (cm, cm, rad) of the simulation's frame

    @property
    def state(self) -> np.ndarray:
        """``x = (p_x, p_y, v_x, v_y, omega)`` ``(5,)`` float64 in the slider's current frame."""
        q, v = self.data.qpos, self.data.qvel
        yaw = float(q[3])
        p = _rotate(q[4:6] - q[0:2], -yaw)
        vel = _rotate(v[0:2], -yaw)
        return np.array([_CM * p[0], _CM * p[1], _CM * vel[0], _CM * vel[1], v[3]])

    def reset(self, p_x: float, p_y: float) -> None:
        """Slider at rest at the origin (heading 0, world pose 0), pusher at rest at
        ``(p_x, p_y)`` cm in its frame (``p_x <= touching_x``: behind the back face)."""
        if not (np.isfinite([p_x, p_y]).all() and p_x <= self.physics.touching_x + 1e-9):
            raise ValueError(f"p_x, p_y: expected finite numbers with p_x <= {self.physics.touching_x:g} cm "
                             f"(not inside the slider), received {p_x!r}, {p_y!r}")
        self._mj.mj_resetData(self.model, self.data)
        self.data.qpos[:] = [0.0, 0.0, self._z_rest, 0.0, p_x / _CM, p_y / _CM]
        self._mj.mj_forward(self.model, self.data)
        self._origin = np.zeros(3)

    @property
    def pose(self) -> np.ndarray:
        """The slider's world pose ``(X, Y, Theta)`` (cm, cm, rad), ``(3,)``."""
        q = self.data.qpos
        d = _rotate(q[0:2], self._origin[2])
        return self._origin + np.array([_CM * d[0], _CM * d[1], q[3]])

    def _rebase(self) -> None:
        """Re-express the simulation in the slider's frame (see the module docstring), keeping
        the world pose."""
        q, v, w = self.data.qpos, self.data.qvel, self.data.qacc_warmstart
        yaw = float(q[3])
        self._origin = self.pose
        q[4:6] = _rotate(q[4:6] - q[0:2], -yaw)
        q[0:2], q[3] = 0.0, 0.0
        for arr in (v, w):
            arr[0:2], arr[4:6] = _rotate(arr[0:2], -yaw), _rotate(arr[4:6], -yaw)
        self._mj.mj_forward(self.model, self.data)

    def step(self, u: Any) -> tuple[np.ndarray, np.ndarray, int]:
        """One control period under the held command ``u = (u_x, u_y)`` (cm/s, slider frame).

        Returns ``(x_next (5,), force (2,), mode)``: the state after the period (in the slider's
        frame at its end), the mean pusher force on the slider over the period (normal, tangential;
        N) and the index of the contact mode in :data:`MODES`.
        """
        m, d, mj = self.model, self.data, self._mj
        u = np.asarray(u, dtype=np.float64)
        if u.shape != (2,) or not np.isfinite(u).all():
            raise ValueError(f"u: expected 2 finite numbers (u_x, u_y in cm/s), received {u!r}")
        self._rebase()
        d.ctrl[:] = u / _CM
        force = np.zeros(2)
        slip, touching = 0.0, 0
        for _ in range(self.physics.substeps):
            mj.mj_step(m, d)
            for i in range(d.ncon):
                c = d.contact[i]
                if {int(c.geom1), int(c.geom2)} != self._pair:
                    continue
                mj.mj_contactForce(m, d, i, self._f6)
                if self._f6[0] <= 0.0:
                    continue
                force += self._f6[:2]  # (normal, first tangent): the force of the pusher on the slider
                tangent = c.frame[3:5]
                arm = c.pos[0:2] - d.qpos[0:2]
                material = d.qvel[0:2] + d.qvel[3] * np.array([-arm[1], arm[0]])
                slip += float(tangent @ (d.qvel[4:6] - material))
                touching += 1
        if touching == 0:
            mode = 0
        else:
            mean_slip = slip / touching
            mode = 1 if abs(mean_slip) <= self.physics.slip_tol else (2 if mean_slip > 0 else 3)
        return self.state, force / self.physics.substeps, mode


@dataclass(frozen=True)
class PusherTransitions(Transitions):
    """:class:`~studies.physics.transitions.Transitions` of the pusher-slider: ``x, x_next``
    ``(N, 5)``, ``u`` ``(N, 2)``, ``force`` ``(N, 2)`` (normal, tangential; N), ``contact``
    ``(N,)`` int (index in :data:`MODES`), and ``pose`` ``(N, 3)``: the slider's world pose
    ``(X, Y, Theta)`` (cm, cm, rad) at the start of each sample."""

    pose: np.ndarray


def sample_transitions(
    n: int,
    seed: int,
    physics: Physics = Physics(),
    sampling: Sampling = Sampling(),
    wide_factor: float = 1.0,
    sensor: str | Sensor = "exact",
) -> PusherTransitions:
    """``n`` transitions of random pushing trajectories (see the module docstring),
    reproducible in ``seed``; ``wide_factor`` widens the ranges of both commands about their
    centres; ``sensor`` (a name of :data:`studies.physics.sensor.SENSORS` ``["pusher"]``) how the
    states are logged (see :func:`sample_measured`)."""
    return sample_measured(n, seed, physics, sampling, wide_factor, sensor)[0]


def sample_measured(
    n: int,
    seed: int,
    physics: Physics = Physics(),
    sampling: Sampling = Sampling(),
    wide_factor: float = 1.0,
    sensor: str | Sensor = "exact",
) -> tuple[PusherTransitions, PusherTransitions]:
    """``(measured, true)``: ``n`` transitions as ``sensor`` logs them, and the same samples with
    the simulator's states (the same ``u``, ``force``, ``contact``, ``traj``, ``step``).

    ``"exact"``: both are the simulator's states, bit for bit the data of the plain generator.
    A differencing sensor (:mod:`studies.physics.sensor`) reads, at every control instant, the
    slider's world pose ``(X, Y, Theta)`` and the pusher's world position ``(X_p, Y_p)`` (cm,
    rad) and logs ``p~ = R(-Theta~_t) (P~_t - S~_t)``, ``v~ = R(-Theta~_t) (S~_t - S~_{t-1}) / dt``
    and ``omega~ = (Theta~_t - Theta~_{t-1}) / dt`` (``S = (X, Y)``, ``P = (X_p, Y_p)``); the
    ``pose`` of a measured sample is the measured pose. Every trajectory starts at rest, so the
    reading one period before its start is of the same positions (with its own jitter): no
    transition is dropped, and the measured samples are the exact data's, one for one. The
    jitter (if any) comes from :func:`studies.physics.sensor.noise_rng`.
    """
    if n < 1:
        raise ValueError(f"n: expected an integer >= 1, received {n!r}")
    sens = get_sensor("pusher", sensor)
    noise = noise_rng(seed)
    sim = PusherSlider(physics)
    rng = np.random.default_rng(seed)
    s = sampling
    ux_mid, ux_half = 0.5 * (s.ux_range[0] + s.ux_range[1]), 0.5 * (s.ux_range[1] - s.ux_range[0]) * wide_factor
    wy = s.uy_noise * wide_factor
    touching = physics.touching_x
    rows: dict[str, list] = {k: [] for k in ("x", "u", "x_next", "force", "contact", "traj", "step", "pose")}
    meas: dict[str, list] = {k: [] for k in rows}
    traj = 0
    while len(rows["x"]) < n:
        sim.reset(touching - rng.uniform(0.0, s.gap0_max), rng.uniform(-s.offset0_max, s.offset0_max))
        x = sim.state
        start = len(rows["x"])
        for t in range(s.traj_len):
            u = np.array([ux_mid + rng.uniform(-ux_half, ux_half), -s.uy_gain * x[1] + rng.uniform(-wy, wy)])
            pose = sim.pose.copy()
            x_next, force, mode = sim.step(u)
            for k, v in zip(rows, (x, u, x_next, force, mode, traj, t, pose), strict=True):
                rows[k].append(v)
            x = x_next
            if len(rows["x"]) >= n or abs(x[1]) > s.face_limit or x[0] < touching - s.gap_limit:
                break
        if not sens.exact:
            _log_trajectory(rows, meas, start, sim.pose.copy(), sens, noise, physics.control_period)
        traj += 1
    true = PusherTransitions.from_lists(rows)
    return (true if sens.exact else PusherTransitions.from_lists(meas)), true


def _log_trajectory(rows: dict[str, list], meas: dict[str, list], start: int, last_pose: np.ndarray,
                    sens: Sensor, noise: np.random.Generator, dt: float) -> None:
    """Append to ``meas`` the logged transitions of the trajectory whose true samples are
    ``rows[...][start:]`` (``last_pose``: the slider's pose at its end): readings of the world
    positions at every instant and one period before the start (at rest: the same positions),
    the states rebuilt from them (:func:`sample_measured`)."""
    X = np.vstack([rows["x"][start], *rows["x_next"][start:]])  # x_0 .. x_T
    pose = np.vstack([*rows["pose"][start:], last_pose])  # (X, Y, Theta) at 0 .. T
    c, s_ = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    pusher = pose[:, :2] + np.stack([c * X[:, 0] - s_ * X[:, 1], s_ * X[:, 0] + c * X[:, 1]], axis=1)
    q = np.hstack([pose, pusher])  # the positions read: X, Y, Theta, X_p, Y_p
    r = sens.read(np.vstack([q[:1], q]), noise)  # readings at -1, 0 .. T
    slider, theta, finger = r[:, :2], r[:, 2], r[:, 3:]
    c, s_ = np.cos(theta[1:]), np.sin(theta[1:])

    def body(v: np.ndarray) -> np.ndarray:  # world vectors (T + 1, 2) into the slider's frame at 0 .. T
        return np.stack([c * v[:, 0] + s_ * v[:, 1], -s_ * v[:, 0] + c * v[:, 1]], axis=1)

    vel = difference(r, dt)  # at 0 .. T
    logged = np.hstack([body(finger[1:] - slider[1:]), body(vel[:, :2]), vel[:, 2:3]])
    for i in range(len(X) - 1):  # the transitions t = 0 .. T - 1
        j = start + i
        for k, v in (("x", logged[i]), ("u", rows["u"][j]), ("x_next", logged[i + 1]),
                     ("force", rows["force"][j]), ("contact", rows["contact"][j]), ("traj", rows["traj"][j]),
                     ("step", rows["step"][j]), ("pose", r[i + 1, :3])):
            meas[k].append(v)
