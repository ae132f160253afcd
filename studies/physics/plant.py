r"""The plant of the physics study: a cart-pole whose pole tip hits two soft walls, simulated
with MuJoCo, and the transitions it generates.

The plant (an MJCF model built by :func:`mjcf`; every number is a field of :class:`Physics`):

- cart: 1.0 kg on a frictionless horizontal slider (joint damping 0.1 N s/m), driven by the
  input ``u``, a horizontal force in N (a motor, gear 1, no force limit);
- pole: a uniform rod of 0.3 kg and 0.6 m hinged at the cart (hinge damping 0.01 N m s/rad);
  angle 0 is upright, positive towards +x, so the tip is at ``x_c + 0.6 sin(theta)``;
- walls: two fixed boxes, 1 m thick, whose inner faces are at ``x = -0.2`` and ``x = +0.2`` m (a
  thin wall would let a fast tip tunnel through the soft contact). Only the pole's
  tip (a massless sphere of radius 0.02 m) collides with them: contact is made when
  ``|x_c + 0.6 sin(theta)| > 0.18`` (at ``|theta| ~ 0.30`` rad with the cart centred);
- wall contacts: frictionless (``condim = 1``: normal force only), stiffness and damping set
  through MuJoCo's contact parameters ``solref = (-200, -5)`` (the "direct" format: stiffness
  200 s^-2 and damping 5 s^-1, mass-normalised) and ``solimp = (0.99, 0.99, 0.001, 0.5, 2)``
  (a constant impedance ``d = 0.99``). MuJoCo then gives the contact the constrained acceleration
  ``a1 = -d (b v + k r) + (1 - d) a0`` along the normal (``r`` the penetration, ``v`` its rate,
  ``a0`` the unconstrained acceleration, ``b = 5 / d``, ``k = 200 / d^2``), i.e. the penetration
  behaves as a damped spring with ``omega = sqrt(200) ~ 14 rad/s`` and damping ratio ~0.18, and
  the solver keeps the normal force ``>= 0`` (a wall pushes, never pulls; the force is the
  projection of the unconstrained solution on ``f >= 0`` -- itself a complementarity condition).
  This is MuJoCo's own soft-contact model, not an LCS: the penetration is geometric
  (``sin(theta)``) and the force couples through the configuration-dependent inertia.
  Penetrations reach up to ~8 cm, and a contact lasts several control periods: a *soft* wall.

Discrete time: MuJoCo's timestep is 2 ms (semi-implicit Euler, float64); a control period is
``substeps = 20`` of them (0.04 s) with the input held (zero-order hold). The state is
``x = (x_c, theta, x_c', theta')`` (m, rad, m/s, rad/s), one input ``u`` (N), and a sample is
``(x_t, u_t, x_{t+1})`` one control period apart. For evaluation only, each sample also records
the mean normal force of each wall over the period (``lam``, N; left, right) and whether that
wall pushed during any substep of it (``contact``).

Data (:func:`sample_transitions`): trajectories from random initial states
``x_c ~ U[-0.15, 0.15]``, ``theta ~ U[-0.2, 0.2]``, ``x_c' ~ U[-0.5, 0.5]``, ``theta' ~ U[-1, 1]``
(the tip strictly inside the walls), under the exploration input
``u = -20 x_c - 5 x_c' + w`` with ``w ~ U[-5, 5]`` N drawn afresh every control period -- random
inputs around a weak cart-centring PD term, which keeps the cart between the walls long enough
for 20-step windows (a free cart drifts away and the pole slides down the wall). Nothing
stabilises the pole: it falls onto a wall, bounces and leans. A trajectory ends after 25 periods
or when ``|x_c| > 0.5`` m or ``|theta| > 0.8`` rad (that last transition is kept), and a new one
starts from a fresh random state. With these settings ~43 % of the samples have a wall contact.
The second test set draws ``w`` from a range ``wide_factor = 1.5`` times wider.

Measured data (``sensor``, :mod:`studies.physics.sensor`): by default the samples hold the
simulator's states. ``sensor = "encoder"`` logs them as encoders would: the cart position read
to 0.1 mm (10 counts per mm), the pole angle to 2π/4096 rad (12 bits), both by rounding to the
nearest count, and the velocities as backward differences of those readings over the control
period (a count is worth 2.5 mm/s and 0.038 rad/s); ``"differenced"`` differences exact
positions. The first transition of each trajectory then only starts the differences and is
dropped (:func:`sample_measured`); the inputs are those of the exact data.

The study that learns an LCS of it is :mod:`studies.physics.study`.
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
    "Transitions",
    "CartPoleWalls",
    "mjcf",
    "sample_transitions",
    "sample_measured",
    "STATE_NAMES",
    "STATE_UNITS",
    "WALLS",
]

STATE_NAMES = ("x_c", "theta", "x_c_dot", "theta_dot")
STATE_UNITS = ("m", "rad", "m/s", "rad/s")
WALLS = ("left", "right")


@dataclass(frozen=True)
class Physics:
    """Physical and numerical parameters of the plant (SI units; see the module docstring)."""

    cart_mass: float = 1.0
    pole_mass: float = 0.3
    pole_length: float = 0.6
    tip_radius: float = 0.02
    wall_distance: float = 0.2  # inner faces of the walls at x = -/+ wall_distance
    wall_stiffness: float = 200.0  # solref[0] = -stiffness (s^-2, mass-normalised)
    wall_damping: float = 5.0  # solref[1] = -damping (s^-1)
    wall_impedance: float = 0.99  # solimp = (d, d, 0.001, 0.5, 2): constant impedance d
    cart_damping: float = 0.1
    hinge_damping: float = 0.01
    timestep: float = 0.002
    substeps: int = 20  # control period = substeps * timestep

    @property
    def control_period(self) -> float:
        return self.substeps * self.timestep


@dataclass(frozen=True)
class Sampling:
    """How transitions are drawn (see :func:`sample_transitions`)."""

    u_max: float = 5.0  # the random part w ~ U[-u_max, u_max] (N)
    kp: float = 20.0  # exploration input u = -kp x_c - kd x_c' + w
    kd: float = 5.0
    traj_len: int = 25  # control periods per trajectory at most
    x0_high: tuple[float, float, float, float] = (0.15, 0.2, 0.5, 1.0)  # x0 ~ U[-high, high]
    x_limit: float = 0.5  # a trajectory ends when |x_c| exceeds this
    theta_limit: float = 0.8  # ... or |theta| exceeds this


def mjcf(p: Physics = Physics()) -> str:
    """The MJCF model of the cart-pole with two soft walls (a string)."""
    wall = (
        f'type="box" size="0.5 0.3 0.6" contype="0" conaffinity="1" condim="1" '
        f'solref="{-p.wall_stiffness:.17g} {-p.wall_damping:.17g}" '
        f'solimp="{p.wall_impedance:.17g} {p.wall_impedance:.17g} 0.001 0.5 2" rgba=".6 .6 .7 1"'
    )
    off = p.wall_distance + 0.5  # 1 m thick: a deep penetration can never reach the far side
    return f"""<mujoco model="cartpole_walls">
  <option timestep="{p.timestep:.17g}" gravity="0 0 -9.81" integrator="Euler"/>
  <worldbody>
    <light pos="0 -2 3"/>
    <geom name="wall_left" pos="{-off:.17g} 0 0.6" {wall}/>
    <geom name="wall_right" pos="{off:.17g} 0 0.6" {wall}/>
    <body name="cart">
      <joint name="slider" type="slide" axis="1 0 0" damping="{p.cart_damping:.17g}"/>
      <geom name="cart" type="box" size="0.1 0.05 0.05" mass="{p.cart_mass:.17g}"
            contype="0" conaffinity="0"/>
      <body name="pole">
        <joint name="hinge" type="hinge" axis="0 1 0" damping="{p.hinge_damping:.17g}"/>
        <geom name="pole" type="capsule" fromto="0 0 0 0 0 {p.pole_length:.17g}" size="0.01"
              mass="{p.pole_mass:.17g}" contype="0" conaffinity="0"/>
        <geom name="tip" type="sphere" pos="0 0 {p.pole_length:.17g}" size="{p.tip_radius:.17g}"
              mass="0" contype="1" conaffinity="0" condim="1"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="slider" gear="1"/>
  </actuator>
</mujoco>
"""


class CartPoleWalls:
    """The MuJoCo simulation at the control rate: :meth:`reset` to a state, :meth:`step` one
    control period (``substeps`` MuJoCo steps with the input held).

    Example:
        >>> sim = CartPoleWalls()
        >>> sim.reset([0.0, 0.25, 0.0, 0.0])
        >>> x_next, force, contact = sim.step(0.0)
        >>> x_next.shape, force.shape, contact.shape
        ((4,), (2,), (2,))
    """

    def __init__(self, physics: Physics = Physics()) -> None:
        import mujoco  # imported here so that the rest of the study imports without it

        self._mj = mujoco
        self.physics = physics
        self.model = mujoco.MjModel.from_xml_string(mjcf(physics))
        self.data = mujoco.MjData(self.model)
        if self.model.opt.timestep != physics.timestep:
            raise RuntimeError("MuJoCo did not take the timestep")
        gid = lambda name: mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)  # noqa: E731
        self._walls = np.array([gid("wall_left"), gid("wall_right")])

    @property
    def state(self) -> np.ndarray:
        """``x = (x_c, theta, x_c', theta')`` float64 ``(4,)``."""
        return np.concatenate([self.data.qpos, self.data.qvel]).astype(np.float64)

    def reset(self, x: Any) -> None:
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (4,) or not np.isfinite(x).all():
            raise ValueError(f"x: expected 4 finite numbers (x_c, theta, x_c', theta'), received {x!r}")
        self._mj.mj_resetData(self.model, self.data)
        self.data.qpos[:] = x[:2]
        self.data.qvel[:] = x[2:]
        self._mj.mj_forward(self.model, self.data)

    def tip_x(self, x: Any | None = None) -> float:
        """Horizontal position of the pole tip (m)."""
        x = self.state if x is None else np.asarray(x, dtype=np.float64)
        return float(x[0] + self.physics.pole_length * math.sin(x[1]))

    def step(self, u: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One control period under the held input ``u`` (N).

        Returns ``(x_next (4,), force (2,), contact (2,) bool)``: the state after the period,
        each wall's (left, right) mean normal force over it (N) and whether it pushed at all.
        """
        m, d, mj = self.model, self.data, self._mj
        d.ctrl[0] = float(u)
        impulse = np.zeros(2)
        contact = np.zeros(2, dtype=bool)
        for _ in range(self.physics.substeps):
            mj.mj_step(m, d)
            n = d.ncon
            if n:  # the contacts and forces of the step just taken
                geoms = d.contact.geom[:n]
                force = d.efc_force[d.contact.efc_address[:n]]
                for k in range(2):
                    on = (geoms == self._walls[k]).any(axis=1)
                    f = float(force[on].sum())
                    impulse[k] += f
                    contact[k] |= f > 0.0
        return self.state, impulse / self.physics.substeps, contact


def sample_transitions(
    n: int,
    seed: int,
    physics: Physics = Physics(),
    sampling: Sampling = Sampling(),
    wide_factor: float = 1.0,
    sensor: str | Sensor = "exact",
) -> Transitions:
    """``n`` transitions of random trajectories (see the module docstring), reproducible in
    ``seed``; ``wide_factor`` scales the range of the random input ``w``; ``sensor`` (a name of
    :data:`studies.physics.sensor.SENSORS` ``["cartpole"]``) how the states are logged (see
    :func:`sample_measured`)."""
    return sample_measured(n, seed, physics, sampling, wide_factor, sensor)[0]


def sample_measured(
    n: int,
    seed: int,
    physics: Physics = Physics(),
    sampling: Sampling = Sampling(),
    wide_factor: float = 1.0,
    sensor: str | Sensor = "exact",
) -> tuple[Transitions, Transitions]:
    """``(measured, true)``: ``n`` transitions as ``sensor`` logs them, and the same samples
    with the simulator's states (the same ``u``, ``force``, ``contact``, ``traj``, ``step``).

    ``"exact"``: both are the simulator's states, bit for bit the data of the plain generator.
    A differencing sensor (:mod:`studies.physics.sensor`) reads ``(x_c, theta)`` at every
    control instant and logs ``x_t = (x_c~_t, theta~_t, (x_c~_t - x_c~_{t-1}) / dt,
    (theta~_t - theta~_{t-1}) / dt)``. A trajectory starts moving, so its first period only
    starts the differences: its first transition is dropped (the trajectory keeps its index, its
    samples their steps ``1 ..``), and trajectories are drawn until ``n`` measured transitions.
    The trajectories are those of the exact data of the same seed; the jitter (if any) comes from
    :func:`studies.physics.sensor.noise_rng`.
    """
    if n < 1:
        raise ValueError(f"n: expected an integer >= 1, received {n!r}")
    sens = get_sensor("cartpole", sensor)
    drop = 0 if sens.exact else 1  # the first transition of a trajectory only starts the differences
    noise = noise_rng(seed)
    dt = physics.control_period
    sim = CartPoleWalls(physics)
    rng = np.random.default_rng(seed)
    high = np.asarray(sampling.x0_high, dtype=np.float64)
    inner = physics.wall_distance - physics.tip_radius
    w_max = sampling.u_max * wide_factor
    keys = ("x", "u", "x_next", "force", "contact", "traj", "step")
    cols: dict[str, list] = {k: [] for k in keys}
    meas: dict[str, list] = {k: [] for k in keys}
    traj = 0
    while len(meas["x"] if drop else cols["x"]) < n:
        while True:  # rejection: the tip starts strictly between the walls
            x0 = rng.uniform(-high, high)
            if abs(sim.tip_x(x0)) < inner:
                break
        sim.reset(x0)
        x = x0
        start = len(cols["x"])
        for t in range(sampling.traj_len):
            u = -sampling.kp * x[0] - sampling.kd * x[2] + rng.uniform(-w_max, w_max)
            x_next, force, contact = sim.step(u)
            for k, v in (("x", x), ("u", [u]), ("x_next", x_next), ("force", force),
                         ("contact", contact), ("traj", traj), ("step", t)):
                cols[k].append(v)
            x = x_next
            logged = len(meas["x"]) + t if drop else len(cols["x"])  # t: the first one is dropped
            if logged >= n or abs(x[0]) > sampling.x_limit or abs(x[1]) > sampling.theta_limit:
                break
        if drop:
            _log_trajectory(cols, meas, start, sens, noise, dt)
        traj += 1
    true = Transitions.from_lists(cols)
    if not drop:
        return true, true
    keep = np.ones(len(true), dtype=bool)
    keep[np.flatnonzero(true.step == 0)] = False
    return Transitions.from_lists(meas), true.select(keep)


def _log_trajectory(cols: dict[str, list], meas: dict[str, list], start: int, sens: Sensor,
                    noise: np.random.Generator, dt: float) -> None:
    """Append to ``meas`` the logged transitions of the trajectory whose true samples are
    ``cols[...][start:]``: readings of ``(x_c, theta)`` at every instant, velocities by backward
    differences, the first transition dropped."""
    X = np.vstack([cols["x"][start], *cols["x_next"][start:]])  # x_0 .. x_T
    q = sens.read(X[:, :2], noise)
    logged = np.hstack([q[1:], difference(q, dt)])  # x~_1 .. x~_T
    for i in range(1, len(X) - 1):  # the transitions t = 1 .. T - 1
        j = start + i
        for k, v in (("x", logged[i - 1]), ("u", cols["u"][j]), ("x_next", logged[i]),
                     ("force", cols["force"][j]), ("contact", cols["contact"][j]),
                     ("traj", cols["traj"][j]), ("step", cols["step"][j])):
            meas[k].append(v)
