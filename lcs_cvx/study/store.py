"""The results store: one SQLite database per output directory, written by the client alone.

Tables (schema version 2)::

    studies  (config_hash PK, name, panel, config_json, path, created)
    cells    (id PK, key UNIQUE, config_hash, study, value_index, value, trial, method,
              seed, seed_truth, seed_train, seed_test, seed_init, seed_fit,
              e_test, final_loss, modes, sigma_min, fit_wall_time, wall_time,
              settings_json, cell_json, warnings_json, host, finished, status, time_limit)
    curves   (cell_id PK -> cells.id, data: zlib-compressed JSON of the cell's fit history, the
              records of ``lcs_cvx.FitResult.history``; read with :meth:`Store.curve`)
    failures (id PK, key, config_hash, study, value_index, trial, method, error, at)
    jobs     (key PK, study, function, result: zlib-compressed JSON, finished) -- the finished
              jobs of a ``kind = "module"`` study (:meth:`Store.add_job`, :meth:`Store.jobs`);
              numpy arrays in a result are stored exactly (dtype, shape, raw bytes in base64)

Every finished cell is one transaction (its row and its curve), committed at once; the database
is in WAL mode with ``synchronous = FULL``, so a Ctrl-C or a killed process loses at most the cell
in flight, and a finished cell is never lost or written twice (``key`` is unique).

The ``jobs`` table came after version 2 without changing the others: opening a database that
lacks it adds it, empty. So did the columns ``cells.status`` (``"ok"``; ``"timeout"`` for a
cell killed at its config's ``time_limit``: e_test NULL, the seconds it ran in the wall times;
``"failed"`` for a baseline whose own fitting algorithm failed on the cell's data: e_test NULL,
the error in ``settings_json["error"]``) and ``cells.time_limit`` (the limit it ran under, NULL
for none): opening an older database adds them, every existing row ``"ok"`` with no limit.

Timed-out cells count as finished (:meth:`Store.finished_keys`) as long as the limit asked for
is not larger than the one they were killed at; a run with a larger limit (or none) runs them
again and its result replaces theirs. Failed cells always count as finished: the method failed
on the problem, and running it again fails again.

``failures`` logs the cells that raised (a bug, a worker's error): they are not in ``cells``
and the next run tries them again. Storing a cell (any status) removes its rows from
``failures``, so the table holds only the cells still to retry.

Schema version 1 stored one row per curve record, which made the databases of the full-scale
studies several times larger; a version-1 database is converted in place when it is opened
(one transaction, then ``VACUUM``).
"""

from __future__ import annotations

import base64
import json
import math
import os
import sqlite3
import time
import zlib
from typing import Any

import numpy as np

__all__ = ["DB_NAME", "Store"]

DB_NAME = "studies.sqlite"
SCHEMA_VERSION = 2
#: The fields of a curve record, in the order of schema version 1's columns.
CURVE_FIELDS = ("iteration", "phase", "loss", "e_test", "eps", "lr", "wall_time", "restart")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS studies (
    config_hash TEXT PRIMARY KEY, name TEXT NOT NULL, panel TEXT, config_json TEXT NOT NULL,
    path TEXT, created TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cells (
    id INTEGER PRIMARY KEY, key TEXT NOT NULL UNIQUE, config_hash TEXT NOT NULL, study TEXT NOT NULL,
    value_index INTEGER NOT NULL, value REAL, trial INTEGER NOT NULL, method TEXT NOT NULL,
    seed INTEGER NOT NULL, seed_truth INTEGER NOT NULL, seed_train INTEGER NOT NULL,
    seed_test INTEGER NOT NULL, seed_init INTEGER NOT NULL, seed_fit INTEGER NOT NULL,
    e_test REAL, final_loss REAL, modes INTEGER, sigma_min REAL, fit_wall_time REAL,
    wall_time REAL, settings_json TEXT NOT NULL, cell_json TEXT NOT NULL, warnings_json TEXT,
    host TEXT, finished TEXT NOT NULL, status TEXT NOT NULL DEFAULT 'ok', time_limit REAL);
CREATE TABLE IF NOT EXISTS curves (
    cell_id INTEGER PRIMARY KEY REFERENCES cells(id), data BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS failures (
    id INTEGER PRIMARY KEY, key TEXT NOT NULL, config_hash TEXT NOT NULL, study TEXT NOT NULL,
    value_index INTEGER, trial INTEGER, method TEXT, error TEXT NOT NULL, at TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS jobs (
    key TEXT PRIMARY KEY, study TEXT NOT NULL, function TEXT NOT NULL, result BLOB NOT NULL,
    finished TEXT NOT NULL);
"""
#: Marks an encoded numpy array in a job result (see :func:`_encode`).
_ARRAY_TAG = "__ndarray__"


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def _real(v: Any) -> float | None:
    """SQLite has no NaN (it stores NULL); infinities are kept."""
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else float(v)


def _pack(records: list[list[Any]]) -> bytes:
    """A curve as ``zlib(JSON [[iteration, phase, loss, ...], ...])`` (fields: CURVE_FIELDS)."""
    return zlib.compress(json.dumps(records, separators=(",", ":")).encode(), 9)


def _encode(o: Any) -> Any:
    """``json.dumps`` default of a job result: a numpy array as ``{"__ndarray__": dtype, "shape",
    "data": base64 of its bytes}`` (exact), a numpy scalar as the Python number."""
    if isinstance(o, np.ndarray):
        if o.dtype.hasobject:
            raise TypeError(f"result: cannot store a numpy array of dtype object (shape {o.shape})")
        return {_ARRAY_TAG: o.dtype.str, "shape": list(o.shape),
                "data": base64.b64encode(np.ascontiguousarray(o).tobytes()).decode()}
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"result: cannot store a value of type {type(o).__name__}")


def _decode(d: dict[str, Any]) -> Any:
    if _ARRAY_TAG not in d:
        return d
    a = np.frombuffer(base64.b64decode(d["data"]), dtype=np.dtype(d[_ARRAY_TAG]))
    return a.reshape(d["shape"]).copy()


def _migrate_v1(conn: sqlite3.Connection) -> bool:
    """Convert a schema-1 database (one curve row per record) to schema 2; True if it did."""
    cols = [r[1] for r in conn.execute("PRAGMA table_info(curves)")]
    if "iteration" not in cols:
        return False
    with conn:
        conn.execute("CREATE TABLE curves_v2 (cell_id INTEGER PRIMARY KEY REFERENCES cells(id), "
                     "data BLOB NOT NULL)")
        per_cell: dict[int, list[list[Any]]] = {}
        q = f"SELECT cell_id, {', '.join(CURVE_FIELDS)} FROM curves ORDER BY cell_id, rowid"
        for cell_id, *rec in conn.execute(q):
            per_cell.setdefault(cell_id, []).append(rec)
        conn.executemany("INSERT INTO curves_v2 VALUES (?, ?)",
                         [(c, _pack(recs)) for c, recs in per_cell.items()])
        conn.execute("DROP TABLE curves")
        conn.execute("ALTER TABLE curves_v2 RENAME TO curves")
        conn.execute("INSERT OR REPLACE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
    conn.execute("VACUUM")
    return True


class Store:
    """The database ``<directory>/studies.sqlite`` (created on first use)."""

    def __init__(self, directory: str | os.PathLike, create: bool = True) -> None:
        directory = os.fspath(directory)
        self.path = os.path.join(directory, DB_NAME)
        if not create and not os.path.isfile(self.path):
            from .._checks import LCSInputError

            raise LCSInputError(f"{directory}: no study database ({DB_NAME}) in this directory")
        os.makedirs(directory, exist_ok=True)
        self.conn = sqlite3.connect(self.path, timeout=60.0)
        self.conn.execute("PRAGMA journal_mode=WAL")
        self.conn.execute("PRAGMA synchronous=FULL")
        self.conn.execute("PRAGMA foreign_keys=ON")
        _migrate_v1(self.conn)
        with self.conn:
            self.conn.executescript(_SCHEMA)
            self.conn.execute("INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)",
                              (str(SCHEMA_VERSION),))
            cols = {r[1] for r in self.conn.execute("PRAGMA table_info(cells)")}
            if "status" not in cols:  # a database from before time limits
                self.conn.execute("ALTER TABLE cells ADD COLUMN status TEXT NOT NULL DEFAULT 'ok'")
            if "time_limit" not in cols:
                self.conn.execute("ALTER TABLE cells ADD COLUMN time_limit REAL")

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- writing (the client only) ------------------------------------------------------
    def add_study(self, h: str, config: dict[str, Any]) -> None:
        """Record the study; a re-run of the same hash refreshes what the hash leaves out (the
        description, the path, ``compare``), so the report follows the config file."""
        body = {k: v for k, v in config.items() if k != "path"}
        with self.conn:
            self.conn.execute(
                "INSERT INTO studies VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT(config_hash) DO UPDATE "
                "SET config_json = excluded.config_json, path = excluded.path",
                (h, config["name"], config.get("panel"), json.dumps(body, sort_keys=True),
                 config.get("path"), _now()),
            )

    def add_cell(self, cell: dict[str, Any], seed: int, result: dict[str, Any]) -> bool:
        """Write one finished cell (``result["status"]`` ``"ok"``, ``"timeout"`` or
        ``"failed"``) and its curve in one transaction, and clear the cell's rows of
        ``failures``; False (the failures cleared all the same) if it was there. A timed-out row of the same cell is replaced (a
        run with a larger time limit)."""
        s = cell["seeds"]
        status = result.get("status", "ok")
        with self.conn:
            self.conn.execute("DELETE FROM curves WHERE cell_id IN (SELECT id FROM cells WHERE "
                              "key = ? AND status = 'timeout')", (cell["key"],))
            self.conn.execute("DELETE FROM cells WHERE key = ? AND status = 'timeout'", (cell["key"],))
            cur = self.conn.execute(
                "INSERT OR IGNORE INTO cells (key, config_hash, study, value_index, value, trial, "
                "method, seed, seed_truth, seed_train, seed_test, seed_init, seed_fit, e_test, "
                "final_loss, modes, sigma_min, fit_wall_time, wall_time, settings_json, cell_json, "
                "warnings_json, host, finished, status, time_limit) "
                "VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (cell["key"], cell["config_hash"], cell["study"], cell["value_index"],
                 _real(cell["value"]), cell["trial"], cell["method"], seed, s["truth"], s["train"],
                 s["test"], s["init"], s["fit"], _real(result["e_test"]), _real(result["final_loss"]),
                 result["modes"], _real(result["sigma_min"]), _real(result["fit_wall_time"]),
                 result["wall_time"], json.dumps(result["settings"], sort_keys=True),
                 json.dumps(cell, sort_keys=True), json.dumps(result["warnings"]),
                 result["host"], _now(), status, _real(cell.get("time_limit"))),
            )
            self.conn.execute("DELETE FROM failures WHERE key = ?", (cell["key"],))
            if cur.rowcount == 0:
                return False
            records = [[r["iteration"], r["phase"], _real(r["loss"]), _real(r["e_test"]),
                        _real(r["eps"]), _real(r["lr"]), r["wall_time"], r["restart"]]
                       for r in result["curve"]]
            self.conn.execute("INSERT INTO curves VALUES (?, ?)", (cur.lastrowid, _pack(records)))
        return True

    def add_failure(self, cell: dict[str, Any], error: str) -> None:
        with self.conn:
            self.conn.execute(
                "INSERT INTO failures (key, config_hash, study, value_index, trial, method, error, at) "
                "VALUES (?,?,?,?,?,?,?,?)",
                (cell["key"], cell["config_hash"], cell["study"], cell["value_index"],
                 cell["trial"], cell["method"], error, _now()),
            )

    def add_job(self, key: str, study: str, function: str, result: dict[str, Any]) -> bool:
        """Write one finished job of a module study (one transaction); False if it was there.

        ``result`` is JSON-able besides numpy arrays and scalars (stored exactly); tuples come
        back as lists, dict keys keep their order, and floats round-trip exactly (``inf`` and
        ``nan`` included).
        """
        blob = zlib.compress(json.dumps(result, default=_encode).encode(), 6)
        with self.conn:
            cur = self.conn.execute("INSERT OR IGNORE INTO jobs VALUES (?, ?, ?, ?, ?)",
                                    (key, study, function, blob, _now()))
        return cur.rowcount == 1

    # -- reading ------------------------------------------------------------------------
    def finished_keys(self, time_limit: float | None = None) -> set[str]:
        """The keys of the cells a run under ``time_limit`` (s; None: no limit) need not run:
        every finished cell (``"ok"`` or ``"failed"``), and every timed-out one whose limit was
        at least ``time_limit``."""
        rows = self.conn.execute("SELECT key, status, time_limit FROM cells")
        return {k for k, status, limit in rows
                if status != "timeout" or (time_limit is not None and limit is not None
                                           and limit >= time_limit)}

    def studies(self) -> list[dict[str, Any]]:
        rows = self.conn.execute(
            "SELECT config_hash, name, panel, config_json, path, created FROM studies ORDER BY created, name")
        return [{"config_hash": h, "name": n, "panel": p, "config": json.loads(c), "path": path,
                 "created": t} for h, n, p, c, path, t in rows]

    def cells(self, keys: list[str]) -> dict[str, dict[str, Any]]:
        """The finished (also timed-out and failed) cells among ``keys``, by key (metrics, seeds, status,
        settings; no curves)."""
        cols = ("id", "key", "e_test", "final_loss", "modes", "sigma_min", "fit_wall_time",
                "wall_time", "seed_truth", "seed_init", "host", "warnings_json", "status",
                "time_limit", "settings_json")
        out: dict[str, dict[str, Any]] = {}
        for i in range(0, len(keys), 500):
            chunk = keys[i : i + 500]
            q = f"SELECT {', '.join(cols)} FROM cells WHERE key IN ({','.join('?' * len(chunk))})"
            for row in self.conn.execute(q, chunk):
                out[row[1]] = dict(zip(cols, row, strict=True))
        return out

    def curve(self, cell_id: int) -> list[dict[str, Any]]:
        """The fit history of cell ``cell_id`` (``cells.id``): one dict per record."""
        row = self.conn.execute("SELECT data FROM curves WHERE cell_id = ?", (cell_id,)).fetchone()
        if row is None:
            return []
        return [dict(zip(CURVE_FIELDS, r, strict=True)) for r in json.loads(zlib.decompress(row[0]))]

    def jobs(self, keys: list[str]) -> dict[str, dict[str, Any]]:
        """The finished jobs among ``keys``: ``{key: result}`` as :meth:`add_job` wrote them."""
        out: dict[str, dict[str, Any]] = {}
        for i in range(0, len(keys), 500):
            chunk = keys[i : i + 500]
            q = f"SELECT key, result FROM jobs WHERE key IN ({','.join('?' * len(chunk))})"
            for key, blob in self.conn.execute(q, chunk):
                out[key] = json.loads(zlib.decompress(blob), object_hook=_decode)
        return out

    def failures(self, config_hash: str) -> list[dict[str, Any]]:
        """The logged failures of study ``config_hash``, oldest first: ``{key, value_index,
        trial, method, error (the traceback), at}`` (a cell stored since has none left)."""
        cols = ("key", "value_index", "trial", "method", "error", "at")
        rows = self.conn.execute(
            f"SELECT {', '.join(cols)} FROM failures WHERE config_hash = ? ORDER BY id", (config_hash,))
        return [dict(zip(cols, r, strict=True)) for r in rows]
