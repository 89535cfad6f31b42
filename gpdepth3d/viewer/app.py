"""Interactive browser viewer (viser): GP-refined vs MDE-only depth in 3D.

`show` starts a viser web server (``http://127.0.0.1:8080`` by default) and returns a `Viewer`
handle; ``gpdepth3d view`` (`gpdepth3d.cli.view`) does the same from files written by
``gpdepth3d complete`` (posterior ``.npz``) and ``gpdepth3d fuse`` (meshes, PLY/GLB/OBJ).

What the page shows, for one frame or a posed sequence (all frames in the world frame):

* layers, each with a checkbox: the MDE-only cloud (``posterior.mde`` back-projected), the
  GP-refined cloud (``posterior.mean``), the sparse measurements the GP was conditioned on,
  the ground truth (when given), the cameras (frustums showing their images) and fused meshes;
* layout ``side-by-side`` (each layer shifted along the first camera's x axis: MDE-only left,
  GP-refined with measurements and cameras in the middle, ground truth and meshes right) or
  ``overlay`` (all at their true position);
* colouring by ``rgb``, ``depth`` (z-depth in the frame's camera, turbo), ``sigma`` (posterior
  standard deviation of the GP depth, viridis; measurements use their own sigma) or ``error``
  (|depth - ground truth| at the pixel, magma); a colour bar image and the range as text form
  the legend. Points without that quantity (e.g. MDE-only when colouring by sigma) are grey;
* a confidence slider "Max σ (m)": GP-refined points whose sigma is above it are removed from the
  cloud (optionally the same pixels of the MDE-only cloud too), live, with the share of points
  shown and, with ground truth, the RMSE of the shown points;
* a metrics panel: `gpdepth3d.metrics.depth_metrics` of MDE-only and GP-refined against ground
  truth over all pixels (mean over frames for a sequence) and the coverage of the +-1/2 sigma
  intervals (`gpdepth3d.metrics.calibration_metrics`);
* a point size slider (metres).

Point positions are sent as float32 (viser's default float16 has a spacing of 3 cm at 50 m).
Back-projection uses `gpdepth3d.mapping.cloud.backproject_depth`; clouds are subsampled with a pixel
stride so that each layer holds at most ``ViewerConfig.max_points`` points.
"""

from __future__ import annotations

import contextlib
import math
import zipfile
import threading
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Optional, Sequence

import numpy as np

from ..camera import PinholeCamera, check_pose
from ..io import load_pose
from ..errors import DataFormatError, EmptyInputError, InvalidInputError, ShapeError, describe

if TYPE_CHECKING:  # pragma: no cover
    import trimesh

    from ..completion.complete import DepthPosterior

ColorBy = Literal["rgb", "depth", "sigma", "error"]
Layout = Literal["side-by-side", "overlay"]
COLOR_MODES: tuple[str, ...] = ("rgb", "depth", "sigma", "error")
LAYOUTS: tuple[str, ...] = ("side-by-side", "overlay")
COLORMAPS = {"depth": "turbo", "sigma": "viridis", "error": "magma"}
"""Matplotlib colormap of each colouring mode."""
LAYER_LABELS = {"mde": "MDE only", "gp": "GP refined", "sparse": "Sparse measurements", "gt": "Ground truth"}
"""GUI/scene label of each point layer (keys are the layer names used in `Viewer.point_clouds`)."""
MISSING_COLOR = np.array([150, 150, 150], dtype=np.uint8)
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
        if self.layout not in LAYOUTS:
            raise InvalidInputError("layout", f"one of {LAYOUTS}", self.layout)
        if self.color_by not in COLOR_MODES:
            raise InvalidInputError("color_by", f"one of {COLOR_MODES}", self.color_by)
        if int(self.max_points) != self.max_points or self.max_points < 1:
            raise InvalidInputError("max_points", "an integer >= 1", self.max_points)
        for name in ("point_size", "frustum_scale"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                raise InvalidInputError(name, "None or a finite size > 0 (metres)", value)


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


def wait_until_stopped(stopped: Callable[[], bool], duration: Optional[float] = None) -> None:
    """Blocks until ``stopped()`` is true, ``duration`` seconds passed (None: no limit) or Ctrl-C."""
    end = math.inf if duration is None else time.monotonic() + float(duration)
    try:
        while not stopped() and time.monotonic() < end:
            time.sleep(min(0.2, max(end - time.monotonic(), 0.0)))
    except KeyboardInterrupt:
        pass


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


def _colorize(values: np.ndarray, vmin: float, vmax: float, cmap: str) -> np.ndarray:
    """Maps values to uint8 RGB with a matplotlib colormap; NaN -> `MISSING_COLOR`."""
    import matplotlib

    span = max(vmax - vmin, 1e-12)
    t = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / span, 0.0, 1.0)
    rgb = (matplotlib.colormaps[cmap](t)[:, :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(values)] = MISSING_COLOR
    return rgb


def colorbar_image(cmap: str, *, width: int = 256, height: int = 20) -> np.ndarray:
    """A horizontal (height, width, 3) uint8 colour bar of a matplotlib colormap, low values left."""
    row = _colorize(np.linspace(0.0, 1.0, width), 0.0, 1.0, cmap)
    return np.ascontiguousarray(np.repeat(row[None], height, axis=0))


def _percentile(values: np.ndarray, q: float, default: float) -> float:
    v = values[np.isfinite(values)]
    return float(np.percentile(v, q)) if v.size else default


def _fmt_m(x: float) -> str:
    return f"{x:.3g} m" if abs(x) >= 0.01 or x == 0 else f"{x * 1000:.3g} mm"


# ---------------------------------------------------------------------- the viewer
class Viewer:
    """A running viewer: the viser server, its scene and GUI. Create it with `show`.

    Stop it with `stop` (frees the port) or use it as a context manager. The attributes give
    the live state for scripts and tests.

    Attributes:
        server: The `viser.ViserServer`.
        url: ``http://host:port`` of the page.
        point_clouds: Layer name ("mde", "gp", "sparse", "gt") -> viser point cloud handle;
            ``point_clouds[name].points`` is what the browser currently draws.
        groups: Group name ("mde", "gp", "sparse", "gt", "cameras", "meshes") -> the viser frame
            node whose visibility the checkbox of that layer toggles.
        frustums: One camera frustum handle per frame.
        meshes: One mesh handle per mesh.
        controls: GUI inputs by key: "show_<group>", "layout", "color_by", "max_sigma",
            "filter_mde", "point_size".
        metrics: {"mde": ..., "gp": ...} `depth_metrics` (mean over frames with ground truth)
            plus "calibration" (`calibration_metrics` means); empty without ground truth.
        loaded: Set when every frame is on the page (or the loading failed: `load_error`).
        load_error: The exception that stopped a background loading, else None.
        events: (what, seconds since the start) of what the page was sent, in order: "loading"
            (the loading text), "preview" (a sequence's first frame), "panel" (the controls),
            "cloud:<layer>" (each point layer), "loaded".
    """

    def __init__(
        self,
        frames: Sequence[ViewerFrame],
        meshes: Sequence[Any],
        config: ViewerConfig,
        host: str,
        port: int,
        *,
        background: bool = False,
    ):
        import viser

        self.config = config
        self.frames = list(frames)
        self._lock = threading.RLock()
        self._stopped = False
        self._syncing = False  # set while the Python API moves a GUI control (its callback then does nothing)
        self.loaded = threading.Event()
        self.load_error: Optional[BaseException] = None
        self.events: list[tuple[str, float]] = []
        self._t0 = time.monotonic()
        # The server and a loading text first: a browser that connects now sees the state at once.
        self.server = viser.ViserServer(host=host, port=port, label=config.title, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self._loading_text = self.server.gui.add_markdown(self._loading_message(0))
        self._event("loading")
        if background:
            threading.Thread(
                target=self._load, args=(list(meshes), True), name="gpdepth3d-viewer-load", daemon=True
            ).start()
        else:
            self._load(list(meshes), False)

    def _event(self, what: str) -> None:
        """Records what the page was sent, in order, with the seconds since the viewer started."""
        self.events.append((what, time.monotonic() - self._t0))

    def _loading_message(self, done: int) -> str:
        n = len(self.frames)
        if n == 0:
            return "**Loading meshes …**"
        return f"**Loading frame {min(done + 1, n)} of {n} …**"

    def _load(self, meshes: list[Any], background: bool) -> None:
        """Prepares the layers frame by frame (the loading text follows), then the panel, then the clouds."""
        try:
            self._prepare_layers()
            self.metrics = self._compute_metrics()
            self._build_gui(meshes)
            self._event("panel")
            self._build_scene(meshes)
            self._update_shown()
            self._loading_text.remove()
            self._event("loaded")
        except BaseException as exc:
            self.load_error = exc
            if not background:
                self.server.stop()
                self.loaded.set()
                raise
            with contextlib.suppress(Exception):
                self._loading_text.content = f"**Loading failed:** {exc}"
        finally:
            self.loaded.set()

    def wait_loaded(self, timeout: Optional[float] = None) -> None:
        """Blocks until every frame is on the page (at once unless `show` ran with ``background=True``).

        Raises:
            TimeoutError: when ``timeout`` seconds pass first.
            Exception: the error that stopped the loading (a bad mesh file, say).
        """
        if not self.loaded.wait(timeout):
            raise TimeoutError(f"the viewer was still loading after {timeout} s")
        if self.load_error is not None:
            raise self.load_error

    # ------------------------------------------------------------------ data
    def _prepare_layers(self) -> None:
        frames = self.frames
        total = sum(f.posterior.shape[0] * f.posterior.shape[1] for f in frames)
        self.stride = max(1, math.ceil(math.sqrt(total / self.config.max_points))) if total else 1
        per_frame = []
        for i, f in enumerate(frames):
            per_frame.append(_frame_layers(f, self.stride))
            if i == 0 and len(frames) > 1:
                self._show_preview(per_frame[0]["gp"], f)
            self._loading_text.content = self._loading_message(i + 1)
        self._layers = {k: _Layer.concat([p[k] for p in per_frame]) for k in LAYER_LABELS}
        gp = self._layers["gp"]
        all_depth = np.concatenate([gp.depth, self._layers["mde"].depth, self._layers["gt"].depth])
        self._ranges = {
            "depth": (_percentile(all_depth, 2, 0.0), _percentile(all_depth, 98, 1.0)),
            "sigma": (0.0, _percentile(gp.sigma, 98, 1.0)),
            "error": (0.0, _percentile(np.concatenate([gp.error, self._layers["mde"].error]), 95, 1.0)),
        }
        finite = gp.sigma[np.isfinite(gp.sigma)]
        self._sigma_max = float(finite.max()) if finite.size else 0.0
        self._max_sigma = math.inf
        self._filter_mde = False
        self._color_by = self.config.color_by if self.config.color_by != "error" or self.has_gt else "rgb"
        if self.config.point_size is not None:
            self._point_size = float(self.config.point_size)
        elif frames:
            # One pixel's footprint at the median depth: depth / fx on the posterior grid.
            footprints = [
                float(np.median(f.posterior.mean[f.posterior.mean > 0]))
                / (f.camera.fx * f.posterior.shape[1] / f.camera.width)
                for f in frames
                if np.any(f.posterior.mean > 0)
            ]
            self._point_size = 1.5 * self.stride * (float(np.median(footprints)) if footprints else 0.01)
        else:
            self._point_size = 0.01

    def _show_preview(self, layer: _Layer, frame: ViewerFrame) -> None:
        """The first frame's GP cloud in RGB at once, while the other frames load (removed when they are in)."""
        if len(layer) == 0:
            return
        mean = frame.posterior.mean
        median = float(np.median(mean[mean > 0])) if np.any(mean > 0) else 1.0
        size = 1.5 * self.stride * median / (frame.camera.fx * frame.posterior.shape[1] / frame.camera.width)
        self._preview = self.server.scene.add_point_cloud(
            "/preview",
            layer.points,
            layer.rgb,
            point_size=size,
            point_shape="square",
            precision="float32",
            point_shading="flat",
        )
        self._event("preview")

    def _group_keys(self, meshes: Sequence[Any]) -> list[str]:
        """The groups the scene will have, in order (known before the scene is built)."""
        keys = [k for k in LAYER_LABELS if len(self._layers[k])]
        return keys + (["cameras"] if self.frames else []) + (["meshes"] if meshes else [])

    @property
    def has_gt(self) -> bool:
        """Whether any frame has ground truth."""
        return any(f.depth_gt is not None for f in self.frames)

    def _compute_metrics(self) -> dict[str, dict[str, float]]:
        from ..metrics import calibration_metrics, depth_metrics

        rows: dict[str, list[dict[str, float]]] = {"mde": [], "gp": [], "calibration": []}
        for f in self.frames:
            if f.depth_gt is None:
                continue
            gt = _resize(f.depth_gt, f.posterior.shape, nearest=True)
            if not np.any(gt > 0):
                continue
            rows["mde"].append(depth_metrics(f.posterior.mde, gt))
            rows["gp"].append(depth_metrics(f.posterior.mean, gt))
            if np.all(np.isfinite(f.posterior.variance)):
                rows["calibration"].append(calibration_metrics(f.posterior.mean, f.posterior.variance, gt))
        return {k: {m: float(np.mean([r[m] for r in v])) for m in v[0]} for k, v in rows.items() if v}

    # ------------------------------------------------------------------ scene
    def _build_scene(self, meshes: Sequence[Any]) -> None:
        import viser.transforms as vtf

        scene = self.server.scene
        T0 = self.frames[0].pose if self.frames else np.eye(4)
        self._right = T0[:3, 0].copy()
        up = -T0[:3, 1]
        forward = T0[:3, 2]
        scene.set_up_direction(tuple(float(x) for x in up))

        loaded = []
        if meshes:
            import trimesh  # slow to import: only when there are meshes
        for i, mesh in enumerate(meshes):
            if isinstance(mesh, (str, Path)):
                mesh = load_mesh(mesh)
            if not isinstance(mesh, trimesh.Trimesh):
                raise InvalidInputError(f"meshes[{i}]", "a trimesh.Trimesh or a mesh file path", type(mesh).__name__)
            loaded.append(mesh)
        gp = self._layers["gp"].points
        ref = gp if len(gp) else np.concatenate([self._layers[k].points for k in LAYER_LABELS])
        if len(ref) == 0 and loaded:
            ref = np.concatenate([np.asarray(m.vertices, dtype=np.float32) for m in loaded])
        if len(ref):
            along = ref.astype(np.float64) @ self._right
            lo, hi = np.percentile(along, [1, 99])
            extent = float(max(hi - lo, 1e-3))
            centre = np.median(ref.astype(np.float64), axis=0)
            height = float(np.ptp(np.percentile(ref.astype(np.float64) @ up, [1, 99])))
        else:
            extent, centre, height = 1.0, T0[:3, 3] + forward, 1.0
        self._spacing = 1.15 * extent

        preview = getattr(self, "_preview", None)
        self.groups: dict[str, Any] = {}
        self.point_clouds: dict[str, Any] = {}
        self._labels: list[Any] = []
        # Each group is created at its place in the layout, labels shown only side by side: the page
        # never draws the layers (and their labels) on top of each other while the scene arrives.
        side = self.config.layout == "side-by-side"
        for key, label in LAYER_LABELS.items():
            layer = self._layers[key]
            if len(layer) == 0:
                continue
            self.groups[key] = scene.add_frame(f"/{key}", show_axes=False, position=self._group_position(key))
            self.point_clouds[key] = scene.add_point_cloud(
                f"/{key}/points",
                layer.points,
                self._colors(key),
                point_size=self._point_size,
                point_shape="square",
                precision="float32",
                point_shading="flat",
            )
            if key != "sparse":
                self._labels.append(
                    scene.add_label(
                        f"/{key}/label",
                        label,
                        position=centre + up * 0.6 * height,
                        anchor="bottom-center",
                        visible=side,
                    )
                )
            self._event(f"cloud:{key}")
        if preview is not None:
            preview.remove()
            self._preview = None
        if "sparse" in self.point_clouds:
            self.point_clouds["sparse"].point_size = 3.0 * self._point_size

        self.frustums = []
        if self.frames:
            self.groups["cameras"] = scene.add_frame(
                "/cameras", show_axes=False, position=self._group_position("cameras")
            )
            scale = self.config.frustum_scale or 0.05 * max(extent, height)
            for i, f in enumerate(self.frames):
                cam = f.camera
                image = None
                if f.rgb is not None:
                    small_w = min(256, f.rgb.shape[1])
                    image = _resize(f.rgb, (max(1, round(f.rgb.shape[0] * small_w / f.rgb.shape[1])), small_w))
                T = f.pose
                self.frustums.append(
                    scene.add_camera_frustum(
                        f"/cameras/{i:04d}",
                        fov=2.0 * math.atan2(cam.height / 2.0, cam.fy),
                        aspect=cam.width / cam.height,
                        scale=scale,
                        image=image,
                        format="jpeg",
                        wxyz=vtf.SO3.from_matrix(T[:3, :3]).wxyz,
                        position=T[:3, 3],
                        color=(230, 80, 30),
                        thickness=0.1 * scale,
                    )
                )

        self.meshes = []
        if loaded:
            self.groups["meshes"] = scene.add_frame("/meshes", show_axes=False, position=self._group_position("meshes"))
            for i, mesh in enumerate(loaded):
                self.meshes.append(scene.add_mesh_trimesh(f"/meshes/{i:03d}", mesh))
            self._labels.append(
                scene.add_label(
                    "/meshes/label",
                    "Fused mesh",
                    position=centre + up * 0.6 * height,
                    anchor="bottom-center",
                    visible=side,
                )
            )

        # Initial view: behind and above the first camera, looking at the scene centre.
        slots = {self._slot(k) for k in self.groups} or {0.0}
        width = self._spacing * (max(slots) - min(slots) + 1.0)
        fov = math.radians(50.0)
        distance = 0.45 * width / math.tan(fov / 2.0) + 0.2 * extent
        # Look at the middle of the layers, shifted right a little: the GUI panel covers the page's right.
        mid = 0.5 * (max(slots) + min(slots))
        look_at = centre + self._right * (self._spacing * mid + 0.12 * width)
        self.server.initial_camera.fov = fov
        self.server.initial_camera.look_at = tuple(float(x) for x in look_at)
        position = look_at - forward * distance + up * 0.3 * distance
        self.server.initial_camera.position = tuple(float(x) for x in position)
        self.server.initial_camera.up = tuple(float(x) for x in up)

    def _group_position(self, group: str, layout: Optional[str] = None) -> tuple[float, float, float]:
        shift = self._slot(group) * self._spacing if (layout or self.config.layout) == "side-by-side" else 0.0
        return tuple(float(x) for x in self._right * shift)

    def _slot(self, group: str) -> float:
        if group == "meshes":  # right of everything else
            return 1.0 + max((_SLOTS[k] for k in self.groups if k in _SLOTS), default=-1.0)
        return float(_SLOTS[group])

    # ------------------------------------------------------------------ GUI
    def _build_gui(self, meshes: Sequence[Any]) -> None:
        gui = self.server.gui
        groups = self._group_keys(meshes)
        self.controls: dict[str, Any] = {}
        names = dict(LAYER_LABELS, cameras="Cameras", meshes="Fused meshes")
        with gui.add_folder("Layers"):
            for key in ("mde", "gp", "sparse", "gt", "cameras", "meshes"):
                if key not in groups:
                    continue
                box = gui.add_checkbox(names[key], True)
                box.on_update(lambda _e, key=key, box=box: self._from_gui(partial(self.set_visible, key), box.value))
                self.controls[f"show_{key}"] = box
            layout = gui.add_dropdown("Layout", LAYOUTS, initial_value=self.config.layout)
            layout.on_update(lambda _e: self._from_gui(self.set_layout, layout.value))
            self.controls["layout"] = layout

        with gui.add_folder("Colour"):
            modes = tuple(m for m in COLOR_MODES if m != "error" or self.has_gt)
            color = gui.add_dropdown("Colour by", modes, initial_value=self._color_by)
            color.on_update(lambda _e: self._from_gui(self.set_color_by, color.value))
            self.controls["color_by"] = color
            self._legend_image = gui.add_image(colorbar_image("turbo"), label="Colour bar", format="png")
            self._legend_text = gui.add_markdown("")

        with gui.add_folder("Confidence"):
            top = self._sigma_max if self._sigma_max > 0 else 1.0
            step = float(f"{top / 200:.2g}")
            top = math.ceil(top / step) * step
            sigma = gui.add_slider(
                "Max σ (m)",
                0.0,
                top,
                step,
                top,
                disabled=self._sigma_max <= 0,
                hint="Hide GP-refined points whose posterior standard deviation is above this (metres).",
            )
            sigma.on_update(lambda _e: self._from_gui(self.set_max_sigma, sigma.value))
            self.controls["max_sigma"] = sigma
            self._sigma_top = top
            if "mde" in groups:
                filt = gui.add_checkbox("Filter MDE too", False, hint="Hide the same pixels in the MDE-only cloud.")
                filt.on_update(lambda _e: self._from_gui(self.set_filter_mde, filt.value))
                self.controls["filter_mde"] = filt
            self._shown_text = gui.add_markdown("")

        with gui.add_folder("Points"):
            ps = self._point_size
            size = gui.add_slider(
                "Point size (m)",
                float(f"{ps / 10:.2g}"),
                float(f"{ps * 5:.2g}"),
                float(f"{ps / 20:.2g}"),
                float(f"{ps:.2g}"),
            )
            size.on_update(lambda _e: self._from_gui(self.set_point_size, size.value))
            self.controls["point_size"] = size

        with gui.add_folder("Metrics"):
            self._metrics_text = gui.add_markdown(self._metrics_markdown())
        self._update_legend()

    def _metrics_markdown(self) -> str:
        if not self.metrics:
            return "No ground truth: metrics unavailable."
        n_gt = sum(f.depth_gt is not None for f in self.frames)
        lines = ["| | RMSE mm | MAE mm | REL | δ1 |", "|---|---:|---:|---:|---:|"]
        for key in ("mde", "gp"):
            m = self.metrics[key]
            lines.append(
                f"| {LAYER_LABELS[key]} | {m['rmse']:.1f} | {m['mae']:.1f} | {m['rel']:.3f} | {m['delta1']:.3f} |"
            )
        text = "\n".join(lines)
        if "calibration" in self.metrics:
            c = self.metrics["calibration"]
            text += (
                f"\n\nGP ±1σ coverage {c['coverage_1sigma']:.2f}, ±2σ {c['coverage_2sigma']:.2f} "
                "(calibrated: 0.68 / 0.95)."
            )
        if len(self.frames) > 1:
            text += f"\n\nMean over {n_gt} frames with ground truth."
        return text

    def _update_legend(self) -> None:
        mode = self._color_by
        if mode == "rgb":
            self._legend_image.visible = False
            self._legend_text.content = "Colours: the RGB image."
            return
        lo, hi = self._ranges[mode]
        what = {
            "depth": "z-depth in the frame's camera",
            "sigma": "GP posterior σ (measurements: their σ)",
            "error": "|depth − ground truth|",
        }[mode]
        self._legend_image.image = colorbar_image(COLORMAPS[mode])
        self._legend_image.visible = True
        self._legend_text.content = (
            f"**{what}** ({COLORMAPS[mode]}): {_fmt_m(lo)} (left) … {_fmt_m(hi)} (right); grey = not available."
        )

    # ------------------------------------------------------------------ state changes
    def _colors(self, key: str) -> np.ndarray:
        layer = self._layers[key]
        mode = self._color_by
        if mode == "rgb":
            return layer.rgb
        values = {"depth": layer.depth, "sigma": layer.sigma, "error": layer.error}[mode]
        lo, hi = self._ranges[mode]
        return _colorize(values, lo, hi, COLORMAPS[mode])

    def _mask(self, key: str) -> np.ndarray:
        layer = self._layers[key]
        if math.isinf(self._max_sigma) or key not in ("gp", "mde") or (key == "mde" and not self._filter_mde):
            return np.ones(len(layer), dtype=bool)
        return ~(layer.gp_sigma > self._max_sigma)  # NaN sigma: kept

    def _refresh_clouds(self) -> None:
        with self._lock:
            if self._stopped:
                return
            with self.server.atomic():
                for key, handle in self.point_clouds.items():
                    mask = self._mask(key)
                    colors = self._colors(key)[mask]
                    points = self._layers[key].points[mask]
                    # Assign both in one atomic batch so the client never pairs N points with M colours.
                    handle.points = points
                    handle.colors = colors if len(points) else np.zeros((0, 3), np.uint8)
            self._update_shown()

    def _update_shown(self) -> None:
        gp = self._layers["gp"]
        if len(gp) == 0:
            self._shown_text.content = ""
            return
        mask = self._mask("gp")
        n = int(mask.sum())
        text = f"GP points shown: {n:,} of {len(gp):,} ({100.0 * n / len(gp):.1f} %)"
        err = gp.error
        if np.isfinite(err).any():
            shown = err[mask & np.isfinite(err)]
            rms_all = float(np.sqrt(np.mean(err[np.isfinite(err)] ** 2))) * 1000
            rms = f"{float(np.sqrt(np.mean(shown**2))) * 1000:.1f} mm" if shown.size else "n/a"
            text += f"; RMSE of shown {rms} (all {rms_all:.1f} mm)"
        self._shown_text.content = text + "."

    def visible_count(self, layer: str) -> int:
        """Number of points the browser draws for a layer ("mde", "gp", "sparse", "gt")."""
        self._require_loaded()
        if layer not in self.point_clouds:
            raise InvalidInputError("layer", f"one of {tuple(self.point_clouds)}", layer)
        return int(self.point_clouds[layer].points.shape[0])

    def set_max_sigma(self, value: float) -> None:
        """Hides GP-refined points with posterior sigma above ``value`` metres (>= the slider top: none hidden)."""
        self._require_loaded()
        value = float(value)
        if not np.isfinite(value) or value < 0:
            raise InvalidInputError("value", "a sigma threshold >= 0 (metres)", value)
        with self._lock:
            self._max_sigma = math.inf if value >= self._sigma_top else value
            self._sync("max_sigma", value)
            self._refresh_clouds()

    def set_filter_mde(self, value: bool) -> None:
        """Whether the sigma threshold also hides the same pixels in the MDE-only cloud."""
        self._require_loaded()
        with self._lock:
            self._filter_mde = bool(value)
            self._sync("filter_mde", bool(value))
            self._refresh_clouds()

    def set_color_by(self, mode: str) -> None:
        """Colours every layer by "rgb", "depth", "sigma" or "error" (needs ground truth)."""
        self._require_loaded()
        modes = tuple(m for m in COLOR_MODES if m != "error" or self.has_gt)
        if mode not in modes:
            raise InvalidInputError("mode", f"one of {modes}", mode)
        with self._lock:
            self._color_by = mode
            self._sync("color_by", mode)
            self._update_legend()
            self._refresh_clouds()

    def set_layout(self, layout: str) -> None:
        """Places the layers "side-by-side" (shifted along the first camera's x axis) or "overlay"."""
        self._require_loaded()
        if layout not in LAYOUTS:
            raise InvalidInputError("layout", f"one of {LAYOUTS}", layout)
        with self._lock:
            for key, group in self.groups.items():
                shift = self._slot(key) * self._spacing if layout == "side-by-side" else 0.0
                group.position = tuple(float(x) for x in self._right * shift)
            for label in self._labels:
                label.visible = layout == "side-by-side"
            self._sync("layout", layout)

    def set_point_size(self, size: float) -> None:
        """Sets the point size of the clouds, metres (measurements are drawn 3x larger)."""
        self._require_loaded()
        size = float(size)
        if not np.isfinite(size) or size <= 0:
            raise InvalidInputError("size", "a point size > 0 (metres)", size)
        with self._lock:
            self._point_size = size
            for key, handle in self.point_clouds.items():
                handle.point_size = size * (3.0 if key == "sparse" else 1.0)
            self._sync("point_size", size)

    def set_visible(self, group: str, visible: bool) -> None:
        """Shows or hides a group ("mde", "gp", "sparse", "gt", "cameras", "meshes")."""
        self._require_loaded()
        if group not in self.groups:
            raise InvalidInputError("group", f"one of {tuple(self.groups)}", group)
        with self._lock:
            self.groups[group].visible = bool(visible)
            self._sync(f"show_{group}", bool(visible))

    def _require_loaded(self) -> None:
        if not self.loaded.is_set() or self.load_error is not None:
            self.wait_loaded()

    def _from_gui(self, setter: Any, value: Any) -> None:
        if not self._syncing:
            setter(value)

    def _sync(self, control: str, value: Any) -> None:
        """Moves a GUI control to a value set from Python, without re-running its callback."""
        handle = getattr(self, "controls", {}).get(control)
        if handle is not None and handle.value != value:
            self._syncing = True
            try:
                handle.value = value
            finally:
                self._syncing = False

    # ------------------------------------------------------------------ lifetime
    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return self.server.get_port()

    def wait(self, duration: Optional[float] = None) -> None:
        """Blocks for ``duration`` seconds (None: until Ctrl-C), then returns (the server keeps running)."""
        wait_until_stopped(lambda: self._stopped, duration)

    def stop(self) -> None:
        """Stops the server and frees its port (idempotent)."""
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
        self.server.stop()

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def show(
    frames: ViewerFrame | Sequence[ViewerFrame] = (),
    *,
    meshes: Sequence[Any] = (),
    config: Optional[ViewerConfig] = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    allow_remote: bool = False,
    background: bool = False,
) -> Viewer:
    """Starts the browser viewer for one frame or a posed sequence.

    The server starts first and the page shows "Loading frame k of n …" while the frames are prepared;
    then the panel, then the clouds (MDE-only first). For a sequence, the first frame's GP cloud is
    shown as soon as it is ready. ``Viewer.events`` records that order.

    Example:
        >>> frame = ViewerFrame(posterior, camera, rgb=rgb, depth_gt=gt)  # doctest: +SKIP
        >>> with show(frame, port=8080) as viewer:  # doctest: +SKIP
        ...     viewer.wait()  # open http://127.0.0.1:8080, Ctrl-C to quit

    Args:
        frames: A `ViewerFrame` or a sequence of them (posed with ``T_world_camera``).
        meshes: Fused meshes (`trimesh.Trimesh` or PLY/GLB/OBJ paths), in the world frame.
        config: Layout, colouring, point budget; default `ViewerConfig()`.
        host: Interface to listen on (127.0.0.1: this machine only; 0.0.0.0: the network, which
            needs ``allow_remote``). Checked at once (`check_host`): an address this machine does
            not have raises instead of hanging.
        port: TCP port; 0 lets the system pick a free one, and a taken port makes viser try the
            next ones (`Viewer.port` and `Viewer.url` tell the port in use).
        allow_remote: Allow a non-loopback ``host`` (the scene is then served to the network).
        background: Return as soon as the server runs and prepare the frames in a thread (the page
            shows the progress; `Viewer.wait_loaded` waits for it and raises its error); the setters
            wait for it. Default: return when everything is on the page.

    Returns:
        The running `Viewer`; call ``stop()`` (or leave its ``with`` block) to free the port.

    Raises:
        EmptyInputError: if there is nothing to show.
        InvalidInputError: for frames that are not `ViewerFrame`, a bad port, or a host that
            cannot be used (see `check_host`).
    """
    if isinstance(frames, ViewerFrame):
        frames = [frames]
    frames = list(frames)
    for i, f in enumerate(frames):
        if not isinstance(f, ViewerFrame):
            raise InvalidInputError(f"frames[{i}]", "a ViewerFrame", type(f).__name__)
    meshes = list(meshes)
    if not frames and not meshes:
        raise EmptyInputError("frames, meshes", "at least one frame or mesh", "none")
    if isinstance(port, (bool, np.bool_)) or not isinstance(port, (int, np.integer)) or not 0 <= port <= 65535:
        raise InvalidInputError("port", "a TCP port 0..65535", describe(port))
    check_host(host, allow_remote=allow_remote)
    return Viewer(frames, meshes, config or ViewerConfig(), host, int(port), background=bool(background))


def check_host(host: str, *, allow_remote: bool = False) -> bool:
    """Checks that the viewer can listen on ``host`` at once (no hang on an address it cannot bind).

    Returns:
        True when ``host`` is a loopback interface (this machine only), False when it serves the
        network (only with ``allow_remote``).

    Raises:
        InvalidInputError: ``host`` is not an IP address or name of this machine (say
            ``999.1.1.1``, or an address of another machine), or is not loopback (``0.0.0.0``,
            a LAN address) without ``allow_remote=True``: the viewer would serve the scene to
            the network.
    """
    import ipaddress
    import socket

    if not isinstance(host, str) or not host or len(host) > 253:
        raise InvalidInputError("host", "an IP address or host name of this machine", describe(host))
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, OSError) as exc:
        raise InvalidInputError("host", "an IP address or host name of this machine", f"{host!r} ({exc})") from None
    addresses, problem = set(), ""
    for family, _, _, _, sockaddr in infos:  # "localhost" may name ::1 on a machine without IPv6: one is enough
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            try:
                sock.bind((sockaddr[0], 0))
                addresses.add(sockaddr[0])
            except OSError as exc:
                problem = exc.strerror or str(exc)
    if not addresses:
        raise InvalidInputError("host", "an address of this machine to listen on", f"{host!r} ({problem})")
    loopback = all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addresses)
    if not loopback and not allow_remote:
        raise InvalidInputError(
            "host",
            "a loopback address such as 127.0.0.1, or allow_remote=True (CLI: --allow-remote) to serve the "
            "scene to every machine that can reach this one",
            host,
        )
    return loopback


def port_taken(host: str, port: int) -> bool:
    """Whether ``port`` on ``host`` is already in use (a listener answers or binding fails)."""
    import socket

    if port == 0:
        return False
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError:
        return False
    family, _, _, _, sockaddr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        try:
            sock.bind(sockaddr)
        except OSError:
            return True
    return False
