"""Model files (:mod:`lcs_cvx.io`): bit-exact round trips, metadata, atomic writes, one clear
error per kind of bad file; and :meth:`lcs_cvx.LCS.to_c3`, the export to the C3 convention."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx import LCS, LCSInputError, count_modes, load_metadata, load_model, save_model
from lcs_cvx.io import FORMAT_VERSION, atomic_write
from lcs_cvx.system import PARAMETER_NAMES

F64 = torch.float64


def _trained_like(dtype: torch.dtype = F64) -> LCS:
    """An LCS whose parameters are not what a fresh ``LCS(...)`` would draw (as after training)
    and whose stiffness is not a round number."""
    model = LCS(3, 2, 4, stiffness=0.3173, seed=11, dtype=dtype)
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(7.3).add_(0.01)
    return model


def _state_equal(a: LCS, b: LCS) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(
        sa[k].dtype == sb[k].dtype and torch.equal(sa[k], sb[k]) for k in sa
    )


def _rewrite(path, **changes) -> None:
    """Rewrite the model file at ``path`` with some arrays changed (None deletes one)."""
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    for k, v in changes.items():
        if v is None:
            del arrays[k]
        else:
            arrays[k] = v
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _meta(path) -> dict:
    with np.load(path) as f:
        return json.loads(str(f["meta"]))


# -- round trip ------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_round_trip_is_bit_exact(tmp_path, dtype):
    model = _trained_like(dtype)
    path = tmp_path / "model.npz"
    save_model(model, path)
    loaded = load_model(path)

    assert _state_equal(model, loaded)  # every parameter and the stiffness buffer, same dtype
    assert loaded.dtype == dtype
    assert (loaded.n_x, loaded.n_u, loaded.n_lam) == (3, 2, 4)
    assert torch.equal(loaded.F, model.F)
    # training continues from the same parameterisation: learnable, on the same G and H
    assert all(p.requires_grad for p in loaded.parameters())
    x = torch.linspace(-5, 5, 30, dtype=F64).reshape(10, 3).to(dtype)
    u = torch.linspace(-2, 2, 20, dtype=F64).reshape(10, 2).to(dtype)
    with torch.no_grad():
        assert torch.equal(loaded.step(x, u), model.step(x, u))


def test_round_trip_keeps_the_factors_of_F_not_a_refactorisation(tmp_path):
    truth = lcs_cvx.random_lcs(4, 2, 3, stiffness=0.5, seed=2)
    exported = LCS.from_matrices(**truth.to_matrices())  # G, H, s differ from truth's
    save_model(exported, tmp_path / "m.npz")
    loaded = load_model(tmp_path / "m.npz")
    for name in ("G", "H", "stiffness"):
        assert torch.equal(getattr(loaded, name), getattr(exported, name))
    assert not torch.equal(loaded.G, truth.G)


def test_stored_F_is_the_models_F(tmp_path):
    model = _trained_like()
    save_model(model, tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz", allow_pickle=False) as f:
        assert sorted(f.files) == sorted([*PARAMETER_NAMES, "stiffness", "F", "meta"])
        np.testing.assert_array_equal(f["F"], model.F.detach().numpy())
        np.testing.assert_array_equal(f["stiffness"], np.float64(0.3173))
        assert f["meta"].dtype.kind == "U"  # a JSON string, readable without pickle


def test_round_trip_without_inputs(tmp_path):
    model = LCS(2, 0, 1, seed=3)
    save_model(model, tmp_path / "m.npz")
    loaded = load_model(tmp_path / "m.npz")
    assert loaded.n_u == 0 and loaded.B.shape == (2, 0) and loaded.E.shape == (1, 0)
    assert _state_equal(model, loaded)


def test_loading_does_not_touch_the_global_generator(tmp_path):
    save_model(_trained_like(), tmp_path / "m.npz")
    state = torch.random.get_rng_state()
    load_model(tmp_path / "m.npz")
    assert torch.equal(torch.random.get_rng_state(), state)


@pytest.mark.parametrize("name", ["model", "model.npz", "model.bin"])
def test_path_is_used_as_given(tmp_path, name):
    save_model(_trained_like(), tmp_path / name)
    assert os.listdir(tmp_path) == [name]  # np.savez alone would write "model.npz" for "model"
    assert _state_equal(load_model(str(tmp_path / name)), _trained_like())


# -- metadata --------------------------------------------------------------------------------


def test_metadata(tmp_path):
    settings = {"loss": "violation", "lr": 1e-3, "betas": [0.9, 0.9], "nested": {"n": 3, "x": None}}
    model = _trained_like(torch.float32)
    save_model(model, tmp_path / "m.npz", metadata={"fit": settings})
    meta = load_metadata(tmp_path / "m.npz")
    assert meta == {
        "format": "lcs_cvx.model",
        "format_version": FORMAT_VERSION,
        "lcs_cvx_version": lcs_cvx.__version__,
        "n_x": 3,
        "n_u": 2,
        "n_lam": 4,
        "stiffness": float(torch.tensor(0.3173, dtype=torch.float32)),
        "dtype": "float32",
        "metadata": {"fit": settings},
        "fixed": [],
        "masks": [],
        "kinematics": None,
    }
    save_model(model, tmp_path / "plain.npz")
    assert load_metadata(tmp_path / "plain.npz")["metadata"] == {}


@pytest.mark.parametrize(
    "metadata",
    [{"when": object()}, {"lr": float("nan")}, {"x": np.float32(1.0)}],
    ids=["object", "nan", "numpy-scalar"],
)
def test_metadata_must_be_json(tmp_path, metadata):
    with pytest.raises(LCSInputError, match=r"^metadata: expected a JSON-serialisable dict"):
        save_model(_trained_like(), tmp_path / "m.npz", metadata=metadata)
    assert os.listdir(tmp_path) == []  # nothing written, not even a temporary file


def test_metadata_must_be_a_dict(tmp_path):
    with pytest.raises(LCSInputError, match=r"^metadata: expected a dict \(or None\), received list"):
        save_model(_trained_like(), tmp_path / "m.npz", metadata=[1, 2])


# -- atomic writes ---------------------------------------------------------------------------


def test_overwrite_leaves_no_temporary_files(tmp_path):
    path = tmp_path / "m.npz"
    save_model(LCS(2, 1, 2, seed=0), path)
    save_model(_trained_like(), path)
    assert os.listdir(tmp_path) == ["m.npz"]
    assert _state_equal(load_model(path), _trained_like())


def test_interrupted_save_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "m.npz"
    old = LCS(2, 1, 2, seed=0)
    save_model(old, path)

    def interrupted_savez(file, **arrays):
        file.write(b"PK\x03\x04 half a zip")  # a truncated archive, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr("lcs_cvx.io.np.savez", interrupted_savez)
    with pytest.raises(KeyboardInterrupt):
        save_model(_trained_like(), path)
    assert os.listdir(tmp_path) == ["m.npz"]
    assert _state_equal(load_model(path), old)


def test_atomic_write_any_writer_and_errors_naming_the_argument(tmp_path):
    """``atomic_write`` (model files, data sets, the CLI's outputs, training checkpoints) takes
    any writer of bytes, e.g. ``torch.save``; an error names the caller's argument."""
    path = tmp_path / "ckpt.pt"
    atomic_write(path, lambda f: torch.save({"step": 3}, f))
    assert os.listdir(tmp_path) == ["ckpt.pt"]
    assert torch.load(path, weights_only=True) == {"step": 3}

    def fails(f):
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, fails)
    assert os.listdir(tmp_path) == ["ckpt.pt"]  # the old file, no temporary one
    assert torch.load(path, weights_only=True) == {"step": 3}
    with pytest.raises(LCSInputError, match=r"^checkpoint: expected a file in an existing directory"):
        atomic_write(tmp_path / "no" / "c.pt", lambda f: None, name="checkpoint")


def test_save_into_a_missing_directory(tmp_path):
    with pytest.raises(LCSInputError, match=r"^path: expected a file in an existing directory"):
        save_model(_trained_like(), tmp_path / "no" / "m.npz")
    with pytest.raises(LCSInputError, match=r"^path: expected a file path, received .* \(a directory\)"):
        save_model(_trained_like(), tmp_path)


def test_save_requires_an_lcs(tmp_path):
    with pytest.raises(LCSInputError, match=r"^model: expected an lcs_cvx.LCS or lcs_cvx.RigidBodyContact, received dict"):
        save_model(_trained_like().to_matrices(), tmp_path / "m.npz")


# -- bad files -------------------------------------------------------------------------------


@pytest.fixture
def saved(tmp_path):
    path = tmp_path / "m.npz"
    save_model(LCS(2, 1, 3, seed=0), path)
    return path


def test_missing_file(tmp_path):
    with pytest.raises(LCSInputError, match=r"^path: expected an existing model file .* \(not found\)"):
        load_model(tmp_path / "none.npz")
    with pytest.raises(LCSInputError, match=r"\(a directory\)"):
        load_metadata(tmp_path)


def test_not_an_npz(tmp_path, saved):
    text = tmp_path / "model.txt"
    text.write_text("A = [[1, 2], [3, 4]]\n")
    with pytest.raises(LCSInputError, match=r"^path: expected an \.npz model file .*could not read it"):
        load_model(text)
    npy = tmp_path / "a.npy"
    np.save(npy, np.eye(2))
    with pytest.raises(LCSInputError, match=r"expected an \.npz model file .*a single \.npy array"):
        load_model(npy)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(saved.read_bytes()[:300])
    with pytest.raises(LCSInputError, match=r"expected an \.npz model file .*could not read it"):
        load_model(truncated)


def test_a_data_set_is_not_a_model(tmp_path):
    data = lcs_cvx.make_dataset(lcs_cvx.random_lcs(2, 1, 2), 10)
    data.save(tmp_path / "data.npz")
    with pytest.raises(LCSInputError, match=r"with a 'meta' array.*\['lam', 'u', 'x', 'x_next'\] -- a data set\?"):
        load_model(tmp_path / "data.npz")


def test_missing_array(saved):
    _rewrite(saved, G=None, c=None)
    with pytest.raises(LCSInputError, match=r"^path: expected arrays .* missing \['G', 'c'\]"):
        load_model(saved)


def test_wrong_shape(saved):
    _rewrite(saved, A=np.zeros((3, 3)))
    with pytest.raises(
        LCSInputError,
        match=r"^path: array 'A' in .*: expected shape \(2, 2\) \(n_x=2, n_u=1, n_lam=3 from its "
        r"metadata\), received \(3, 3\)",
    ):
        load_model(saved)


def test_wrong_dtype(saved):
    _rewrite(saved, C=np.zeros((2, 3), dtype=np.float32))
    with pytest.raises(LCSInputError, match=r"array 'C' .*expected dtype float64 \(from its metadata\), received float32"):
        load_model(saved)


def test_non_finite_values(saved):
    with np.load(saved) as f:
        D = f["D"].copy()
    D[0, 0], D[1, 1] = np.nan, np.inf
    _rewrite(saved, D=D)
    with pytest.raises(LCSInputError, match=r"array 'D' .*expected finite values, received 2 NaN/inf entries"):
        load_model(saved)


def test_newer_format_version(saved):
    meta = _meta(saved)
    meta["format_version"] = FORMAT_VERSION + 1
    meta["lcs_cvx_version"] = "9.0"
    _rewrite(saved, meta=np.array(json.dumps(meta)), A=None)  # a newer layout may differ too
    with pytest.raises(
        LCSInputError,
        match=rf"^path: expected a model file of format version <= {FORMAT_VERSION}, received "
        rf"version {FORMAT_VERSION + 1} .*\(written by lcs_cvx 9\.0\); upgrade lcs_cvx",
    ):
        load_metadata(saved)


def test_bad_meta(saved):
    _rewrite(saved, meta=np.array("{not json"))
    with pytest.raises(LCSInputError, match=r"array 'meta' .*expected valid JSON"):
        load_model(saved)
    _rewrite(saved, meta=np.array(json.dumps({"format": "something else"})))
    with pytest.raises(LCSInputError, match=r"array 'meta' .*expected a JSON object with format 'lcs_cvx.model'"):
        load_model(saved)


def test_inconsistent_F(saved):
    with np.load(saved) as f:
        F = f["F"] + 1e-3
    _rewrite(saved, F=F)
    with pytest.raises(LCSInputError, match=r"array 'F' .*differs by 0\.001 \(F is derived"):
        load_model(saved)


def test_non_positive_stiffness(saved):
    _rewrite(saved, stiffness=np.array(-1.0))
    with pytest.raises(LCSInputError, match=r"array 'stiffness' .*expected a number > 0, received -1\.0"):
        load_model(saved)


# -- the C3 convention -----------------------------------------------------------------------


def test_to_c3_mapping():
    model = lcs_cvx.random_lcs(4, 2, 3, seed=5)
    ours, c3 = model.to_matrices(), model.to_c3()
    assert list(c3) == ["A", "B", "D", "d", "E", "F", "H", "c"]
    mapping = {"A": "A", "B": "B", "D": "C", "d": "d", "E": "D", "F": "F", "H": "E", "c": "c"}
    for key, ours_key in mapping.items():
        assert c3[key].dtype == np.float64
        np.testing.assert_array_equal(c3[key], ours[ours_key])
    shapes = {"A": (4, 4), "B": (4, 2), "D": (4, 3), "d": (4,), "E": (3, 4), "F": (3, 3), "H": (3, 2), "c": (3,)}
    assert {k: v.shape for k, v in c3.items()} == shapes
    c3["D"][:] = 0.0  # copies: editing the export leaves the model alone
    assert bool((model.C != 0).any())


def test_to_c3_simulates_like_the_model():
    model = lcs_cvx.random_lcs(4, 2, 3, seed=5)
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(400, 4, generator=g, dtype=F64) * 2 - 1) * 10
    u = (torch.rand(400, 2, generator=g, dtype=F64) * 2 - 1) * 5
    assert count_modes(model, lcs_cvx.Dataset(x, u, x)) >= 4  # the samples cross the mode boundaries

    m = {k: torch.from_numpy(v) for k, v in model.to_c3().items()}
    # C3: x' = A x + B u + D lam + d,  0 <= lam _|_ E x + F lam + H u + c >= 0
    lam = lcs_cvx.solve_lcp(m["F"], x @ m["E"].T + u @ m["H"].T + m["c"]).lam
    x_next = x @ m["A"].T + u @ m["B"].T + lam @ m["D"].T + m["d"]

    with torch.no_grad():
        assert torch.allclose(lam, model.solve_lcp(x, u).lam, rtol=0, atol=1e-10)
        assert torch.allclose(x_next, model.step(x, u), rtol=0, atol=1e-10)
    assert float(lam.abs().max()) > 1.0  # the contact term matters


def test_damaged_files_are_named(tmp_path):
    """Every truncation, and every byte of the file inverted in turn, gives either a file that
    still reads or an :class:`LCSInputError` naming it -- never zipfile's, numpy's or zlib's
    own exception (a flipped byte in a zip header raised NotImplementedError or RuntimeError)."""
    data = lcs_cvx.make_dataset(lcs_cvx.random_lcs(2, 1, 2), 5)
    trajs = lcs_cvx.Trajectories([np.ones((3, 2)), np.ones((4, 2))], [np.ones((2, 1)), np.ones((3, 1))])
    files = {"m.npz": lambda p: save_model(LCS(2, 1, 2, seed=0), p), "d.npz": data.save, "t.npz": trajs.save}
    loaders = {"m.npz": load_model, "d.npz": lcs_cvx.Dataset.load, "t.npz": lcs_cvx.Trajectories.load}
    bad = tmp_path / "bad.npz"
    for name, write in files.items():
        write(tmp_path / name)
        good = (tmp_path / name).read_bytes()
        damaged = [good[:cut] for cut in range(0, len(good), 11)]
        damaged += [good[:i] + bytes([good[i] ^ 0xFF]) + good[i + 1:] for i in range(len(good))]
        for content in damaged:
            bad.write_bytes(content)
            try:
                loaders[name](bad)
            except LCSInputError as exc:
                assert "bad.npz" in str(exc)
