"""Compact forms of the float arrays a saved map holds: half precision, sigma for a variance, fixed point.

A saved map (`gpdepth3d.mapping.map_store`, `gpdepth3d.mapping.tsdf.storage`) stores its float32
arrays in these forms inside a compressed ``.npz``: float32 noise does not compress, and the
map's own errors (depth, fusion) are orders of magnitude above what the forms lose. Each form
keeps zero as zero and any non-zero value non-zero (a voxel observed with a tiny weight stays
observed), NaN as NaN and signs as they were.

* `to_half`: float16 (relative error <= 2^-11) when every finite value fits, else float32.
* `sigma_of`: a variance (m^2, >= 0) as its square root in `to_half`'s form, so that small
  variances keep their relative precision (a float16 variance of 1e-6 m^2 would be subnormal).
* `to_fixed`: values in [-1, 1] as int16 steps of 1 / `FIXED_STEPS`.
"""

from __future__ import annotations

import io
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

HALF_MAX = float(np.finfo(np.float16).max)
FIXED_STEPS = 32767
"""`to_fixed`'s int16 steps per unit."""


def to_half(a: np.ndarray) -> np.ndarray:
    """``a`` as float16 when every finite value fits (non-zero values stay non-zero), else as float32."""
    a = np.asarray(a, dtype=np.float32)
    finite = np.isfinite(a)
    if finite.any() and np.abs(a[finite]).max() > HALF_MAX:
        return a
    h = a.astype(np.float16)
    lost = (h == 0) & (a != 0)  # below float16's smallest subnormal: the smallest value of the same sign
    if lost.any():
        tiny = np.float16(np.finfo(np.float16).smallest_subnormal)
        h[lost] = np.where(a[lost] > 0, tiny, -tiny)
    return h


def sigma_of(variance: np.ndarray) -> np.ndarray:
    """A variance array (m^2; NaN kept, values below 0 read as 0) as its square root in `to_half`'s form."""
    v = np.asarray(variance, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        return to_half(np.sqrt(np.where(v > 0, v, np.where(np.isnan(v), v, 0))))


def variance_of(sigma: np.ndarray) -> np.ndarray:
    """The float32 variance (m^2) of a stored `sigma_of` array."""
    s = np.asarray(sigma, dtype=np.float32)
    return s * s


def to_fixed(a: np.ndarray) -> np.ndarray:
    """Values in [-1, 1] (clipped) as int16 steps of 1 / `FIXED_STEPS`; a non-zero value stays non-zero."""
    a = np.clip(np.asarray(a, dtype=np.float32), -1.0, 1.0)
    q = np.rint(a * FIXED_STEPS).astype(np.int16)
    q[(q == 0) & (a > 0)] = 1
    q[(q == 0) & (a < 0)] = -1
    return q


def from_fixed(q: np.ndarray) -> np.ndarray:
    """The float32 values of a `to_fixed` array."""
    return np.multiply(q, np.float32(1.0 / FIXED_STEPS), dtype=np.float32)


def read_npz_members(path: str | Path, names: list[str]) -> dict[str, np.ndarray]:
    """The members ``names`` of an ``.npz``, decompressed in parallel threads (zlib releases the GIL).

    Only the decompression runs in the threads; each ``.npy`` header is parsed on the calling thread,
    because NumPy parses it with `ast.literal_eval`, which CPython 3.11 does not run safely from several
    threads at once (``SystemError: AST constructor recursion depth mismatch``).

    Raises:
        KeyError: a member is missing. OSError, ValueError, zipfile.BadZipFile: not a readable ``.npz``.
    """

    def raw(name: str) -> bytes:
        with zipfile.ZipFile(path) as archive:  # one archive handle per thread
            return archive.read(name + ".npy")

    with np.load(path, allow_pickle=False) as d:
        missing = [n for n in names if n not in d.files]
    if missing:
        raise KeyError(f"no member {missing[0]!r}")
    with ThreadPoolExecutor(max_workers=min(4, max(1, len(names)))) as pool:
        members = list(pool.map(raw, names))
    return {n: np.lib.format.read_array(io.BytesIO(b), allow_pickle=False) for n, b in zip(names, members)}
