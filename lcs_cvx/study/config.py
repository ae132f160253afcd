"""Study configurations: one TOML file per study (``studies/configs/``), read and checked here.

A *grid* study (``kind = "grid"``, the default) is the grid swept value x trial x method of the
paper's Fig. 1 (Sec. 5.1, panels (a)-(e)). Its keys::

    name = "fig1a_n_lam"            # required; names the study in the database and the report
    panel = "a"                     # optional: the Fig. 1 panel (selects studies/anchors.toml rows)
    description = "..."             # optional, free text (not part of the config hash)
    extends = "fig1a_n_lam.toml"    # optional: start from another config (path relative to this
                                    # file); tables are merged key by key, other values replaced
    seed = 0                        # root of every seed (see lcs_cvx.study.cells.cell_seeds)
    trials = 30                     # training rounds per swept value
    methods = ["prediction", "violation"]    # methods trained at every swept value
    reference_methods = []          # methods trained once per trial, independent of the value
                                    # (needs sweep.shared_truth: a fit-option sweep)
    recipe = "paper"                # lcs_cvx.fit's recipe: "paper" or "best"
    time_limit = 3600               # optional: seconds per cell; a cell still running then is
                                    # killed and recorded as timed out (lcs_cvx.study.limits)
    method_trials = { parc = 3 }    # optional: fewer trials for a method (its first n trials)
    compare = "fig1a_n_lam"         # optional: the study this one is reported beside (its e_test
                                    # and fit time per swept value, when it is in the same
                                    # database; lcs_cvx.study.report); not part of the config hash
    convention = "paper"            # "authors": gamma, eps (and reg for the violation loss) are
                                    # given in the authors' code's scaling and converted
    [sweep]   param = "system.n_lam", values = [...], shared_truth = false, label = "n_lam"
    [system]  n_x, n_u, n_lam, stiffness = 0.5, g_scale = 1.0       (the ground truth, random_lcs)
    [data]    n_train, n_test = 1000, noise = 0.01, x_scale = 10.0, u_scale = 5.0
    [learner] stiffness = 1.0, init_scale = 0.1                     (lcs_cvx.LCS)
    [fit]     any flat option of lcs_cvx.fit (lcs_cvx.train.FLAT_OPTIONS) but loss, recipe and seed; a value may be a table
              keyed by method ([fit.lr] prediction = 1e-3, violation = 5e-3). Sub-tables
              [fit.paper] / [fit.best] hold options used only under that recipe.
    [baselines.<name>]  options of a baseline method (lcs_cvx.study.baselines.OPTIONS)

A method is a loss (``"prediction"``, ``"violation"``: :func:`lcs_cvx.fit` with the config's
``recipe``), a loss with its own recipe (``"violation@best"``: ``[fit.best]`` and per-method
values keyed ``"violation@best"``, else ``"violation"``, apply to it), or a baseline
(``"affine"``, ``"mlp"``, ``"parc"``: :mod:`lcs_cvx.study.baselines`).

A *module* study (``kind = "module"``, ``module = "dotted.path"``) is run by that module's
``run_study(config: dict, out_dir: str, workers: int) -> None`` (called with a ``scheduler=``
keyword as well when ``lcs-cvx study run`` is given ``--scheduler``); its other keys are the
module's.

Every error is an :class:`lcs_cvx.LCSInputError` naming the file and the key.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import tomllib
from typing import Any

from .._checks import LCSInputError
from ..train.phase_options import LOSSES
from ..train.recipes import FLAT_OPTIONS, RECIPES, VIOLATION_ONLY, resolve_options
from .baselines import BASELINES, baseline_options

__all__ = ["load_config", "config_hash", "fit_options", "method_parts", "CONVENTIONS", "SWEEPABLE"]

CONVENTIONS = ("paper", "authors")
KINDS = ("grid", "module")
#: Options a config may not set: the method sets ``loss``, ``recipe`` is a top-level key and the
#: seed of the minibatch order is derived per cell.
_FIT_RESERVED = ("loss", "recipe", "seed")
_FIT_KEYS = tuple(k for k in FLAT_OPTIONS if k not in _FIT_RESERVED)

#: Recipe options the prediction loss cannot take, and what it gets instead
#: (:data:`lcs_cvx.train.recipes.VIOLATION_ONLY`): written into a prediction cell's options, so
#: part of its key.
_VIOLATION_ONLY = VIOLATION_ONLY

_TOP = {"name", "panel", "description", "kind", "module", "extends", "seed", "trials", "methods",
        "reference_methods", "recipe", "convention", "sweep", "system", "data", "learner", "fit",
        "time_limit", "method_trials", "baselines", "compare"}
#: ``"violation@best"``: the loss, the separator, the recipe.
RECIPE_SEP = "@"
# section -> {key: (default or REQUIRED, check)}
_REQUIRED = object()


def _int(lo: int):
    def check(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= lo
    check.expected = f"an integer >= {lo}"  # type: ignore[attr-defined]
    return check


def _num(lo: float, strict: bool):
    def check(v: Any) -> bool:
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        return ok and (v > lo if strict else v >= lo)
    check.expected = f"a finite number {'>' if strict else '>='} {lo:g}"  # type: ignore[attr-defined]
    return check


_SECTIONS: dict[str, dict[str, tuple[Any, Any]]] = {
    "system": {"n_x": (_REQUIRED, _int(1)), "n_u": (_REQUIRED, _int(0)),
               "n_lam": (_REQUIRED, _int(1)), "stiffness": (0.5, _num(0, True)),
               "g_scale": (1.0, _num(0, False))},
    "data": {"n_train": (_REQUIRED, _int(1)), "n_test": (1000, _int(1)),
             "noise": (0.01, _num(0, False)), "x_scale": (10.0, _num(0, True)),
             "u_scale": (5.0, _num(0, True))},
    "learner": {"stiffness": (1.0, _num(0, True)), "init_scale": (0.1, _num(0, False))},
}
#: Sweepable parameters: every key of the sections above and every fit option.
SWEEPABLE = tuple(f"{s}.{k}" for s, keys in _SECTIONS.items() for k in keys) + tuple(
    f"fit.{k}" for k in _FIT_KEYS
)


def _fail(where: str, key: str, message: str) -> LCSInputError:
    return LCSInputError(f"{where}: {key}: {message}")


def read_toml(path: str, missing: str) -> dict[str, Any]:
    """The TOML file at ``path``; ``LCSInputError`` ``"{path}: {missing}"`` if it does not exist,
    and one naming the file if it does not parse."""
    if not os.path.isfile(path):
        raise LCSInputError(f"{path}: {missing}")
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise LCSInputError(f"{path}: not valid TOML: {exc}") from None


def _read_toml(path: str, chain: tuple[str, ...] = ()) -> dict[str, Any]:
    """The TOML at ``path`` with its ``extends`` chain merged in (cycles refused)."""
    where = f" (extended by {chain[-1]!r})" if chain else ""
    raw = read_toml(path, f"config file not found{where}")
    base = raw.pop("extends", None)
    if base is None:
        return raw
    if not isinstance(base, str):
        raise _fail(path, "extends", f"expected a file name, received {base!r}")
    base_path = os.path.normpath(os.path.join(os.path.dirname(path), base))
    if os.path.abspath(base_path) in (*map(os.path.abspath, chain), os.path.abspath(path)):
        raise _fail(path, "extends", f"circular: {base_path!r} extends back to this file")
    return _merge(_read_toml(base_path, (*chain, path)), raw)


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _check_keys(where: str, prefix: str, table: Any, allowed: Any) -> None:
    if not isinstance(table, dict):
        raise _fail(where, prefix.rstrip("."), f"expected a table, received {table!r}")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise _fail(where, prefix + unknown[0],
                    f"unknown key; expected one of {sorted(allowed)}")


def method_parts(method: str, recipe: str | None) -> tuple[str, str | None]:
    """``(loss, recipe)`` of an LCS method -- ``"violation"`` -> ``("violation", recipe)``,
    ``"violation@best"`` -> ``("violation", "best")`` -- and ``(name, None)`` of a baseline."""
    if method in BASELINES:
        return method, None
    loss, sep, own = method.partition(RECIPE_SEP)
    return loss, (own if sep else recipe)


def _is_method(m: Any) -> bool:
    if not isinstance(m, str):
        return False
    loss, sep, recipe = m.partition(RECIPE_SEP)
    return m in BASELINES or (loss in LOSSES and (not sep or recipe in RECIPES))


def _method_list(where: str, key: str, v: Any, allow_empty: bool) -> list[str]:
    if not isinstance(v, list) or (not v and not allow_empty) or not all(map(_is_method, v)) \
            or len(set(v)) != len(v):
        raise _fail(where, key, f"expected a list of distinct methods: a loss {LOSSES}, a loss "
                    f"with a recipe ('violation{RECIPE_SEP}best', recipes {tuple(RECIPES)}) or a "
                    f"baseline {BASELINES}; received {v!r}")
    return list(v)


def _choice(where: str, key: str, v: Any, allowed: tuple) -> Any:
    if v not in allowed:
        raise _fail(where, key, f"expected one of {allowed}, received {v!r}")
    return v


def _section(where: str, name: str, raw: dict, swept: str | None) -> dict[str, Any]:
    table = raw.get(name, {})
    _check_keys(where, f"{name}.", table, _SECTIONS[name])
    out = {}
    for key, (default, check) in _SECTIONS[name].items():
        full = f"{name}.{key}"
        if full == swept:
            if key in table:
                raise _fail(where, full, "is set by sweep.param; remove it here")
            continue
        if key not in table:
            if default is _REQUIRED:
                raise _fail(where, full, "required key is missing")
            out[key] = default
        elif not check(table[key]):
            raise _fail(where, full, f"expected {check.expected}, received {table[key]!r}")
        else:
            out[key] = table[key]
    return out


def _fit_section(where: str, raw: dict, swept: str | None, methods: list[str]) -> dict[str, Any]:
    table = raw.get("fit", {})
    _check_keys(where, "fit.", table, (*_FIT_KEYS, *RECIPES))
    for r in RECIPES:
        if r in table:
            _check_keys(where, f"fit.{r}.", table[r], _FIT_KEYS)
    for prefix, tab in [("fit.", table)] + [(f"fit.{r}.", table[r]) for r in RECIPES if r in table]:
        for key, v in tab.items():
            if key in RECIPES and prefix == "fit.":
                continue
            if f"fit.{key}" == swept:
                raise _fail(where, prefix + key, "is set by sweep.param; remove it here")
            if isinstance(v, dict):
                _check_keys(where, f"{prefix}{key}.", v,
                            (*LOSSES, *(m for m in methods if RECIPE_SEP in m)))
    return copy.deepcopy(table)


def _sweep(where: str, raw: dict) -> dict[str, Any]:
    sw = raw.get("sweep")
    if sw is None:
        raise _fail(where, "sweep", "required table is missing (param, values)")
    _check_keys(where, "sweep.", sw, ("param", "values", "shared_truth", "label"))
    param = sw.get("param")
    if param not in SWEEPABLE:
        raise _fail(where, "sweep.param", f"expected one of {list(SWEEPABLE)}, received {param!r}")
    values = sw.get("values")
    if not isinstance(values, list) or not values or len(set(values)) != len(values) or any(
        isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in values
    ):
        raise _fail(where, "sweep.values", f"expected a non-empty list of distinct numbers, received {values!r}")
    shared = sw.get("shared_truth", False)
    if not isinstance(shared, bool):
        raise _fail(where, "sweep.shared_truth", f"expected true or false, received {shared!r}")
    if shared and not param.startswith("fit."):
        raise _fail(where, "sweep.shared_truth",
                    f"true needs a fit-option sweep (the truth and data cannot depend on it); "
                    f"sweep.param is {param!r}")
    label = sw.get("label", param.split(".", 1)[1])
    if not isinstance(label, str):
        raise _fail(where, "sweep.label", f"expected a string, received {label!r}")
    return {"param": param, "values": list(values), "shared_truth": shared, "label": label}


def fit_options(config: dict[str, Any], method: str, value: Any = None) -> dict[str, Any]:
    """The explicit options passed to :func:`lcs_cvx.fit` for one ``method`` (and swept ``value``,
    None for a reference cell): ``[fit]``, then ``[fit.<recipe>]``, then the sweep, with per-method
    tables picked and the ``"authors"`` convention converted; the seed is added per cell.

    The authors' code writes the violation loss without the 1/2 factors,
    ``|e_dyn|^2 + (1/eps')(lam.phi + |w - phi|^2 / gamma')``: twice eq. (9) with
    ``eps = 2 eps'`` and ``gamma = gamma' / 2``; their ``omega'`` then weighs half as much:
    ``reg = omega' / 2``. The prediction loss is passed unchanged.

    Under a recipe with violation-only parts (``"best"``: Gauss--Newton refinement, extra units),
    the prediction loss gets ``refine = None`` and ``extra_units = 0`` unless the config says.
    """
    loss, recipe = method_parts(method, config["recipe"])
    if recipe is None:
        raise LCSInputError(f"method: {method!r} is a baseline; it takes no lcs_cvx.fit options")
    table = config["fit"]
    opts = {k: v for k, v in table.items() if k not in RECIPES}
    opts.update(table.get(recipe, {}))
    sweep = config["sweep"]
    if value is not None and sweep["param"].startswith("fit."):
        opts[sweep["param"][4:]] = value
    # a per-method table: the value for the method's full name, else for its loss, else unset
    picked = {}
    for k, v in opts.items():
        if not isinstance(v, dict):
            picked[k] = v
        elif method in v or loss in v:
            picked[k] = v[method] if method in v else v[loss]
    opts = picked
    for k, v in opts.items():  # TOML arrays -> the tuples FitOptions expects
        if isinstance(v, list):
            opts[k] = tuple(v)
    if loss == "violation" and config["convention"] == "authors":
        for k, factor in (("eps", 2.0), ("eps_start", 2.0), ("gamma", 0.5), ("reg", 0.5)):
            if opts.get(k) is not None:
                opts[k] = opts[k] * factor
    if loss == "prediction":  # drop the recipe's violation-only parts (see _VIOLATION_ONLY)
        flat = RECIPES[recipe].flat()
        opts.update({k: v for k, v in _VIOLATION_ONLY.items()
                     if k in _FIT_KEYS and flat.get(k) and k not in opts})
    return {**opts, "loss": loss}


def _check_fit(where: str, config: dict[str, Any]) -> None:
    """Resolve every method's options once, so a bad value fails at load time, not in a worker."""
    values = config["sweep"]["values"] if config["sweep"]["param"].startswith("fit.") else [None]
    cases = [(m, v) for m in config["methods"] for v in values]
    cases += [(m, None) for m in config["reference_methods"]]
    two_s = 2.0 * config["learner"]["stiffness"]
    for method, value in cases:
        loss, recipe = method_parts(method, config["recipe"])
        if recipe is None:  # a baseline: its options are checked by _baselines
            continue
        opts = fit_options(config, method, value)
        try:
            settings = resolve_options(recipe, **opts)
        except TypeError:  # a comparison with a value of the wrong type: find the option
            for key, v in opts.items():
                try:
                    resolve_options(None, **{key: v})
                except TypeError:
                    raise _fail(where, f"fit.{key}", f"invalid value {v!r}") from None
                except LCSInputError:
                    pass
            raise
        except LCSInputError as exc:
            key = str(exc).split(":", 1)[0]
            swept = config["sweep"]["param"] == f"fit.{key}"
            raise _fail(where, "sweep.values" if swept else f"fit.{key}",
                        f"{str(exc).split(':', 1)[-1].strip()} (method {method!r})") from None
        if loss == "violation" and not settings.objective.gamma < two_s:
            # sigma_min(F + F^T) of the learner is >= 2 s for every G, H (Sec. 5); Lemma 2
            raise _fail(where, "fit.gamma", f"expected gamma < 2 * learner.stiffness = {two_s:g} "
                        f"(Lemma 2: gamma < sigma_min(F + F^T)), received {settings.objective.gamma:g}")


def _limits(where: str, raw: dict, cfg: dict[str, Any]) -> None:
    """``time_limit``, ``method_trials`` and ``[baselines]`` into ``cfg``, each only when it
    applies (a config without them keeps the hash it had before they existed)."""
    limit = raw.get("time_limit")
    if limit is not None:
        if not _num(0, True)(limit):
            raise _fail(where, "time_limit", f"expected a number of seconds > 0, received {limit!r}")
        cfg["time_limit"] = limit
    trials = raw.get("method_trials")
    every = cfg["methods"] + cfg["reference_methods"]
    if trials is not None:  # a method this config does not run is allowed (a config it extends may)
        if not isinstance(trials, dict):
            raise _fail(where, "method_trials", f"expected a table method = trials, received {trials!r}")
        for m, n in trials.items():
            if not _is_method(m):
                raise _fail(where, f"method_trials.{m}", "unknown method")
            if not _int(1)(n) or (m in every and n > cfg["trials"]):
                raise _fail(where, f"method_trials.{m}",
                            f"expected an integer in [1, trials = {cfg['trials']}], received {n!r}")
        used = {m: n for m, n in trials.items() if m in every}
        if used:
            cfg["method_trials"] = used
    table = raw.get("baselines", {})
    _check_keys(where, "baselines.", table, BASELINES)
    try:
        options = {m: baseline_options(m, table.get(m)) for m in BASELINES}
    except LCSInputError as exc:
        raise LCSInputError(f"{where}: {exc}") from None
    used_baselines = [m for m in every if m in BASELINES]
    if used_baselines:
        cfg["baselines"] = {m: options[m] for m in used_baselines}


def _compare(where: str, v: Any, name: str) -> str:
    """``compare``: the name of another study (a report shows it beside this one)."""
    if not isinstance(v, str) or not v or any(c in v for c in "/\\ "):
        raise _fail(where, "compare", f"expected the name of another study (a string without "
                    f"spaces or slashes), received {v!r}")
    if v == name:
        raise _fail(where, "compare", f"expected the name of another study, received this "
                    f"study's own name {v!r}")
    return v


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """Read, merge (``extends``), check and complete the config at ``path``.

    Returns a plain dict (JSON-able): the grid config with every default filled in, or, for
    ``kind = "module"``, the merged TOML as written. ``config["path"]`` is the file it came from.
    """
    where = os.fspath(path)
    raw = _read_toml(where)
    kind = _choice(where, "kind", raw.get("kind", "grid"), KINDS)
    name = raw.get("name")
    if not isinstance(name, str) or not name or any(c in name for c in "/\\ "):
        raise _fail(where, "name", f"expected a non-empty name without spaces or slashes, received {name!r}")
    if kind == "module":
        module = raw.get("module")
        if not isinstance(module, str) or not module:
            raise _fail(where, "module", f"expected a dotted module path, received {module!r}")
        return {**raw, "kind": "module", "path": where}
    _check_keys(where, "", raw, _TOP - {"module"})
    sweep = _sweep(where, raw)
    cfg: dict[str, Any] = {
        "name": name,
        "kind": "grid",
        "panel": raw.get("panel"),
        "description": raw.get("description", ""),
        "seed": raw.get("seed", 0),
        "trials": raw.get("trials"),
        "methods": _method_list(where, "methods", raw.get("methods"), allow_empty=False),
        "reference_methods": _method_list(where, "reference_methods",
                                          raw.get("reference_methods", []), allow_empty=True),
        "recipe": _choice(where, "recipe", raw.get("recipe", "paper"), tuple(RECIPES)),
        "convention": _choice(where, "convention", raw.get("convention", "paper"), CONVENTIONS),
        "sweep": sweep,
    }
    for key, check in (("seed", _int(0)), ("trials", _int(1))):
        if not check(cfg[key]) or cfg[key] >= 2**32:
            raise _fail(where, key, f"expected {check.expected} (and < 2**32), received {cfg[key]!r}")
    for key in ("panel", "description"):
        if cfg[key] is not None and not isinstance(cfg[key], str):
            raise _fail(where, key, f"expected a string, received {cfg[key]!r}")
    if cfg["reference_methods"] and not sweep["shared_truth"]:
        raise _fail(where, "reference_methods",
                    "needs sweep.shared_truth = true (a reference is trained once per trial, on "
                    "the truth and data every swept value of that trial shares)")
    clash = set(cfg["methods"]) & set(cfg["reference_methods"])
    if clash:
        raise _fail(where, "reference_methods", f"{sorted(clash)} also in methods")
    for name_ in _SECTIONS:
        cfg[name_] = _section(where, name_, raw, sweep["param"])
    cfg["fit"] = _fit_section(where, raw, sweep["param"], cfg["methods"] + cfg["reference_methods"])
    _limits(where, raw, cfg)
    if "compare" in raw:  # only when set: a config without it keeps its stored JSON
        cfg["compare"] = _compare(where, raw["compare"], name)
    swept_section, swept_key = sweep["param"].split(".", 1)
    if swept_section in _SECTIONS:
        check = _SECTIONS[swept_section][swept_key][1]
        bad = [v for v in sweep["values"] if not check(v)]
        if bad:
            raise _fail(where, "sweep.values", f"{sweep['param']}: expected {check.expected}, received {bad[0]!r}")
    _check_fit(where, cfg)
    cfg["path"] = where
    return cfg


def config_hash(config: dict[str, Any]) -> str:
    """16 hex digits of the SHA-256 of the config's canonical JSON (``description``, ``path`` and
    ``compare`` left out: they do not change any result)."""
    body = {k: v for k, v in config.items() if k not in ("description", "path", "compare")}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]
