"""World points from a system we did not write (a COLMAP model, a SLAM map), with a calibrated depth sigma.

`read_given_points` reads a COLMAP sparse model (binary or text; a folder of numbered models is one
piece per model: a SLAM or SfM run that lost tracking and started again), or world points with an
optional per-point sigma: a PLY with a ``sigma`` property, an NPZ with ``xyz`` and ``sigma``, or a
text file of lines ``x y z [sigma]`` (metres).

`PointSigmaRule` gives the depth sigma of such a point seen from a camera. Neither a stated sigma nor
COLMAP's reprojection error is honest about the depth of a point against the true surface (pose error,
matches on edges, the sensor's own registration); the rule widens them by factors fitted so that
``±2 sigma`` covers 95 % of the points against sensor depth (`fit_sigma_rule`;
docs/mapping.md gives the rule and its coverage on the shared sequences).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...camera import PinholeCamera, transform_points
from ...errors import DataFormatError, InvalidInputError, ShapeError, describe
from ...io.poses import ColmapModel, invert_pose, read_colmap_model

POINT_FILE_SUFFIXES = (".ply", ".npz", ".txt", ".xyz")
"""Endings of world-point files `read_given_points` reads (besides COLMAP model folders)."""


@dataclass(frozen=True)
class GivenPoints:
    """One piece of given world points (one COLMAP model, or one points file).

    Attributes:
        points: (M, 3) world positions, metres (a COLMAP model's units for a model).
        sigma: (M,) stated depth sigma per point, metres, or None when the source states none.
        reprojection_error: (M,) mean reprojection error per point, pixels (COLMAP), or None.
        angle_deg: (M,) largest angle between two rays that observe each point, degrees (COLMAP), or None.
        model: The COLMAP model (poses, cameras, which image observes which point), or None.
        source: The file or folder read.
    """

    points: np.ndarray
    sigma: np.ndarray | None = None
    reprojection_error: np.ndarray | None = None
    angle_deg: np.ndarray | None = None
    model: ColmapModel | None = None
    source: str = ""
    _rows: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.points)

    def observed_by(self, image_id: int) -> np.ndarray:
        """Indices (into ``points``) of the points a COLMAP image observes."""
        if self.model is None:
            raise InvalidInputError("image_id", "a COLMAP model's image (these points have no model)", image_id)
        if image_id not in self.model.images:
            raise InvalidInputError("image_id", "the id of an image of the model", image_id)
        if not self._rows:
            self._rows.update({int(pid): i for i, pid in enumerate(self.model.point_ids)})
        ids = self.model.images[image_id].point3D_ids
        return np.array([self._rows[int(p)] for p in ids if int(p) in self._rows], dtype=np.int64)


@dataclass(frozen=True)
class PointSigmaRule:
    """Depth sigma of a given point seen from a camera: a share of its distance, widened by its geometry.

    ``sigma = d * sqrt(relative**2 + (geometric * e / (f * sin(a)))**2)``, with ``d`` the point's
    distance from the camera (metres), ``e`` its reprojection error (pixels, at least ``min_error_px``),
    ``f`` the focal length (pixels) and ``a`` its largest ray angle; ``e / (f sin a)`` is the relative
    depth error a triangulation with that angle and pixel error makes. A stated sigma ``s`` is kept
    and widened the same way: ``sqrt(s**2 + (relative * d)**2)``. Without reprojection error or angle
    only the relative term counts. The defaults are fitted on pycolmap's points of the shared 7-Scenes
    frames (exact poses, ``±2 sigma`` covering 95 % against the Kinect depth) and checked on the
    HoloLens walk (docs/mapping.md).

    Attributes:
        relative: Share of the distance every point is uncertain by (pose error, matches on edges).
        geometric: Factor on the triangulation's own relative error.
        min_error_px: Smallest reprojection error used, pixels.
    """

    relative: float = 0.03
    geometric: float = 4.0
    min_error_px: float = 0.5

    def __post_init__(self) -> None:
        if not (np.isfinite(self.relative) and self.relative > 0):
            raise InvalidInputError("relative", "a finite share > 0", self.relative)
        for name in ("geometric", "min_error_px"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InvalidInputError(name, "a finite value >= 0", value)

    def sigma(
        self,
        distance: np.ndarray,
        *,
        stated: np.ndarray | None = None,
        reprojection_error: np.ndarray | None = None,
        angle_deg: np.ndarray | None = None,
        focal: float | None = None,
    ) -> np.ndarray:
        """(M,) depth sigma, metres, of points at ``distance`` (metres) from a camera; > 0 by construction."""
        d = np.asarray(distance, dtype=np.float64)
        rel2 = np.full(d.shape, self.relative**2)
        if self.geometric > 0 and reprojection_error is not None and angle_deg is not None and focal:
            e = np.maximum(np.asarray(reprojection_error, dtype=np.float64), self.min_error_px)
            s = np.sin(np.radians(np.clip(np.asarray(angle_deg, dtype=np.float64), 0.1, 90.0)))
            rel2 = rel2 + (self.geometric * e / (float(focal) * s)) ** 2
        var = rel2 * d**2
        if stated is not None:
            var = var + np.asarray(stated, dtype=np.float64) ** 2
        return np.sqrt(np.maximum(var, 1e-12))


def visible_points(
    points_world: np.ndarray,
    T_world_camera: np.ndarray,
    camera: PinholeCamera,
    *,
    cell: int = 8,
    tolerance: float = 0.1,
) -> np.ndarray:
    """Indices of the world points a camera sees: in front, inside the image, not behind a nearer point.

    A world-point file says nothing of which camera saw which point; a point far behind a nearer one
    that projects into the same ``cell`` x ``cell`` pixels is taken as hidden (more than ``tolerance``
    of the nearer one's depth behind it).
    """
    p_cam = transform_points(invert_pose(np.asarray(T_world_camera, dtype=np.float64)), points_world)
    z = p_cam[:, 2]
    idx = np.flatnonzero(z > 1e-3)
    uv, _ = camera.project(p_cam[idx])
    inside = camera.in_image(uv)
    idx, uv = idx[inside], uv[inside]
    if idx.size == 0:
        return idx
    cols = -(-camera.width // cell)
    key = (np.rint(uv[:, 1]).astype(np.int64) // cell) * cols + np.rint(uv[:, 0]).astype(np.int64) // cell
    nearest = np.full(key.max() + 1, np.inf)
    np.minimum.at(nearest, key, z[idx])
    return idx[z[idx] <= (1.0 + tolerance) * nearest[key]]


def sigma_coverage(relative_error: np.ndarray, relative_sigma: np.ndarray, k: float = 2.0) -> float:
    """Share of points whose error lies within ``±k`` sigma (both relative to the depth, or both metres)."""
    e, s = np.abs(np.asarray(relative_error, dtype=np.float64)), np.asarray(relative_sigma, dtype=np.float64)
    if e.size == 0 or e.shape != s.shape:
        raise ShapeError("relative_sigma", f"one sigma per error ({e.size}, at least one)", describe(s))
    return float(np.mean(e <= k * s))


def fit_sigma_rule(
    relative_error: np.ndarray,
    *,
    reprojection_error: np.ndarray | None = None,
    angle_deg: np.ndarray | None = None,
    focal: float | None = None,
    coverage: float = 0.95,
    geometric: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 2.0),
) -> PointSigmaRule:
    """The `PointSigmaRule` whose ``±2 sigma`` covers ``coverage`` of the points with the smallest median sigma.

    For each factor of ``geometric``, the ``relative`` share that makes the coverage exact is found by
    bisection; of those rules the sharpest (smallest median sigma) is returned.

    Args:
        relative_error: (M,) signed depth errors of points against a reference, over the reference depth.
        reprojection_error: (M,) their reprojection errors, pixels (without: only ``relative`` is fitted).
        angle_deg: (M,) their largest ray angles, degrees.
        focal: Focal length, pixels.
        coverage: Share of points to cover at ``±2 sigma``.
        geometric: Factors on the triangulation error tried.

    Raises:
        InvalidInputError: a coverage outside (0, 1) or no error given.
    """
    e = np.abs(np.asarray(relative_error, dtype=np.float64))
    if e.size == 0:
        raise InvalidInputError("relative_error", "at least one error", 0)
    if not 0 < coverage < 1:
        raise InvalidInputError("coverage", "a share in (0, 1)", coverage)
    has_geometry = reprojection_error is not None and angle_deg is not None and focal
    best, best_width = None, np.inf
    for g in geometric if has_geometry else (0.0,):
        lo, hi = 1e-5, 10.0
        for _ in range(60):
            mid = np.sqrt(lo * hi)
            rule = PointSigmaRule(relative=mid, geometric=g)
            width = rule.sigma(np.ones_like(e), reprojection_error=reprojection_error, angle_deg=angle_deg, focal=focal)
            lo, hi = (lo, mid) if np.mean(e <= 2 * width) >= coverage else (mid, hi)
        rule = PointSigmaRule(relative=hi, geometric=g)
        width = float(
            np.median(
                rule.sigma(np.ones_like(e), reprojection_error=reprojection_error, angle_deg=angle_deg, focal=focal)
            )
        )
        if width < best_width:
            best, best_width = rule, width
    return best


def ray_angles(model: ColmapModel) -> np.ndarray:
    """(M,) largest angle between two of the rays that observe each point of a COLMAP model, degrees."""
    rows = {int(pid): i for i, pid in enumerate(model.point_ids)}
    seen: list[list[np.ndarray]] = [[] for _ in range(len(model.point_ids))]
    for image in model.images.values():
        centre = image.T_world_camera[:3, 3]
        for pid in image.point3D_ids:
            i = rows.get(int(pid))
            if i is not None:
                seen[i].append(centre)
    angles = np.zeros(len(model.point_ids))
    for i, centres in enumerate(seen):
        if len(centres) < 2:
            continue
        rays = np.asarray(centres) - model.points[i]
        rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
        angles[i] = np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0)))
    return angles


def _from_model(folder: Path) -> GivenPoints:
    model = read_colmap_model(folder, ignore_distortion=True)
    return GivenPoints(
        points=model.points,
        reprojection_error=model.errors,
        angle_deg=ray_angles(model),
        model=model,
        source=str(folder),
    )


def _is_model(folder: Path) -> bool:
    return any((folder / f"images.{ext}").is_file() for ext in ("bin", "txt"))


def _checked(path: Path, xyz, sigma) -> GivenPoints:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise ShapeError(str(path), "(M, 3) world points, M >= 1", describe(xyz))
    keep = np.all(np.isfinite(xyz), axis=1)
    if sigma is not None:
        sigma = np.asarray(sigma, dtype=np.float64).reshape(-1)
        if sigma.shape != (len(xyz),):
            raise ShapeError(str(path), f"one sigma per point ({len(xyz)})", describe(sigma))
        if np.any(sigma[keep] < 0) or not np.all(np.isfinite(sigma[keep])):
            raise DataFormatError(path, "sigma: finite values >= 0 metres expected")
        sigma = sigma[keep]
    return GivenPoints(points=xyz[keep], sigma=sigma, source=str(path))


def _read_file(path: Path) -> GivenPoints:
    suffix = path.suffix.lower()
    if suffix == ".npz":
        from ...io import load_npz_arrays

        import zipfile

        try:
            with np.load(path, allow_pickle=False) as data:
                names = ["xyz", "sigma"] if "sigma" in getattr(data, "files", ()) else ["xyz"]
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            names = ["xyz"]  # load_npz_arrays names what is wrong with the file
        arrays = load_npz_arrays(path, names, "world points")
        return _checked(path, arrays["xyz"], arrays.get("sigma"))
    if suffix == ".ply":
        from ...extras import require

        o3d = require("open3d")
        cloud = o3d.t.io.read_point_cloud(str(path))
        if "positions" not in cloud.point or cloud.point.positions.shape[0] == 0:
            raise DataFormatError(path, "no points (not a PLY point cloud?)")
        sigma = cloud.point.sigma.numpy() if "sigma" in cloud.point else None
        return _checked(path, cloud.point.positions.numpy(), sigma)
    try:
        table = np.loadtxt(path, ndmin=2, comments="#")
    except ValueError as exc:
        raise DataFormatError(path, f"lines 'x y z [sigma]' expected ({exc})") from None
    if table.shape[1] not in (3, 4):
        raise DataFormatError(path, f"lines 'x y z [sigma]' expected, got {table.shape[1]} columns")
    return _checked(path, table[:, :3], table[:, 3] if table.shape[1] == 4 else None)


def read_given_points(path: str | Path) -> list[GivenPoints]:
    """Reads world points: a COLMAP model, a folder of numbered COLMAP models (one piece each), or a points file.

    Args:
        path: A COLMAP sparse model folder (``cameras``, ``images``, ``points3D`` as .bin or .txt), a
            folder whose sub-folders are such models (``sparse/0``, ``sparse/1``: pieces, largest
            first), or a file: PLY (x y z, optional ``sigma``), NPZ (``xyz`` (M, 3), optional ``sigma``
            (M,)) or text (``x y z [sigma]`` a line, ``#`` comments), metres.

    Returns:
        The pieces, the one with the most points first (one for a file or a single model).

    Raises:
        DataFormatError: a missing path, an unreadable file or model, a folder without models.
        ShapeError: points that are not (M, 3), a sigma per point that does not match.
    """
    path = Path(path)
    if path.is_dir():
        if _is_model(path):
            return [_from_model(path)]
        subs = sorted((p for p in path.iterdir() if p.is_dir() and _is_model(p)), key=lambda p: p.name)
        if not subs:
            raise DataFormatError(path, "no COLMAP model here (images.bin / images.txt, or sub-folders with them)")
        pieces = [_from_model(p) for p in subs]
        return sorted(pieces, key=lambda g: -len(g.model.images))
    if not path.is_file():
        raise DataFormatError(path, "points file or COLMAP model folder not found")
    if path.suffix.lower() not in POINT_FILE_SUFFIXES:
        raise DataFormatError(path, f"a points file ({', '.join(POINT_FILE_SUFFIXES)}) or a COLMAP model folder")
    return [_read_file(path)]
