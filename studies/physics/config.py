"""Reading the config of a physics study (a dict as TOML reads it): tables into dataclasses or
into dicts with defaults, unknown keys refused with the section and key named, and the ``[lcs]``
section both studies share.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["RUNNER_KEYS", "check_sections", "from_table", "section", "lcs_section"]

#: Keys the ``lcs-cvx study`` runner puts in a config besides the study's own sections.
RUNNER_KEYS = ("name", "kind", "module", "description", "path", "extends")
_LOSSES = ("violation", "prediction")


def check_sections(config: dict[str, Any], sections: tuple[str, ...]) -> None:
    """Refuse a top-level key that is neither one of ``sections`` nor a runner key."""
    unknown = sorted(set(config) - set(sections) - set(RUNNER_KEYS))
    if unknown:
        raise ValueError(f"config: {unknown[0]}: unknown key; expected sections {list(sections)}")


def from_table(cls: type, table: dict[str, Any] | None, where: str) -> Any:
    """Build the dataclass ``cls`` from a config table, refusing unknown keys (lists become
    tuples of floats)."""
    table = dict(table or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}; expected one of {sorted(names)}")
    for k, v in list(table.items()):
        if isinstance(v, list):
            table[k] = tuple(float(e) for e in v)
    return cls(**table)


def section(config: dict[str, Any], name: str, defaults: dict[str, Any]) -> dict[str, Any]:
    """The table ``[name]`` over ``defaults``, refusing keys that ``defaults`` lacks."""
    table = config.get(name, {})
    if not isinstance(table, dict):
        raise ValueError(f"config: [{name}] must be a table, received {table!r}")
    unknown = sorted(set(table) - set(defaults))
    if unknown:
        raise ValueError(f"config: {name}.{unknown[0]}: unknown key; expected one of {sorted(defaults)}")
    return {**defaults, **table}


def lcs_section(config: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    """The ``[lcs]`` table: ``n_lam``, ``seeds`` and ``losses`` non-empty lists of distinct
    values (each value is one training job: a repeat would be one too), losses among
    ``violation`` / ``prediction``, and per loss a table ``[lcs.<loss>]`` of :func:`lcs_cvx.fit`
    options merged key by key over ``defaults[loss]``. ``init`` (the starts of
    :func:`lcs_cvx.fit`, when the study has the key) may be one name or a list of them: each is
    one set of restarts."""
    lcs = section(config, "lcs", defaults)
    if isinstance(lcs.get("init"), str):
        lcs["init"] = [lcs["init"]]
    for key in ("n_lam", "seeds", "losses", "init"):
        if key not in lcs:
            continue
        v = lcs[key]
        if not isinstance(v, list) or not v or len(set(v)) != len(v):
            raise ValueError(f"config: lcs.{key}: expected a non-empty list of distinct values, "
                             f"received {v!r}")
    for loss in lcs["losses"]:
        if loss not in _LOSSES:
            raise ValueError(f"config: lcs.losses: expected 'violation' or 'prediction', received {loss!r}")
        given = config.get("lcs", {}).get(loss, {})
        if not isinstance(given, dict):
            raise ValueError(f"config: [lcs.{loss}] must be a table, received {given!r}")
        lcs[loss] = {**defaults[loss], **given}
    return lcs
