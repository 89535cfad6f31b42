"""Stored arrays: ``.npy`` headers checked before a byte is read, ``.npz`` members, text matrices."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import DataFormatError, GPDepthError, InvalidInputError, describe


def _read_npy_header(fp) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, header bytes) of the .npy stream ``fp``, read without touching its data."""
    start = fp.tell()
    version = np.lib.format.read_magic(fp)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
    else:
        shape, _, dtype = np.lib.format._read_array_header(fp, version)
    return tuple(int(s) for s in shape), np.dtype(dtype), fp.tell() - start


def check_stored_array(
    path: str | Path, member: str | None = None, *, copies: float = 2.0
) -> tuple[tuple[int, ...], np.dtype]:
    """Reads the header of an ``.npy`` file (or of ``member`` of an ``.npz``) and checks its size first.

    A header claiming more values than the file holds (a corrupt or forged file) is refused
    before NumPy allocates the array it claims, and so is an array whose ``copies`` (the array
    and its float64 copy) exceed `gpdepth3d.limits.memory_limit`.

    Returns:
        The stored (shape, dtype).

    Raises:
        DataFormatError: no such member, an unreadable header, or more data claimed than stored.
        ProblemTooLargeError: an array too large for the memory limit.
    """
    from ..limits import check_array_size

    path = Path(path)
    try:
        if member is None:
            with open(path, "rb") as fp:
                shape, dtype, header = _read_npy_header(fp)
                stored = os.fstat(fp.fileno()).st_size - header
            label = str(path)
        else:
            with zipfile.ZipFile(path) as zf:
                name = member if member.endswith(".npy") else member + ".npy"
                info = zf.getinfo(name)
                with zf.open(info) as fp:
                    shape, dtype, header = _read_npy_header(fp)
                stored = info.file_size - header
            label = f"{path}[{member}]"
    except KeyError:
        raise DataFormatError(path, f"no array '{member}'") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFormatError(path, f"corrupt or unreadable array header: {exc}") from None
    claimed = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if claimed > stored:
        raise DataFormatError(
            label,
            f"corrupt: the header claims shape {shape} of {dtype} ({claimed} bytes), the file stores {max(stored, 0)}",
        )
    check_array_size(f"array {label}", shape, dtype, copies=copies * max(1.0, 8.0 / max(dtype.itemsize, 1)))
    return shape, dtype


def load_npz_arrays(path: str | Path, names: Sequence[str], what: str = "arrays") -> dict[str, np.ndarray]:
    """Reads the arrays ``names`` of an ``.npz``, each header checked first (`check_stored_array`).

    Raises:
        DataFormatError: a missing, corrupt or forged file (naming it), or a missing array.
        ProblemTooLargeError: an array too large for the memory limit.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, f"{what} not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise DataFormatError(path, f"{what}: an .npz archive expected (this is a single array)")
            missing = [n for n in names if n not in data.files]
            if missing:
                raise DataFormatError(path, f"{what}: no array {missing[0]!r} (has {data.files})")
            out = {}
            for n in names:
                check_stored_array(path, n)
                out[n] = data[n]
            return out
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        if isinstance(exc, GPDepthError):
            raise
        raise DataFormatError(path, f"{what}: corrupt or unreadable ({type(exc).__name__}: {exc})") from None


def _as_path(path, argument: str = "path") -> Path:
    """``path`` as a `Path`; a value that is no path at all (None, a number) is refused by name."""
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise InvalidInputError(argument, "a file path", describe(path))
    return Path(path)


def _pick_key(path: Path, keys: list[str], key: str | None) -> str:
    if key is not None:
        if key not in keys:
            raise DataFormatError(path, f"no array '{key}' (has {keys})")
        return key
    if len(keys) == 1:
        return keys[0]
    for k in ("depth", "mean", "velodyne_depth"):
        if k in keys:
            return k
    raise DataFormatError(path, f"several arrays {keys}: say which with key=")


def read_matrix(path: Path, shape: tuple[int, ...], what: str) -> np.ndarray:
    """Reads a whitespace-separated text matrix and checks its shape; DataFormatError otherwise."""
    if not path.is_file():
        raise DataFormatError(path, f"{what} not found")
    try:
        m = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DataFormatError(path, f"{what}: not a numeric matrix ({exc})") from None
    if m.size != int(np.prod(shape)):
        raise DataFormatError(path, f"{what}: expected {shape} values, got shape {m.shape}")
    m = m.reshape(shape)
    if not np.all(np.isfinite(m)):
        raise DataFormatError(path, f"{what}: non-finite values")
    return m
