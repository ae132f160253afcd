"""The solver studies' resumable records: one JSON line per finished cell, read back as a dict.

Each study appends a line per cell as it finishes and, on a rerun, skips the cells already
recorded; :func:`load` reads the file back keyed by the fields that name a cell.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

__all__ = ["load"]


def load(path: Path, key: Callable[[dict], tuple]) -> dict[tuple, dict]:
    """The records of ``path`` (a JSON-lines file; empty lines skipped, a missing file: none) by
    ``key(record)``; a later line of the same cell replaces an earlier one."""
    done: dict[tuple, dict] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                record = json.loads(line)
                done[key(record)] = record
    return done
