"""Dataset files never run pickled code, and damaged ones fail at load time naming the file.

Malicious pickles (a ``__reduce__`` that creates a marker file) are planted in SYMSOL's
``rotations.npz`` and ModelNet10-SO(3)'s ``viewID2quat.pkl``; readers, data modules and
``python -m image2sphere.data.verify`` must refuse them without creating the marker. The published
formats (Python 2 protocol-2 pickles, object arrays, NaN- and zero-padded arrays) must still load.
"""

from __future__ import annotations

import os
import pickle
import re
import struct
import subprocess
import sys
import textwrap
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest

from image2sphere.data.datamodule import ModelNet10DataModule, SymsolDataModule
from image2sphere.data.fixtures.modelnet10 import write_modelnet10
from image2sphere.data.fixtures.symsol import write_symsol
from image2sphere.data.modelnet import close_lmdb_environments
from image2sphere.data.modelnet_labels import load_modelnet10_labels
from image2sphere.data.safe_io import DatasetFileError, UnsafePickleError, load_npz, load_pickle, open_lmdb
from image2sphere.data.symsol_labels import load_symsol_rotations
from image2sphere.data.verify import main as verify

SIZE = 16


@pytest.fixture(autouse=True)
def _close_environments():
    yield
    close_lmdb_environments()


class OpenMarker:
    """Unpickling this calls ``open(path, "w")``: the file appearing proves code ran."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


class SystemMarker:
    """Unpickling this runs a shell command through ``os.system`` that creates the file."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (os.system, (f"touch '{self.path}'",))


ATTACKS = [
    pytest.param(OpenMarker, r"(builtins|__builtin__|io|_io)\.open", id="open"),
    pytest.param(SystemMarker, r"(posix|nt)\.system", id="os.system"),
]


def _assert_refused(message: str, path: Path, refused: str) -> None:
    assert str(path) in message and "refused" in message and re.search(refused, message), message


# ---------------------------------------------------------------------------------------------
# malicious pickles


def _symsol_with_payload(tmp_path: Path, payload: object) -> tuple[Path, Path]:
    """A valid SYMSOL tree whose train/rotations.npz has ``payload`` as image 1 of the tetX object array."""
    root = tmp_path / "symsol"
    write_symsol(root, shapes=("cube", "tetX"), per_split={"train": 4, "test": 2}, image_size=SIZE)
    npz = root / "train" / "rotations.npz"
    with np.load(npz, allow_pickle=True) as archive:  # our own fixture, trusted
        arrays = {k: archive[k] for k in archive.files}
    arrays["tetX"][1] = payload
    np.savez(npz, **arrays)
    return root, npz


@pytest.mark.parametrize("attack, refused", ATTACKS)
def test_symsol_object_array_with_code_is_refused_everywhere(tmp_path, capsys, attack, refused):
    marker = tmp_path / "pwned"
    root, npz = _symsol_with_payload(tmp_path, attack(marker))

    with pytest.raises(UnsafePickleError) as info:
        load_symsol_rotations(root / "train", ["cube", "tetX"])
    _assert_refused(str(info.value), npz, refused)
    dm = SymsolDataModule(root=str(root), shapes=["cube", "tetX"], image_size=SIZE, batch_size=2)
    with pytest.raises(UnsafePickleError) as info:
        dm.setup("fit")
    _assert_refused(str(info.value), npz, refused)
    assert verify(["symsol", str(root), "--quiet", "--no-decode"]) == 1
    _assert_refused(capsys.readouterr().out, npz, refused)
    assert not marker.exists()

    # the payload is live: numpy's own loader with pickles allowed runs it
    with np.load(npz, allow_pickle=True) as archive:
        archive["tetX"]
    assert marker.exists()


def _modelnet_with_payload(tmp_path: Path, payload: object) -> tuple[Path, Path]:
    """A valid ModelNet10-SO(3) tree whose test_20V pickle maps one view id to ``payload``."""
    root = tmp_path / "ModelNet10-SO3"
    write_modelnet10(root, instances_per_class=1, views={"train_20V": 2, "test_20V": 2}, image_size=SIZE)
    pkl = root / "test_20V.Rawjpg.lmdb" / "viewID2quat.pkl"
    with open(pkl, "rb") as f:
        quats = pickle.load(f, encoding="latin1")  # our own fixture, trusted
    quats[sorted(quats)[3]] = payload
    with open(pkl, "wb") as f:
        pickle.dump(quats, f, protocol=2)
    return root, pkl


@pytest.mark.parametrize("attack, refused", ATTACKS)
def test_modelnet_pickle_with_code_is_refused_everywhere(tmp_path, capsys, attack, refused):
    marker = tmp_path / "pwned"
    root, pkl = _modelnet_with_payload(tmp_path, attack(marker))

    with pytest.raises(UnsafePickleError) as info:
        load_modelnet10_labels(pkl.parent)
    _assert_refused(str(info.value), pkl, refused)
    dm = ModelNet10DataModule(root, train_split="train_20V", batch_size=2, image_size=SIZE)
    with pytest.raises(UnsafePickleError) as info:
        dm.setup("test")
    _assert_refused(str(info.value), pkl, refused)
    assert verify(["modelnet10", str(root), "--quiet", "--no-decode"]) == 1
    _assert_refused(capsys.readouterr().out, pkl, refused)
    assert not marker.exists()

    with open(pkl, "rb") as f:  # the payload is live: a plain pickle.load runs it
        pickle.load(f, encoding="latin1")
    assert marker.exists()


def test_restricted_unpickler_refuses_other_globals_and_codecs(tmp_path):
    path = tmp_path / "x.pkl"
    # builtins.eval("...") written by hand: GLOBAL, argument tuple, REDUCE
    path.write_bytes(b"\x80\x02cbuiltins\neval\nX\x04\x00\x00\x001+1q\x00\x85R.")
    with pytest.raises(UnsafePickleError, match=r"x\.pkl.*builtins\.eval"):
        load_pickle(path)
    # _codecs.encode is only there for latin1 bytes; any other codec is refused
    path.write_bytes(b"\x80\x02c_codecs\nencode\nX\x02\x00\x00\x00hiX\x05\x00\x00\x00rot13\x86R.")
    with pytest.raises(UnsafePickleError, match=r"x\.pkl: refused to load.*encoding 'rot13'"):
        load_pickle(path)
    # persistent ids are refused too
    path.write_bytes(b"\x80\x02X\x01\x00\x00\x00aQ.")
    with pytest.raises(UnsafePickleError, match="persistent id"):
        load_pickle(path)
    # a truncated pickle names the file
    path.write_bytes(pickle.dumps({"a": np.ones(4)}, protocol=2)[:-20])
    with pytest.raises(DatasetFileError, match=r"cannot read .*x\.pkl.*truncated or corrupt"):
        load_pickle(path)


# ---------------------------------------------------------------------------------------------
# the published formats still load


def _py2_string(data: bytes) -> bytes:
    """A Python 2 ``str`` in a protocol-2 pickle (SHORT_BINSTRING or BINSTRING)."""
    return b"U" + bytes([len(data)]) + data if len(data) < 256 else b"T" + struct.pack("<i", len(data)) + data


def _python2_pickle(quaternions: dict[str, np.ndarray]) -> bytes:
    """The bytes Python 2 with numpy 1.x wrote for ``pickle.dump({key: float64 array}, f, 2)``: 8-bit
    strings for keys and buffers, numpy under its old module name ``numpy.core.multiarray``."""
    dtype = b"cnumpy\ndtype\n" + _py2_string(b"f8") + b"K\x00K\x01\x87R"  # dtype('f8', 0, 1)
    dtype += b"(K\x03" + _py2_string(b"<") + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb"  # its state
    out = b"\x80\x02}("  # PROTO 2, EMPTY_DICT, MARK
    for key, q in quaternions.items():
        out += _py2_string(key.encode())
        out += b"cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85" + _py2_string(b"b") + b"\x87R"
        out += b"(K\x01K\x04\x85" + dtype + b"\x89" + _py2_string(q.astype("<f8").tobytes()) + b"tb"
    return out + b"u."  # SETITEMS, STOP


def test_quaternion_pickles_in_every_published_form_load_the_same(tmp_path):
    rng = np.random.default_rng(0)
    quats = {f"chair_{k:04d}.v001": q / np.linalg.norm(q) for k, q in enumerate(rng.normal(size=(5, 4)), 1)}
    path = tmp_path / "viewID2quat.pkl"
    path.write_bytes(_python2_pickle(quats))
    with open(path, "rb") as f:  # the handmade bytes are a valid pickle of the same dict
        reference = pickle.load(f, encoding="latin1")
    assert set(reference) == set(quats)
    forms = {"python 2": path.read_bytes()}
    for protocol in (2, 4, 5):
        forms[f"protocol {protocol}"] = pickle.dumps(quats, protocol=protocol)
        forms[f"protocol {protocol}, bytes keys"] = pickle.dumps({k.encode(): v for k, v in quats.items()}, protocol)
    for form, data in forms.items():
        path.write_bytes(data)
        loaded = load_pickle(path, encoding="latin1")
        assert {k.decode() if isinstance(k, bytes) else k for k in loaded} == set(quats), form
        for key, value in loaded.items():
            key = key.decode() if isinstance(key, bytes) else key
            assert isinstance(value, np.ndarray) and value.dtype == np.float64, form
            np.testing.assert_array_equal(value, quats[key], err_msg=form)

    # plain containers and numpy scalars pass too
    plain = OrderedDict(a={1, 2}, b=frozenset([3]), c=(1.5, b"", b"\x00\xff", bytearray(b"xy"), 2j), d=np.float64(0.25))
    for protocol in (2, 5):
        path.write_bytes(pickle.dumps(plain, protocol=protocol))
        assert load_pickle(path) == plain


def test_modelnet_reader_reads_a_python2_pickle(tmp_path):
    root = tmp_path / "ModelNet10-SO3"
    truth = write_modelnet10(root, instances_per_class=1, views={"test_20V": 2}, image_size=SIZE)["test_20V"]
    pkl = root / "test_20V.Rawjpg.lmdb" / "viewID2quat.pkl"
    with open(pkl, "rb") as f:
        quats = pickle.load(f, encoding="latin1")
    pkl.write_bytes(_python2_pickle(quats))
    labels = load_modelnet10_labels(pkl.parent)
    assert labels.keys == sorted(truth)
    np.testing.assert_allclose(labels.rotations, np.stack([truth[k] for k in labels.keys]), atol=1e-5)


def test_symsol_object_nan_padded_and_zero_padded_forms_give_the_same_rotations(tmp_path):
    root = tmp_path / "symsol"
    truth = write_symsol(root, shapes=("cube", "tetX"), per_split={"train": 6}, image_size=SIZE)["train"]
    npz = root / "train" / "rotations.npz"
    with np.load(npz, allow_pickle=True) as archive:
        reference = {k: archive[k] for k in archive.files}
    assert reference["tetX"].dtype == object
    loaded = load_npz(npz)  # without running pickled code, the same arrays as numpy's own loader
    assert set(loaded) == set(reference)
    np.testing.assert_array_equal(loaded["cube"], reference["cube"])
    assert loaded["tetX"].shape == reference["tetX"].shape
    for ours, theirs in zip(loaded["tetX"], reference["tetX"], strict=True):
        np.testing.assert_array_equal(ours, theirs)

    sets = truth["tetX"]
    m = max(len(s) for s in sets)
    assert len({len(s) for s in sets}) > 1
    results = {}
    for form, fill in (("object", None), ("NaN-padded", np.nan), ("zero-padded", 0.0)):
        if fill is not None:
            padded = np.full((len(sets), m, 3, 3), fill, np.float32)
            for i, s in enumerate(sets):
                padded[i, : len(s)] = s
            np.savez(npz, cube=reference["cube"], tetX=padded)
        dense, counts = load_symsol_rotations(root / "train", ["tetX"])["tetX"]
        assert counts.tolist() == [len(s) for s in sets], form
        for i, s in enumerate(sets):
            np.testing.assert_array_equal(dense[i, : counts[i]], s, err_msg=form)
        results[form] = dense
    np.testing.assert_array_equal(results["object"], results["NaN-padded"])
    np.testing.assert_array_equal(results["object"], results["zero-padded"])


# ---------------------------------------------------------------------------------------------
# values checked at load time


def _symsol_tree(tmp_path: Path) -> tuple[Path, Path, dict[str, np.ndarray]]:
    root = tmp_path / "symsol"
    write_symsol(root, shapes=("cube", "tetX"), per_split={"train": 4, "test": 2}, image_size=SIZE)
    npz = root / "train" / "rotations.npz"
    with np.load(npz, allow_pickle=True) as archive:
        return root, npz, {k: archive[k] for k in archive.files}


def _with_nan(R: np.ndarray) -> np.ndarray:
    R[0, 1] = np.nan
    return R


def _with_inf(R: np.ndarray) -> np.ndarray:
    R[2, 2] = np.inf
    return R


def _scaled(R: np.ndarray) -> np.ndarray:
    return R * 1.5


def _reflected(R: np.ndarray) -> np.ndarray:
    return R * np.array([1.0, 1.0, -1.0], np.float32)  # orthonormal, det -1


@pytest.mark.parametrize(
    "edit, what",
    [(_with_nan, "holds NaN or inf"), (_with_inf, "holds NaN or inf"), (_scaled, "is not orthonormal"),
     (_reflected, "has determinant -1")],
    ids=["nan", "inf", "scaled", "reflection"],
)  # fmt: skip
def test_bad_equivalent_rotation_names_file_key_image_and_entry(tmp_path, capsys, edit, what):
    """A broken entry other than [:, 0] (here image 2, equivalent 5 of the cube) fails at load time."""
    root, npz, arrays = _symsol_tree(tmp_path)
    cube = arrays["cube"].copy()
    cube[2, 5] = edit(cube[2, 5].copy())
    np.savez(npz, **{**arrays, "cube": cube})
    entry = r"image 2 \(images/cube_00002\.png\), equivalent rotation 5 "
    expected = rf"{re.escape(str(npz))}\['cube'\]: rows \[2\].*{entry}.*{what}"
    with pytest.raises(ValueError, match=expected):
        load_symsol_rotations(root / "train", ["cube"])
    dm = SymsolDataModule(root=str(root), shapes=["cube", "tetX"], image_size=SIZE, batch_size=2)
    with pytest.raises(ValueError, match=expected):
        dm.setup("fit")
    assert verify(["symsol", str(root), "--quiet", "--no-decode"]) == 1
    assert re.search(expected, capsys.readouterr().out)


def test_bad_rotation_inside_an_object_array_and_padding_in_unmarked_shape(tmp_path):
    root, npz, arrays = _symsol_tree(tmp_path)
    tetx = arrays["tetX"].copy()
    row = next(i for i, s in enumerate(tetx) if len(s) > 1)
    tetx[row] = tetx[row].copy()
    tetx[row][1, 0, 0] = np.nan
    np.savez(npz, **{**arrays, "tetX": tetx})
    with pytest.raises(ValueError, match=rf"\['tetX'\].*image {row} .*equivalent rotation 1 holds NaN"):
        load_symsol_rotations(root / "train", ["tetX"])
    # a whole NaN matrix in an unmarked shape would be taken for padding: refused
    cube = arrays["cube"].copy()
    cube[3, 7] = np.nan
    np.savez(npz, **{**arrays, "cube": cube})
    with pytest.raises(ValueError, match=r"\['cube'\]: rows \[3\] have fewer equivalent rotations \(23\).*unmarked"):
        load_symsol_rotations(root / "train", ["cube"])


@pytest.mark.parametrize("value", [np.nan, np.inf], ids=["nan", "inf"])
def test_non_finite_quaternion_is_refused_naming_pickle_and_key(tmp_path, capsys, value):
    root = tmp_path / "ModelNet10-SO3"
    write_modelnet10(root, instances_per_class=1, views={"train_20V": 2, "test_20V": 2}, image_size=SIZE)
    pkl = root / "test_20V.Rawjpg.lmdb" / "viewID2quat.pkl"
    with open(pkl, "rb") as f:
        quats = pickle.load(f, encoding="latin1")
    key = sorted(quats)[4]
    quats[key] = np.array([value, 0.0, 0.0, 1.0])
    with open(pkl, "wb") as f:
        pickle.dump(quats, f, protocol=2)
    expected = rf"{re.escape(str(pkl))}\[{re.escape(repr(key))}\]: quaternion .* holds NaN or inf"
    with pytest.raises(ValueError, match=expected):
        load_modelnet10_labels(pkl.parent)
    assert verify(["modelnet10", str(root), "--quiet", "--no-decode"]) == 1
    assert re.search(expected, capsys.readouterr().out)


# ---------------------------------------------------------------------------------------------
# truncated and corrupt files


def test_truncated_or_corrupt_npz_names_the_file(tmp_path, capsys):
    root, npz, arrays = _symsol_tree(tmp_path)
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])
    expected = rf"{re.escape(str(npz))}.*truncated or corrupt.*re-download"
    with pytest.raises(DatasetFileError, match=expected):
        load_symsol_rotations(root / "train", ["cube"])
    dm = SymsolDataModule(root=str(root), shapes=["cube", "tetX"], image_size=SIZE, batch_size=2)
    with pytest.raises(DatasetFileError, match=expected):
        dm.setup("fit")
    assert verify(["symsol", str(root), "--quiet", "--no-decode"]) == 1
    assert re.search(expected, capsys.readouterr().out)

    # same size, one flipped byte inside the cube member's numbers: the CRC check catches it
    np.savez(npz, **arrays)
    data = bytearray(npz.read_bytes())
    at = bytes(data).index(arrays["cube"].tobytes()[:64]) + 100
    data[at] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(DatasetFileError, match=rf"{re.escape(str(npz))} \(member cube\.npy\).*truncated or corrupt"):
        load_symsol_rotations(root / "train", ["cube"])


def _truncate(path: Path, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)


def test_open_lmdb_compares_the_file_with_its_header(tmp_path):
    root = tmp_path / "ModelNet10-SO3"
    write_modelnet10(root, instances_per_class=1, views={"test_20V": 2}, image_size=SIZE)
    directory = root / "test_20V.Rawjpg.lmdb"
    data = directory / "data.mdb"
    env = open_lmdb(directory)
    psize, needed = env.stat()["psize"], (env.info()["last_pgno"] + 1) * env.stat()["psize"]
    env.close()
    assert data.stat().st_size >= needed
    _truncate(data, needed)  # exactly complete: accepted
    open_lmdb(directory).close()
    _truncate(data, needed - psize)  # one page short: refused before any record is read
    with pytest.raises(DatasetFileError, match=rf"{re.escape(str(data))} is truncated.*{needed - psize} bytes"):
        open_lmdb(directory)
    _truncate(data, 100)  # not even the meta pages
    with pytest.raises(DatasetFileError, match=rf"cannot open {re.escape(str(data))} as an LMDB"):
        open_lmdb(directory, remedy="re-extract it")


def test_truncated_lmdb_fails_with_a_message_instead_of_sigbus(tmp_path):
    """Reader and verify in a child process: a SIGBUS there shows as a negative return code."""
    root = tmp_path / "ModelNet10-SO3"
    write_modelnet10(root, instances_per_class=1, views={"train_20V": 2, "test_20V": 2}, image_size=SIZE)
    data = root / "test_20V.Rawjpg.lmdb" / "data.mdb"
    _truncate(data, data.stat().st_size // 2)
    script = textwrap.dedent(
        f"""
        import sys
        from image2sphere.data.verify import main
        code = main(["modelnet10", {str(root)!r}, "--quiet"])
        print("verify exit status", code, flush=True)
        from image2sphere.data.modelnet import ModelNet10Dataset
        dataset = ModelNet10Dataset({str(root)!r}, "test_20V", image_size={SIZE})
        print("read", [dataset[i]["index"] for i in range(len(dataset))])
        """
    )
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 1, (done.returncode, done.stdout, done.stderr)  # a Python exception, not a signal
    assert "verify exit status 1" in done.stdout
    message = rf"{re.escape(str(data))} is truncated: .*[Rr]e-extract ModelNet10-SO3\.tar\.gz"
    assert re.search(message, done.stdout), done.stdout  # verify's report
    assert re.search(rf"DatasetFileError: {message}", done.stderr), done.stderr  # the reader's error
