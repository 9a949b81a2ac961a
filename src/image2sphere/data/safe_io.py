"""Readers for the dataset files that could run code or crash the process, made safe.

Policy
------
A dataset file is data downloaded from somewhere else: reading it must never run code from it, and a
damaged copy must fail when it is opened, with an error that names the file and says how to repair it.

* Pickles. Two published formats embed them: ModelNet10-SO(3)'s ``viewID2quat.pkl`` (a dict view id
  -> quaternion written by Python 2) and SYMSOL's ``rotations.npz`` when the number of equivalent
  rotations varies per image (an object array holding one float array per image). Both are read with
  :class:`RestrictedUnpickler`, which rebuilds numpy arrays, dtypes and scalars and plain containers
  and nothing else: any other global a pickle asks for (a function such as ``os.system`` or
  ``builtins.open``, any other class) is refused with :class:`UnsafePickleError` before it is
  imported or called. :func:`load_pickle` reads a ``.pkl`` file, :func:`load_npz` an ``.npz``
  archive (numeric members without any pickle, object members with the restricted unpickler).
* Truncated or corrupt archives (a zip whose directory or members are cut short, a member whose
  ``.npy`` header is damaged, a pickle that ends early) raise :class:`DatasetFileError` naming the
  file instead of a bare ``zipfile.BadZipFile`` or ``EOFError``.
* LMDB environments are memory-mapped, so reading a page past the end of a truncated ``data.mdb``
  kills the process with ``SIGBUS`` rather than raising. :func:`open_lmdb` compares the file's size
  with the size its own meta pages record before any record is read.

Every error is a :class:`DatasetFileError` (a ``ValueError``) whose message starts with the file.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from collections import OrderedDict
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

import numpy as np

from image2sphere.checks import ConfigError, InputNotFoundError

__all__ = [
    "DatasetFileError",
    "RestrictedUnpickler",
    "UnsafePickleError",
    "load_npz",
    "load_pickle",
    "npz_keys",
    "open_lmdb",
]

DEFAULT_REMEDY = "re-download the dataset (or re-extract its archive)"


class DatasetFileError(ConfigError):
    """A dataset file that is truncated, corrupt or holds something it must not; the message names it."""


class UnsafePickleError(DatasetFileError):
    """A pickle inside a dataset file asked for a global outside the allowed set; nothing of it was run."""


# ----------------------------------------------------------------------------------------------
# the restricted unpickler


def _numpy_module(name: str):
    """``numpy._core.<name>`` (numpy >= 2) or ``numpy.core.<name>`` (numpy 1.x), without the
    deprecation warning that importing ``numpy.core`` gives under numpy 2."""
    import importlib

    try:
        return importlib.import_module(f"numpy._core.{name}")
    except ImportError:
        return importlib.import_module(f"numpy.core.{name}")


def _allowed_globals() -> dict[tuple[str, str], Any]:
    """Every global a dataset pickle may name, mapped to the object it gets (module names as written
    by numpy 1.x, numpy 2.x, Python 2 and Python 3)."""
    multiarray = _numpy_module("multiarray")
    numeric = _numpy_module("numeric")
    table: dict[tuple[str, str], Any] = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
    for package in ("numpy.core", "numpy._core"):
        table[(f"{package}.multiarray", "_reconstruct")] = multiarray._reconstruct  # ndarray.__reduce__
        table[(f"{package}.multiarray", "scalar")] = multiarray.scalar  # numpy scalars (np.float64(1.0))
        table[(f"{package}.numeric", "_frombuffer")] = numeric._frombuffer  # arrays under protocol 5
    for module in ("builtins", "__builtin__"):  # Python 3 and Python 2 names
        for name, value in (("set", set), ("frozenset", frozenset), ("complex", complex), ("bytes", bytes),
                            ("bytearray", bytearray), ("list", list), ("dict", dict), ("tuple", tuple)):  # fmt: skip
            table[(module, name)] = value
    table[("collections", "OrderedDict")] = OrderedDict
    return table


_ALLOWED: dict[tuple[str, str], Any] | None = None


class RestrictedUnpickler(pickle.Unpickler):
    """A :class:`pickle.Unpickler` that rebuilds only numpy arrays, dtypes, scalars and plain
    containers (dict, list, tuple, set, str, bytes, numbers).

    ``source`` names the file (and member) in errors. Any other global, and persistent ids, raise
    :class:`UnsafePickleError` before anything is imported or called.
    """

    def __init__(self, file: IO[bytes], source: str | Path, **kwargs: Any):
        super().__init__(file, **kwargs)
        self.source = str(source)

    def find_class(self, module: str, name: str) -> Any:
        global _ALLOWED
        if _ALLOWED is None:
            _ALLOWED = _allowed_globals()
        if (module, name) == ("_codecs", "encode"):
            return self._latin1_encode
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise UnsafePickleError(
                f"{self.source}: refused to load: its pickled data asks for {module}.{name}, which a dataset "
                "file never needs (only numpy arrays and plain containers are read) and which could run code; "
                "nothing was executed. The file was altered or is not the published one: delete it and "
                "re-download the dataset from its official source"
            ) from None

    def _latin1_encode(self, text: object, encoding: object = "utf-8", errors: object = "strict") -> bytes:
        """What ``_codecs.encode`` is for in a legitimate pickle: protocols 0-2 store ``bytes`` (e.g. the
        buffer of a numpy array) as ``_codecs.encode(text, "latin1")``. Any other use is refused."""
        codec = str(encoding).lower().replace("-", "").replace("_", "")
        if not isinstance(text, str) or codec not in ("latin1", "iso88591") or errors != "strict":
            raise UnsafePickleError(
                f"{self.source}: refused to load: its pickled data calls _codecs.encode with encoding {encoding!r} "
                "(pickles only use it to store bytes as latin1 text); delete it and re-download the dataset from "
                "its official source"
            )
        return text.encode("latin1")

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError(
            f"{self.source}: refused to load: its pickled data uses a persistent id, which a dataset file never "
            "holds; delete it and re-download the dataset from its official source"
        )


def _restricted_load(file: IO[bytes], source: str, encoding: str) -> Any:
    return RestrictedUnpickler(file, source, encoding=encoding).load()


def load_pickle(path: str | Path, encoding: str = "latin1", remedy: str = DEFAULT_REMEDY) -> Any:
    """The object pickled in ``path``, through :class:`RestrictedUnpickler`.

    ``encoding="latin1"`` reads Python 2 pickles (their ``str`` load as ``str``, numpy buffers
    correctly). Raises ``FileNotFoundError`` for a missing file, :class:`UnsafePickleError` for a
    refused global and :class:`DatasetFileError` (naming the file and ``remedy``) for any other
    failure (truncated or not a pickle).
    """
    path = Path(path)
    with open(path, "rb") as f:
        try:
            return _restricted_load(f, str(path), encoding)
        except DatasetFileError:
            raise
        except Exception as e:  # truncated or foreign pickles raise many different types
            raise DatasetFileError(
                f"cannot read {path} ({type(e).__name__}: {e}): the file is truncated or corrupt; {remedy}"
            ) from e


# ----------------------------------------------------------------------------------------------
# npz archives


def _corrupt_archive(path: Path, error: BaseException, remedy: str, member: str | None = None) -> DatasetFileError:
    where = f"{path}" if member is None else f"{path} (member {member})"
    return DatasetFileError(
        f"cannot read {where} ({type(error).__name__}: {error}): the file is truncated or corrupt (an interrupted "
        f"download or extraction); {remedy}"
    )


def _open_zip(path: Path, remedy: str) -> zipfile.ZipFile:
    if not path.is_file():
        raise InputNotFoundError(f"{path} not found")
    try:
        return zipfile.ZipFile(path)
    except (zipfile.BadZipFile, EOFError, ValueError, OSError) as e:
        if isinstance(e, (FileNotFoundError, PermissionError, IsADirectoryError)):
            raise
        raise _corrupt_archive(path, e, remedy) from e


def _member_key(name: str) -> str:
    """The key of an npz member, as ``numpy.load`` names it (``cube.npy`` -> ``cube``)."""
    return name[: -len(".npy")] if name.endswith(".npy") else name


def npz_keys(path: str | Path, remedy: str = DEFAULT_REMEDY) -> list[str]:
    """The array names in the npz archive ``path`` (reads only the zip directory; nothing is unpickled)."""
    path = Path(path)
    with _open_zip(path, remedy) as zf:
        return [_member_key(info.filename) for info in zf.infolist() if not info.is_dir()]


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, source: str) -> np.ndarray:
    """One ``.npy`` member: numeric arrays through ``numpy.lib.format.read_array(allow_pickle=False)``,
    object arrays through the restricted unpickler (checked against the shape in their header)."""
    fmt = np.lib.format
    with zf.open(info) as f:
        version = fmt.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(f)
        else:
            raise ConfigError(f".npy format version {version[0]}.{version[1]} is not supported (1.0 and 2.0 are)")
        if dtype.hasobject:
            array = _restricted_load(f, source, encoding="latin1")
            if not isinstance(array, np.ndarray) or array.shape != tuple(shape):
                raise ConfigError(f"the pickled payload is not the {tuple(shape)} array its header announces")
            return array
    with zf.open(info) as f:
        return fmt.read_array(f, allow_pickle=False)


def load_npz(
    path: str | Path, keys: Iterable[str] | None = None, remedy: str = DEFAULT_REMEDY
) -> dict[str, np.ndarray]:
    """The arrays of the npz archive ``path`` (those named in ``keys``, default all) without running
    pickled code: object arrays go through :class:`RestrictedUnpickler`.

    Raises ``FileNotFoundError`` for a missing file, ``KeyError`` for a key the archive lacks,
    :class:`UnsafePickleError` for a refused global and :class:`DatasetFileError` (naming the file,
    the member and ``remedy``) for a truncated or corrupt archive.
    """
    path = Path(path)
    with _open_zip(path, remedy) as zf:
        members = {_member_key(info.filename): info for info in zf.infolist() if not info.is_dir()}
        wanted = list(members) if keys is None else list(keys)
        absent = [k for k in wanted if k not in members]
        if absent:
            raise KeyError(f"{path} has no key {absent[0]!r} (keys: {sorted(members)})")
        out = {}
        for key in wanted:
            info = members[key]
            try:
                out[key] = _read_member(zf, info, f"{path} (member {info.filename})")
            except DatasetFileError:
                raise
            except Exception as e:  # BadZipFile (CRC), EOFError, zlib.error, ValueError (header), damaged pickles
                raise _corrupt_archive(path, e, remedy, info.filename) from e
    return out


# ----------------------------------------------------------------------------------------------
# LMDB environments


def open_lmdb(directory: str | Path, remedy: str = DEFAULT_REMEDY):
    """Open the LMDB environment ``directory`` read-only (no lock file, no readahead), after checking
    that its ``data.mdb`` is complete.

    Opening reads only the two meta pages at the start of the file (with ``pread``); they record the
    page size and the last page in use, so a file shorter than ``(last_pgno + 1) * psize`` bytes is
    truncated and is refused here, before a read past its end could kill the process with SIGBUS.
    Raises ``FileNotFoundError`` without ``data.mdb`` and :class:`DatasetFileError` (naming the file
    and ``remedy``) when it is not an LMDB or is truncated.
    """
    import lmdb

    directory = Path(directory)
    data = directory / "data.mdb"
    if not data.is_file():
        raise InputNotFoundError(f"LMDB environment not found: {data}")
    try:
        env = lmdb.open(str(directory), subdir=True, readonly=True, lock=False, readahead=False, meminit=False)
    except lmdb.Error as e:
        raise DatasetFileError(
            f"cannot open {data} as an LMDB ({type(e).__name__}: {e}): the file is truncated, damaged or not an "
            f"LMDB; {remedy}"
        ) from e
    try:
        psize = int(env.stat()["psize"])
        needed = (int(env.info()["last_pgno"]) + 1) * psize
        size = os.path.getsize(data)
    except BaseException:
        env.close()
        raise
    if size < needed:
        env.close()
        raise DatasetFileError(
            f"{data} is truncated: it has {size} bytes, but its header says the database fills {needed} bytes "
            f"({needed // psize} pages of {psize} bytes); an interrupted download or extraction leaves such a file, "
            f"and reading it would crash the process. {remedy[:1].upper()}{remedy[1:]}"
        )
    return env
