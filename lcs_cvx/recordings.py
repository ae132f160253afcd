"""Robot logs in: ROS 2 bags (MCAP), HDF5 demonstrations and LeRobot datasets, as timestamped
:class:`~lcs_cvx.streams.Stream` s put on one clock by :func:`lcs_cvx.streams.align`.

The readers behind :meth:`lcs_cvx.Trajectories.from_mcap`, :meth:`~lcs_cvx.Trajectories.from_hdf5`
and :meth:`~lcs_cvx.Trajectories.from_lerobot` (the ``logs`` extra installs ``mcap``,
``mcap-ros2-support``, ``h5py`` and ``pyarrow``). Each returns the runs' ``(xs, us)`` pairs, the
state and input column names and the :class:`~lcs_cvx.streams.Description` of what was read.

A field is named by a path into a message or a run: ``"position[0]"`` (element 0 of the field
``position``), ``"pose.position.x"``, ``"obs/joint_pos"`` (an HDF5 dataset, every column) or
``"obs/joint_pos[2]"`` (one column).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ._checks import LCSInputError
from ._optional import require
from .streams import Description, Stream, align

__all__ = ["read_mcap", "read_hdf5", "read_lerobot"]

_PART = re.compile(r"^([^\[\]]+)((?:\[\d+\])*)$")

Runs = tuple[list[tuple[np.ndarray, np.ndarray]], tuple[str, ...], tuple[str, ...], Description]


def _spec(name: str, spec: Any) -> dict[str, list[str]]:
    """``{source: [field, ...]}`` from a mapping (or, for ``input``, nothing)."""
    if spec is None:
        return {}
    if not isinstance(spec, Mapping) or not all(
            isinstance(k, str) and isinstance(v, Sequence) and not isinstance(v, str) and v
            and all(isinstance(f, str) for f in v) for k, v in spec.items()):
        raise LCSInputError(f"{name}: expected a mapping of topics to lists of fields, e.g. "
                            f"{{'/joint_states': ['position[0]', 'velocity[0]']}}, received {spec!r}")
    return {k: list(v) for k, v in spec.items()}


def _get(message: Any, path: str, where: str) -> float:
    """The number at ``path`` in a decoded message (attributes or keys, ``[i]`` elements)."""
    value = message
    for part in path.split("."):
        m = _PART.match(part)
        if m is None:
            raise LCSInputError(f"{where}: expected a field path such as 'position[0]' or 'pose.position.x', "
                                f"received {path!r}")
        key = m.group(1)
        if isinstance(value, Mapping):
            if key not in value:
                raise LCSInputError(f"{where}: expected a field {key!r} (of {path!r}), received fields {sorted(value)}")
            value = value[key]
        else:
            if not hasattr(value, key):
                fields = getattr(value, "__slots__", None) or [k for k in vars(value) if not k.startswith("_")]
                raise LCSInputError(f"{where}: expected a field {key!r} (of {path!r}), received fields "
                                    f"{sorted(str(f) for f in fields)}")
            value = getattr(value, key)
        for index in re.findall(r"\[(\d+)\]", m.group(2)):
            i = int(index)
            if i >= len(value):
                raise LCSInputError(f"{where}: field {path!r}: index {i} out of range (length {len(value)})")
            value = value[i]
    try:
        return float(value)
    except (TypeError, ValueError):
        raise LCSInputError(f"{where}: field {path!r}: expected a number, received {type(value).__name__}") from None


def _chunk_bytes(chunk: Any) -> bytes:
    """A chunk's records, decompressed."""
    if chunk.compression == "zstd":
        return require("zstandard", "logs", "Trajectories.from_mcap").decompress(chunk.data, chunk.uncompressed_size)
    if chunk.compression == "lz4":
        return require("lz4.frame", "logs", "Trajectories.from_mcap").decompress(chunk.data)
    if chunk.compression:
        raise LCSInputError(f"path: expected chunks compressed with zstd, lz4 or not at all, received {chunk.compression!r}")
    return bytes(chunk.data)


def _messages(path: str, channels: dict[int, Any]) -> dict[int, tuple[list, list, list, list]]:
    """``{channel id: (buffers, log times, starts, lengths)}`` of the messages of ``channels``,
    in file order, read in place from the file's decompressed chunks (the compiled scan,
    :mod:`lcs_cvx._kernels.mcap`) and from messages outside chunks."""
    records = require("mcap.records", "logs", "Trajectories.from_mcap")
    stream_reader = require("mcap.stream_reader", "logs", "Trajectories.from_mcap")
    from ._kernels.mcap import scan_messages

    wanted = np.zeros(max(channels) + 1, dtype=np.bool_)
    wanted[list(channels)] = True
    out: dict[int, tuple[list, list, list, list]] = {c: ([], [], [], []) for c in channels}
    with open(path, "rb") as f:
        for rec in stream_reader.StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, records.Chunk):
                buf, channel, log_time, start, length = scan_messages(_chunk_bytes(rec), wanted)
                for c in np.unique(channel):
                    at = channel == c
                    for lst, v in zip(out[int(c)], (buf, log_time[at], start[at], length[at]), strict=True):
                        lst.append(v)
            elif isinstance(rec, records.Message) and rec.channel_id in channels:
                for lst, v in zip(out[rec.channel_id], (np.frombuffer(rec.data, np.uint8), np.array([rec.log_time]),
                                                        np.array([0]), np.array([len(rec.data)])), strict=True):
                    lst.append(v)
    return out


def _numbers(channel: Any, schema: Any, found: tuple[list, list, list, list], fields: list[str],
             where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(log times (ns), values (N, len(fields)))`` of one channel's messages."""
    buffers, times, starts, lengths = found
    t = np.concatenate(times) if times else np.zeros(0, np.int64)
    if channel.message_encoding == "cdr":
        from .ros2 import parse_definition, read_fields

        definition = parse_definition(schema.name, schema.data.decode())
        return t, read_fields(definition, buffers, starts, lengths, fields, where)
    if channel.message_encoding == "json":
        rows = [[_get(json.loads(buf[s:s + n].tobytes()), p, where) for p in fields]
                for buf, st, ln in zip(buffers, starts, lengths, strict=True) for s, n in zip(st, ln, strict=True)]
        return t, np.array(rows, dtype=np.float64).reshape(len(rows), len(fields))
    raise LCSInputError(f"{where}: expected a ROS 2 (cdr) or JSON channel, received message encoding "
                        f"{channel.message_encoding!r}")


def read_mcap(path: str | os.PathLike, state: Mapping[str, Sequence[str]],
              input: Mapping[str, Sequence[str]] | None = None, dt: float | None = None,
              max_gap: float | None = None, drop_nan: bool = False) -> Runs:
    """One MCAP file: each topic of ``state`` and ``input`` one stream, timed by the messages'
    log time, in file order; ROS 2 (CDR, :mod:`lcs_cvx.ros2`) and JSON channels. The file's
    summary names its channels."""
    reader_mod = require("mcap.reader", "logs", "Trajectories.from_mcap")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise LCSInputError(f"path: expected an existing MCAP file, received {path!r} (not found)")
    specs = {"state": _spec("state", state), "input": _spec("input", input)}
    if not specs["state"]:
        raise LCSInputError("state: expected at least one topic, received none")
    topics = {t: kind for kind, s in specs.items() for t in s}
    with open(path, "rb") as f:
        summary = reader_mod.make_reader(f).get_summary()
    if summary is None:
        raise LCSInputError(f"path: expected an MCAP file with a summary section (its channels), received {path!r}")
    by_topic = {c.topic: c for c in summary.channels.values()}
    missing = [t for t in topics if t not in by_topic]
    if missing:
        raise LCSInputError(f"state/input: expected topics {missing} in {path!r}, which has {sorted(by_topic)}")
    found = _messages(path, {by_topic[t].id: t for t in topics})
    streams, t0 = [], None
    raw = {}
    for topic, kind in topics.items():
        ch = by_topic[topic]
        raw[topic] = _numbers(ch, summary.schemas.get(ch.schema_id), found[ch.id], specs[kind][topic],
                              f"{path!r}, topic {topic!r}")
        if len(raw[topic][0]):
            t0 = int(raw[topic][0][0]) if t0 is None else min(t0, int(raw[topic][0][0]))
    for topic, kind in topics.items():
        t, values = raw[topic]
        names = tuple(f"{topic}.{p}" for p in specs[kind][topic])
        streams.append(Stream(topic, (t - (t0 or 0)) * 1e-9, values, kind, names, run=os.path.basename(path)))
    runs, desc = align(streams, dt, max_gap, drop_nan, run=os.path.basename(path))
    return runs, _names(streams, "state"), _names(streams, "input"), _with_source(desc, path)


def _names(streams: Sequence[Stream], kind: str) -> tuple[str, ...]:
    return tuple(n for s in streams if s.kind == kind for n in s.names)


def _with_source(desc: Description, path: str) -> Description:
    return dataclasses.replace(desc, source=os.path.basename(path))


def _columns(name: str, group: Any, spec: str, where: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """An HDF5 dataset of ``group`` (``"obs/q"`` or ``"obs/q[i]"``) as ``(N, k)`` numbers."""
    m = re.match(r"^(.+?)(?:\[(\d+)\])?$", spec)
    key, col = m.group(1), m.group(2)
    if key not in group:
        have: list[str] = []
        group.visit(lambda n: have.append(n) if hasattr(group[n], "shape") else None)
        raise LCSInputError(f"{name}: expected a dataset {key!r} in {where}, which has {sorted(have)}")
    a = np.asarray(group[key][()], dtype=np.float64)
    a = a.reshape(len(a), -1)
    if col is not None:
        if int(col) >= a.shape[1]:
            raise LCSInputError(f"{name}: {spec!r} in {where}: column {col} out of range ({a.shape[1]} columns)")
        return a[:, [int(col)]], (spec,)
    return a, tuple(f"{key}[{j}]" for j in range(a.shape[1])) if a.shape[1] > 1 else (key,)


def read_hdf5(path: str | os.PathLike, state: Sequence[str], input: Sequence[str] = (), runs: Any = "data",
              time: str | Mapping[str, str] | None = None, period: float | None = None, dt: float | None = None,
              max_gap: float | None = None, drop_nan: bool = False) -> Runs:
    """An HDF5 file of runs (robomimic's layout: ``data/demo_0``, ``data/demo_1``, ...): each
    dataset of ``state`` and ``input`` a stream, timed by the run's ``time`` dataset (one for all,
    or a mapping from a dataset to its own) or, without one, by ``period`` seconds per row."""
    h5py = require("h5py", "logs", "Trajectories.from_hdf5")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise LCSInputError(f"path: expected an existing HDF5 file, received {path!r} (not found)")
    for name, spec in (("state", state), ("input", input)):
        if isinstance(spec, str) or not all(isinstance(s, str) for s in spec):
            raise LCSInputError(f"{name}: expected a list of dataset paths such as ['obs/joint_pos'], received {spec!r}")
    if not state:
        raise LCSInputError("state: expected at least one dataset, received none")
    if time is None and (period is None or not period > 0):
        raise LCSInputError(f"period: expected the seconds per row (> 0) when there is no time dataset, received {period!r}")
    out: list[tuple[np.ndarray, np.ndarray]] = []
    desc: Description | None = None
    all_streams: list[Stream] = []
    with h5py.File(path, "r") as f:
        if isinstance(runs, str):
            if runs not in f:
                raise LCSInputError(f"runs: expected a group {runs!r} in {path!r}, which has {sorted(f)}")
            names = sorted(f[runs], key=lambda s: [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)])
            groups = [f"{runs}/{n}" for n in names]
        else:
            groups = list(runs)
        for g in groups:
            if g not in f:
                raise LCSInputError(f"runs: expected a group {g!r} in {path!r}")
            group, where = f[g], f"{path!r}, run {g!r}"
            streams = []
            for kind, specs in (("state", state), ("input", input)):
                for spec in specs:
                    values, cols = _columns(kind, group, spec, where)
                    base = spec.split("[")[0]
                    tname = time.get(base) if isinstance(time, Mapping) else time
                    if tname is not None:
                        t, _ = _columns("time", group, tname, where)
                        t = t[:, 0]
                    else:
                        t = np.arange(len(values)) * float(period)
                    streams.append(Stream(spec, t, values, kind, cols, run=g))
            pieces, d = align(streams, dt, max_gap, drop_nan, run=g)
            out += pieces
            desc = d if desc is None else desc.merge(d)
            all_streams = streams
    return out, _names(all_streams, "state"), _names(all_streams, "input"), _with_source(desc, path)


def read_lerobot(path: str | os.PathLike, state: str = "observation.state", input: str | None = "action",
                 dt: float | None = None, max_gap: float | None = None, drop_nan: bool = False) -> Runs:
    """A LeRobot dataset folder (``meta/info.json``; parquet files under ``data/``, one per
    episode in v2.1, several episodes per file in v3.0): each episode one run, its ``state``
    and ``input`` columns timed by ``timestamp``."""
    pq = require("pyarrow.parquet", "logs", "Trajectories.from_lerobot")
    root = os.fspath(path)
    info_path = os.path.join(root, "meta", "info.json")
    if not os.path.isfile(info_path):
        raise LCSInputError(f"path: expected a LeRobot dataset folder with meta/info.json, received {root!r}")
    with open(info_path, encoding="utf-8") as fh:
        info = json.load(fh)
    version = str(info.get("codebase_version", ""))
    if not version.startswith(("v2.", "v3.")):
        raise LCSInputError(f"path: expected a LeRobot dataset of codebase_version v2.x or v3.x, received {version!r}")
    features = info.get("features", {})
    wanted = [state] + ([input] if input else [])
    missing = [c for c in wanted if c not in features]
    if missing:
        raise LCSInputError(f"state/input: expected features {missing} in {info_path!r}, which has {sorted(features)}")
    files = sorted(os.path.join(d, n) for d, _, ns in os.walk(os.path.join(root, "data")) for n in ns
                   if n.endswith(".parquet"))
    if not files:
        raise LCSInputError(f"path: expected parquet files under {os.path.join(root, 'data')!r}, found none")
    columns = ["episode_index", "frame_index", "timestamp", *wanted]
    episodes: dict[int, list[dict[str, np.ndarray]]] = {}
    for file in files:
        table = pq.read_table(file, columns=columns)
        arrays = {c: _column(table.column(c)) for c in columns}
        for e in np.unique(arrays["episode_index"]):
            rows = arrays["episode_index"][:, 0] == e
            episodes.setdefault(int(e), []).append({c: a[rows] for c, a in arrays.items()})

    def names(feature: str, k: int) -> tuple[str, ...]:
        given = features[feature].get("names")
        if isinstance(given, Mapping):
            given = next(iter(given.values()), None)
        return tuple(given) if isinstance(given, list) and len(given) == k else tuple(f"{feature}[{j}]" for j in range(k))

    out: list[tuple[np.ndarray, np.ndarray]] = []
    desc: Description | None = None
    streams: list[Stream] = []
    for e in sorted(episodes):
        parts = episodes[e]
        cat = {c: np.concatenate([p[c] for p in parts]) for c in columns}
        order = np.argsort(cat["frame_index"][:, 0], kind="stable")
        t = cat["timestamp"][order, 0]
        streams = [Stream(state, t, cat[state][order], "state", names(state, cat[state].shape[1]), run=f"episode {e}")]
        if input:
            streams.append(Stream(input, t, cat[input][order], "input", names(input, cat[input].shape[1]),
                                  run=f"episode {e}"))
        pieces, d = align(streams, dt if dt is not None else (1.0 / info["fps"] if info.get("fps") else None),
                          max_gap, drop_nan, run=f"episode {e}")
        out += pieces
        desc = d if desc is None else desc.merge(d)
    return out, _names(streams, "state"), _names(streams, "input"), _with_source(desc, root)


def _column(col: Any) -> np.ndarray:
    """A pyarrow column of numbers or of fixed-length lists as ``(N, k)`` float64."""
    col = col.combine_chunks()
    if hasattr(col, "flatten") and hasattr(col.type, "value_type"):
        flat = col.flatten().to_numpy(zero_copy_only=False).astype(np.float64)
        return flat.reshape(len(col), -1)
    return col.to_numpy(zero_copy_only=False).astype(np.float64).reshape(len(col), -1)
