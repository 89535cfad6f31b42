"""``gpdepth3d view``: the 3D viewer in the browser, from any file the library writes (frames, meshes, clouds, maps)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

from ..viewer.launch import open_view
from ..viewer.scene_data import ColorBy, Layout, ViewerConfig
from ..viewer.serving import check_duration


def view_command(
    *,
    files: tuple[Path, ...] = (),
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
    """Open the 3D viewer in the browser: any file the library writes (frames, meshes, clouds, maps).

    Serves http://HOST:PORT until Ctrl-C (or --duration seconds). One posterior is a frame, several (with
    --poses) a sequence; --rgb, --gt and --poses are matched to them by order.

    Args:
        files: Any files the library writes, by content: posteriors, meshes, point clouds (.ply), map folders.
        posterior: Posterior .npz files written by `gpdepth3d complete`.
        rgb: The frames' images (same order as --posterior).
        intrinsics: The RGB image's camera: a 3x3 K text file, a KITTI calibration or "fx,fy,cx,cy" (pixels).
            Default: the K stored in the posterior file, else a 60 degree horizontal field of view.
        gt: Ground-truth depth maps (.npy/.npz metres or 16-bit .png), same order.
        gt_png_scale: Metres per unit of a 16-bit ground-truth PNG (1/1000 for Kinect millimetres).
        gt_invalid_value: Raw PNG value that marks invalid ground truth (65535 for 7-Scenes).
        poses: Camera-to-world poses: one 4x4 (or 3x4) text file per frame, or one file with a 3x4 pose per line.
        mesh: Meshes (.ply/.glb/.obj), point clouds (.ply) or map folders, world frame.
        host: Interface to listen on (127.0.0.1 = this machine only; any other, e.g. 0.0.0.0, needs --allow-remote).
        port: TCP port of the page (when it is taken the next free one is used, and said).
        layout: "side-by-side" or "overlay".
        color_by: Initial colouring: rgb, depth, sigma or error (needs --gt).
        max_points: Most points per layer; frames are subsampled to stay below it.
        duration: Stop after this many seconds (default: run until Ctrl-C).
        allow_remote: Allow a --host other than loopback: everyone who can reach this machine sees the scene.
    """
    check_duration(duration, "--duration")
    config = ViewerConfig(layout=layout, color_by=color_by, max_points=max_points)
    opened = open_view(files, posterior=posterior, rgb=rgb, intrinsics=intrinsics, gt=gt, poses=poses, mesh=mesh,
                       gt_png_scale=gt_png_scale, gt_invalid_value=gt_invalid_value, config=config, host=host,
                       port=port, allow_remote=allow_remote)  # fmt: skip
    with opened.viewer as viewer:
        for line in opened.warnings:
            print(f"view: WARNING: {line}", file=sys.stderr)
        for line in opened.notes:
            print(f"view: {line}")
        until = "Ctrl-C to stop" if duration is None else f"{duration:g} s"
        print(f"viewer running at {viewer.url} ({until})", flush=True)
        viewer.wait_loaded()
        print(f"view: {len(viewer.frames)} frame(s) and {len(viewer.meshes)} mesh(es) or cloud(s) on the page "
              f"({viewer.events[-1][1]:.1f} s after the server started)", flush=True)  # fmt: skip
        viewer.wait(duration)
    print("viewer stopped")
