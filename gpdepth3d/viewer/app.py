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
import threading
import time
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional, Sequence

import numpy as np

from ..errors import EmptyInputError, InvalidInputError, describe

if TYPE_CHECKING:  # pragma: no cover
    pass
from .colors import COLORMAPS, _colorize, _percentile, _fmt_m, colorbar_image, MISSING_COLOR
from .files import load_geometry
from .scene_data import (
    ViewerConfig,
    ViewerFrame,
    _Layer,
    _frame_layers,
    LAYER_LABELS,
    _SLOTS,
    COLOR_MODES,
    LAYOUTS,
    _resize,
)
from .serving import check_host, wait_until_stopped


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
        scene = self.server.scene
        T0 = self.frames[0].pose if self.frames else np.eye(4)
        self._right = T0[:3, 0].copy()
        up = -T0[:3, 1]
        forward = T0[:3, 2]
        scene.set_up_direction(tuple(float(x) for x in up))

        loaded = _check_meshes(meshes)
        extent, centre, height = self._scene_extent(loaded, T0, up, forward)
        self._spacing = 1.15 * extent

        # Each group is created at its place in the layout, labels shown only side by side: the page
        # never draws the layers (and their labels) on top of each other while the scene arrives.
        side = self.config.layout == "side-by-side"
        label_at = centre + up * 0.6 * height
        self._add_layers(label_at, side)
        self._add_frustums(0.05 * max(extent, height))
        self._add_meshes(loaded, label_at, side)
        self._set_initial_view(centre, extent, up, forward)

    def _scene_extent(self, loaded: list[Any], T0: np.ndarray, up: np.ndarray, forward: np.ndarray) -> tuple:
        """The layers' (else the meshes') width along the camera's right, centre and height, metres."""
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
        return extent, centre, height

    def _add_layers(self, label_at: np.ndarray, side: bool) -> None:
        """Draws each non-empty layer's points (and label) in its group; drops the preview cloud."""
        scene = self.server.scene
        preview = getattr(self, "_preview", None)
        self.groups: dict[str, Any] = {}
        self.point_clouds: dict[str, Any] = {}
        self._labels: list[Any] = []
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
                    scene.add_label(f"/{key}/label", label, position=label_at, anchor="bottom-center", visible=side)
                )
            self._event(f"cloud:{key}")
        if preview is not None:
            preview.remove()
            self._preview = None
        if "sparse" in self.point_clouds:
            self.point_clouds["sparse"].point_size = 3.0 * self._point_size

    def _add_frustums(self, default_scale: float) -> None:
        """Draws the cameras' frustums (with a small image each) in the cameras group."""
        import viser.transforms as vtf

        scene = self.server.scene
        self.frustums = []
        if not self.frames:
            return
        self.groups["cameras"] = scene.add_frame("/cameras", show_axes=False, position=self._group_position("cameras"))
        scale = self.config.frustum_scale or default_scale
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

    def _add_meshes(self, loaded: list[Any], label_at: np.ndarray, side: bool) -> None:
        """Draws the given meshes and clouds (and their label) in the meshes group."""
        scene = self.server.scene
        self.meshes = []
        if not loaded:
            return
        self.groups["meshes"] = scene.add_frame("/meshes", show_axes=False, position=self._group_position("meshes"))
        for i, mesh in enumerate(loaded):
            self.meshes.append(self._add_geometry(f"/meshes/{i:03d}", mesh))
        clouds = sum(not hasattr(m, "faces") for m in loaded)
        self._labels.append(
            scene.add_label(
                "/meshes/label",
                "Fused mesh" if not clouds else "Point cloud" if clouds == len(loaded) else "Mesh and cloud",
                position=label_at,
                anchor="bottom-center",
                visible=side,
            )
        )

    def _set_initial_view(self, centre: np.ndarray, extent: float, up: np.ndarray, forward: np.ndarray) -> None:
        """Initial view: behind and above the first camera, looking at the scene centre."""
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

    def _add_geometry(self, name: str, item: Any) -> Any:
        """Draws a mesh, or a point cloud in its own colours (grey without) at the layers' point size."""
        if hasattr(item, "faces"):
            return self.server.scene.add_mesh_trimesh(name, item)
        colors = np.asarray(item.colors)[:, :3] if len(getattr(item, "colors", ())) else None
        return self.server.scene.add_point_cloud(
            name,
            np.asarray(item.vertices, dtype=np.float32),
            colors if colors is not None else tuple(int(c) for c in MISSING_COLOR),
            point_size=self._point_size,
            point_shape="square",
            precision="float32",
            point_shading="flat",
        )

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


def _check_meshes(meshes: Sequence[Any]) -> list[Any]:
    """The viewer's extra geometry: trimesh objects as given, paths loaded (`load_geometry`)."""
    loaded = []
    if meshes:
        import trimesh  # slow to import: only when there are meshes
    for i, mesh in enumerate(meshes):
        if isinstance(mesh, (str, Path)):
            loaded.extend(load_geometry(mesh))  # a mesh, a point cloud or a map folder
            continue
        if not isinstance(mesh, (trimesh.Trimesh, trimesh.PointCloud)):
            raise InvalidInputError(
                f"meshes[{i}]", "a trimesh.Trimesh or PointCloud, or a mesh, cloud or map path", type(mesh).__name__
            )
        loaded.append(mesh)
    return loaded


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
        meshes: Fused meshes and point clouds (`trimesh.Trimesh`, `trimesh.PointCloud`, or paths of a mesh,
            a point-cloud PLY or a map folder: `gpdepth3d.viewer.files.load_geometry`), in the world frame.
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
