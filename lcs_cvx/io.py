r"""Model files: an :class:`lcs_cvx.LCS` (or a :class:`lcs_cvx.RigidBodyContact`, see the end) saved
to, and rebuilt from, one ``.npz`` (no pickle).

The file holds the learnable parameters exactly as they are stored in the model, so a round
trip is bit-exact (same values, same dtype) and training continues from the same
parameterisation ``F = G G^T + H - H^T + s I`` (paper Sec. 5):

=============  ===================  =====================================================
array          shape                meaning
=============  ===================  =====================================================
``A``          ``(n_x, n_x)``       ``x' = A x + B u + C lam + d``  (eq. (1))
``B``          ``(n_x, n_u)``
``C``          ``(n_x, n_lam)``
``d``          ``(n_x,)``
``D``          ``(n_lam, n_x)``     ``0 <= lam _|_ D x + E u + F lam + c >= 0``
``E``          ``(n_lam, n_u)``
``G``, ``H``   ``(n_lam, n_lam)``   learnable factors of ``F``
``c``          ``(n_lam,)``
``stiffness``  ``()``               ``s`` (the model's buffer)
``F``          ``(n_lam, n_lam)``   derived, for readers without torch; checked on load
``meta``       ``()`` str           JSON, see :func:`load_metadata`
``mask_A``...  the parameter's      bool, one per masked parameter (:attr:`LCS.masks`;
               shape                ``meta["masks"]`` lists them)
=============  ===================  =====================================================

The known structure travels with the model: ``meta["fixed"]`` lists the fixed parameters
(loaded with ``requires_grad`` False) and the ``mask_*`` arrays the masks; a masked entry is held
at its stored value (format version 3: 0 for :meth:`~lcs_cvx.LCS.mask`, any value for
:meth:`~lcs_cvx.LCS.hold`; version 2 held masked entries at 0 only, and such files load as
before). Files of version 1 (no structure) load as models with every parameter learnable.
``meta["kinematics"]`` (version 4) is the model's :class:`lcs_cvx.Kinematics` as a JSON object
(:meth:`~lcs_cvx.Kinematics.to_dict`), or null.

All numeric arrays have the model's dtype (float32 or float64). The path is used exactly as
given: unlike ``np.savez``, no ``.npz`` is appended when it is missing.

A :class:`lcs_cvx.RigidBodyContact`'s file holds its parameters and buffers (``state_dict``) as
arrays ``param_<name>`` and ``meta`` with ``"kind": "rigid_body"``, its constructor's settings
(``"config"``) and the names of its learnable parameters (``"learnable"``); a round trip is
bit-exact too.
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Callable, Mapping
from typing import IO, Any

import numpy as np
import torch

from ._checks import LCSInputError
from ._version import __version__
from .kinematics import Kinematics
from .system import LCS, MASKABLE, PARAMETER_NAMES, parameter_shapes

__all__ = ["save_model", "load_model", "load_metadata", "atomic_write", "FORMAT", "FORMAT_VERSION"]

#: Value of ``meta["format"]`` in every model file.
FORMAT = "lcs_cvx.model"
#: Version of the file layout written by :func:`save_model`; files of a newer version are refused.
#: 2: the fixed parameters (``meta["fixed"]``) and masks (``mask_*`` arrays, ``meta["masks"]``).
#: 3: masked entries hold their stored values (:meth:`lcs_cvx.LCS.hold`), not only 0.
#: 4: the known kinematics (``meta["kinematics"]``).
FORMAT_VERSION = 4
#: Arrays every model file holds.
ARRAY_NAMES = PARAMETER_NAMES + ("stiffness", "F", "meta")

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


# -- writing ---------------------------------------------------------------------------------
def save_model(model: LCS, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None) -> None:
    """Write ``model`` to ``path`` as an ``.npz`` (see the module docstring for its arrays).

    Args:
        model: an :class:`lcs_cvx.LCS` (any device; the arrays are written from the CPU).
        path: the file to write, used exactly as given (no ``.npz`` is appended). Its
            directory must exist. The write is atomic: the arrays go to a temporary file in the
            same directory, which then replaces ``path`` (``os.replace``), so an interrupted
            save leaves either the old file or the new one, never a truncated one.
        metadata: optional JSON-serialisable dict (str keys; str, int, finite float, bool,
            None, list and dict values), e.g. the training settings; :func:`load_metadata`
            returns it under ``"metadata"`` as JSON reads it back (tuples become lists).

    Raises:
        LCSInputError: ``model`` is not an LCS, ``metadata`` is not a JSON-serialisable dict,
            or ``path`` is not a writable file in an existing directory.
    """
    from .rigid_body import RigidBodyContact

    if not isinstance(model, (LCS, RigidBodyContact)):
        raise LCSInputError(f"model: expected an lcs_cvx.LCS or lcs_cvx.RigidBodyContact, received "
                            f"{type(model).__name__}")
    if metadata is not None and not isinstance(metadata, Mapping):
        raise LCSInputError(
            f"metadata: expected a dict (or None), received {type(metadata).__name__}"
        )
    if isinstance(model, RigidBodyContact):
        _save_rigid_body(model, path, metadata)
        return
    dtype = str(model.dtype).removeprefix("torch.")
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "lcs_cvx_version": __version__,
        "n_x": model.n_x,
        "n_u": model.n_u,
        "n_lam": model.n_lam,
        "stiffness": float(model.stiffness),
        "dtype": dtype,
        "metadata": dict(metadata) if metadata is not None else {},
        "fixed": [k for k in PARAMETER_NAMES if not getattr(model, k).requires_grad],
        "masks": [k for k in MASKABLE if k in model.masks],
        "kinematics": None if model.kinematics is None else model.kinematics.to_dict(),
    }
    try:
        meta_json = json.dumps(meta, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise LCSInputError(
            "metadata: expected a JSON-serialisable dict (str keys; str, int, finite float, "
            f"bool, None, list and dict values), received one that is not: {exc}"
        ) from None
    with torch.no_grad():
        arrays = {k: getattr(model, k).detach().cpu().numpy() for k in PARAMETER_NAMES}
        arrays["stiffness"] = model.stiffness.detach().cpu().numpy()
        arrays["F"] = model.F.detach().cpu().numpy()
    arrays["meta"] = np.array(meta_json)
    arrays.update({f"mask_{k}": m.numpy() for k, m in model.masks.items()})
    atomic_write(path, lambda f: np.savez(f, **arrays))


def atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], Any], *, name: str = "path") -> None:
    """Write the file ``path`` atomically: ``write(f)`` writes the bytes into ``f``, an open
    binary temporary file in ``path``'s directory (e.g. ``np.savez(f, ...)``, which appends no
    ``.npz`` to a file object, or ``torch.save(obj, f)``), which is then flushed to disk and
    moved onto ``path`` (``os.replace``). An interrupted write leaves the old file or the new
    one, never a truncated one; the temporary file is removed on any error.

    ``name`` is the argument named in error messages (a directory, a missing directory, an
    unwritable place: :class:`LCSInputError`).
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise LCSInputError(f"{name}: expected a file path, received {path!r} (a directory)")
    if not os.path.isdir(directory):
        raise LCSInputError(
            f"{name}: expected a file in an existing directory, received {path!r} "
            f"(directory {directory!r} not found)"
        )
    tmp = os.path.join(directory, f".{os.path.basename(path)}.{secrets.token_hex(6)}.tmp")
    try:
        # os.open with mode 0o666 applies the umask, as open(path, "wb") would
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as exc:
        raise LCSInputError(f"{name}: could not write {path!r}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# -- reading ---------------------------------------------------------------------------------
def load_model(path: str | os.PathLike) -> LCS:
    """Rebuild the :class:`lcs_cvx.LCS` written by :func:`save_model`, bit-exactly.

    The parameters get the stored values and dtype (on the CPU; they require grad, as in a new
    ``LCS``, so training can continue, except the fixed ones), and the stored masks. The global
    torch random state is not touched.

    Raises:
        LCSInputError: the file is missing or not an ``.npz``, lacks an array, has an array of
            the wrong shape or dtype for the dimensions in its metadata, holds non-finite
            values, a stored ``F`` that does not match ``G``, ``H`` and ``stiffness``, a
            mask that is not a bool array of its parameter's shape, or was written in a newer
            format version.
    """
    rigid = _read_rigid_body(path)
    if rigid is not None:
        return rigid
    path_s, arrays, meta = _read(path)
    model = LCS(
        meta["n_x"],
        meta["n_u"],
        meta["n_lam"],
        stiffness=float(arrays["stiffness"]),
        init_scale=0.0,
        seed=0,  # a fixed seed: loading must not advance the global generator
        dtype=_DTYPES[meta["dtype"]],
    )
    with torch.no_grad():
        for name in PARAMETER_NAMES:
            getattr(model, name).copy_(torch.from_numpy(arrays[name]))
        model.stiffness.copy_(torch.from_numpy(arrays["stiffness"]))
        F = model.F.numpy()
    tol = 1e-5 if meta["dtype"] == "float32" else 1e-12
    scale = 1.0 + float(np.abs(F).max(initial=0.0))
    diff = float(np.abs(F - arrays["F"]).max(initial=0.0))
    if not diff <= tol * scale:
        raise LCSInputError(
            f"path: array 'F' in {path_s!r}: expected G G^T + H - H^T + s I of the stored G, H "
            f"and stiffness, received one that differs by {diff:.3g} (F is derived: change G, H "
            "or stiffness instead)"
        )
    masks = {k: torch.from_numpy(arrays[f"mask_{k}"]) for k in meta["masks"]}
    if masks:
        model.replace_masks(masks, zero=False)  # held at the stored values
    for name in meta["fixed"]:
        getattr(model, name).requires_grad_(False)
    if meta.get("kinematics") is not None:
        try:
            model.with_kinematics(Kinematics.from_dict(meta["kinematics"]))
        except (LCSInputError, TypeError) as exc:
            raise LCSInputError(f"path: 'kinematics' in {path_s!r}: {exc}") from None
    return model


def load_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The metadata of a model file (the file is fully validated, as by :func:`load_model`).

    Returns a dict with keys ``"format"`` (``"lcs_cvx.model"``), ``"format_version"``,
    ``"lcs_cvx_version"`` (the package that wrote it), ``"n_x"``, ``"n_u"``, ``"n_lam"``,
    ``"stiffness"``, ``"dtype"`` (``"float32"`` or ``"float64"``), ``"metadata"`` (the
    user's dict given to :func:`save_model`; ``{}`` if none), ``"fixed"`` and ``"masks"``
    (the names of the fixed and of the masked parameters; ``[]`` in version-1 files) and
    ``"kinematics"`` (:meth:`lcs_cvx.Kinematics.to_dict`'s dict, or None; None before version 4).
    A :class:`lcs_cvx.RigidBodyContact`'s file has ``"kind": "rigid_body"``, its ``"config"``
    (:meth:`~lcs_cvx.RigidBodyContact.config`), ``"learnable"`` and ``"metadata"`` instead.
    """
    rigid = _rigid_body_meta(path)
    return rigid[1] if rigid is not None else _read(path)[2]


def read_npz(path: str, expected: str) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file at ``path``, read in full with the file closed again
    (also when it is truncated or not an ``.npz``: then an :class:`LCSInputError` naming
    ``path``, the ``expected`` file and what went wrong). No pickles."""
    not_npz = f"path: expected {expected}, received {path!r}"
    try:
        with open(path, "rb") as fh:
            f = np.load(fh, allow_pickle=False)
            if not isinstance(f, np.lib.npyio.NpzFile):  # np.load also opens .npy files
                raise LCSInputError(f"{not_npz} (a single .npy array)")
            with f:
                return {k: f[k] for k in f.files}
    except LCSInputError:
        raise
    except Exception as exc:  # a damaged file fails in many ways, all named here:
        # BadZipFile, EOFError, ValueError (a bad .npy header), OSError; from flipped bytes
        # also NotImplementedError (an unknown compression method), RuntimeError ("encrypted")
        raise LCSInputError(f"{not_npz} (could not read it: {type(exc).__name__}: {exc})") from None


def _read(path: str | os.PathLike) -> tuple[str, dict[str, np.ndarray], dict[str, Any]]:
    """Open, parse and validate a model file; return ``(path, arrays, meta)``."""
    path_s = os.fspath(path)
    if not os.path.isfile(path_s):
        what = "a directory" if os.path.isdir(path_s) else "not found"
        raise LCSInputError(f"path: expected an existing model file (.npz), received {path_s!r} ({what})")
    arrays = read_npz(path_s, "an .npz model file written by lcs_cvx.save_model")

    if "meta" not in arrays:
        hint = " -- a data set?" if {"x", "u", "x_next"} <= set(arrays) else ""
        raise LCSInputError(
            f"path: expected an lcs_cvx model file with a 'meta' array, received {path_s!r} "
            f"with arrays {sorted(arrays)}{hint}"
        )
    meta = _parse_meta(path_s, arrays["meta"])  # the version first: a newer layout may differ
    missing = [k for k in ARRAY_NAMES if k not in arrays]
    if missing:
        raise LCSInputError(
            f"path: expected arrays {list(ARRAY_NAMES)} in {path_s!r}, missing {missing} "
            f"(found {sorted(arrays)})"
        )

    dims = {"n_x": meta["n_x"], "n_u": meta["n_u"], "n_lam": meta["n_lam"]}
    dims_text = ", ".join(f"{k}={v}" for k, v in dims.items())
    expected = parameter_shapes(meta["n_x"], meta["n_u"], meta["n_lam"])
    expected["stiffness"] = ()
    dtype = np.dtype(meta["dtype"])
    for name in PARAMETER_NAMES + ("stiffness", "F"):
        a = arrays[name]
        where = f"path: array {name!r} in {path_s!r}"
        if a.shape != expected[name]:
            raise LCSInputError(
                f"{where}: expected shape {expected[name]} ({dims_text} from its metadata), "
                f"received {a.shape}"
            )
        if a.dtype != dtype:
            raise LCSInputError(
                f"{where}: expected dtype {dtype} (from its metadata), received {a.dtype}"
            )
        if not np.isfinite(a).all():
            raise LCSInputError(
                f"{where}: expected finite values, received {int((~np.isfinite(a)).sum())} NaN/inf entries"
            )
    s = float(arrays["stiffness"])
    if not s > 0:
        raise LCSInputError(f"path: array 'stiffness' in {path_s!r}: expected a number > 0, received {s!r}")
    for name in meta["masks"]:
        where = f"path: array 'mask_{name}' in {path_s!r}"
        m = arrays.get(f"mask_{name}")
        if m is None:
            raise LCSInputError(f"{where}: expected it (meta lists {name!r} as masked), missing")
        if m.dtype != np.bool_ or m.shape != expected[name]:
            raise LCSInputError(
                f"{where}: expected a bool array of shape {expected[name]}, received shape "
                f"{m.shape} and dtype {m.dtype}"
            )
        if meta["format_version"] < 3 and (arrays[name][~m] != 0).any():  # version 2: masks hold 0
            raise LCSInputError(f"{where}: expected {name} to be 0 where the mask is False (format version "
                                f"{meta['format_version']}), received {int((arrays[name][~m] != 0).sum())} "
                                "nonzero entries there")
    return path_s, arrays, meta


def _parse_meta(path_s: str, raw: np.ndarray) -> dict[str, Any]:
    where = f"path: array 'meta' in {path_s!r}"
    if raw.dtype.kind != "U" or raw.shape != ():
        raise LCSInputError(
            f"{where}: expected a JSON string (0-d unicode array), received shape {raw.shape} "
            f"and dtype {raw.dtype}"
        )
    try:
        meta = json.loads(str(raw))
    except ValueError as exc:
        raise LCSInputError(f"{where}: expected valid JSON, received text that is not ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise LCSInputError(f"{where}: expected a JSON object with format {FORMAT!r}, received {str(raw)[:80]!r}")
    version = meta.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise LCSInputError(f"{where}: expected an integer format_version >= 1, received {version!r}")
    if version > FORMAT_VERSION:
        raise LCSInputError(
            f"path: expected a model file of format version <= {FORMAT_VERSION}, received version "
            f"{version} in {path_s!r} (written by lcs_cvx {meta.get('lcs_cvx_version', '?')}); "
            "upgrade lcs_cvx to read it"
        )
    for key, low in (("n_x", 1), ("n_u", 0), ("n_lam", 1)):
        v = meta.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise LCSInputError(f"{where}: expected {key} an integer >= {low}, received {v!r}")
    if meta.get("dtype") not in _DTYPES:
        raise LCSInputError(
            f"{where}: expected dtype one of {sorted(_DTYPES)}, received {meta.get('dtype')!r}"
        )
    if not isinstance(meta.get("metadata", {}), dict):
        raise LCSInputError(f"{where}: expected 'metadata' a JSON object, received {meta['metadata']!r}")
    meta.setdefault("metadata", {})
    meta.setdefault("kinematics", None)
    for key, allowed in (("fixed", PARAMETER_NAMES), ("masks", MASKABLE)):  # version 1: none
        names = meta.setdefault(key, [])
        if not isinstance(names, list) or not all(n in allowed for n in names) \
                or len(set(names)) != len(names):
            raise LCSInputError(
                f"{where}: expected {key!r} a list of distinct names among {allowed}, received "
                f"{names!r}"
            )
    return meta



# -- a rigid body's contact model --------------------------------------------------------------
#: ``meta["kind"]`` of a :class:`lcs_cvx.RigidBodyContact` file: its ``config()`` in ``meta["config"]``,
#: its parameters and buffers (``state_dict``) as arrays ``param_<name>``, which parameters it
#: learns in ``meta["learnable"]``.
RIGID_BODY = "rigid_body"


def _save_rigid_body(model: Any, path: str | os.PathLike, metadata: Mapping[str, Any] | None) -> None:
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "lcs_cvx_version": __version__,
            "kind": RIGID_BODY, "config": model.config(),
            "learnable": [k for k, p in model.named_parameters() if p.requires_grad],
            "metadata": dict(metadata) if metadata is not None else {}}
    try:
        meta_json = json.dumps(meta, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise LCSInputError(f"metadata: expected a JSON-serialisable dict, received one that is not: {exc}") from None
    arrays = {f"param_{k}": v.detach().cpu().numpy() for k, v in model.state_dict().items()}
    arrays["meta"] = np.array(meta_json)
    atomic_write(path, lambda f: np.savez(f, **arrays))


def _rigid_body_meta(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """``(arrays, meta)`` of a rigid body's model file; None for any other file (:func:`_read`
    then reads it, or names what is wrong with it)."""
    path_s = os.fspath(path)
    if not os.path.isfile(path_s):
        return None
    arrays = read_npz(path_s, "an .npz model file written by lcs_cvx.save_model")
    raw = arrays.get("meta")
    if raw is None or raw.dtype.kind != "U" or raw.shape != ():
        return None
    try:
        meta = json.loads(str(raw))
    except ValueError:
        return None
    if not isinstance(meta, dict) or meta.get("kind") != RIGID_BODY or meta.get("format") != FORMAT:
        return None
    version = meta.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise LCSInputError(f"path: expected a model file of format version <= {FORMAT_VERSION}, received "
                            f"version {version!r} in {path_s!r}; upgrade lcs_cvx to read it")
    return arrays, meta


def _read_rigid_body(path: str | os.PathLike) -> Any:
    """The :class:`lcs_cvx.RigidBodyContact` of a rigid body's file, None for another file."""
    found = _rigid_body_meta(path)
    if found is None:
        return None
    arrays, meta = found
    path_s = os.fspath(path)
    from .rigid_body import RigidBodyContact

    try:
        model = RigidBodyContact.from_config(meta["config"])
        state = {k.removeprefix("param_"): torch.from_numpy(v) for k, v in arrays.items() if k.startswith("param_")}
        for k, v in state.items():
            if not np.isfinite(v.numpy()).all():
                raise LCSInputError(f"array 'param_{k}' holds non-finite values")
        model.load_state_dict(state)
    except (LCSInputError, KeyError, TypeError, RuntimeError) as exc:
        raise LCSInputError(f"path: expected a rigid body's model file, received {path_s!r} ({exc})") from None
    for k, p in model.named_parameters():
        p.requires_grad_(k in meta["learnable"])
    return model
