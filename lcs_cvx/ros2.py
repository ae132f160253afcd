"""ROS 2 messages in CDR, read in bulk: a message definition parsed, the byte layout of one
message walked, and the numbers of many messages read at once.

A ROS 2 message is serialised as CDR (little- or big-endian, a 4-byte encapsulation header): its
fields in order, each primitive aligned to its size from the end of the header, a string as a
``uint32`` length (with its terminating zero) and its bytes, a sequence as a ``uint32`` count and
its elements, a fixed array ``T[N]`` as its elements. Where the messages of a topic have the
same layout (the same byte at every length prefix: the same frame id, joint names and array
sizes), the number at a field path sits at the same offset in every message, and
:func:`read_fields` reads it from all of them with one NumPy gather; messages of another layout
are walked one by one.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ._checks import LCSInputError

__all__ = ["MessageDefinition", "Layout", "parse_definition", "layout", "read_fields", "JOINT_STATE"]

#: ``sensor_msgs/msg/JointState``'s definition with its dependencies, as a bag stores it (what a
#: writer registers for the commonest robot message: ``register_msgdef("sensor_msgs/msg/JointState",
#: JOINT_STATE)``).
JOINT_STATE = """std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""

#: Primitive ROS 2 types and their NumPy dtypes (little-endian; CDR's byte order is the header's).
PRIMITIVES = {
    "bool": "u1", "byte": "u1", "char": "u1", "uint8": "u1", "int8": "i1", "uint16": "u2", "int16": "i2",
    "uint32": "u4", "int32": "i4", "float32": "f4", "uint64": "u8", "int64": "i8", "float64": "f8",
}
_FIELD = re.compile(r"^([A-Za-z][\w/]*)(?:<=\d+)?(\[(<=)?(\d*)\])?\s+([A-Za-z]\w*)(\s*=.*)?")


@dataclass(frozen=True)
class Field:
    type: str
    name: str
    array: int | None  # None: scalar; -1: sequence; N: fixed array


@dataclass(frozen=True)
class MessageDefinition:
    """A message type's fields and those of every type it uses (``{type name: fields}``)."""

    name: str
    types: dict[str, tuple[Field, ...]]


def _key(type_name: str, package: str) -> str:
    """``pkg/Name`` for ``pkg/msg/Name``, ``pkg/Name`` or ``Name`` (of ``package``)."""
    parts = type_name.split("/")
    if len(parts) == 1:
        return "std_msgs/Header" if type_name == "Header" else f"{package}/{type_name}"
    return f"{parts[0]}/{parts[-1]}"


def parse_definition(name: str, text: str) -> MessageDefinition:
    """The ``.msg`` definition ``text`` of ``name`` (``sensor_msgs/msg/JointState``) with its
    dependencies after ``===`` lines and ``MSG: pkg/Name`` headers, as MCAP stores it."""
    types: dict[str, tuple[Field, ...]] = {}
    current, fields = _key(name, name.split("/")[0]), []
    for raw in text.splitlines() + ["=" * 3]:
        line = raw.split("#", 1)[0].strip()
        if line.startswith("==="):
            types[current] = tuple(fields)
            current, fields = None, []
            continue
        if not line:
            continue
        if line.startswith("MSG:"):
            current = _key(line[4:].strip(), "")
            continue
        m = _FIELD.match(line)
        if m is None or m.group(6) is not None:  # not a field, or a constant (NAME=value)
            continue
        typ, arr, bounded, size, fname = m.group(1), m.group(2), m.group(3), m.group(4), m.group(5)
        array = None if arr is None else (-1 if bounded or not size else int(size))
        package = current.split("/")[0] if current else ""
        fields.append(Field(typ if typ in PRIMITIVES or typ == "string" else _key(typ, package), fname, array))
    return MessageDefinition(_key(name, name.split("/")[0]), types)


@dataclass(frozen=True)
class Layout:
    """One message walked: ``scalars`` ``{path: (offset, dtype)}`` of its primitive numbers,
    ``arrays`` ``{path: (offset, count, dtype)}`` of its primitive arrays, ``prefixes`` the
    offsets of its length prefixes (strings and sequences); offsets from the data's start."""

    scalars: dict[str, tuple[int, str]]
    arrays: dict[str, tuple[int, int, str]]
    prefixes: tuple[int, ...]
    size: int

    def locate(self, path: str, where: str) -> tuple[int, str]:
        """``(offset, dtype)`` of the number at ``path`` (``"position[0]"``, ``"header.stamp.sec"``)."""
        if path in self.scalars:
            return self.scalars[path]
        m = re.match(r"^(.*)\[(\d+)\]$", path)
        if m is not None and m.group(1) in self.arrays:
            offset, count, dtype = self.arrays[m.group(1)]
            i = int(m.group(2))
            if i >= count:
                raise LCSInputError(f"{where}: field {path!r}: index {i} out of range (length {count})")
            return offset + i * np.dtype(dtype).itemsize, dtype
        top = sorted({re.split(r"[.\[]", p)[0] for p in (*self.scalars, *self.arrays)})
        raise LCSInputError(f"{where}: expected a numeric field {path!r}, received fields {top}")


def layout(definition: MessageDefinition, data: np.ndarray) -> Layout:
    """The layout of one serialised message ``data`` (``uint8``, with its encapsulation header)."""
    little = int(data[1]) & 1 == 1
    if not little:
        raise LCSInputError("ros2: big-endian CDR messages are not read; received representation "
                            f"identifier {int(data[0]):#04x}{int(data[1]):02x}")
    scalars: dict[str, tuple[int, str]] = {}
    arrays: dict[str, tuple[int, int, str]] = {}
    prefixes: list[int] = []
    base = 4

    def align(pos: int, size: int) -> int:
        return base + -(-(pos - base) // size) * size

    def u32(pos: int) -> int:
        return int.from_bytes(data[pos:pos + 4].tobytes(), "little")

    def walk(type_name: str, pos: int, path: str) -> int:
        if type_name not in definition.types:
            raise LCSInputError(f"ros2: the message definition of {definition.name!r} has no type {type_name!r}")
        for f in definition.types[type_name]:
            p = f"{path}{f.name}"
            count = f.array
            if count == -1:
                pos = align(pos, 4)
                prefixes.append(pos)
                count = u32(pos)
                pos += 4
            if f.type in PRIMITIVES:
                dtype = PRIMITIVES[f.type]
                size = np.dtype(dtype).itemsize
                pos = align(pos, size)
                if count is None:
                    scalars[p] = (pos - base, dtype)
                    pos += size
                else:
                    arrays[p] = (pos - base, count, dtype)
                    pos += size * count
            elif f.type == "string":
                for i in range(1 if count is None else count):
                    pos = align(pos, 4)
                    prefixes.append(pos)
                    pos += 4 + u32(pos)
                    del i
            else:
                for i in range(1 if count is None else count):
                    pos = walk(f.type, pos, f"{p}." if count is None else f"{p}[{i}].")
        return pos

    end = walk(definition.name, base, "")
    return Layout(scalars, arrays, tuple(q - base for q in prefixes), end - base)


def read_fields(definition: MessageDefinition, buffers: list[np.ndarray], starts: list[np.ndarray],
                lengths: list[np.ndarray], paths: list[str], where: str) -> np.ndarray:
    """The numbers at ``paths`` of every message, ``(N, len(paths))`` float64: message ``j`` of
    piece ``k`` is ``buffers[k][starts[k][j] : starts[k][j] + lengths[k][j]]``."""
    n = sum(len(s) for s in starts)
    out = np.empty((n, len(paths)))
    if n == 0:
        return out
    first = next(k for k, s in enumerate(starts) if len(s))
    head = buffers[first][starts[first][0]:starts[first][0] + lengths[first][0]]
    lay = layout(definition, head)
    where_at = [lay.locate(p, where) for p in paths]
    head_prefixes = [_gather(head, np.array([4 + q]), "u4")[0] for q in lay.prefixes]
    row = 0
    for buf, st, ln in zip(buffers, starts, lengths, strict=True):
        if not len(st):
            continue
        same = ln == len(head)  # (a serialiser may pad the end past the layout's size)
        for q, value in zip(lay.prefixes, head_prefixes, strict=True):  # the same prefixes: the same layout
            same[same] &= _gather(buf, st[same] + 4 + q, "u4") == value
        for j, (offset, dtype) in enumerate(where_at):
            out[row:row + len(st), j][same] = _gather(buf, st[same] + 4 + offset, dtype)
        for i in np.flatnonzero(~same):  # another layout: walked on its own
            own = layout(definition, buf[st[i]:st[i] + ln[i]])
            for j, p in enumerate(paths):
                offset, dtype = own.locate(p, where)
                out[row + i, j] = _gather(buf, np.array([st[i] + 4 + offset]), dtype)[0]
        row += len(st)
    return out


def _gather(buf: np.ndarray, at: np.ndarray, dtype: str) -> np.ndarray:
    """The ``dtype`` numbers (little-endian) starting at the byte offsets ``at`` of ``buf``."""
    size = np.dtype(dtype).itemsize
    raw = buf[at[:, None] + np.arange(size)]
    return np.ascontiguousarray(raw).view("<" + dtype).reshape(-1).astype(np.float64)
