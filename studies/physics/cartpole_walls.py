r"""A cart-pole whose pole tip hits two soft walls, simulated with MuJoCo, and the study that
learns an LCS of it.

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

The study (:func:`run_study`; config ``studies/configs/physics_cartpole.toml``) is described in
the README's "Learning your own system" section and in the report it writes. Run it with::

    python -m studies.physics.cartpole_walls --config studies/configs/physics_cartpole.toml \
        --out studies/results/physics [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import sys
import time
import tomllib
from dataclasses import dataclass
from typing import Any

import numpy as np

from lcs_cvx import Dataset

__all__ = [
    "Physics",
    "Sampling",
    "Transitions",
    "CartPoleWalls",
    "mjcf",
    "sample_transitions",
    "run_study",
    "main",
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


def _from_table(cls: type, table: dict[str, Any] | None, where: str) -> Any:
    """Build the dataclass ``cls`` from a config table, refusing unknown keys."""
    table = dict(table or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}; expected one of {sorted(names)}")
    for k, v in list(table.items()):
        if isinstance(v, list):
            table[k] = tuple(float(e) for e in v)
    return cls(**table)


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


@dataclass(frozen=True)
class Transitions:
    """Samples ``(x, u, x')`` with their trajectory structure and the true contact state.

    Attributes:
        x, x_next: ``(N, 4)``; u: ``(N, 1)``; force: ``(N, 2)`` mean wall forces (left, right),
        contact: ``(N, 2)`` bool; traj: ``(N,)`` trajectory index; step: ``(N,)`` index in it.
    """

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    force: np.ndarray
    contact: np.ndarray
    traj: np.ndarray
    step: np.ndarray

    def __len__(self) -> int:
        return self.x.shape[0]

    @property
    def in_contact(self) -> np.ndarray:
        """``(N,)`` bool: some wall pushed during the sample's control period."""
        return self.contact.any(axis=1)

    def select(self, mask: np.ndarray) -> Transitions:
        """The samples where ``mask`` is true (select whole trajectories to keep windows intact)."""
        return Transitions(*(getattr(self, f.name)[mask] for f in dataclasses.fields(self)))

    def dataset(self) -> Dataset:
        """The transitions as an :class:`lcs_cvx.Dataset` (``lam`` = the wall forces)."""
        return Dataset.from_arrays(self.x, self.u, self.x_next, lam=self.force)

    def windows(self, horizon: int) -> np.ndarray:
        """Start indices ``i`` of every ``horizon``-step window inside one trajectory."""
        n = len(self)
        if horizon < 1 or n < horizon:
            return np.zeros(0, dtype=np.int64)
        i = np.arange(n - horizon + 1)
        same = self.traj[i + horizon - 1] == self.traj[i]
        return i[same]


def sample_transitions(
    n: int,
    seed: int,
    physics: Physics = Physics(),
    sampling: Sampling = Sampling(),
    wide_factor: float = 1.0,
) -> Transitions:
    """``n`` transitions of random trajectories (see the module docstring), reproducible in
    ``seed``; ``wide_factor`` scales the range of the random input ``w``."""
    if n < 1:
        raise ValueError(f"n: expected an integer >= 1, received {n!r}")
    sim = CartPoleWalls(physics)
    rng = np.random.default_rng(seed)
    high = np.asarray(sampling.x0_high, dtype=np.float64)
    inner = physics.wall_distance - physics.tip_radius
    w_max = sampling.u_max * wide_factor
    cols: dict[str, list] = {k: [] for k in ("x", "u", "x_next", "force", "contact", "traj", "step")}
    traj = 0
    while len(cols["x"]) < n:
        while True:  # rejection: the tip starts strictly between the walls
            x0 = rng.uniform(-high, high)
            if abs(sim.tip_x(x0)) < inner:
                break
        sim.reset(x0)
        x = x0
        for t in range(sampling.traj_len):
            u = -sampling.kp * x[0] - sampling.kd * x[2] + rng.uniform(-w_max, w_max)
            x_next, force, contact = sim.step(u)
            for k, v in (("x", x), ("u", [u]), ("x_next", x_next), ("force", force),
                         ("contact", contact), ("traj", traj), ("step", t)):
                cols[k].append(v)
            x = x_next
            if len(cols["x"]) >= n or abs(x[0]) > sampling.x_limit or abs(x[1]) > sampling.theta_limit:
                break
        traj += 1
    out = {k: np.asarray(v) for k, v in cols.items()}
    for k in ("x", "u", "x_next", "force"):
        out[k] = out[k].astype(np.float64)
    return Transitions(**out)


# -- the study ---------------------------------------------------------------------------------
#: Keys of a study config (besides the runner's ``name``, ``kind``, ``module``, ``description``).
CONFIG_SECTIONS = ("physics", "sampling", "data", "lcs", "mlp", "eval")
_RUNNER_KEYS = ("name", "kind", "module", "description", "path", "extends")

_DATA_DEFAULTS = {"n_train": 20000, "n_test": 5000, "n_wide": 5000, "seed_train": 0, "seed_test": 1,
                  "seed_wide": 2, "wide_factor": 1.5, "val_every": 10}
_LCS_DEFAULTS = {"n_lam": [2, 4, 8], "losses": ["violation", "prediction"], "seeds": [0, 1, 2, 3],
                 "init": "affine", "stiffness": 1.0, "init_scale": 0.1,
                 "violation": {"recipe": "best", "iterations": 12000},
                 "prediction": {"recipe": "paper", "lr": 5e-3, "iterations": 12000}}
_MLP_DEFAULTS = {"hidden": [64, 64], "iterations": 20000, "batch_size": 256, "lr": 3e-3,
                 "weight_decay": 0.0, "seed": 0}
_EVAL_DEFAULTS = {"horizons": [1, 5, 20], "active_tol": 1e-9}


def _section(config: dict[str, Any], name: str, defaults: dict[str, Any]) -> dict[str, Any]:
    table = config.get(name, {})
    if not isinstance(table, dict):
        raise ValueError(f"config: [{name}] must be a table, received {table!r}")
    unknown = sorted(set(table) - set(defaults))
    if unknown:
        raise ValueError(f"config: {name}.{unknown[0]}: unknown key; expected one of {sorted(defaults)}")
    return {**defaults, **table}


def parse_config(config: dict[str, Any]) -> dict[str, Any]:
    """Check a study config (a dict as TOML reads it) and fill in the defaults."""
    unknown = sorted(set(config) - set(CONFIG_SECTIONS) - set(_RUNNER_KEYS))
    if unknown:
        raise ValueError(f"config: {unknown[0]}: unknown key; expected sections {list(CONFIG_SECTIONS)}")
    lcs = _section(config, "lcs", _LCS_DEFAULTS)
    for loss in lcs["losses"]:
        if loss not in ("violation", "prediction"):
            raise ValueError(f"config: lcs.losses: expected 'violation' or 'prediction', received {loss!r}")
        given = config.get("lcs", {}).get(loss, {})
        if not isinstance(given, dict):
            raise ValueError(f"config: [lcs.{loss}] must be a table, received {given!r}")
        lcs[loss] = {**_LCS_DEFAULTS[loss], **given}  # per key: a table may set only some options
    return {
        "name": config.get("name", "physics_cartpole"),
        "physics": _from_table(Physics, config.get("physics"), "config: [physics]"),
        "sampling": _from_table(Sampling, config.get("sampling"), "config: [sampling]"),
        "data": _section(config, "data", _DATA_DEFAULTS),
        "lcs": lcs,
        "mlp": _section(config, "mlp", _MLP_DEFAULTS),
        "eval": _section(config, "eval", _EVAL_DEFAULTS),
    }


def _log(msg: str) -> None:
    print(f"[cartpole_walls] {msg}", file=sys.stderr, flush=True)


def _run_jobs(jobs: list[tuple[str, dict[str, Any]]], workers: int) -> list[dict[str, Any]]:
    """Run ``(function name in studies.physics.models, job)`` pairs, ``workers`` processes."""
    from . import models

    if workers <= 1:
        return [getattr(models, fn)(job) for fn, job in jobs]
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(getattr(models, fn), job) for fn, job in jobs]
        return [f.result() for f in futures]


def run_study(config: dict[str, Any], out_dir: str, workers: int = 2) -> None:
    """Run the whole study (data, training, evaluation, report) into ``out_dir``.

    Writes ``report.md`` (tables and conclusions), ``metrics.json``, ``rollouts.png``,
    ``error_vs_horizon.png`` and ``models/lcs_<loss>_nlam<k>.npz`` (the selected LCSs in
    physical units, :func:`lcs_cvx.save_model` files). ``config`` is the TOML as a dict (the
    ``lcs-cvx study`` runner's ``kind = "module"`` protocol); ``workers`` training processes.
    """
    import torch

    import lcs_cvx

    from . import evaluation as ev
    from .models import (
        AffineModel,
        LCSModel,
        ModeAffineModel,
        Scaling,
        mlp_from_result,
    )

    torch.set_num_threads(1)
    t_start = time.perf_counter()
    code = _code_version()
    cfg = parse_config(config)
    phys, samp, dcfg, lcfg, mcfg, ecfg = (cfg[k] for k in ("physics", "sampling", "data", "lcs", "mlp", "eval"))
    horizons = [int(h) for h in ecfg["horizons"]]
    H = max(horizons)
    os.makedirs(os.path.join(out_dir, "models"), exist_ok=True)

    # data --------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    train_all = sample_transitions(dcfg["n_train"], dcfg["seed_train"], phys, samp)
    test = sample_transitions(dcfg["n_test"], dcfg["seed_test"], phys, samp)
    wide = sample_transitions(dcfg["n_wide"], dcfg["seed_wide"], phys, samp, dcfg["wide_factor"])
    is_val = train_all.traj % dcfg["val_every"] == dcfg["val_every"] - 1
    train, val = train_all.select(~is_val), train_all.select(is_val)
    t_data = time.perf_counter() - t0
    _log(f"data: {len(train)} train + {len(val)} validation, {len(test)} test, {len(wide)} wide "
         f"({t_data:.1f} s); contact fraction {train_all.in_contact.mean():.3f}")

    scaling = Scaling.fit(train.x, train.u, train.x_next)
    z, v, y = scaling.encode(train.x, train.u, train.x_next)
    zv, vv, yv = scaling.encode(val.x, val.u, val.x_next)

    # training jobs -------------------------------------------------------------------------------
    jobs: list[tuple[str, dict[str, Any]]] = []
    keys: list[tuple[str, int, int]] = []
    for n_lam in sorted(lcfg["n_lam"], reverse=True):  # the slow ones first
        for loss in lcfg["losses"]:
            opts = {k: (tuple(v_) if isinstance(v_, list) else v_) for k, v_ in lcfg[loss].items()}
            recipe = opts.pop("recipe")
            for seed in lcfg["seeds"]:
                jobs.append(("fit_lcs", {
                    "z": z, "v": v, "y": y, "z_val": zv, "v_val": vv, "y_val": yv,
                    "n_lam": int(n_lam), "loss": loss, "recipe": recipe, "options": opts,
                    "stiffness": lcfg["stiffness"], "init_scale": lcfg["init_scale"],
                    "init": lcfg["init"], "seed": int(seed)}))
                keys.append((loss, int(n_lam), int(seed)))
    mlp_job = {"z": z, "v": v, "y": y, "z_val": zv, "v_val": vv, "y_val": yv, **mcfg}
    jobs.insert(len(jobs) // 2, ("fit_mlp", mlp_job))
    t0 = time.perf_counter()
    _log(f"training {len(jobs)} jobs on {workers} worker(s)")
    results = _run_jobs(jobs, workers)
    t_train = time.perf_counter() - t0
    _log(f"training done in {t_train:.0f} s")
    mlp_result = results.pop(len(jobs) // 2)

    # selection: per (loss, n_lam) the restart with the lowest validation error -------------------
    restarts: dict[str, list[dict[str, Any]]] = {}
    chosen: dict[str, tuple[dict[str, Any], tuple[str, int, int]]] = {}
    for key, res in zip(keys, results, strict=True):
        loss, n_lam, seed = key
        name = f"LCS {loss} n_λ={n_lam}"
        restarts.setdefault(name, []).append({"seed": seed, "val_error": res["val_error"],
                                              "wall_time": res["wall_time"], "result": res})
        if res["matrices"] is None:
            _log(f"{name}, seed {seed} failed: {res['error']}")
            continue
        if name not in chosen or res["val_error"] < chosen[name][0]["val_error"]:
            chosen[name] = (res, key)

    models: dict[str, Any] = {}
    train_time: dict[str, float] = {}
    exported: dict[str, str] = {}
    for name, (res, (loss, n_lam, seed)) in chosen.items():
        phys_m = scaling.to_physical(res["matrices"])
        model = LCSModel.from_matrices(phys_m)
        models[name] = model
        train_time[name] = sum(r["wall_time"] for r in restarts[name])
        path = os.path.join(out_dir, "models", f"lcs_{loss}_nlam{n_lam}.npz")
        lcs_cvx.save_model(model.lcs, path, metadata={
            "study": cfg["name"], "system": "cart-pole with soft walls (MuJoCo)",
            "state": list(STATE_NAMES), "state_units": list(STATE_UNITS), "input": ["force (N)"],
            "control_period_s": phys.control_period, "loss": loss, "n_lam": n_lam, "seed": seed,
            "val_error_normalised": res["val_error"], "fit_settings": res["settings"],
        })
        exported[name] = os.path.relpath(path, out_dir)
    t0 = time.perf_counter()
    models["affine (least squares)"] = AffineModel.fit(train.x, train.u, train.x_next)
    train_time["affine (least squares)"] = time.perf_counter() - t0
    models["MLP"] = mlp_from_result(mlp_result, scaling, train.x.shape[1] + train.u.shape[1], train.x.shape[1])
    train_time["MLP"] = mlp_result["wall_time"]
    t0 = time.perf_counter()
    models["affine per true mode (oracle)"] = ModeAffineModel.fit(train.x, train.u, train.x_next, train.contact)
    train_time["affine per true mode (oracle)"] = time.perf_counter() - t0

    # evaluation ---------------------------------------------------------------------------------
    t0 = time.perf_counter()
    sets = {"test": test, "wide-input test (1.5×)": wide}
    metrics: dict[str, Any] = {}
    curves: dict[str, dict[str, np.ndarray]] = {}
    for set_name, data in sets.items():
        rows, curves[set_name] = [], {}
        for name, model in models.items():
            errs = ev.rollout_errors(model, data, H)
            curves[set_name][name] = errs
            agreement = None
            if isinstance(model, LCSModel):
                active = model.lam(data.x, data.u) > ecfg["active_tol"]
                agreement = ev.contact_agreement(active, data.contact)
            rows.append({
                "name": name,
                "one_step": ev.one_step_errors(model, data),
                "rollout": {str(h): float(errs[h - 1]) for h in horizons},
                "rollout_curve": [float(e) for e in errs],
                "agreement": agreement,
                "train_s": train_time[name],
            })
        metrics[set_name] = rows
    restart_rows = []
    for name, entries in restarts.items():
        for e in entries:
            ok = e["result"]["matrices"] is not None
            m = LCSModel.from_matrices(scaling.to_physical(e["result"]["matrices"])) if ok else None
            restart_rows.append({"model": name, "seed": e["seed"], "val_error": e["val_error"],
                                 "test_one_step": ev.one_step_errors(m, test) if ok else None,
                                 "selected": name in chosen and e["result"] is chosen[name][0],
                                 "error": e["result"].get("error"), "wall_time": e["wall_time"]})

    # figures --------------------------------------------------------------------------------------
    start = ev.pick_contact_window(test, H)
    best_of = {}
    for loss in lcfg["losses"]:
        names = [n for n in chosen if f" {loss} " in n]
        if names:
            best_of[loss] = min(names, key=lambda n: chosen[n][0]["val_error"])
    fig_models = {n: models[n] for n in best_of.values()}
    for n in ("affine (least squares)", "MLP", "affine per true mode (oracle)"):
        fig_models[n] = models[n]
    if start is not None:
        ev.plot_rollouts(fig_models, test, start, H, phys, os.path.join(out_dir, "rollouts.png"),
                         f"Open-loop rollout of {H} steps through a wall contact (test window {start})")
    ev.plot_error_vs_horizon(curves, os.path.join(out_dir, "error_vs_horizon.png"))
    t_eval = time.perf_counter() - t0

    wall = time.perf_counter() - t_start
    summary = {
        "config": {k: (dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v) for k, v in cfg.items()},
        "data": {name: {"n": len(d), "contact_fraction": float(d.in_contact.mean()),
                        "contact_fraction_per_wall": [float(f) for f in d.contact.mean(axis=0)],
                        "trajectories": int(len(np.unique(d.traj))), "windows_H": int(len(d.windows(H)))}
                 for name, d in {"train": train, "validation": val, **sets}.items()},
        "metrics": metrics,
        "restarts": restart_rows,
        "exported_models": exported,
        "fit_settings": {loss: next((chosen[n][0]["settings"] for n in chosen if f" {loss} " in n), None)
                         for loss in lcfg["losses"]},
        "rollout_window_start": start,
        "timing_s": {"data": t_data, "training": t_train, "evaluation": t_eval, "total": wall},
        "workers": workers,
        "code": code,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
                   f"torch {torch.__version__}, mujoco {_mujoco_version()}",
    }
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(summary, f, indent=1, default=_json_default)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write(_report(summary, cfg, horizons, best_of, config.get("name", cfg["name"])))
    _log(f"done in {wall:.0f} s; wrote {out_dir}/report.md")


def _code_version() -> dict[str, Any]:
    """The git commit the study ran on and the files of ``lcs_cvx/`` changed since (the fit
    recipes evolve: the results belong to this snapshot)."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", "-C", root, *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout if out.returncode == 0 else None

    commit = git("rev-parse", "--short", "HEAD")
    dirty = git("status", "--porcelain", "--", "lcs_cvx")  # lines "XY path"
    return {"commit": None if commit is None else commit.strip(),
            "lcs_cvx_changed": None if dirty is None else [ln[3:] for ln in dirty.splitlines() if ln]}


def _mujoco_version() -> str:
    import mujoco

    return mujoco.__version__


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def _ratio_text(a: float, b: float) -> str:
    """How ``a`` (ours) compares with ``b`` (a baseline): "3.2× lower" / "1.5× higher"."""
    if not (np.isfinite(a) and np.isfinite(b)) or a <= 0 or b <= 0:
        return "not comparable (a model diverged)"
    return f"{b / a:.1f}× lower" if a < b else f"{a / b:.1f}× higher"


_SHOWN_SETTINGS = ("optimizer", "iterations", "batch_size", "lr", "lr_schedule", "gamma", "eps",
                   "eps_start", "reg", "reinit_saturated", "extra_units", "refine",
                   "refine_iterations", "refine_batch")


def _report(s: dict[str, Any], cfg: dict[str, Any], horizons: list[int], best_of: dict[str, str],
            name: str) -> str:
    from .evaluation import markdown_table

    p, sm, d, lc = cfg["physics"], cfg["sampling"], cfg["data"], cfg["lcs"]
    t = s["timing_s"]
    H = max(horizons)
    out = [
        "# Learning an LCS of a MuJoCo cart-pole with two soft walls",
        "",
        f"Study `{name}`, written by `studies/physics/cartpole_walls.py` "
        f"(`python -m studies.physics.cartpole_walls --config studies/configs/{name}.toml --out <dir>`, "
        f"or `lcs-cvx study run studies/configs/{name}.toml --out <dir>`).",
        f"Code: commit `{s['code']['commit']}`"
        + (f" with uncommitted changes to {', '.join(s['code']['lcs_cvx_changed'])}"
           if s["code"]["lcs_cvx_changed"] else "") + ". "
        f"Machine: {s['machine']}; {s['workers']} training process(es), one torch thread each. "
        f"Wall time **{t['total']:.0f} s** (data {t['data']:.0f} s, training {t['training']:.0f} s, "
        f"evaluation and figures {t['evaluation']:.0f} s).",
        "",
        "## System and data",
        "",
        f"Cart {p.cart_mass} kg, uniform pole {p.pole_mass} kg × {p.pole_length} m, frictionless walls "
        f"at x = ±{p.wall_distance} m touched by the pole tip (sphere of radius {p.tip_radius} m), "
        f"MuJoCo contact `solref = (-{p.wall_stiffness:g}, -{p.wall_damping:g})` (stiffness "
        f"{p.wall_stiffness:g} s⁻², damping {p.wall_damping:g} s⁻¹, mass-normalised), `solimp` "
        f"impedance {p.wall_impedance}; timestep {p.timestep} s, control period "
        f"{p.control_period:.3g} s ({p.substeps} substeps, zero-order hold). State "
        "x = (x_c, θ, ẋ_c, θ̇), input u = force on the cart (N).",
        f"Inputs u = −{sm.kp:g} x_c − {sm.kd:g} ẋ_c + w, w ~ U[−{sm.u_max:g}, {sm.u_max:g}] N per period "
        f"(wide-input test: w range × {d['wide_factor']:g}); trajectories of ≤ {sm.traj_len} periods "
        f"from random states, reset when |x_c| > {sm.x_limit:g} m or |θ| > {sm.theta_limit:g} rad. "
        f"Seeds: train {d['seed_train']}, test {d['seed_test']}, wide {d['seed_wide']}; every "
        f"{d['val_every']}th training trajectory is held out for validation (model selection only).",
        "",
        "| set | samples | trajectories | in contact | left / right wall | "
        f"{H}-step windows |",
        "|---|---|---|---|---|---|",
    ]
    for set_name, info in s["data"].items():
        l, r = info["contact_fraction_per_wall"]
        out.append(f"| {set_name} | {info['n']} | {info['trajectories']} | "
                   f"{100 * info['contact_fraction']:.1f} % | {100 * l:.1f} % / {100 * r:.1f} % | "
                   f"{info['windows_H']} |")
    opts = {loss: ", ".join(f"{k}={v}" for k, v in lc[loss].items()) for loss in lc["losses"]}
    out += [
        "",
        "## Models",
        "",
        f"- **LCS** (`lcs_cvx.fit`), n_λ ∈ {lc['n_lam']}, learned in normalised coordinates "
        "(x, u and the increment x' − x scaled to zero mean and unit variance on the training set) "
        "and folded back into an exact LCS in physical units (`studies/physics/models.py`). "
        + "; ".join(f"{loss} loss: {opts[loss]}" for loss in lc["losses"])
        + f". Initialisation `{lc['init']}` (A, B, d from the affine least-squares fit, the rest "
        f"{lc['init_scale']}·N(0, 1); F stiffness {lc['stiffness']}); restarts with seeds "
        f"{lc['seeds']}, the one with the lowest validation error kept.",
        "  Resolved `lcs_cvx.fit` settings (the recipe as it stood when the study ran): "
        + "; ".join(f"{loss}: " + ", ".join(f"{k}={v}" for k, v in (s['fit_settings'].get(loss) or {}).items()
                                               if k in _SHOWN_SETTINGS and not (
                                                   k.startswith("refine_") and not s['fit_settings'][loss].get("refine")))
                    for loss in lc["losses"]) + ".",
        "- **affine (least squares)**: x' = A x + B u + d on the same training samples.",
        f"- **MLP**: x' = x + f(x, u), tanh MLP with hidden layers {cfg['mlp']['hidden']}, Adam "
        f"(lr {cfg['mlp']['lr']:g}, cosine) for {cfg['mlp']['iterations']} iterations of batch "
        f"{cfg['mlp']['batch_size']}, best validation iterate.",
        "- **affine per true mode (oracle)**: one least-squares affine model per true contact mode "
        "(free / left / right), given the true mode of every sample and every rollout step.",
        "",
        "One-step error: Σ‖x̂' − x'‖² / Σ‖x'‖² (the paper's e_test) over the free samples, the samples "
        "in which a wall pushes during the control period, and all samples. Rollout error at H: "
        f"open-loop from the true state over the recorded inputs, Σ‖x̂_H − x_H‖² / Σ‖x_H‖² over all "
        f"{H}-step windows. λ/contact agreement: fraction of (sample, wall) pairs where \"some λ_i "
        "assigned to the wall is > 0\" matches the true contact, under the best assignment of λ's "
        "coordinates to {left, right, neither}; the trivial \"never in contact\" level is given "
        "below each table. \"Either sign\": each wall identified with one coordinate (distinct), "
        "counted as in contact when that coordinate is active or, if that agrees better, inactive "
        "-- an LCS may describe a wall by a unit that is active off contact.",
    ]
    for set_name, rows in s["metrics"].items():
        trivial = next((r["agreement"]["trivial"] for r in rows if r["agreement"]), None)
        out += ["", f"## Results: {set_name}", "", markdown_table(rows, horizons), ""]
        if trivial is not None:
            out.append(f"Trivial agreement (never in contact): {trivial:.3f}. \"train (s)\": the "
                       "summed wall time of all restarts of that model.")
    # conclusions, computed
    rows = {r["name"]: r for r in s["metrics"]["test"]}
    lcs_names = [n for n in rows if n.startswith("LCS")]
    base = {b: rows[b] for b in ("affine (least squares)", "MLP") if b in rows}
    out += ["", "## Conclusions (computed from the test set)", ""]
    if lcs_names and base:
        best = min(lcs_names, key=lambda n: rows[n]["one_step"]["contact"])
        for b, br in base.items():
            beaten = [n for n in lcs_names if rows[n]["one_step"]["contact"] < br["one_step"]["contact"]]
            out.append(
                f"- In contact, {len(beaten)} of {len(lcs_names)} LCS models beat the {b} baseline "
                f"(one-step contact error {br['one_step']['contact']:.3g}); the best, {best}, is "
                f"{_ratio_text(rows[best]['one_step']['contact'], br['one_step']['contact'])} "
                f"({rows[best]['one_step']['contact']:.3g})."
            )
        best_roll = min(lcs_names, key=lambda n: rows[n]["rollout"][str(H)])
        for b, br in base.items():
            out.append(
                f"- {H}-step rollouts: the best LCS, {best_roll} ({rows[best_roll]['rollout'][str(H)]:.3g}), "
                f"is {_ratio_text(rows[best_roll]['rollout'][str(H)], br['rollout'][str(H)])} than "
                f"the {b} ({br['rollout'][str(H)]:.3g})."
            )
        orc = rows.get("affine per true mode (oracle)")
        if orc:
            out.append(
                f"- Against the mode oracle (contact {orc['one_step']['contact']:.3g}, free "
                f"{orc['one_step']['free']:.3g}, {H}-step {orc['rollout'][str(H)]:.3g}) the best "
                f"LCS's contact error is {_ratio_text(rows[best]['one_step']['contact'], orc['one_step']['contact'])}."
            )
        wide = {r["name"]: r for r in s["metrics"].get("wide-input test (1.5×)", [])}
        if wide:
            wb = min(lcs_names, key=lambda n: wide[n]["one_step"]["contact"])
            parts = [f"{b}: {wide[b]['one_step']['contact']:.3g}" for b in base]
            out.append(f"- Wide inputs: best LCS contact error {wide[wb]['one_step']['contact']:.3g} "
                       f"({wb}) against " + ", ".join(parts) + ".")
    out += ["", "## Restarts (model selection on the validation trajectories)", "",
            "| model | seed | validation error (normalised) | test 1-step all | selected | time (s) |",
            "|---|---|---|---|---|---|"]
    for r in s["restarts"]:
        test_all = "failed: " + r["error"] if r["test_one_step"] is None else f"{r['test_one_step']['all']:.4f}"
        out.append(f"| {r['model']} | {r['seed']} | {r['val_error']:.4f} | {test_all} | "
                   f"{'yes' if r['selected'] else ''} | {r['wall_time']:.0f} |")
    out += ["", "## Figures", ""]
    if s["rollout_window_start"] is not None:
        shown = ", ".join(best_of.values())
        out += [f"Open-loop rollouts through a wall contact (LCS shown: the lowest validation error "
                f"per loss, {shown}):", "", "![rollouts](rollouts.png)", ""]
    out += ["Rollout error against the horizon:", "", "![error vs horizon](error_vs_horizon.png)", "",
            "## Exported models", "",
            "The selected LCSs in physical units (`lcs_cvx.load_model(path)`; `model.to_matrices()` "
            "or `model.to_c3()` for the matrices):", ""]
    out += [f"- {n}: `{path}`" for n, path in s["exported_models"].items()]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Cart-pole with soft walls (MuJoCo): learn LCSs and baselines.")
    ap.add_argument("--config", required=True, help="TOML config (studies/configs/physics_cartpole.toml)")
    ap.add_argument("--out", required=True, help="output directory (e.g. studies/results/physics)")
    ap.add_argument("--workers", type=int, default=2, help="training processes (default 2)")
    args = ap.parse_args(argv)
    with open(args.config, "rb") as f:
        config = tomllib.load(f)
    config.setdefault("name", os.path.splitext(os.path.basename(args.config))[0])
    run_study(config, args.out, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
