"""``gpdepth3d view``: the 3D viewer in the browser, from files written by ``complete`` and ``fuse``."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InvalidInputError
from ..camera import read_intrinsics
from ..io import load_pose, load_poses
from ..viewer.app import show
from ..viewer.scene_data import ColorBy, Layout, ViewerConfig, ViewerFrame, stored_intrinsics
from ..viewer.serving import check_host, port_taken


def view_command(
    *,
    posterior: tuple[Path, ...] = (),
    rgb: tuple[Path, ...] = (),
    intrinsics: Optional[str] = None,
    gt: tuple[Path, ...] = (),
    gt_png_scale: float = 1.0 / 256.0,
    gt_invalid_value: Optional[int] = None,
    poses: tuple[Path, ...] = (),
    mesh: tuple[Path, ...] = (),
    host: str = "127.0.0.1",
    port: int = 8080,
    layout: Layout = "side-by-side",
    color_by: ColorBy = "rgb",
    max_points: int = 400_000,
    duration: Optional[float] = None,
    allow_remote: bool = False,
) -> None:
    """Open the 3D viewer in the browser: GP-refined vs MDE-only point clouds, measurements, meshes.

    Serves http://HOST:PORT until Ctrl-C (or --duration seconds). Give one --posterior for a frame,
    several (with --poses) for a sequence; --rgb, --gt and --poses are matched to them by order.

    Args:
        posterior: Posterior .npz files written by `gpdepth3d complete`.
        rgb: The frames' images (same order as --posterior).
        intrinsics: The camera of the RGB image (of the posterior grid without --rgb): a text file holding the
            3x3 K, a KITTI calibration (calib_*.txt with P2, calib_cam_to_cam.txt or its folder) or "fx,fy,cx,cy"
            in pixels. Default: the K stored in the posterior file, else a 60 degree horizontal field of view.
        gt: Ground-truth depth maps (.npy/.npz metres or 16-bit .png), same order.
        gt_png_scale: Metres per unit of a 16-bit ground-truth PNG (1/1000 for Kinect millimetres).
        gt_invalid_value: Raw PNG value that marks invalid ground truth (65535 for 7-Scenes).
        poses: Camera-to-world poses: one 4x4 (or 3x4) text file per frame, or one file with a 3x4 pose per line.
        mesh: Meshes written by `gpdepth3d fuse` (.ply/.glb/.obj), world frame.
        host: Interface to listen on (127.0.0.1 = this machine only; another address, such as 0.0.0.0, serves the
            scene to the network and needs --allow-remote).
        port: TCP port of the page (when it is taken the next free one is used, and said).
        layout: "side-by-side" or "overlay".
        color_by: Initial colouring: rgb, depth, sigma or error (needs --gt).
        max_points: Most points per layer; frames are subsampled to stay below it.
        duration: Stop after this many seconds (default: run until Ctrl-C).
        allow_remote: Allow a --host other than loopback: everyone who can reach this machine sees the scene.
    """
    if duration is not None and (
        isinstance(duration, bool) or not isinstance(duration, (int, float)) or math.isnan(duration) or duration < 0
    ):
        raise InvalidInputError("--duration", "seconds >= 0 (or no --duration: until Ctrl-C)", duration)
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise InvalidInputError("--port", "a TCP port 0..65535", port)
    local = check_host(host, allow_remote=allow_remote)  # before loading anything: fails at once
    if not local:
        print(
            f"view: WARNING: serving on {host}:{port} to the network (--allow-remote): anyone who can reach this "
            "machine can see the scene",
            file=sys.stderr,
        )
    n = len(posterior)
    if color_by == "error" and not gt:
        raise InvalidInputError("--color-by", "rgb, depth or sigma without --gt", color_by)
    for name, items in (("rgb", rgb), ("gt", gt)):
        if items and len(items) != n:
            raise InvalidInputError(f"--{name}", f"{n} files (one per --posterior)", f"{len(items)} files")
    if len(poses) == 1 and n > 1:
        pose_list: list[Optional[np.ndarray]] = list(load_poses(poses[0]))
        if len(pose_list) != n:
            raise InvalidInputError("--poses", f"{n} poses (one per --posterior)", f"{len(pose_list)} lines")
    elif poses:
        if len(poses) != n:
            raise InvalidInputError("--poses", f"{n} files (one per --posterior)", f"{len(poses)} files")
        pose_list = [load_pose(p) for p in poses]
    else:
        pose_list = [None] * n
    K = read_intrinsics(intrinsics) if intrinsics is not None else None
    stored = [None if K is not None else stored_intrinsics(path) for path in posterior]
    if K is None and n and any(k is None for k in stored):
        print(
            "view: no --intrinsics and none in the posterior file; assuming a 60 degree horizontal field of view "
            "(give --intrinsics K.txt, a KITTI calib file or fx,fy,cx,cy)"
        )
    frames = [
        ViewerFrame.from_files(
            path,
            K=K,
            rgb=rgb[i] if rgb else None,
            depth_gt=gt[i] if gt else None,
            gt_png_scale=gt_png_scale,
            gt_invalid_value=gt_invalid_value,
            T_world_camera=pose_list[i],
        )
        for i, path in enumerate(posterior)
    ]
    config = ViewerConfig(layout=layout, color_by=color_by, max_points=max_points)
    taken = port_taken(host, port)
    with show(
        frames, meshes=list(mesh), config=config, host=host, port=port, allow_remote=allow_remote, background=True
    ) as viewer:
        if taken or (port and viewer.port != port):
            print(f"view: port {port} is taken (by another program); using port {viewer.port} instead")
        print(
            f"viewer running at {viewer.url} ({'Ctrl-C to stop' if duration is None else f'{duration:g} s'})",
            flush=True,
        )
        viewer.wait_loaded()
        print(
            f"view: {len(frames)} frame(s) and {len(mesh)} mesh(es) on the page "
            f"({viewer.events[-1][1]:.1f} s after the server started)",
            flush=True,
        )
        viewer.wait(duration)
    print("viewer stopped")
