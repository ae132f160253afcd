"""The cells of the study reports' tables: e_test of stored cells, a statistic that is None
without data, a number as the tables print it, an anchor (authors') value of a swept value."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["e_tests", "stat", "fmt", "anchor"]


def e_tests(rows: list[dict[str, Any]]) -> list[float]:
    return [r["e_test"] for r in rows if r["e_test"] is not None]


def fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def stat(xs: list[float], f) -> float | None:
    return f(xs) if xs else None


def anchor(aset: dict[str, Any], value: float, metric: str) -> Any:
    for row in aset["rows"]:
        if math.isclose(float(row["value"]), float(value), rel_tol=1e-9) and metric in row:
            return row[metric]
    return None
