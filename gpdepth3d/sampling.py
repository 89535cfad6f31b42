"""Sampling protocols: which sparse measurements a depth-completion method is given.

Every protocol draws from the *available* points (the valid pixels of a dense ground-truth map,
or a `SparseDepth` such as a projected LiDAR scan), returns a `SparseDepth` and takes a
``numpy.random.Generator`` (or a seed) so that runs are reproducible.

* `sample_uniform`: N points, or a density (share of the available points), uniformly at random.
* `PAPER_DENSITIES`: eight density levels from 1/64 to 1x of the available points.
* `sample_band`: biased measurements that cover only a horizontal band (a range of rows) or a
  vertical band (a range of columns) of the image, like a sensor with a narrow field of view
  (Fig. 4 of Yoon & Kim 2020).
* `sample_scanlines`: keep every k-th LiDAR beam; the beam of each projected point is recovered
  from its elevation angle in the LiDAR frame (`lidar_elevation`, `beam_ids`).
* `holdout_split` (`holdout_mask`): complete from one share of the points and evaluate on the rest
  (for data without dense ground truth, such as ``kitti_tiny``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .camera import PinholeCamera
from .errors import EmptyInputError, InvalidInputError, ShapeError, describe
from .measurements import LidarCalibration, SparseDepth

PAPER_DENSITIES: tuple[float, ...] = (1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 3 / 4, 1.0)
"""Eight density levels (share of the available points), 1/64 ... 1x: powers of two up to 1/2,
then 3/4 and all points."""

SeedLike = int | np.random.Generator | None


def make_rng(seed: SeedLike) -> np.random.Generator:
    """A numpy Generator from a seed, an existing Generator (returned as is) or None (fresh entropy)."""
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None:
        return np.random.default_rng()
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, (bool, np.bool_)):
        if seed < 0:
            raise InvalidInputError("rng", "an int seed >= 0, a numpy.random.Generator or None", int(seed))
        return np.random.default_rng(int(seed))
    raise InvalidInputError("rng", "an int seed >= 0, a numpy.random.Generator or None", describe(seed))


def as_available(source: np.ndarray | SparseDepth) -> SparseDepth:
    """The available points of a source: a `SparseDepth` as is, or the valid pixels of an (H, W) map."""
    if isinstance(source, SparseDepth):
        return source
    d = np.asarray(source)
    if d.ndim != 2:
        raise ShapeError("source", "an (H, W) depth map in metres or a SparseDepth", describe(d))
    return SparseDepth.from_depth_map(d)


def _count(n_available: int, n: int | None, density: float | None) -> int:
    if (n is None) == (density is None):
        raise InvalidInputError("n, density", "exactly one of n (points) or density (share)", (n, density))
    if n is not None:
        if (
            isinstance(n, (bool, np.bool_))
            or not isinstance(n, (int, float, np.integer, np.floating))
            or not np.isfinite(n)
            or int(n) != n
            or n < 0
        ):
            raise InvalidInputError("n", "a whole number of points >= 0", describe(n))
        return min(int(n), n_available)
    if (
        isinstance(density, (bool, np.bool_))
        or not isinstance(density, (int, float, np.integer, np.floating))
        or not np.isfinite(density)
        or not 0 < density <= 1
    ):
        raise InvalidInputError("density", "a share of the available points in (0, 1]", density)
    return max(1, int(round(density * n_available))) if n_available else 0


def sample_uniform(
    source: np.ndarray | SparseDepth, *, n: int | None = None, density: float | None = None, rng: SeedLike = 0
) -> SparseDepth:
    """Uniform random subset of the available points, without replacement.

    Args:
        source: (H, W) depth map (metres, 0/NaN = none) or a `SparseDepth`.
        n: Number of points (fewer if fewer are available).
        density: Share of the available points in (0, 1] (give n or density).
        rng: Seed or Generator.

    Returns:
        `SparseDepth` of min(n, available) points, in the source's image.
    """
    avail = as_available(source)
    k = _count(len(avail), n, density)
    idx = make_rng(rng).choice(len(avail), size=k, replace=False)
    return avail.subset(np.sort(idx))


def band_mask(sparse: SparseDepth, *, axis: Literal["horizontal", "vertical"], start: float, stop: float) -> np.ndarray:
    """Boolean mask of the points inside a band of the image.

    Args:
        sparse: The points.
        axis: "horizontal": a band of rows v in [start, stop) * height (a horizontal stripe);
            "vertical": a band of columns u in [start, stop) * width.
        start: Band start as a fraction of the image size in [0, 1).
        stop: Band end as a fraction in (start, 1].
    """
    if axis not in ("horizontal", "vertical"):
        raise InvalidInputError("axis", "'horizontal' (rows) or 'vertical' (columns)", axis)
    if not (0.0 <= start < stop <= 1.0):
        raise InvalidInputError("start, stop", "fractions with 0 <= start < stop <= 1", (start, stop))
    h, w = sparse.image_size
    coord, size = (sparse.v, h) if axis == "horizontal" else (sparse.u, w)
    pos = (coord + 0.5) / size  # pixel-centre convention: pixel i covers [i/size, (i+1)/size)
    return (pos >= start) & (pos < stop)


def sample_band(
    source: np.ndarray | SparseDepth,
    *,
    axis: Literal["horizontal", "vertical"] = "horizontal",
    start: float = 0.5,
    stop: float = 1.0,
    n: int | None = None,
    density: float | None = None,
    rng: SeedLike = 0,
) -> SparseDepth:
    """Biased measurements: a uniform random subset of the points inside one band of the image.

    ``n`` counts points in the band; ``density`` is a share of *all* available points (so a
    band and the uniform protocol at one density get the same number of points, when the band
    holds enough). See `band_mask` for the band.
    """
    avail = as_available(source)
    inside = avail.subset(band_mask(avail, axis=axis, start=start, stop=stop))
    if density is not None:
        k = _count(len(avail), None, density)
        return sample_uniform(inside, n=min(k, len(inside)), rng=rng)
    return sample_uniform(inside, n=n, rng=rng)


def lidar_elevation(
    sparse: SparseDepth, calibration: LidarCalibration | None = None, camera: PinholeCamera | None = None
) -> np.ndarray:
    """Elevation angle (degrees) of each projected LiDAR point, seen from the LiDAR.

    The points are lifted back to 3-D with the projection matrix (``calibration.P``, exact for
    KITTI's ``P2`` including its baseline term) and moved into the LiDAR frame with
    ``calibration.T_camera_lidar``; the elevation is atan2(z, hypot(x, y)) there. Without a
    calibration the camera is used (``camera`` required) and the elevation is measured from the
    camera centre, with y down (coarser: it ignores the LiDAR's offset and tilt).

    Args:
        sparse: Projected LiDAR points (z-depth in metres).
        calibration: LiDAR-to-camera calibration the points were projected with.
        camera: The camera, when no calibration is given (must match ``sparse.image_size``).

    Returns:
        (N,) elevations in degrees.
    """
    u, v, d = sparse.u, sparse.v, sparse.depth
    if calibration is not None:
        P = calibration.P
        z = d - P[2, 3]  # the depth written by LidarCalibration.project is P's third row
        x = (u * d - P[0, 2] * z - P[0, 3]) / P[0, 0]
        y = (v * d - P[1, 2] * z - P[1, 3]) / P[1, 1]
        cam = np.stack([x, y, z], axis=1)
        T = np.linalg.inv(calibration.T_camera_lidar)
        p = cam @ T[:3, :3].T + T[:3, 3]
        return np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    if camera is None:
        raise InvalidInputError("calibration, camera", "a LidarCalibration or a PinholeCamera", None)
    if camera.shape != sparse.image_size:
        raise ShapeError("camera", f"a camera of the image size {sparse.image_size}", camera.shape)
    p = camera.backproject_pixels(sparse.uv, d)
    return np.degrees(np.arctan2(-p[:, 1], np.hypot(p[:, 0], p[:, 2])))


def beam_ids(elevation_deg: np.ndarray, *, min_separation_deg: float = 0.25, bin_deg: float = 0.02) -> np.ndarray:
    """Beam index of each point from its elevation angle (0 = the highest beam).

    A multi-beam LiDAR (KITTI: Velodyne HDL-64E, beams 1/3 to 1/2 degree apart) sweeps each beam
    at a fixed elevation, so the histogram of elevations has one peak per beam; pixel rounding
    and the beams' different mounting heights widen the peaks for near points. The histogram
    (``bin_deg`` bins, lightly smoothed) is split at its minima between peaks that are at least
    ``min_separation_deg`` apart, and each point gets the index of its peak.

    Args:
        elevation_deg: (N,) elevations in degrees (see `lidar_elevation`).
        min_separation_deg: Smallest angle between two beams, degrees.
        bin_deg: Histogram bin width, degrees.

    Returns:
        (N,) int beam ids, 0 for the highest beam, increasing downwards.
    """
    from scipy.ndimage import gaussian_filter1d
    from scipy.signal import find_peaks

    e = np.asarray(elevation_deg, dtype=np.float64)
    if e.ndim != 1 or not np.all(np.isfinite(e)):
        raise InvalidInputError("elevation_deg", "a 1-D array of finite angles", describe(e))
    if not (np.isfinite(min_separation_deg) and min_separation_deg > 0 and np.isfinite(bin_deg) and bin_deg > 0):
        raise InvalidInputError("min_separation_deg, bin_deg", "angles > 0", (min_separation_deg, bin_deg))
    if e.size == 0:
        return np.zeros(0, dtype=np.int64)
    x = -e  # highest beam first
    lo = x.min() - 2 * min_separation_deg
    n_bins = int(np.ceil((x.max() + 2 * min_separation_deg - lo) / bin_deg)) + 1
    hist = np.bincount(((x - lo) / bin_deg).astype(np.int64), minlength=n_bins).astype(np.float64)
    smooth = gaussian_filter1d(hist, sigma=max(1.0, 0.1 * min_separation_deg / bin_deg))
    distance = max(1, int(min_separation_deg / bin_deg))
    peaks, _ = find_peaks(smooth, distance=distance, prominence=0.05 * smooth.max())
    if peaks.size <= 1:
        return np.zeros(e.size, dtype=np.int64)
    cuts = np.array([a + int(np.argmin(smooth[a : b + 1])) for a, b in zip(peaks[:-1], peaks[1:])])
    edges = lo + (cuts + 0.5) * bin_deg
    return np.searchsorted(edges, x).astype(np.int64)


def sample_scanlines(
    sparse: SparseDepth,
    *,
    keep_every: int,
    offset: int = 0,
    calibration: LidarCalibration | None = None,
    camera: PinholeCamera | None = None,
    beams: np.ndarray | None = None,
) -> SparseDepth:
    """Simulates a LiDAR with fewer beams: keeps the points of every ``keep_every``-th beam.

    Args:
        sparse: Projected LiDAR points.
        keep_every: k >= 1: beams offset, offset + k, offset + 2k, ... are kept (64 -> 16 beams
            with k = 4).
        offset: First kept beam, 0 <= offset < k.
        calibration: For `lidar_elevation` (preferred).
        camera: For `lidar_elevation` when there is no calibration.
        beams: (N,) beam ids if already known (skips the elevation clustering).
    """
    if int(keep_every) != keep_every or keep_every < 1:
        raise InvalidInputError("keep_every", "an integer >= 1", keep_every)
    if int(offset) != offset or not 0 <= offset < keep_every:
        raise InvalidInputError("offset", f"an integer in [0, {keep_every})", offset)
    if beams is None:
        beams = beam_ids(lidar_elevation(sparse, calibration, camera))
    beams = np.asarray(beams)
    if beams.shape != (len(sparse),):
        raise ShapeError("beams", f"shape ({len(sparse)},) like sparse", describe(beams))
    return sparse.subset((beams - offset) % keep_every == 0)


def holdout_mask(n: int, *, holdout: float = 0.2, rng: SeedLike = 0) -> np.ndarray:
    """Which of ``n`` measurements are held out: a seeded random ``holdout`` share, at least one kept.

    The one hold-out rule (`holdout_split`, the evaluation's frames): round(holdout * n)
    measurements, at least 1 and at most n - 1, chosen by one ``permutation(n)`` of ``rng``.

    Args:
        n: Number of measurements, >= 2.
        holdout: Share held out, in (0, 1).
        rng: Seed or Generator.

    Returns:
        (n,) bool, True = held out.
    """
    if not np.isfinite(holdout) or not 0 < holdout < 1:
        raise InvalidInputError("holdout", "a share in (0, 1)", holdout)
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)):
        raise InvalidInputError("n", "an integer number of measurements", describe(n))
    if n < 2:
        raise EmptyInputError("sparse", "at least two measurements to split", int(n))
    n_out = min(n - 1, max(1, int(round(holdout * n))))
    perm = make_rng(rng).permutation(n)
    test = np.zeros(n, dtype=bool)
    test[perm[:n_out]] = True
    return test


def holdout_split(sparse: SparseDepth, *, holdout: float = 0.2, rng: SeedLike = 0) -> tuple[SparseDepth, SparseDepth]:
    """Splits measurements into an input share and a held-out share used as ground truth.

    Args:
        sparse: All measurements.
        holdout: Share held out, in (0, 1) (`holdout_mask`).
        rng: Seed or Generator.

    Returns:
        (input points, held-out points); disjoint, together all points.
    """
    test = holdout_mask(len(sparse), holdout=holdout, rng=rng)
    return sparse.subset(~test), sparse.subset(test)


def gross_outliers(
    sparse: SparseDepth, share: float, *, rng: SeedLike = 0, low: float = 0.1, high: float = 3.0
) -> SparseDepth:
    """The measurements with a ``share`` of them turned into gross outliers (robustness experiments).

    round(share * n) measurements, chosen without replacement, get their depth multiplied by a
    factor drawn uniformly from [low, high]; each keeps its sigma (an outlier that claims a good
    point's precision). Positions and the other depths are unchanged.

    Args:
        sparse: The clean measurements.
        share: Share corrupted, in [0, 1].
        rng: Seed or Generator (the indices are drawn first, then the factors).
        low, high: Range of the depth factor, 0 < low < high.

    Returns:
        A new `SparseDepth`.

    Raises:
        InvalidInputError: share outside [0, 1], or not 0 < low < high.
    """
    if not np.isfinite(share) or not 0.0 <= share <= 1.0:
        raise InvalidInputError("share", "a share in [0, 1]", share)
    if not (np.isfinite(low) and np.isfinite(high) and 0.0 < low < high):
        raise InvalidInputError("low, high", "0 < low < high", (low, high))
    rng = make_rng(rng)
    k = int(round(share * len(sparse)))
    idx = rng.choice(len(sparse), k, replace=False)
    depth = np.array(sparse.depth, dtype=np.float64, copy=True)
    depth[idx] *= rng.uniform(low, high, k)
    return SparseDepth(sparse.u, sparse.v, depth, sparse.image_size, sparse.sigma)
