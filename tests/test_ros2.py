"""lcs_cvx.ros2: message definitions parsed and messages read in bulk, against the CDR that
mcap-ros2-support's serialiser writes."""

from __future__ import annotations

import io

import numpy as np
import pytest

from lcs_cvx import LCSInputError
from lcs_cvx.ros2 import layout, parse_definition, read_fields

ros2_writer = pytest.importorskip("mcap_ros2.writer")
mcap_reader = pytest.importorskip("mcap.reader")

DEFINITION = """# a test message
int32 LIMIT=7
string<=8 label
float32[3] gains
Point[] points
bool flag
float64 scale 1.5
uint16[<=4] ids
================================================================================
MSG: test_msgs/Point
float64 x
int8 k
"""


def serialised(messages):
    """The CDR bytes of ``messages`` as mcap-ros2-support writes them."""
    out = io.BytesIO()
    w = ros2_writer.Writer(out)
    schema = w.register_msgdef("test_msgs/msg/Probe", DEFINITION)
    for i, m in enumerate(messages):
        w.write_message("/probe", schema, m, log_time=i, publish_time=i)
    w.finish()
    out.seek(0)
    return [np.frombuffer(msg.data, np.uint8) for _, _, msg in mcap_reader.make_reader(out).iter_messages()]


def message(i, label="ab"):
    return {"label": label, "gains": [0.5, 1.5, 2.5 + i], "points": [{"x": 1.0 + i, "k": -i}, {"x": -2.0, "k": 3}],
            "flag": bool(i % 2), "scale": 0.25 * i, "ids": [i, 2 * i, 9]}


def test_a_definition_with_constants_defaults_and_arrays():
    d = parse_definition("test_msgs/msg/Probe", DEFINITION)
    assert d.name == "test_msgs/Probe"
    fields = {f.name: (f.type, f.array) for f in d.types["test_msgs/Probe"]}
    assert fields == {"label": ("string", None), "gains": ("float32", 3), "points": ("test_msgs/Point", -1),
                      "flag": ("bool", None), "scale": ("float64", None), "ids": ("uint16", -1)}


def test_fields_read_in_bulk_and_one_by_one_are_the_values_written():
    """The same layout (bulk), and labels of other lengths (walked one by one), both exact."""
    d = parse_definition("test_msgs/msg/Probe", DEFINITION)
    msgs = [message(i, label="ab" if i < 5 else "abcdefg"[: i % 7 + 1]) for i in range(9)]
    data = serialised(msgs)
    buf = np.concatenate(data)
    starts = np.cumsum([0] + [len(m) for m in data[:-1]])
    paths = ["gains[2]", "points[0].x", "points[1].k", "flag", "scale", "ids[1]"]
    got = read_fields(d, [buf], [starts], [np.array([len(m) for m in data])], paths, "probe")
    want = [[np.float32(2.5 + i), 1.0 + i, 3, i % 2, 0.25 * i, 2 * i] for i in range(9)]
    assert np.array_equal(got, np.array(want, dtype=np.float64))
    lay = layout(d, data[0])
    with pytest.raises(LCSInputError, match=r"probe: field 'ids\[3\]': index 3 out of range \(length 3\)"):
        lay.locate("ids[3]", "probe")
    with pytest.raises(LCSInputError, match=r"probe: expected a numeric field 'label', received fields "
                                            r"\['flag', 'gains', 'ids', 'points', 'scale'\]"):
        lay.locate("label", "probe")
