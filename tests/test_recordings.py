"""Robot logs in (lcs_cvx.recordings, lcs_cvx.streams): files written here with the real writers
(mcap's and mcap-ros2-support's, h5py, pyarrow) read back through Trajectories.from_mcap,
from_hdf5 and from_lerobot, onto one clock."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import lcs_cvx
from lcs_cvx import LCSInputError
from lcs_cvx.ros2 import JOINT_STATE

h5py = pytest.importorskip("h5py")
pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
mcap_writer = pytest.importorskip("mcap.writer")
ros2_writer = pytest.importorskip("mcap_ros2.writer")

FLOAT64 = "float64 data\n"
OMEGA = 2 * math.pi * 0.5  # the sine's angular frequency (rad/s)


def joint(t):
    return np.sin(OMEGA * t), OMEGA * np.cos(OMEGA * t)


def effort(k):
    return float((-1.0) ** k * (1 + 0.1 * k))


def write_ros2_bag(path, t_joint, t_effort, frame=lambda k: ""):
    """``/joint_states`` (sensor_msgs/msg/JointState: a sine and its rate) at the times
    ``t_joint`` and ``/effort`` (std_msgs/msg/Float64) at ``t_effort`` (s; 1 ns resolution);
    ``frame(k)`` the frame id of joint message ``k``."""
    with open(path, "wb") as f:
        w = ros2_writer.Writer(f)
        js = w.register_msgdef("sensor_msgs/msg/JointState", JOINT_STATE)
        fl = w.register_msgdef("std_msgs/msg/Float64", FLOAT64)
        for k, t in enumerate(t_joint):
            ns = round(t * 1e9)
            p, v = joint(t)
            w.write_message("/joint_states", js, {
                "header": {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": frame(k)},
                "name": ["slider", "hinge"], "position": [p, 2 * p], "velocity": [v, 2 * v], "effort": []},
                log_time=ns, publish_time=ns)
        for k, t in enumerate(t_effort):
            ns = round(t * 1e9)
            w.write_message("/effort", fl, {"data": effort(k)}, log_time=ns, publish_time=ns)
        w.finish()


def write_json_bag(path, t_state, t_input):
    with open(path, "wb") as f:
        w = mcap_writer.Writer(f)
        w.start()
        schema = w.register_schema(name="State", encoding="jsonschema", data=b'{"type": "object"}')
        s = w.register_channel(topic="/state", message_encoding="json", schema_id=schema)
        c = w.register_channel(topic="/command", message_encoding="json", schema_id=schema)
        for t in t_state:
            p, v = joint(t)
            w.add_message(s, log_time=round(t * 1e9), data=json.dumps({"q": [p], "qd": [v]}).encode(),
                          publish_time=round(t * 1e9))
        for k, t in enumerate(t_input):
            w.add_message(c, log_time=round(t * 1e9), data=json.dumps({"u": effort(k)}).encode(),
                          publish_time=round(t * 1e9))
        w.finish()


STATE = {"/joint_states": ["position[0]", "velocity[0]"]}
INPUT = {"/effort": ["data"]}


def test_a_ros2_bag_reads_back_to_the_arrays_written(tmp_path):
    """JointState at 200 Hz and a command at 50 Hz on a 200 Hz clock: the states are the
    messages' own numbers (the grid is their time stamps), the inputs each command held until
    the next."""
    path = tmp_path / "run.mcap"
    t_joint, t_effort = np.arange(400) * 0.005, np.arange(100) * 0.02
    write_ros2_bag(path, t_joint, t_effort)
    runs = lcs_cvx.Trajectories.from_mcap(path, STATE, INPUT, dt=0.005)
    assert len(runs) == 1 and runs.n_x == 2 and runs.n_u == 1
    x, u = runs.xs[0].numpy(), runs.us[0].numpy()
    assert x.shape == (398, 2)  # the span both topics cover: 0 .. 1.985 s (the last command held one step)
    want = np.column_stack(joint(t_joint[:398]))
    assert np.abs(x - want).max() <= 1e-12
    assert np.abs(u[:, 0] - [effort(k // 4) for k in range(397)]).max() <= 1e-12
    assert runs.names == ("/joint_states.position[0]", "/joint_states.velocity[0]")
    assert runs.input_names == ("/effort.data",)
    text = runs.describe(velocities={0: 1})
    assert "/joint_states: 400 samples, median period 0.005 s (200 Hz)" in text
    assert "/effort: 100 samples, median period 0.02 s (50 Hz) -- resampled" in text
    assert "1 runs, 397 transitions on one clock of dt = 0.005 s" in text
    # forward differences of a sine against the next rate: close to the clock, not equal
    period = float(text.split("effective period of /joint_states.position[0] by /joint_states.velocity[0]: ")[1].split()[0])
    assert abs(period - 0.005) < 1e-4


def test_messages_of_other_layouts_are_read_one_by_one(tmp_path):
    """Frame ids of changing length move the arrays behind them: every message is read at its
    own offsets (the bulk read takes those of the first message's layout only)."""
    path = tmp_path / "frames.mcap"
    t_joint = np.arange(100) * 0.005
    write_ros2_bag(path, t_joint, np.arange(25) * 0.02, frame=lambda k: "base" + "_" * (k % 7))
    runs = lcs_cvx.Trajectories.from_mcap(path, STATE, INPUT, dt=0.005)
    want = np.column_stack(joint(t_joint[: len(runs.xs[0])]))
    assert np.abs(runs.xs[0].numpy() - want).max() <= 1e-12
    stamp = lcs_cvx.Trajectories.from_mcap(path, {"/joint_states": ["header.stamp.nanosec"]}, dt=0.005)
    assert np.abs(stamp.xs[0].numpy()[:, 0] - np.round(t_joint * 1e9) % 10**9).max() == 0


def test_two_rates_resampled_onto_one_clock_against_the_sine(tmp_path):
    """A JSON channel: the state at 100 Hz, the command at 30 Hz; the default clock is the
    slower stream's period, and the interpolated sine is within the linear interpolation's
    bound ``omega^2 h^2 / 8`` of the sine itself."""
    path = tmp_path / "json.mcap"
    h = 0.01
    t_state, t_input = np.arange(300) * h, 0.004 + np.arange(89) / 30
    write_json_bag(path, t_state, t_input)
    runs = lcs_cvx.Trajectories.from_mcap(path, {"/state": ["q[0]", "qd[0]"]}, {"/command": ["u"]})
    assert runs.description.dt == pytest.approx(1 / 30, rel=1e-6)
    x, u = runs.xs[0].numpy(), runs.us[0].numpy()
    grid = 0.004 + np.arange(len(x)) / 30  # the common span starts at the first command
    bound = OMEGA**2 * h**2 / 8
    assert np.abs(x[:, 0] - np.sin(OMEGA * grid)).max() <= bound * (1 + 1e-9)
    assert np.abs(x[:, 1] - OMEGA * np.cos(OMEGA * grid)).max() <= OMEGA * bound * (1 + 1e-9)
    assert np.abs(x[:, 0] - np.sin(OMEGA * grid)).max() > bound / 10  # really interpolated
    assert np.abs(u[:, 0] - [effort(k) for k in range(len(u))]).max() <= 1e-12  # each command once


def test_a_gap_splits_the_run_and_is_counted(tmp_path):
    path = tmp_path / "gap.mcap"
    t_joint = np.arange(400) * 0.005
    t_joint = t_joint[(t_joint < 0.8) | (t_joint >= 1.2)]  # 0.4 s without joint states
    write_ros2_bag(path, t_joint, np.arange(100) * 0.02)
    runs = lcs_cvx.Trajectories.from_mcap(path, STATE, INPUT, dt=0.01)
    assert len(runs) == 2 and runs.description.splits == 1
    assert runs.xs[0][-1, 0].item() == pytest.approx(np.sin(OMEGA * 0.79), abs=1e-12)
    assert runs.xs[1][0, 0].item() == pytest.approx(np.sin(OMEGA * 1.2), abs=1e-12)
    assert "1 gaps" in runs.describe() and "split at 1 gaps" in runs.describe()


def test_bad_mcap_input_is_named(tmp_path):
    path = tmp_path / "run.mcap"
    write_ros2_bag(path, np.arange(40) * 0.005, np.arange(10) * 0.02)
    with pytest.raises(LCSInputError, match=r"expected topics \['/odom'\] in .*which has \['/effort', '/joint_states'\]"):
        lcs_cvx.Trajectories.from_mcap(path, {"/odom": ["x"]})
    with pytest.raises(LCSInputError, match=r"expected a numeric field 'positions\[0\]', received fields \['effort', 'header', 'position', 'velocity'\]"):
        lcs_cvx.Trajectories.from_mcap(path, {"/joint_states": ["positions[0]"]})
    with pytest.raises(LCSInputError, match=r"index 2 out of range \(length 2\)"):
        lcs_cvx.Trajectories.from_mcap(path, {"/joint_states": ["position[2]"]})
    for dt, says in ((0.0, "dt: expected a number > 0"), (0.05, r"dt: expected at most the slowest stream's period, 0.02 s")):
        with pytest.raises(LCSInputError, match=says):
            lcs_cvx.Trajectories.from_mcap(path, STATE, INPUT, dt=dt)
    with pytest.raises(LCSInputError, match=r"state: expected a mapping of topics to lists of fields"):
        lcs_cvx.Trajectories.from_mcap(path, ["/joint_states"])
    with pytest.raises(LCSInputError, match=r"expected an existing MCAP file"):
        lcs_cvx.Trajectories.from_mcap(tmp_path / "none.mcap", STATE)


# -- HDF5 -------------------------------------------------------------------------------------
def write_hdf5(path, q_nan=None, backwards=False, apart=False):
    """Two robomimic-style demonstrations: ``obs/q`` (2 columns) at 100 Hz with its own time
    ``obs/t_q``, ``actions`` at 25 Hz with ``t_a``."""
    written = {}
    with h5py.File(path, "w") as f:
        for d, n in ((0, 120), (1, 80)):
            g = f.create_group(f"data/demo_{d}")
            t_q = np.arange(n) * 0.01
            q = np.column_stack([np.sin(OMEGA * t_q) + d, np.cos(OMEGA * t_q)])
            t_a = np.arange(n // 4) * 0.04 + (5.0 if apart and d == 1 else 0.0)
            a = np.arange(n // 4, dtype=float)[:, None] * 0.5 - d
            if q_nan is not None and d == 1:
                q[q_nan, 0] = np.nan
            if backwards and d == 1:
                t_q[50] = t_q[48]
            g["obs/q"], g["obs/t_q"], g["actions"], g["t_a"] = q, t_q, a, t_a
            written[d] = (q, a)
    return written


TIME = {"obs/q": "obs/t_q", "actions": "t_a"}


def test_hdf5_runs_read_back_to_the_arrays_written(tmp_path):
    path = tmp_path / "demos.hdf5"
    written = write_hdf5(path)
    runs = lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], input=["actions"], time=TIME, dt=0.01)
    assert len(runs) == 2 and runs.names == ("obs/q[0]", "obs/q[1]") and runs.input_names == ("actions",)
    for d, (x, u) in enumerate(zip(runs.xs, runs.us, strict=True)):
        q, a = written[d]
        T = len(u)
        assert T == (len(q) // 4 - 1) * 4 + 1  # the span the actions cover, the last held one step
        assert np.abs(x.numpy() - q[: T + 1]).max() <= 1e-12
        assert np.abs(u.numpy()[:, 0] - a[np.arange(T) // 4, 0]).max() <= 1e-12
    one = lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q[1]"], runs=["data/demo_1"], time="obs/t_q")
    assert one.n_x == 1 and one.n_u == 0 and np.abs(one.xs[0].numpy()[:, 0] - written[1][0][:, 1]).max() <= 1e-12
    fixed = lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], period=0.01)  # rows at a known rate
    assert fixed.lengths == (119, 79)


def test_bad_hdf5_input_is_named(tmp_path):
    path = tmp_path / "demos.hdf5"
    write_hdf5(path, q_nan=30)
    with pytest.raises(LCSInputError, match=r"stream 'obs/q' of run 'data/demo_1': expected finite values, received 1 "
                                            r"samples with NaN/inf, the first at t = 0.3 s .*drop_nan=True"):
        lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], input=["actions"], time=TIME, dt=0.01)
    dropped = lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], input=["actions"], time=TIME, dt=0.01,
                                             drop_nan=True)
    assert dropped.description.dropped_nan == 1 and "and 1 samples with NaN" in dropped.describe()
    with pytest.raises(LCSInputError, match=r"state: expected a dataset 'obs/p' in .*which has \['actions', 'obs/q', 'obs/t_q', 't_a'\]"):
        lcs_cvx.Trajectories.from_hdf5(path, state=["obs/p"], time=TIME)
    with pytest.raises(LCSInputError, match=r"period: expected the seconds per row"):
        lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"])
    write_hdf5(path, backwards=True)
    with pytest.raises(LCSInputError, match=r"stream 'obs/q' of run 'data/demo_1': expected increasing time stamps, "
                                            r"received t = 0.49 s then 0.48 s \(samples 49, 50\)"):
        lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], time=TIME)
    write_hdf5(path, apart=True)  # run 1's actions start after its states end
    with pytest.raises(LCSInputError, match=r"run 'data/demo_1': expected at least one step of dt = 0.04 s where every "
                                            r"stream has samples, received none"):
        lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], input=["actions"], time=TIME)


# -- LeRobot ----------------------------------------------------------------------------------
def write_lerobot(root, version, episodes=((0, 40), (1, 25)), fps=30):
    """A LeRobot dataset: ``meta/info.json`` and parquet files under ``data/`` (one per episode
    in v2.1, one file of every episode in v3.0); float32 states and actions and time stamps, as
    LeRobot writes them."""
    info = {"codebase_version": version, "fps": fps, "features": {
        "observation.state": {"dtype": "float32", "shape": [2], "names": ["x", "v"]},
        "action": {"dtype": "float32", "shape": [1], "names": ["force"]},
        "timestamp": {"dtype": "float32", "shape": [1]}, "frame_index": {"dtype": "int64", "shape": [1]},
        "episode_index": {"dtype": "int64", "shape": [1]}}}
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps(info))
    written, tables = {}, []
    for e, n in episodes:
        k = np.arange(n)
        state = np.column_stack([np.sin(0.1 * k + e), np.cos(0.1 * k)]).astype(np.float32)
        action = (0.01 * k[:, None] - e).astype(np.float32)
        written[e] = (state, action)
        tables.append(pa.table({
            "observation.state": pa.array(list(state), type=pa.list_(pa.float32(), 2)),
            "action": pa.array(list(action), type=pa.list_(pa.float32(), 1)),
            "timestamp": pa.array((k / fps).astype(np.float32)), "frame_index": pa.array(k),
            "episode_index": pa.array(np.full(n, e)), "index": pa.array(k)}))
    data = root / "data" / "chunk-000"
    data.mkdir(parents=True)
    if version.startswith("v2"):
        for (e, _), t in zip(episodes, tables, strict=True):
            pq.write_table(t, data / f"episode_{e:06d}.parquet")
    else:
        pq.write_table(pa.concat_tables(tables[::-1]), data / "file-000.parquet")  # episodes in any order
    return written


@pytest.mark.parametrize("version", ["v2.1", "v3.0"])
def test_a_lerobot_dataset_reads_back_to_the_arrays_written(tmp_path, version):
    written = write_lerobot(tmp_path / "ds", version)
    runs = lcs_cvx.Trajectories.from_lerobot(tmp_path / "ds")
    assert len(runs) == 2 and runs.names == ("x", "v") and runs.input_names == ("force",)
    assert runs.description.dt == pytest.approx(1 / 30)
    for e, (x, u) in enumerate(zip(runs.xs, runs.us, strict=True)):
        state, action = written[e]
        assert np.abs(x.numpy() - state.astype(np.float64)).max() <= 1e-12
        assert np.abs(u.numpy() - action[:-1].astype(np.float64)).max() <= 1e-12
    with pytest.raises(LCSInputError, match=r"expected features \['observation.images'\] .*which has \["):
        lcs_cvx.Trajectories.from_lerobot(tmp_path / "ds", state="observation.images")
    with pytest.raises(LCSInputError, match=r"expected a LeRobot dataset folder with meta/info.json"):
        lcs_cvx.Trajectories.from_lerobot(tmp_path)


def test_a_fit_takes_what_a_reader_made(tmp_path):
    """The runs of a log are Trajectories like any other: fit holds out whole runs."""
    path = tmp_path / "demos.hdf5"
    write_hdf5(path)
    runs = lcs_cvx.Trajectories.from_hdf5(path, state=["obs/q"], input=["actions"], time=TIME, dt=0.01)
    first, second = runs.split(0.5, seed=0)
    assert first.names == runs.names and second.input_names == runs.input_names
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 1, seed=0), runs, recipe="plain", iterations=20, progress=False,
                         rollout_horizon=None)
    assert result.heldout_error is not None and math.isfinite(result.heldout_error)
