"""The viewer's scene data: what a frame brings (`ViewerFrame`), the options (`ViewerConfig`), and the
point layers built from them (back-projected MDE-only and GP-refined clouds, measurements, ground truth)."""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Optional

import numpy as np

from ..camera import PinholeCamera, check_pose
from ..io import load_pose
from ..checks import Choice, Int, check_fields, positive
from ..errors import DataFormatError, EmptyInputError, InvalidInputError, ShapeError, describe

if TYPE_CHECKING:  # pragma: no cover
    import trimesh

    from ..completion.complete import DepthPosterior
from .colors import MISSING_COLOR


ColorBy = Literal["rgb", "depth", "sigma", "error"]
Layout = Literal["side-by-side", "overlay"]
COLOR_MODES: tuple[str, ...] = ("rgb", "depth", "sigma", "error")
LAYOUTS: tuple[str, ...] = ("side-by-side", "overlay")


LAYER_LABELS = {"mde": "MDE only", "gp": "GP refined", "sparse": "Sparse measurements", "gt": "Ground truth"}
"""GUI/scene label of each point layer (keys are the layer names used in `Viewer.point_clouds`)."""


_SLOTS = {"mde": -1, "gp": 0, "sparse": 0, "cameras": 0, "gt": 1}


# ---------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class ViewerConfig:
    """Options of the viewer.

    Attributes:
        layout: "side-by-side" (layers shifted apart) or "overlay" (layers at their true place).
        color_by: Initial colouring: "rgb", "depth", "sigma" or "error" (error needs ground truth).
        max_points: At most this many points per layer (over all frames); frames are subsampled
            with a common pixel stride to stay below it.
        point_size: Point size in metres; None picks about one pixel's footprint at the median depth.
        frustum_scale: Size of the camera frustums in metres; None: 5 % of the scene extent.
        title: Label at the top of the GUI panel.
    """

    layout: Layout = "side-by-side"
    color_by: ColorBy = "rgb"
    max_points: int = 400_000
    point_size: Optional[float] = None
    frustum_scale: Optional[float] = None
    title: str = "gpdepth3d"

    def __post_init__(self) -> None:
        rules = {"layout": Choice(LAYOUTS), "color_by": Choice(COLOR_MODES), "max_points": Int(1)}
        rules.update(point_size=positive("metres", optional=True), frustum_scale=positive("metres", optional=True))
        check_fields(self, rules)


@dataclass(frozen=True)
class ViewerFrame:
    """One frame to show: a depth posterior with its camera, image, ground truth and pose.

    Attributes:
        posterior: The GP result (mean, variance, the MDE it started from and the measurements).
        camera: Intrinsics of the image; it is rescaled to the posterior's grid when the sizes
            differ (the aspect ratio must agree within 1 %).
        rgb: Optional (H', W', 3) uint8 image of the frame (any resolution of the same view);
            points are grey without it.
        depth_gt: Optional (H'', W'') ground-truth z-depth in metres (0/NaN = none), any
            resolution of the same view.
        T_world_camera: Optional 4x4 camera pose; None = identity (world = camera frame).
        name: Name shown for the frame (default "frame <index>").
    """

    posterior: "DepthPosterior"
    camera: PinholeCamera
    rgb: Optional[np.ndarray] = None
    depth_gt: Optional[np.ndarray] = None
    T_world_camera: Optional[np.ndarray] = None
    name: str = ""

    def __post_init__(self) -> None:
        mean = getattr(self.posterior, "mean", None)
        if mean is None or getattr(self.posterior, "variance", None) is None or np.ndim(mean) != 2:
            raise InvalidInputError("posterior", "a DepthPosterior", type(self.posterior).__name__)
        if not isinstance(self.camera, PinholeCamera):
            raise InvalidInputError("camera", "a PinholeCamera", type(self.camera).__name__)
        _check_aspect(self.camera, mean.shape, "posterior")
        if self.rgb is not None:
            object.__setattr__(self, "rgb", _as_rgb(self.rgb))
            _check_aspect(self.camera, self.rgb.shape[:2], "rgb")
        if self.depth_gt is not None:
            gt = np.asarray(self.depth_gt, dtype=np.float64)
            if gt.ndim != 2:
                raise ShapeError("depth_gt", "a 2-D (H, W) depth map in metres", describe(gt))
            _check_aspect(self.camera, gt.shape, "depth_gt")
            object.__setattr__(self, "depth_gt", np.where(np.isfinite(gt) & (gt > 0), gt, 0.0))
        if self.T_world_camera is not None:
            object.__setattr__(self, "T_world_camera", check_pose(self.T_world_camera, "T_world_camera"))

    @property
    def pose(self) -> np.ndarray:
        """The 4x4 ``T_world_camera`` (identity when none was given)."""
        return np.eye(4) if self.T_world_camera is None else self.T_world_camera

    @classmethod
    def from_files(
        cls,
        posterior: str | Path,
        *,
        camera: Optional[PinholeCamera] = None,
        K: Optional[np.ndarray] = None,
        rgb: Optional[str | Path] = None,
        depth_gt: Optional[str | Path] = None,
        gt_png_scale: float = 1.0 / 256.0,
        gt_invalid_value: Optional[int] = None,
        T_world_camera: Optional[np.ndarray | str | Path] = None,
    ) -> "ViewerFrame":
        """Loads a frame written by ``gpdepth3d complete`` plus its image, ground truth and pose.

        Args:
            posterior: ``.npz`` written by `DepthPosterior.save`.
            camera: Intrinsics (of the RGB image or of the posterior grid).
            K: Instead of ``camera``: a 3x3 intrinsic matrix of the RGB image (of the posterior
                grid without ``rgb``). With neither, the K saved in the posterior file (key ``K``),
                else a 60 degree horizontal field of view (a guess: pass the real intrinsics).
            rgb: Image file (any format OpenCV reads).
            depth_gt: Ground-truth depth (``.npy``/``.npz`` metres or 16-bit ``.png``).
            gt_png_scale: Metres per unit of a 16-bit ground-truth PNG (1/1000 for Kinect).
            gt_invalid_value: Raw PNG value marking invalid ground truth (65535 for 7-Scenes).
            T_world_camera: 4x4 pose, or a text file holding it (4x4, or 12 numbers = 3x4).
        """
        from ..completion.complete import DepthPosterior
        from ..io import load_depth, load_rgb

        post = DepthPosterior.load(posterior)
        image = load_rgb(rgb) if rgb is not None else None
        if camera is None:
            h, w = image.shape[:2] if image is not None else post.shape
            K = stored_intrinsics(posterior) if K is None else K
            camera = default_camera(w, h) if K is None else PinholeCamera.from_K(K, w, h)
        gt = load_depth(depth_gt, png_scale=gt_png_scale, invalid_value=gt_invalid_value) if depth_gt else None
        if isinstance(T_world_camera, (str, Path)):
            T_world_camera = load_pose(T_world_camera)
        return cls(post, camera, image, gt, T_world_camera, name=Path(posterior).stem)


def stored_intrinsics(posterior: Path) -> Optional[np.ndarray]:
    """The 3x3 K saved with a posterior (key ``K`` of the ``.npz``), or None when the file holds none."""
    try:
        z = np.load(posterior, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None  # unreadable: loading the posterior itself reports it
    if not hasattr(z, "files"):  # a .npy, not a posterior: loading it reports that
        return None
    with z:
        try:
            return np.asarray(z["K"], dtype=np.float64).reshape(3, 3) if "K" in z.files else None
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            return None  # a corrupt member: loading the posterior itself reports it


def default_camera(width: int, height: int, *, hfov_deg: float = 60.0) -> PinholeCamera:
    """A camera with the given horizontal field of view and centred principal point (a fallback guess)."""
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return PinholeCamera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def load_mesh(path: str | Path) -> "trimesh.Trimesh":
    """Reads a mesh written by ``gpdepth3d fuse`` (PLY, GLB, OBJ) with trimesh."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise DataFormatError(path, f"not a readable mesh: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DataFormatError(path, "no triangles in the file")
    return mesh


def _as_rgb(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ShapeError("rgb", "an (H, W, 3) RGB image", describe(a))
    if a.dtype != np.uint8:
        if np.issubdtype(a.dtype, np.floating) and a.size and np.nanmax(a) <= 1.0:
            a = a * 255.0
        a = np.clip(np.nan_to_num(a.astype(np.float64)), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a[..., :3])


def _check_aspect(camera: PinholeCamera, shape: tuple[int, ...], argument: str) -> None:
    h, w = int(shape[0]), int(shape[1])
    if abs((w / h) / (camera.width / camera.height) - 1.0) > 0.01:
        raise ShapeError(
            argument, f"an image with the aspect ratio of the camera ({camera.width}x{camera.height})", f"{w}x{h}"
        )


def _resize(image: np.ndarray, shape: tuple[int, int], nearest: bool = False) -> np.ndarray:
    if image.shape[:2] == tuple(shape):
        return image
    import cv2

    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if image.shape[0] > shape[0] else cv2.INTER_LINEAR
    return cv2.resize(image, (shape[1], shape[0]), interpolation=interp)


# ---------------------------------------------------------------------- layers
@dataclass
class _Layer:
    """One point layer over all frames (world frame)."""

    points: np.ndarray  # (N, 3) float32 world
    rgb: np.ndarray  # (N, 3) uint8
    depth: np.ndarray  # (N,) z-depth in the frame's camera
    sigma: np.ndarray  # (N,) own sigma (NaN = none)
    error: np.ndarray  # (N,) |depth - gt| (NaN = no gt)
    gp_sigma: np.ndarray  # (N,) GP sigma at the point's pixel (NaN = none): used by the filter

    @classmethod
    def empty(cls) -> "_Layer":
        z = np.zeros(0)
        return cls(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), z, z, z, z)

    @classmethod
    def concat(cls, layers: list["_Layer"]) -> "_Layer":
        if not layers:
            return cls.empty()
        return cls(*(np.concatenate([getattr(x, f) for x in layers]) for f in cls.__dataclass_fields__))

    def __len__(self) -> int:
        return int(self.points.shape[0])


def _lift_map(
    depth: np.ndarray, rgb: np.ndarray, camera: PinholeCamera, T: np.ndarray, stride: int, extras: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Back-projects a depth map with `cloud.backproject_depth`; samples per-pixel ``extras`` at each point."""
    from ..mapping.cloud import backproject_depth
    from ..camera import transform_points

    try:
        cloud = backproject_depth(depth, rgb, camera, stride=stride)
    except EmptyInputError:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), {k: np.zeros(0) for k in extras}
    # The cloud is in the camera frame: projecting it gives back its pixel centres exactly.
    uv, _ = camera.project(cloud.points)
    cols = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, camera.width - 1)
    rows = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, camera.height - 1)
    sampled = {k: v[rows, cols] for k, v in extras.items()}
    return transform_points(T, cloud.points), cloud.colors, cloud.depth, sampled


def _frame_layers(frame: ViewerFrame, stride: int) -> dict[str, _Layer]:
    """The four point layers of one frame."""
    from ..camera import transform_points

    post = frame.posterior
    ho, wo = post.shape
    T = frame.pose
    cam = frame.camera.resized(wo, ho) if frame.camera.shape != (ho, wo) else frame.camera
    grey = np.full((ho, wo, 3), MISSING_COLOR, np.uint8)
    rgb = _resize(frame.rgb, (ho, wo)) if frame.rgb is not None else grey
    std = np.asarray(post.std, dtype=np.float64)
    nan = np.full((ho, wo), np.nan)
    if frame.depth_gt is not None:
        gt = _resize(frame.depth_gt, (ho, wo), nearest=True)
        gt = np.where(gt > 0, gt, np.nan)
    else:
        gt = nan
    layers: dict[str, _Layer] = {}
    for key, depth, own_sigma in (("gp", post.mean, std), ("mde", post.mde, nan)):
        d = np.asarray(depth, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            d = np.where(d > 0, d, 0.0)  # a posterior mean <= 0 (or NaN) is no surface: not drawn
            err = np.abs(d - gt)
        pts, col, z, ex = _lift_map(d, rgb, cam, T, stride, {"sigma": own_sigma, "error": err, "gp_sigma": std})
        layers[key] = _Layer(pts.astype(np.float32), col, z, ex["sigma"], ex["error"], ex["gp_sigma"])

    if frame.depth_gt is not None:
        gh, gw = frame.depth_gt.shape
        cam_gt = frame.camera.resized(gw, gh) if frame.camera.shape != (gh, gw) else frame.camera
        if frame.rgb is not None:
            rgb_gt = _resize(frame.rgb, (gh, gw))
        else:
            rgb_gt = np.full((gh, gw, 3), MISSING_COLOR, np.uint8)
        gt_stride = max(1, int(round(stride * gh / ho)))
        pts, col, z, _ = _lift_map(frame.depth_gt, rgb_gt, cam_gt, T, gt_stride, {})
        n = len(z)
        none = np.full(n, np.nan)  # ground truth has no sigma, and no error against itself
        layers["gt"] = _Layer(pts.astype(np.float32), col, z, none, none, none)
    else:
        layers["gt"] = _Layer.empty()

    sparse = post.sparse
    if len(sparse):
        sh, sw = sparse.image_size
        cam_s = frame.camera.resized(sw, sh) if frame.camera.shape != (sh, sw) else frame.camera
        uv = np.stack([sparse.u, sparse.v], axis=1).astype(np.float64)
        z = np.asarray(sparse.depth, dtype=np.float64)
        pts = transform_points(T, cam_s.backproject_pixels(uv, z))
        r = np.clip(np.rint(sparse.v).astype(np.int64), 0, sh - 1)
        c = np.clip(np.rint(sparse.u).astype(np.int64), 0, sw - 1)
        col = _resize(frame.rgb, (sh, sw))[r, c] if frame.rgb is not None else np.tile(MISSING_COLOR, (len(z), 1))
        gts = _resize(gt, (sh, sw), nearest=True)[r, c] if frame.depth_gt is not None else np.full(len(z), np.nan)
        sig = np.asarray(sparse.sigma, dtype=np.float64) if sparse.sigma is not None else np.full(len(z), np.nan)
        layers["sparse"] = _Layer(pts.astype(np.float32), col, z, sig, np.abs(z - gts), np.full(len(z), np.nan))
    else:
        layers["sparse"] = _Layer.empty()
    return layers
