"""Any file the library writes, opened for the viewer: posteriors, meshes, point clouds and saved maps.

`file_kind` tells a path's kind from its content: a posterior ``.npz`` (``gpdepth3d complete``), a mesh
(``.ply`` with faces, ``.glb``, ``.obj``: ``gpdepth3d fuse``, ``gpdepth3d map``), a point cloud (a ``.ply``
without faces: ``complete --ply``, a map's ``cloud.ply``) or a map folder (the output folder of
``gpdepth3d map``, or a folder written by `gpdepth3d.mapping.Mapper.save`). `load_geometry` reads the
last three as trimesh objects for `gpdepth3d.viewer.show` (`gpdepth3d.viewer.launch.open_view` sorts a
command line's files by kind).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DataFormatError, EmptyInputError
from .scene_data import load_mesh

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
