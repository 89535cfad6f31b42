"""Starting the viewer on files the library wrote: the work of ``gpdepth3d view`` (`open_view`).

Every file is sorted by its kind (`gpdepth3d.viewer.files.file_kind`): posteriors become frames (with their
images, ground truth, poses and intrinsics), meshes, clouds and map folders join the scene's geometry; then
`gpdepth3d.viewer.show` starts the server. What the command should tell the user comes back as lines.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..errors import EmptyInputError, InvalidInputError
from .files import file_kind
from .scene_data import ViewerConfig, ViewerFrame, stored_intrinsics


@dataclass
class OpenedView:
    """A running viewer of files (`open_view`) and what the command says about them.

    Attributes:
        viewer: The running `gpdepth3d.viewer.Viewer` (loading in the background; stop it when done).
        notes: Lines to tell the user (an assumed field of view, a port taken).
        warnings: Lines to warn about (serving to the network).
        kinds: The kind of each given file, in order (`VIEW_KINDS`).
    """

    viewer: Any
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)


def _frame_poses(poses: Sequence[Path], n: int) -> list[Optional[np.ndarray]]:
    """One pose per frame: one file of 3x4 lines for a sequence, or one 4x4 / 3x4 file per frame."""
    from ..io.poses import load_pose, load_poses

    if len(poses) == 1 and n > 1:
        pose_list: list[Optional[np.ndarray]] = list(load_poses(poses[0]))
        if len(pose_list) != n:
            raise InvalidInputError("--poses", f"{n} poses (one per --posterior)", f"{len(pose_list)} lines")
        return pose_list
    if poses:
        if len(poses) != n:
            raise InvalidInputError("--poses", f"{n} files (one per --posterior)", f"{len(poses)} files")
        return [load_pose(p) for p in poses]
    return [None] * n


def open_view(
    files: Sequence[Path] = (),
    *,
    posterior: Sequence[Path] = (),
    rgb: Sequence[Path] = (),
    intrinsics: Optional[str] = None,
    gt: Sequence[Path] = (),
    gt_png_scale: float = 1.0 / 256.0,
    gt_invalid_value: Optional[int] = None,
    poses: Sequence[Path] = (),
    mesh: Sequence[Path] = (),
    config: Optional[ViewerConfig] = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    allow_remote: bool = False,
) -> OpenedView:
    """Starts the viewer on files the library wrote: the work of ``gpdepth3d view`` (its options, by name).

    ``files`` may hold any kind (`file_kind`): posteriors join ``posterior`` as frames (after it, in
    order), meshes, clouds and map folders join ``mesh``. Errors name the command's options.

    Raises:
        InvalidInputError: for lists of different lengths, a bad port or host, --color-by error without --gt.
        DataFormatError: for a file of no kind the viewer opens, or one that is not what its kind should be.
        EmptyInputError: with nothing to show.
    """
    from ..camera import read_intrinsics
    from .app import show
    from .serving import check_host, port_taken

    config = config or ViewerConfig()
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise InvalidInputError("--port", "a TCP port 0..65535", port)
    local = check_host(host, allow_remote=allow_remote)  # before loading anything: fails at once
    kinds = [file_kind(p) for p in files]
    posterior = [*posterior, *(Path(p) for p, k in zip(files, kinds) if k == "posterior")]
    geometry = [*mesh, *(Path(p) for p, k in zip(files, kinds) if k != "posterior")]
    n = len(posterior)
    if not n and not geometry:
        raise EmptyInputError("files", "a posterior, mesh, point cloud or map folder to show", "none")
    if config.color_by == "error" and not gt:
        raise InvalidInputError("--color-by", "rgb, depth or sigma without --gt", config.color_by)
    for name, items in (("rgb", rgb), ("gt", gt)):
        if items and len(items) != n:
            raise InvalidInputError(f"--{name}", f"{n} files (one per --posterior)", f"{len(items)} files")
    pose_list = _frame_poses(poses, n)
    K = read_intrinsics(intrinsics) if intrinsics is not None else None
    opened = OpenedView(viewer=None, kinds=kinds)
    if not local:
        opened.warnings.append(
            f"serving on {host}:{port} to the network (--allow-remote): anyone who can reach this machine can see "
            "the scene"
        )
    if K is None and n and any(stored_intrinsics(p) is None for p in posterior):
        opened.notes.append(
            "no --intrinsics and none in the posterior file; assuming a 60 degree horizontal field of view "
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
    taken = port_taken(host, port)
    opened.viewer = show(
        frames, meshes=geometry, config=config, host=host, port=port, allow_remote=allow_remote, background=True
    )
    if taken or (port and opened.viewer.port != port):
        opened.notes.append(f"port {port} is taken (by another program); using port {opened.viewer.port} instead")
    return opened
