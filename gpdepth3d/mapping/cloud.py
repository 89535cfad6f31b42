"""Coloured point clouds with per-point depth uncertainty, from a depth posterior.

A `ColoredCloud` holds one point per valid pixel of a depth map: its position (metres, in the
camera frame or, after `ColoredCloud.transformed`, in the world), its colour, the posterior
variance of its depth and a confidence weight derived from it.

Confidence (documented once, here): with the depth standard deviation ``sigma`` (metres) and the
z-depth ``z`` (metres), the *relative sigma* is ``rho = sigma / z`` and

    confidence = 1 / (1 + (rho / rho_ref)^2)        in (0, 1]

with ``rho_ref`` = `DEFAULT_RHO_REF` (0.05: a point whose sigma is 5 % of its depth has
confidence 0.5; 1 % gives 0.96, 20 % gives 0.06). It is scale free (the same at 1 m and at 30 m,
as depth errors of triangulation and of monocular networks grow with depth), monotone in the
variance, and 1 exactly when the variance is 0. Points without a variance (plain depth maps)
get confidence 1 and variance NaN.

PLY files (`ColoredCloud.save_ply`) are binary little-endian with the vertex properties
``x y z`` (float32, metres), ``red green blue`` (uchar), ``confidence`` (float32), ``sigma``
(float32, metres) and ``variance`` (float32, m^2). Open3D's tensor reader
(``open3d.t.io.read_point_cloud``) returns them as the point attributes ``positions``,
``colors``, ``confidence``, ``sigma`` and ``variance``; trimesh returns a ``PointCloud`` with the
colours and keeps the other properties in ``metadata["_ply_raw"]["vertex"]["data"]``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..camera import PinholeCamera, check_pose, transform_points
from ..errors import DataFormatError, EmptyInputError, InvalidDepthError, InvalidInputError, ShapeError, describe
from ..extras import require
from ..io import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from ..completion.complete import DepthPosterior

DEFAULT_RHO_REF = 0.05
"""Relative sigma (sigma / depth) at which the confidence is 0.5."""


class MaskedDepthWarning(UserWarning):
    """Depth values that break the convention (negative) were masked as "no depth"; the message counts them."""


def confidence_from_variance(
    variance: np.ndarray, depth: np.ndarray, *, rho_ref: float = DEFAULT_RHO_REF
) -> np.ndarray:
    """Confidence weight ``1 / (1 + (sigma / depth / rho_ref)^2)`` in (0, 1] (see the module docstring).

    Args:
        variance: Depth variance, m^2, any shape; NaN means unknown (confidence 1).
        depth: z-depth, metres, > 0, the same shape.
        rho_ref: Relative sigma at which the confidence is 0.5.

    Returns:
        Confidence, the shape of ``variance``.
    """
    variance = np.asarray(variance, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    if variance.shape != depth.shape:
        raise ShapeError("variance", f"the shape of depth {depth.shape}", describe(variance))
    if not np.isfinite(rho_ref) or rho_ref <= 0:
        raise InvalidInputError("rho_ref", "a finite relative sigma > 0", rho_ref)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho2 = np.maximum(variance, 0.0) / depth**2 / rho_ref**2
    return np.where(np.isnan(variance), 1.0, 1.0 / (1.0 + rho2))


@dataclass(frozen=True)
class ColoredCloud:
    """A coloured point cloud with per-point depth variance and confidence.

    Attributes:
        points: (N, 3) float64 positions, metres (camera frame unless transformed).
        colors: (N, 3) uint8 RGB.
        variance: (N,) float64 variance of each point's z-depth in the camera it was seen from,
            m^2 (NaN = unknown).
        confidence: (N,) float64 confidence in (0, 1] (see the module docstring).
        depth: (N,) float64 z-depth of each point in the camera it was seen from, metres
            (kept through `transformed` so that ``sigma / depth`` stays available).
    """

    points: np.ndarray
    colors: np.ndarray
    variance: np.ndarray
    confidence: np.ndarray
    depth: np.ndarray | None = None

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ShapeError("points", "an (N, 3) array", describe(p))
        n = p.shape[0]
        c = np.asarray(self.colors)
        if c.shape != (n, 3):
            raise ShapeError("colors", f"an ({n}, 3) array", describe(c))
        if c.dtype != np.uint8:
            if np.issubdtype(c.dtype, np.floating) or np.any(c < 0) or np.any(c > 255):
                raise InvalidInputError("colors", "uint8 RGB values (0..255)", describe(c))
            c = c.astype(np.uint8)
        arrays = {}
        for name in ("variance", "confidence", "depth"):
            value = getattr(self, name)
            if value is None:
                value = p[:, 2] if name == "depth" else np.full(n, np.nan)
            a = np.asarray(value, dtype=np.float64)
            if a.shape != (n,):
                raise ShapeError(name, f"shape ({n},)", describe(a))
            arrays[name] = a
        if not np.all(np.isfinite(p)):
            raise InvalidDepthError("points", "finite coordinates", "NaN or inf")
        conf = arrays["confidence"]
        if np.any(~np.isfinite(conf)) or np.any(conf < 0) or np.any(conf > 1):
            raise InvalidInputError("confidence", "values in [0, 1]", "values outside")
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "colors", c)
        for name, a in arrays.items():
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def sigma(self) -> np.ndarray:
        """(N,) depth standard deviation, metres (NaN = unknown)."""
        return np.sqrt(np.maximum(self.variance, 0.0))

    @property
    def relative_sigma(self) -> np.ndarray:
        """(N,) sigma / depth (dimensionless; NaN = unknown)."""
        return self.sigma / self.depth

    # ------------------------------------------------------------------ operations
    def subset(self, index: np.ndarray) -> "ColoredCloud":
        """The points selected by a boolean mask or an index array."""
        return ColoredCloud(
            self.points[index], self.colors[index], self.variance[index], self.confidence[index], self.depth[index]
        )

    def filter(
        self,
        *,
        min_confidence: float | None = None,
        max_relative_sigma: float | None = None,
        max_sigma: float | None = None,
    ) -> "ColoredCloud":
        """Keeps the points passing every given threshold.

        Args:
            min_confidence: Keep confidence >= this (0..1).
            max_relative_sigma: Keep sigma / depth <= this (points with unknown variance pass).
            max_sigma: Keep sigma <= this, metres (points with unknown variance pass).

        Returns:
            The filtered cloud (possibly empty).
        """
        keep = np.ones(len(self), dtype=bool)
        if min_confidence is not None:
            if not 0.0 <= min_confidence <= 1.0:
                raise InvalidInputError("min_confidence", "a value in [0, 1]", min_confidence)
            keep &= self.confidence >= min_confidence
        unknown = np.isnan(self.variance)
        if max_relative_sigma is not None:
            if not max_relative_sigma > 0:
                raise InvalidInputError("max_relative_sigma", "a value > 0", max_relative_sigma)
            keep &= unknown | (self.relative_sigma <= max_relative_sigma)
        if max_sigma is not None:
            if not max_sigma > 0:
                raise InvalidInputError("max_sigma", "a value > 0 (metres)", max_sigma)
            keep &= unknown | (self.sigma <= max_sigma)
        return self.subset(keep)

    def transformed(self, T: np.ndarray) -> "ColoredCloud":
        """The cloud moved by a rigid 4x4 transform (e.g. ``T_world_camera``); depths are kept."""
        T = check_pose(T, "T")
        return ColoredCloud(transform_points(T, self.points), self.colors, self.variance, self.confidence, self.depth)

    def concatenate(self, *others: "ColoredCloud") -> "ColoredCloud":
        """This cloud followed by others (all in the same frame)."""
        clouds = (self, *others)
        return ColoredCloud(
            np.concatenate([c.points for c in clouds]),
            np.concatenate([c.colors for c in clouds]),
            np.concatenate([c.variance for c in clouds]),
            np.concatenate([c.confidence for c in clouds]),
            np.concatenate([c.depth for c in clouds]),
        )

    # ------------------------------------------------------------------ conversion / export
    def to_open3d(self, device: str = "CPU:0") -> Any:
        """An ``open3d.t.geometry.PointCloud`` with positions, colors (float32 0..1), confidence, sigma, variance."""
        o3d = require("open3d")
        o3c = require("open3d.core")

        dev = o3c.Device(device)
        pcd = o3d.t.geometry.PointCloud(dev)
        pcd.point.positions = o3c.Tensor(self.points.astype(np.float32), device=dev)
        pcd.point.colors = o3c.Tensor(self.colors.astype(np.float32) / 255.0, device=dev)
        pcd.point.confidence = o3c.Tensor(self.confidence.astype(np.float32)[:, None], device=dev)
        pcd.point.sigma = o3c.Tensor(self.sigma.astype(np.float32)[:, None], device=dev)
        pcd.point.variance = o3c.Tensor(self.variance.astype(np.float32)[:, None], device=dev)
        return pcd

    def to_trimesh(self) -> Any:
        """A ``trimesh.PointCloud`` with RGBA colours; confidence, sigma and variance in ``metadata``."""
        import trimesh

        rgba = np.concatenate([self.colors, np.full((len(self), 1), 255, np.uint8)], axis=1)
        pc = trimesh.PointCloud(self.points.copy(), colors=rgba)
        pc.metadata.update(
            {"confidence": self.confidence.copy(), "sigma": self.sigma, "variance": self.variance.copy()}
        )
        return pc

    def save_ply(self, path: str | Path) -> Path:
        """Writes a binary PLY (format in the module docstring) atomically; returns the path.

        Raises:
            EmptyInputError: if the cloud has no points.
        """
        if len(self) == 0:
            raise EmptyInputError("cloud", "at least one point to write", "an empty cloud")
        path = Path(path)
        if path.suffix.lower() != ".ply":
            raise InvalidInputError("path", "a .ply file name", str(path))
        vertex = np.empty(
            len(self),
            dtype=[
                ("x", "<f4"),
                ("y", "<f4"),
                ("z", "<f4"),
                ("red", "u1"),
                ("green", "u1"),
                ("blue", "u1"),
                ("confidence", "<f4"),
                ("sigma", "<f4"),
                ("variance", "<f4"),
            ],
        )
        for i, axis in enumerate("xyz"):
            vertex[axis] = self.points[:, i]
        for i, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = self.colors[:, i]
        vertex["confidence"] = self.confidence
        vertex["sigma"] = self.sigma
        vertex["variance"] = self.variance
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment gpdepth3d ColoredCloud\n"
            f"element vertex {len(self)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            "property float confidence\nproperty float sigma\nproperty float variance\nend_header\n"
        )
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                f.write(header.encode("ascii"))
                f.write(vertex.tobytes())
        return path

    @classmethod
    def load_ply(cls, path: str | Path) -> "ColoredCloud":
        """Reads a PLY written by `save_ply` (or any PLY point cloud with x y z and colours) via Open3D.

        Missing ``confidence``/``variance`` properties become 1 / NaN. Depth along the original
        ray is not stored in the file; it is taken as the point's z.
        """
        o3d = require("open3d")

        path = Path(path)
        if not path.is_file():
            raise DataFormatError(path, "PLY file not found")
        pcd = o3d.t.io.read_point_cloud(str(path))
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            raise DataFormatError(path, "no points (not a PLY point cloud?)")
        pts = pcd.point.positions.numpy().astype(np.float64)
        n = pts.shape[0]
        if "colors" in pcd.point:
            col = pcd.point.colors.numpy()
            col = np.rint(col * 255.0) if np.issubdtype(col.dtype, np.floating) else col
            col = np.clip(col, 0, 255).astype(np.uint8)
        else:
            col = np.zeros((n, 3), np.uint8)
        conf = pcd.point.confidence.numpy().reshape(n) if "confidence" in pcd.point else np.ones(n)
        var = pcd.point.variance.numpy().reshape(n) if "variance" in pcd.point else np.full(n, np.nan)
        return cls(pts, col, var.astype(np.float64), np.clip(conf.astype(np.float64), 0.0, 1.0))


# ---------------------------------------------------------------------- construction
def _check_rgb(rgb: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    if rgb.ndim != 3 or rgb.shape[2] not in (3, 4):
        raise ShapeError("rgb", "an (H, W, 3) RGB image", describe(rgb))
    camera.check_image(rgb, "rgb")
    if rgb.dtype != np.uint8:
        if np.issubdtype(rgb.dtype, np.floating) and rgb.size and np.nanmax(rgb) <= 1.0:
            rgb = np.clip(rgb * 255.0, 0, 255)
        rgb = np.clip(np.nan_to_num(rgb), 0, 255).astype(np.uint8)
    return rgb[..., :3]


def backproject_depth(
    depth: np.ndarray,
    rgb: np.ndarray,
    camera: PinholeCamera,
    *,
    variance: np.ndarray | None = None,
    T_world_camera: np.ndarray | None = None,
    min_depth: float = 0.0,
    max_depth: float = np.inf,
    rho_ref: float = DEFAULT_RHO_REF,
    stride: int = 1,
) -> ColoredCloud:
    """Lifts a depth map with its RGB image to a coloured cloud with per-point variance.

    Args:
        depth: (H, W) z-depth, metres (0/NaN/inf = no depth; negative values are masked the
            same way, with a `MaskedDepthWarning` counting them); (H, W) must be the camera's.
        rgb: (H, W, 3) RGB image of the same size (uint8, or float in 0..1).
        camera: Intrinsics of the depth map.
        variance: Optional (H, W) depth variance, m^2, >= 0 (InvalidInputError otherwise); pixels with
            non-finite variance are dropped.
        T_world_camera: Optional 4x4 pose; the points are returned in the world frame.
        min_depth: Pixels with depth <= this are dropped (metres).
        max_depth: Pixels with depth > this are dropped (metres).
        rho_ref: Relative sigma at confidence 0.5 (see the module docstring).
        stride: Keep every ``stride``-th row and column (1 = all pixels).

    Returns:
        The cloud, row-major pixel order.

    Raises:
        ShapeError: if depth, rgb, variance and camera sizes disagree.
        EmptyInputError: if no pixel has a valid depth.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ShapeError("depth", "a 2-D (H, W) depth map", describe(d))
    camera.check_image(d, "depth")
    d = d.astype(np.float64)
    finite = np.isfinite(d)
    with np.errstate(invalid="ignore"):
        negative = finite & (d < 0)
    if negative.any():
        # a posterior mean can dip below zero next to an outlier measurement: masked, counted, not fatal
        warnings.warn(
            f"depth: {int(negative.sum())} pixels with negative depth (minimum {d[negative].min():.3g} m) masked",
            MaskedDepthWarning,
            stacklevel=2,
        )
        d = np.where(negative, 0.0, d)
    rgb = _check_rgb(rgb, camera)
    if variance is not None:
        var = np.asarray(variance, dtype=np.float64)
        if var.shape != d.shape:
            raise ShapeError("variance", f"the shape of depth {d.shape}", describe(var))
        with np.errstate(invalid="ignore"):
            negative = var < -1e-12  # round-off of a posterior variance may dip a hair below 0
        if np.any(negative):
            raise InvalidInputError(
                "variance",
                "variances >= 0 m^2 (NaN = unknown)",
                f"{int(negative.sum())} negative, min {var[negative].min():.3g}",
            )
    else:
        var = np.full(d.shape, np.nan)
    if int(stride) != stride or stride < 1:
        raise InvalidInputError("stride", "an integer >= 1", stride)
    valid = finite & (d > max(min_depth, 0.0)) & (d <= max_depth)
    if variance is not None:
        valid &= np.isfinite(var)
    if stride > 1:
        keep = np.zeros_like(valid)
        keep[::stride, ::stride] = True
        valid &= keep
    if not valid.any():
        raise EmptyInputError("depth", "at least one pixel with a valid depth (and variance)", "none")
    u, v = camera.pixel_grid()
    uv = np.stack([u[valid], v[valid]], axis=1)
    z = d[valid]
    points = camera.backproject_pixels(uv, z)
    pvar = var[valid]
    conf = confidence_from_variance(pvar, z, rho_ref=rho_ref)
    cloud = ColoredCloud(points, rgb[valid], pvar, conf, z)
    if T_world_camera is not None:
        cloud = cloud.transformed(check_pose(T_world_camera))
    return cloud


def backproject_posterior(
    posterior: "DepthPosterior",
    rgb: np.ndarray,
    camera: PinholeCamera,
    *,
    T_world_camera: np.ndarray | None = None,
    min_depth: float = 0.0,
    max_depth: float = np.inf,
    rho_ref: float = DEFAULT_RHO_REF,
    stride: int = 1,
) -> ColoredCloud:
    """Back-projects a `DepthPosterior` (mean and variance) with its RGB image into a `ColoredCloud`.

    ``camera`` must describe the posterior's output grid (``posterior.shape``); use
    `PinholeCamera.resized` when the posterior has another resolution than the original image,
    and resize ``rgb`` to match. See `backproject_depth` for the other arguments.
    """
    mean = getattr(posterior, "mean", None)
    if mean is None or getattr(posterior, "variance", None) is None:
        raise InvalidInputError("posterior", "a DepthPosterior with mean and variance", type(posterior).__name__)
    return backproject_depth(
        posterior.mean,
        rgb,
        camera,
        variance=posterior.variance,
        T_world_camera=T_world_camera,
        min_depth=min_depth,
        max_depth=max_depth,
        rho_ref=rho_ref,
        stride=stride,
    )
