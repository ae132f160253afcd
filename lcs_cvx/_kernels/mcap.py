"""The records of an MCAP chunk, found by a compiled scan.

An MCAP chunk's decompressed records are ``opcode (1 byte) | length (uint64) | content``; a
Message record's content is ``channel_id (uint16) | sequence (uint32) | log_time (uint64) |
publish_time (uint64) | data``. :func:`scan_messages` walks the records once and returns, for
the messages of the wanted channels, their channel, log time and the start and length of their
data in the chunk (the messages' bytes are then read in place, :mod:`lcs_cvx.ros2`).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["scan_messages", "MESSAGE_OPCODE"]

#: The opcode of an MCAP Message record.
MESSAGE_OPCODE = 0x05
_HEADER = 9  # opcode and length
_FIXED = 22  # channel_id, sequence, log_time, publish_time


@numba.njit(cache=True, nogil=True)
def _scan(buf: np.ndarray, wanted: np.ndarray) -> tuple:  # pragma: no cover (compiled)
    n = buf.shape[0]
    most = n // (_HEADER + _FIXED) + 1
    channel = np.empty(most, np.int64)
    log_time = np.empty(most, np.int64)
    start = np.empty(most, np.int64)
    length = np.empty(most, np.int64)
    k = 0
    pos = 0
    while pos + _HEADER <= n:
        op = buf[pos]
        size = 0
        for b in range(8):
            size |= np.int64(buf[pos + 1 + b]) << (8 * b)
        body = pos + _HEADER
        if op == MESSAGE_OPCODE and size >= _FIXED and body + size <= n:
            ch = np.int64(buf[body]) | (np.int64(buf[body + 1]) << 8)
            if ch < wanted.shape[0] and wanted[ch]:
                t = np.int64(0)
                for b in range(8):
                    t |= np.int64(buf[body + 6 + b]) << (8 * b)
                channel[k] = ch
                log_time[k] = t
                start[k] = body + _FIXED
                length[k] = size - _FIXED
                k += 1
        pos = body + size
    return channel[:k], log_time[:k], start[:k], length[:k]


def scan_messages(chunk: bytes, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(buffer, channel, log_time, start, length)`` of the Message records of the decompressed
    ``chunk`` whose channel id ``c`` has ``wanted[c]`` (a bool array), in file order; ``buffer``
    is the chunk as ``uint8`` (the data of message ``i`` is ``buffer[start[i]:start[i] +
    length[i]]``)."""
    buf = np.frombuffer(chunk, dtype=np.uint8)
    return (buf, *_scan(buf, wanted))
