"""How long reading a robot log takes: a ROS 2 bag (MCAP) of 10^6 messages read into
lcs_cvx.Trajectories by Trajectories.from_mcap, on one core.

The bag holds ``sensor_msgs/msg/JointState`` at 1 kHz (two joints' positions and velocities)
and a ``std_msgs/msg/Float64`` command at 100 Hz, ``--messages`` in all (written with
mcap-ros2-support's writer, zstd chunks, the first time only); the read takes two numbers of
the joint states and the command onto a 1 kHz clock. Run with

    python -m studies.mcap_read --out studies/results/mcap_read [--messages 1000000] [--repeats 3]

and it writes ``mcap_read.json`` and ``mcap_read.md`` there (the median of the repeats).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import numpy as np
import torch

import lcs_cvx
from lcs_cvx.ros2 import JOINT_STATE


def write_bag(path: str, messages: int) -> None:
    """``messages`` messages: 10 joint states (1 kHz) to every command (100 Hz)."""
    from mcap_ros2.writer import Writer

    joints = messages * 10 // 11
    with open(path, "wb") as f:
        w = Writer(f)
        js = w.register_msgdef("sensor_msgs/msg/JointState", JOINT_STATE)
        cmd = w.register_msgdef("std_msgs/msg/Float64", "float64 data\n")
        for k in range(joints):
            ns = k * 1_000_000
            p = float(np.sin(1e-3 * k))
            w.write_message("/joint_states", js, {
                "header": {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": "base"},
                "name": ["slider", "hinge"], "position": [p, -p], "velocity": [np.cos(1e-3 * k), 0.0],
                "effort": []}, log_time=ns, publish_time=ns)
            if k % 10 == 0:
                w.write_message("/command", cmd, {"data": float(k % 7)}, log_time=ns, publish_time=ns)
        w.finish()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--messages", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    os.makedirs(args.out, exist_ok=True)
    bag = os.path.join(args.out, f"bag_{args.messages}.mcap")
    if not os.path.exists(bag):
        t0 = time.perf_counter()
        write_bag(bag, args.messages)
        print(f"wrote {bag} in {time.perf_counter() - t0:.1f} s", flush=True)
    state, command = {"/joint_states": ["position[0]", "velocity[0]"]}, {"/command": ["data"]}
    lcs_cvx.Trajectories.from_mcap(bag, state, command)  # compiles the scan (cached after)
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        runs = lcs_cvx.Trajectories.from_mcap(bag, state, command, dt=1e-3)
        times.append(time.perf_counter() - t0)
    row = {"messages": args.messages, "bytes": os.path.getsize(bag), "seconds": times,
           "median_s": statistics.median(times), "transitions": sum(runs.lengths),
           "machine": f"{platform.machine()}, {os.cpu_count()} cores, 1 torch thread",
           "date": time.strftime("%Y-%m-%d")}
    with open(os.path.join(args.out, "mcap_read.json"), "w") as f:
        json.dump(row, f, indent=1)
    with open(os.path.join(args.out, "mcap_read.md"), "w") as f:
        f.write(f"# Reading a ROS 2 bag\n\n`python -m studies.mcap_read --out {args.out} --messages {args.messages}`: "
                f"{args.messages:,} messages ({row['bytes'] / 2**20:.0f} MiB, zstd chunks; JointState at 1 kHz and a "
                f"command at 100 Hz) read by `Trajectories.from_mcap` onto a 1 kHz clock in **{row['median_s']:.2f} s** "
                f"(median of {args.repeats}; {', '.join(f'{t:.2f}' for t in times)} s), {row['transitions']:,} "
                f"transitions.\n\nMeasured on {row['date']}, {row['machine']}.\n")
    print(open(os.path.join(args.out, "mcap_read.md")).read())


if __name__ == "__main__":
    main()
