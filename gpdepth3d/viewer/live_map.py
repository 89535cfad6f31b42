"""The map as it grows, in the browser (viser): sigma-coloured surface points, the mesh, camera frusta.

`LiveMapViewer` starts a viser server and draws, before any frame is mapped, the whole camera path
and the first camera (with its image) so that the page has a picture at once; then, as the
`gpdepth3d.mapping.Mapper` fuses frames (`LiveMapViewer.update`, the ``on_frame`` callback of
`gpdepth3d.pipelines.mapping_run.map_sequence`), each frame's camera frustum and, at most every
``refresh_s`` seconds, the map's surface points coloured by their fused sigma (viridis; the colour bar
and its range in the panel). `LiveMapViewer.finish` draws the final points and mesh. ``gpdepth3d map
--view`` uses it.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Optional

import numpy as np

from ..camera import PinholeCamera
from ..errors import InvalidInputError, describe
from .colors import COLORMAPS, MISSING_COLOR, colorbar_image
from .serving import check_host, wait_until_stopped


def sigma_colors(sigma: np.ndarray, vmax: Optional[float] = None) -> tuple[np.ndarray, float]:
    """(N, 3) uint8 viridis colours of sigmas (metres) from 0 to ``vmax`` (default their 95th percentile).

    Points without a sigma (NaN) get `MISSING_COLOR`. Returns the colours and the ``vmax`` used.
    """
    import matplotlib

    sigma = np.asarray(sigma, dtype=np.float64)
    finite = sigma[np.isfinite(sigma)]
    if vmax is None:
        vmax = float(np.percentile(finite, 95)) if finite.size else 1.0
    vmax = max(float(vmax), 1e-6)
    t = np.clip(np.nan_to_num(sigma, nan=0.0) / vmax, 0.0, 1.0)
    rgb = (matplotlib.colormaps[COLORMAPS["sigma"]](t)[:, :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(sigma)] = MISSING_COLOR
    return rgb, vmax


class LiveMapViewer:
    """A browser page that shows a map while it is built.

    Args:
        camera: Intrinsics of the sequence's images (the frusta's field of view).
        poses: (N, 4, 4) ``T_world_camera`` of all frames: the camera path drawn at once.
        first_rgb: The first image, shown in the first frustum at once (optional).
        host: Interface to listen on (loopback unless ``allow_remote``; `check_host`).
        port: TCP port (the next free one when taken; `url` tells).
        allow_remote: Allow a non-loopback ``host``.
        refresh_s: Least seconds between two redraws of the map's points while mapping.
        max_points: Most points sent to the page (a random subset beyond).

    Attributes:
        server: The viser server. url: ``http://host:port``.
        frustums: Frame index -> camera frustum handle.
        cloud: The point-cloud handle of the map (None before the first refresh).
        mesh: The mesh handle (after `finish`), or None.
        events: (what, seconds since start): "path", "first_camera", "cloud" (each redraw), "mesh".
        refreshes: How many times the map's points were redrawn.
        errors: Updates that failed to draw (the mapping went on).
    """

    def __init__(
        self,
        camera: PinholeCamera,
        poses: np.ndarray,
        *,
        first_rgb: Optional[np.ndarray] = None,
        host: str = "127.0.0.1",
        port: int = 8080,
        allow_remote: bool = False,
        refresh_s: float = 2.0,
        max_points: int = 300_000,
    ):
        import viser

        if not isinstance(camera, PinholeCamera):
            raise InvalidInputError("camera", "a PinholeCamera", type(camera).__name__)
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
            raise InvalidInputError("poses", "an (N, 4, 4) array with N >= 1", describe(poses))
        if isinstance(port, (bool, np.bool_)) or not isinstance(port, (int, np.integer)) or not 0 <= port <= 65535:
            raise InvalidInputError("port", "a TCP port 0..65535", describe(port))
        if not (isinstance(refresh_s, (int, float)) and math.isfinite(refresh_s) and refresh_s >= 0):
            raise InvalidInputError("refresh_s", "seconds >= 0", refresh_s)
        if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 1:
            raise InvalidInputError("max_points", "an integer >= 1", max_points)
        check_host(host, allow_remote=allow_remote)
        self.camera = camera
        self.poses = poses
        self.refresh_s = float(refresh_s)
        self.max_points = int(max_points)
        self.events: list[tuple[str, float]] = []
        self.frustums: dict[int, Any] = {}
        self.cloud: Any = None
        self.mesh: Any = None
        self.refreshes = 0
        self.errors: list[str] = []
        self._t0 = time.monotonic()
        self._last_refresh = -math.inf
        self._stopped = False
        self._lock = threading.Lock()
        self.server = viser.ViserServer(host=host, port=int(port), label="gpdepth3d map", verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self._status = self.server.gui.add_markdown("**Mapping:** starting …")
        self._legend = self.server.gui.add_image(colorbar_image(COLORMAPS["sigma"]), label="σ (m)", format="png")
        self._range = self.server.gui.add_markdown("σ: 0 … (no map yet)")
        self._draw_path()
        self._scale = self._frustum_scale()
        self.add_camera(0, first_rgb)
        self._event("first_camera")
        self._set_view()

    # ------------------------------------------------------------------ drawing
    def _event(self, what: str) -> None:
        self.events.append((what, time.monotonic() - self._t0))

    def _draw_path(self) -> None:
        centres = self.poses[:, :3, 3].astype(np.float32)
        if len(centres) > 1:
            segments = np.stack([centres[:-1], centres[1:]], axis=1)
            self.server.scene.add_line_segments(
                "/path", segments, colors=(230, 80, 30), thickness=2.0, thickness_units="screen"
            )
        self.server.scene.set_up_direction(tuple(float(x) for x in -self.poses[0][:3, 1]))
        self._event("path")

    def _frustum_scale(self) -> float:
        centres = self.poses[:, :3, 3]
        extent = float(np.max(np.ptp(centres, axis=0))) if len(centres) > 1 else 0.0
        return float(np.clip(0.03 * extent, 0.05, 0.3))

    def _set_view(self) -> None:
        T = self.poses[0]
        forward, up = T[:3, 2], -T[:3, 1]
        centres = self.poses[:, :3, 3]
        extent = max(float(np.max(np.ptp(centres, axis=0))) if len(centres) > 1 else 0.0, 2.0)
        look_at = centres.mean(axis=0) + forward
        position = look_at - forward * 1.2 * extent + up * 0.6 * extent
        self.server.initial_camera.look_at = tuple(float(x) for x in look_at)
        self.server.initial_camera.position = tuple(float(x) for x in position)
        self.server.initial_camera.up = tuple(float(x) for x in up)

    def add_camera(self, index: int, rgb: Optional[np.ndarray] = None) -> None:
        """Draws frame ``index``'s camera frustum (with a small copy of its image when given)."""
        import viser.transforms as vtf

        if not 0 <= index < len(self.poses):
            raise InvalidInputError("index", f"a frame index in 0..{len(self.poses) - 1}", index)
        image = None
        if rgb is not None:
            import cv2

            w = min(160, rgb.shape[1])
            image = cv2.resize(rgb, (w, max(1, round(rgb.shape[0] * w / rgb.shape[1]))), interpolation=cv2.INTER_AREA)
        T = self.poses[index]
        cam = self.camera
        with self._lock:
            old = self.frustums.pop(index, None)
            if old is not None:
                old.remove()
            self.frustums[index] = self.server.scene.add_camera_frustum(
                f"/cameras/{index:05d}",
                fov=2.0 * math.atan2(cam.height / 2.0, cam.fy),
                aspect=cam.width / cam.height,
                scale=self._scale,
                image=image,
                format="jpeg",
                wxyz=vtf.SO3.from_matrix(T[:3, :3]).wxyz,
                position=T[:3, 3],
                color=(230, 80, 30),
                thickness=1.5,
                thickness_units="screen",
            )

    def show_points(self, points: np.ndarray, sigma: np.ndarray) -> None:
        """Redraws the map's points (world frame, metres) coloured by sigma (metres)."""
        points = np.asarray(points, dtype=np.float32)
        sigma = np.asarray(sigma, dtype=np.float64)
        if len(points) > self.max_points:
            keep = np.random.default_rng(0).choice(len(points), self.max_points, replace=False)
            points, sigma = points[keep], sigma[keep]
        colors, vmax = sigma_colors(sigma)
        with self._lock:
            if self.cloud is None:
                self.cloud = self.server.scene.add_point_cloud(
                    "/map/points",
                    points,
                    colors,
                    point_size=0.6 * self._voxel,
                    point_shape="square",
                    precision="float32",
                    point_shading="flat",
                )
            else:
                self.cloud.points = points
                self.cloud.colors = colors
            self._range.content = f"σ: 0 … {vmax * 100:.1f} cm ({len(points)} points; grey: no σ)"
        self.refreshes += 1
        self._event("cloud")

    _voxel = 0.02
    """Point size of the map's points is 0.6 voxel (updated from the mapper's fusion config)."""

    # ------------------------------------------------------------------ the mapping callback
    def update(self, event: Any) -> None:
        """The ``on_frame`` callback of `map_sequence`: the frame's camera, and the map when it is time.

        The viewer never stops the mapping: a failure to draw (a closed connection, say) is kept in
        ``errors`` and the page misses that update.

        Args:
            event: A `gpdepth3d.pipelines.mapping_run.FrameEvent`: the mapper (its `point_cloud` is
                drawn), the frame added (its camera is drawn; its index among ``poses`` is found by its
                pose) and the `FrameResult` fused in that call, if any.
        """
        try:
            mapper, result, frame = event.mapper, event.result, event.added
            if frame is not None:
                index = self._index(frame.pose)
                if index is not None:
                    self.add_camera(index, frame.rgb)
            self._voxel = float(mapper.config.fusion.voxel_size)
            fused = len(mapper.keyframes)
            self._status.content = f"**Mapping:** {len(self.frustums)} of {len(self.poses)} frames added, {fused} fused"
            now = time.monotonic()
            if result is not None and result.fused and now - self._last_refresh >= self.refresh_s:
                self._last_refresh = now
                self._refresh(mapper)
        except Exception as exc:  # noqa: BLE001 - drawing must not end a mapping run
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def _index(self, pose: np.ndarray) -> Optional[int]:
        d = np.abs(self.poses - np.asarray(pose)[None]).reshape(len(self.poses), -1).max(axis=1)
        i = int(np.argmin(d))
        return i if d[i] < 1e-6 else None

    def _refresh(self, mapper: Any) -> None:
        from ..errors import EmptyInputError

        try:
            cloud = mapper.point_cloud()
        except EmptyInputError:
            return
        if len(cloud):
            self.show_points(cloud.points, cloud.sigma)

    def finish(self, result: Any) -> None:
        """Draws the final map: its points by sigma and its mesh (vertex colours), hidden behind a checkbox."""
        self._refresh(result.mapper)
        if len(result.mesh.faces):
            with self._lock:
                self.mesh = self.server.scene.add_mesh_trimesh("/map/mesh", result.mesh, visible=False)
            box = self.server.gui.add_checkbox("Show mesh", initial_value=False)

            @box.on_update
            def _(_event) -> None:
                self.mesh.visible = box.value
                if self.cloud is not None:
                    self.cloud.visible = not box.value

            self._event("mesh")
        self._status.content = f"**Mapped:** {result.frames_fused} of {result.frames} frames fused"

    # ------------------------------------------------------------------ lifetime
    def wait(self, duration: Optional[float] = None) -> None:
        """Blocks for ``duration`` seconds (None: until Ctrl-C)."""
        wait_until_stopped(lambda: self._stopped, duration)

    def stop(self) -> None:
        """Stops the server and frees its port (idempotent)."""
        if not self._stopped:
            self._stopped = True
            self.server.stop()

    def __enter__(self) -> "LiveMapViewer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
