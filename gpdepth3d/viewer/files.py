"""Any file the library writes, opened for the viewer: posteriors, meshes, point clouds and saved maps.

`file_kind` tells a path's kind from its content: a posterior ``.npz`` (``gpdepth3d complete``), a mesh
(``.ply`` with faces, ``.glb``, ``.obj``: ``gpdepth3d fuse``, ``gpdepth3d map``), a point cloud (a ``.ply``
without faces: ``complete --ply``, a map's ``cloud.ply``) or a map folder (the output folder of
``gpdepth3d map``, or a folder written by `gpdepth3d.mapping.Mapper.save`). `load_geometry` reads the
last three as trimesh objects for `gpdepth3d.viewer.show`; `open_view` is the work of ``gpdepth3d view``:
every file sorted by kind, the frames built, the viewer started.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..errors import DataFormatError, EmptyInputError, InvalidInputError
from .scene_data import ViewerConfig, ViewerFrame, load_mesh, stored_intrinsics

VIEW_KINDS = ("posterior", "mesh", "cloud", "map")
"""What the viewer opens (`file_kind`)."""

MAP_MESHES = ("mesh.ply", "mesh.glb", "mesh.obj")
"""The mesh of a ``gpdepth3d map`` output folder (one of these names)."""

MAP_CLOUD = "cloud.ply"
"""The cloud with per-point sigma of a ``gpdepth3d map`` output folder."""

_PLY_HEADER_LIMIT = 1 << 16  # bytes of a PLY header read at most


def ply_face_count(path: str | Path) -> int:
    """The number of faces a PLY file's header declares (0 for a point cloud).

    Raises:
        DataFormatError: if the file is not a PLY (no ``ply`` magic, or no ``end_header`` in its first 64 KiB).
    """
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(_PLY_HEADER_LIMIT)
    if not head.startswith(b"ply"):
        raise DataFormatError(path, "not a PLY file (no 'ply' magic)")
    end = head.find(b"end_header")
    if end < 0:
        raise DataFormatError(path, "not a PLY file (no end_header)")
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element" and words[1] == "face":
            return int(words[2]) if words[2].isdigit() else 0
    return 0


def _is_map_folder(folder: Path) -> bool:
    from ..mapping.map_store import MAP_FILES

    names = (*MAP_MESHES, MAP_CLOUD)
    return any((folder / n).is_file() for n in names) or all((folder / n).is_file() for n in MAP_FILES)


def file_kind(path: str | Path) -> str:
    """The kind of a file or folder the library writes (one of `VIEW_KINDS`), from its suffix and content.

    Raises:
        DataFormatError: if the path does not exist or is none of those kinds (the message lists them).
    """
    path = Path(path)
    what = "a posterior .npz, a mesh (.ply/.glb/.obj), a point cloud .ply or a map folder"
    if path.is_dir():
        if _is_map_folder(path):
            return "map"
        raise DataFormatError(
            path, f"a folder without a map in it (mesh.ply, cloud.ply or a saved map); expected {what}"
        )
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return "posterior"
    if suffix in (".glb", ".obj"):
        return "mesh"
    if suffix == ".ply":
        return "mesh" if ply_face_count(path) > 0 else "cloud"
    raise DataFormatError(path, f"not a file the viewer opens; expected {what}")


def load_cloud(path: str | Path) -> Any:
    """Reads a point-cloud PLY (`gpdepth3d.mapping.ColoredCloud.save_ply`, any PLY of points) as a ``trimesh.PointCloud``.

    Raises:
        DataFormatError: if the file is missing, unreadable or holds no points.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "point cloud file not found")
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types for unreadable files
        raise DataFormatError(path, f"not a readable point cloud: {exc}") from None
    if isinstance(loaded, trimesh.Trimesh):  # a PLY of vertices only may come back as a mesh without faces
        colors = loaded.visual.vertex_colors if loaded.visual.kind == "vertex" else None
        loaded = trimesh.PointCloud(np.asarray(loaded.vertices), colors=colors)
    if not isinstance(loaded, trimesh.PointCloud) or len(loaded.vertices) == 0:
        raise DataFormatError(path, "no points in the file")
    return loaded


def load_map(folder: str | Path) -> list[Any]:
    """A map folder's mesh and cloud (trimesh objects): its files when ``gpdepth3d map`` wrote them, else the saved map.

    A folder holding only what `gpdepth3d.mapping.Mapper.save` writes is loaded with `Mapper.load` (the
    ``[mapping]`` extra) and its mesh and surface points extracted; a mesh without faces (a map whose surface
    is not yet above the fusion's weight threshold) is left out.

    Raises:
        DataFormatError: if the folder holds no map, or its files are not what the library writes.
        EmptyInputError: if the map has neither a surface nor points.
    """
    folder = Path(folder)
    if not folder.is_dir() or not _is_map_folder(folder):
        raise DataFormatError(folder, "not a map folder (mesh.ply, cloud.ply or the files of Mapper.save)")
    items = [load_mesh(folder / n) for n in MAP_MESHES if (folder / n).is_file()][:1]
    if (folder / MAP_CLOUD).is_file():
        items.append(load_cloud(folder / MAP_CLOUD))
    if not items:
        from ..mapping.mapper import Mapper

        mapper = Mapper.load(folder)
        mesh, cloud = mapper.mesh(), mapper.point_cloud()
        items = ([mesh] if len(mesh.faces) else []) + ([cloud.to_trimesh()] if len(cloud) else [])
    if not items:
        raise EmptyInputError(str(folder), "a map with a surface or points", "an empty map")
    return items


def load_geometry(path: str | Path) -> list[Any]:
    """A mesh, point cloud or map folder as the trimesh objects the viewer draws (`file_kind` decides).

    Raises:
        DataFormatError: for a posterior (give it as a frame) or a path of no kind the viewer opens.
    """
    kind = file_kind(path)
    if kind == "posterior":
        raise DataFormatError(path, "a posterior, not a mesh, cloud or map (give it as a frame: --posterior)")
    if kind == "mesh":
        return [load_mesh(path)]
    return [load_cloud(path)] if kind == "cloud" else load_map(path)


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
