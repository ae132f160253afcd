r"""Measured data for the physics studies: positions read by a sensor, velocities by finite
differences of the readings, as a user's logging produces them.

The simulators give exact states. A real log does not: positions come from encoders or a
motion-capture system, and the velocities are differences of those positions. A
:class:`Sensor` turns the true positions of a trajectory into readings, and :func:`measure`
builds the logged states from the readings:

- each position coordinate ``q_i`` is read as ``round(q_i / r_i) r_i`` (quantisation to the
  resolution ``r_i``; an encoder) or as ``q_i + e_i``, ``e_i ~ N(0, sigma_i^2)`` drawn afresh at
  every reading (jitter; motion capture), or exactly (``r_i = sigma_i = 0``);
- the velocity logged at time ``t`` is the backward difference of two consecutive readings
  over the control period ``dt``: ``(q~_t - q~_{t-1}) / dt`` -- the mean velocity over the last
  period, not the instantaneous one;
- a state is logged once and used twice: the ``x_{t+1}`` of one transition is the ``x_t`` of
  the next, with the same noise.

The sensors (:data:`SENSORS`; ``[data] sensor = "<name>"`` in a study config):

- ``"exact"`` (the default): the simulator's states, instantaneous velocities, no noise -- the
  data as the studies have always had them, bit for bit;
- ``"differenced"``: exact positions, velocities by backward differences: the finite difference
  without noise (what a noisy sensor's log would be with a perfect sensor);
- ``"encoder"`` (the cart-pole, :mod:`studies.physics.plant`): the cart position quantised to
  0.1 mm (a linear encoder of 10 counts per mm) and the pole angle to 2π/4096 rad (a 12-bit
  rotary encoder, ~0.088°); the quantisation is deterministic. Over the control period of 0.04 s
  a count is worth 2.5 mm/s of cart velocity and 0.038 rad/s of pole rate;
- ``"mocap"`` (the pusher-slider, :mod:`studies.physics.pusher_plant`): motion capture of the
  slider's pose and the pusher's position in the world, Gaussian jitter of standard deviation
  0.5 mm on every horizontal position coordinate and 0.005 rad (~0.29°) on the slider's heading,
  independent between readings. Over the control period of 0.05 s the differenced velocities
  carry noise of standard deviation ``sqrt(2) 0.05 cm / 0.05 s ~ 1.4 cm/s`` and
  ``sqrt(2) 0.005 / 0.05 ~ 0.14 rad/s``.

How each plant's positions are read and its state rebuilt is in its module
(:func:`studies.physics.plant.sample_transitions`,
:func:`studies.physics.pusher_plant.sample_transitions`, argument ``sensor``). The jitter is drawn
from its own random stream (:func:`noise_rng`), so the simulated trajectories -- initial states
and inputs -- are those of the exact data with the same seed; the exploration inputs are computed
from the simulator's state, as before (only the log is measured).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Sensor", "SENSORS", "sensor", "noise_rng", "difference"]


@dataclass(frozen=True)
class Sensor:
    """How positions are read (see the module docstring).

    Attributes:
        name: the sensor's name (:data:`SENSORS`).
        differenced: whether velocities are backward differences of the readings (False: the
            simulator's state, only for ``"exact"``).
        resolution: per position coordinate, the quantisation step (0: none), in the plant's
            position units.
        noise: per position coordinate, the standard deviation of the Gaussian jitter (0: none).
        description: one line for the reports.
    """

    name: str
    differenced: bool
    resolution: tuple[float, ...] = ()
    noise: tuple[float, ...] = ()
    description: str = ""

    @property
    def exact(self) -> bool:
        """The simulator's states themselves (no sensor)."""
        return not self.differenced

    def read(self, q: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Readings of the true positions ``q`` ``(T, k)`` (one row per reading): quantised to
        :attr:`resolution` and jittered by :attr:`noise` (``rng`` draws the jitter; it may be
        None for a sensor without jitter)."""
        q = np.asarray(q, dtype=np.float64)
        out = q.copy()
        k = q.shape[1]
        res = np.asarray(self.resolution or (0.0,) * k, dtype=np.float64)
        sig = np.asarray(self.noise or (0.0,) * k, dtype=np.float64)
        if res.shape != (k,) or sig.shape != (k,):
            raise ValueError(f"sensor {self.name!r}: expected {k} resolutions and noise levels (one per "
                             f"position coordinate), received {res.shape[0]} and {sig.shape[0]}")
        quantised = res > 0
        if quantised.any():
            out[:, quantised] = np.round(q[:, quantised] / res[quantised]) * res[quantised]
        if (sig > 0).any():
            if rng is None:
                raise ValueError(f"sensor {self.name!r}: its jitter needs a random generator")
            out = out + rng.standard_normal(q.shape) * sig
        return out


_TWO_PI = 2.0 * np.pi
#: The sensors by name; the position coordinates are the plant's: the cart-pole's ``(x_c [m],
#: theta [rad])``, the pusher-slider's ``(X, Y [cm], Theta [rad], pusher X, Y [cm])`` in the world.
SENSORS: dict[str, dict[str, Sensor]] = {
    "cartpole": {
        "exact": Sensor("exact", False, description="the simulator's states (no sensor)"),
        "differenced": Sensor("differenced", True, (0.0, 0.0), (0.0, 0.0),
                              "exact positions, velocities by backward differences"),
        "encoder": Sensor("encoder", True, (1e-4, _TWO_PI / 4096), (0.0, 0.0),
                          "encoders: cart position quantised to 0.1 mm, pole angle to 2π/4096 rad; "
                          "velocities by backward differences"),
    },
    "pusher": {
        "exact": Sensor("exact", False, description="the simulator's states (no sensor)"),
        "differenced": Sensor("differenced", True, (0.0,) * 5, (0.0,) * 5,
                              "exact positions, velocities by backward differences"),
        "mocap": Sensor("mocap", True, (0.0,) * 5, (0.05, 0.05, 0.005, 0.05, 0.05),
                        "motion capture: Gaussian jitter of 0.5 mm on positions and 0.005 rad on the "
                        "slider's heading; velocities by backward differences"),
    },
}


def sensor(plant: str, name: str | Sensor) -> Sensor:
    """The sensor ``name`` of ``plant`` (``"cartpole"`` or ``"pusher"``), or ``name`` itself if
    it is a :class:`Sensor`; an unknown name is a ``ValueError`` listing the known ones."""
    if isinstance(name, Sensor):
        return name
    known = SENSORS[plant]
    if name not in known:
        raise ValueError(f"sensor: expected one of {sorted(known)} for the {plant} study, received {name!r}")
    return known[name]


def noise_rng(seed: int) -> np.random.Generator:
    """The random stream of a data set's sensor jitter: its own stream, so that the simulation's
    draws (``default_rng(seed)``) are those of the exact data."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), 0x5E2502]))


def difference(readings: np.ndarray, dt: float) -> np.ndarray:
    """Backward differences ``(q~_t - q~_{t-1}) / dt`` of readings ``(T + 1, k)``: ``(T, k)``,
    the velocity logged at ``t = 1 .. T``."""
    return (readings[1:] - readings[:-1]) / dt
