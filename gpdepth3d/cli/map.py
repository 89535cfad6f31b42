"""``gpdepth3d map``: a map (mesh, cloud with sigma, reloadable map) of a user's own posed image sequence."""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path
from typing import Any, Literal, Optional

from ..errors import InvalidInputError
from ..io.poses import ASSOCIATIONS, POSE_FORMATS

# the choices come from the one format table (gpdepth3d.io.poses): a new format is a new choice
PoseFormat = Literal[("auto", *POSE_FORMATS)]  # type: ignore[valid-type]
Association = Literal[ASSOCIATIONS]  # type: ignore[valid-type]


def map_command(
    images: Path,
    *,
    poses: Optional[Path] = None,
    points: Optional[Path] = None,
    intrinsics: Optional[str] = None,
    pose_format: PoseFormat = "auto",
    association: Association = "auto",
    max_time_difference: float = 0.02,
    depth: Optional[Path] = None,
    depth_scale: float = 0.001,
    depth_invalid: Optional[int] = None,
    depth_intrinsics: Optional[str] = None,
    output: Path = Path("map_out"),
    mde: str = "fastdepth",
    models_dir: Optional[Path] = None,
    working_width: int = 320,
    stride: int = 1,
    frames: Optional[int] = None,
    voxel_size: float = 0.02,
    depth_max: float = 5.0,
    threshold: float = 0.05,
    metric_samples: int = 50_000,
    mesh_format: Literal["ply", "glb", "obj"] = "ply",
    view: bool = False,
    host: str = "127.0.0.1",
    port: int = 8080,
    view_duration: Optional[float] = None,
    allow_remote: bool = False,
    force: bool = False,
) -> dict[str, Any]:
    """Map an image sequence, posed or not: mesh, coloured cloud with per-point sigma, reloadable map, metrics.

    Each image's depth comes from a monocular network (--mde), refined by a GP with points the
    library triangulates from the posed images themselves (and a COLMAP model's points when the poses
    are one), then fused into a TSDF with weights from the posterior variance. Writes into --output,
    all together or nothing: ``mesh.<format>``, ``cloud.ply`` (x y z, colour, confidence, sigma,
    variance), ``mapper.json`` + ``keyframes.npz`` + ``volume.npz`` (``Mapper.load(output)`` goes on
    from them) and ``metrics.json`` (with --depth: F-score at --threshold against the mesh fused from
    that depth, and the MDE alone's). Without --poses, pycolmap's structure from motion poses the images
    (or --points gives a COLMAP model's poses), the metric scale comes from the network's depth at the SfM
    points, and each piece the images fall into is mapped on its own (``output/piece<k>``; the SfM models
    in ``output/sparse``). See docs/mapping.md.

    Args:
        images: Image folder (its *.color.* files if any, else every .png/.jpg), or a quoted glob pattern.
        poses: Camera-to-world poses: a TUM trajectory (timestamp tx ty tz qx qy qz qw), KITTI rows (3x4),
            rows of a flattened 4x4 (one per image), a folder of per-image 4x4 files (*.pose.txt), or a
            COLMAP model folder. Without it: pycolmap SfM on the images (or the --points COLMAP model's poses).
        points: Given world points: a COLMAP model folder (or a folder of numbered models: pieces), or a
            points file in the poses' frame, metres: PLY (x y z, optional sigma), NPZ (xyz, optional sigma)
            or text (x y z [sigma] a line). Their depth sigma is calibrated (docs/mapping.md).
        intrinsics: Colour camera: a K file (3x3) or fx,fy,cx,cy in pixels (optional with a COLMAP model).
        pose_format: The pose format (default: recognised from the file).
        association: How poses find their images: by name (pose files, COLMAP), by timestamp (TUM, images
            named by their time), by order; auto picks the first that applies.
        max_time_difference: Largest image-to-pose time difference when associating by timestamp, seconds.
        depth: Sensor depth for evaluation: a folder (its *.depth.* files if any), or a quoted glob pattern.
        depth_scale: Metres per unit of 16-bit depth PNGs (0.001: millimetres; TUM RGB-D: 0.0002).
        depth_invalid: PNG value of invalid depth besides 0 (7-Scenes: 65535).
        depth_intrinsics: Depth camera's K file or fx,fy,cx,cy when it is not the colour camera (same pose).
        output: Output folder.
        mde: Monocular front-end: "fastdepth" (FastDepth TFLite, indoor; the [tflite] extra), "rtmonodepth"
            (RT-MonoDepth-S ONNX, outdoor) or a .tflite/.onnx model file.
        models_dir: Folder of the named front-ends' models (default: $GPDEPTH3D_MODELS or ../shared/models).
        working_width: Width of refinement and fusion, pixels (wider images are scaled down to it).
        stride: Use every STRIDE-th image.
        frames: Use at most this many images (after --stride; default: all).
        voxel_size: TSDF voxel size, metres.
        depth_max: Depths beyond this are not fused, metres.
        threshold: F-score distance, metres.
        metric_samples: Surface samples per mesh for the metrics.
        mesh_format: File format of the mesh.
        view: Show the map in the browser as it grows (viser): sigma-coloured cloud and camera frusta.
        host: Interface of the viewer (127.0.0.1: this machine only).
        port: Port of the viewer (the next free one when taken).
        view_duration: With --view, keep the page open this many seconds after mapping (default: until Ctrl-C).
        allow_remote: With --view, allow a --host other than this machine (the map is then served to every
            machine that can reach this one).
        force: Map on when most frames fail the pose check (their feature tracks do not triangulate with
            their poses: inverted poses, w-first quaternions, another frame's poses); by default map stops
            there with one line naming the likely cause. A camera that only rotates fails it too.

    Returns:
        The summary written to ``metrics.json``.
    """
    from ..pipelines.mapping_run import open_map_inputs

    if view_duration is not None and not (math.isfinite(view_duration) and view_duration >= 0):
        raise InvalidInputError("--view-duration", "seconds >= 0 (or none: until Ctrl-C)", view_duration)
    if poses is None:
        if view:
            raise InvalidInputError("--view", "--poses (the live view draws the camera path first)", "no --poses")
        return _map_unposed(
            images, intrinsics=intrinsics, points=points, output=output, mde=mde, models_dir=models_dir,
            stride=stride, frames=frames, voxel_size=voxel_size, depth_max=depth_max, depth=depth,
            depth_kw={"depth_scale": depth_scale, "depth_invalid": depth_invalid, "depth_intrinsics": depth_intrinsics},
            map_kw={"working_width": working_width, "threshold": threshold, "metric_samples": metric_samples},
            mesh_format=mesh_format,
        )  # fmt: skip
    inputs = open_map_inputs(images, poses, intrinsics, output=output, pose_format=pose_format,
                             association=association, max_time_difference=max_time_difference, depth=depth,
                             depth_scale=depth_scale, depth_invalid=depth_invalid,
                             depth_intrinsics=depth_intrinsics, points=points)  # fmt: skip
    run = dict(mde=mde, models_dir=models_dir, working_width=working_width, stride=stride, frames=frames,
               voxel_size=voxel_size, depth_max=depth_max, threshold=threshold, metric_samples=metric_samples,
               mesh_format=mesh_format, force=force)  # fmt: skip
    summary, live = _map_posed(inputs, output, run, (host, port, allow_remote) if view else None)
    if live is not None:
        print(f"viewer at {live.url} ({'Ctrl-C to stop' if view_duration is None else f'{view_duration:g} s'})")
        live.wait(view_duration)
        live.stop()
    return summary


def _map_posed(inputs, output: Path, run: dict, viewer: tuple | None):
    """``map`` with --poses: the sequence mapped frame by frame (`map_files` with the options ``run``), the live
    view at ``viewer`` (host, port, allow_remote) fed as it grows, the result printed; returns (summary, the live
    viewer or None)."""
    from ..pipelines.mapping_run import map_files
    from ._warnings import quiet_third_party, report_warnings

    seq = inputs.sequence
    print(
        f"map: {len(seq)} images of {seq.camera.width}x{seq.camera.height}, poses: {inputs.pose_format}"
        + (", with depth" if seq.depth_files is not None else ""),
        flush=True,
    )
    live = None if viewer is None else _start_viewer(seq, *viewer)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_third_party()
        try:
            result, summary, written = map_files(
                inputs, output, progress=sys.stderr.isatty(), on_frame=None if live is None else live.update, **run
            )
        except BaseException:
            if live is not None:
                live.stop()
            raise
    report_warnings(caught, dict(enumerate(seq.names)))
    _print_result(result, written, output, run["threshold"])
    if live is not None:
        live.finish(result)
    return summary, live


def _start_viewer(seq, host: str, port: int, allow_remote: bool):
    """The live map viewer of ``--view``: the cameras now, the map as it grows."""
    from ..viewer.live_map import LiveMapViewer

    live = LiveMapViewer(
        seq.camera, seq.poses, first_rgb=seq.frame(0).rgb, host=host, port=port, allow_remote=allow_remote
    )
    print(f"viewer running at {live.url} (the map appears as it grows)", flush=True)
    return live


def _print_result(result, written: list, output: Path, threshold: float) -> None:
    """The frames skipped, fused without points and mapped, the files written and the F-score line."""
    for message in result.frame_errors:
        print(f"skipped {message}")
    if result.frames_without_points:
        print(
            f"{len(result.frames_without_points)} frame(s) had no sparse point and were fused from the MDE with "
            "its prior variance"
        )
    print(
        f"mapped {result.frames_fused} of {result.frames} frames in {result.timing['wall']:.1f} s "
        f"(median {result.sparse_points:.0f} points a frame); wrote {len(written)} files "
        f"({sum(p.stat().st_size for p in written) / 1e6:.1f} MB) to {Path(output).resolve()}"
    )
    for path in written:
        print(f"wrote {path}")
    if result.metrics is not None:
        print(_fscore_line(result.metrics, threshold))


def _map_unposed(
    images: Path,
    *,
    intrinsics: Optional[str],
    points: Optional[Path],
    output: Path,
    mde: str,
    models_dir: Optional[Path],
    stride: int,
    frames: Optional[int],
    voxel_size: float,
    depth_max: float,
    depth: Optional[Path],
    depth_kw: dict,
    map_kw: dict,
    mesh_format: str,
) -> dict[str, Any]:
    """``map`` without --poses: SfM (or the --points COLMAP model), metric scale from the network, one map per piece
    (``depth_kw``: how to read --depth; ``map_kw``: working width and metrics of each piece's map)."""
    import tempfile

    from dataclasses import replace

    from ..io import check_output_folder
    from ..mapping.mapper_config import MapperConfig
    from ..mde import load_frontend
    from ..pipelines.sfm import map_unposed, pieces_summary, write_pieces
    from ._warnings import quiet_third_party, report_warnings

    check_output_folder(Path(output), "--output")
    base = MapperConfig()
    config = replace(base, fusion=replace(base.fusion, voxel_size=voxel_size, depth_max=depth_max))
    print(f"map: no poses: {'the COLMAP model ' + str(points) if points else 'pycolmap SfM on the images'}")
    with tempfile.TemporaryDirectory(prefix="gpdepth3d-sfm-") as tmp, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_third_party()
        result = map_unposed(
            str(images),
            intrinsics,
            mde=load_frontend(mde, models_dir=models_dir, argument="--mde"),
            points=points,
            workdir=tmp,
            stride=stride,
            max_frames=frames,
            config=config,
            depth=None if depth is None else str(depth),
            depth_kw=depth_kw,
            map_kw=map_kw,
        )
        named = {"images": images, "points": points, "intrinsics": intrinsics, "depth": depth, "mde": mde}
        inputs = {k: None if v is None else str(v) for k, v in named.items()}
        written = write_pieces(result, output, summary={"inputs": inputs}, mesh_format=mesh_format)
    report_warnings(caught)
    _print_pieces(result, map_kw["threshold"])
    print(f"wrote {len(written)} files to {Path(output).resolve()} in {result.timing['wall']:.1f} s")
    for path in written:
        print(f"wrote {path}")
    return pieces_summary(result)


def _print_pieces(result, threshold: float) -> None:
    """The images registered, and per piece its frames, scale and F-score, or why it was not mapped."""
    print(f"registered {result.registered} of {result.frames} images in {len(result.pieces)} piece(s)")
    for k, piece in enumerate(result.pieces):
        s = piece.scale
        scale = "" if s is None else f", scale {s.scale:.4f} ± {s.sigma:.4f} m per unit ({s.points} points)"
        if piece.error:
            print(f"piece {k} of {len(piece.names)} frames not mapped{scale}: {piece.error}")
        else:
            print(f"piece {k}: {len(piece.names)} frames{scale}")
        if piece.result is not None and piece.result.metrics is not None:
            print(f"piece {k}: " + _fscore_line(piece.result.metrics, threshold))


def _fscore_line(metrics: dict, threshold: float) -> str:
    """One line with the map's and the MDE-only map's F-score against the sensor depth."""

    def f(m):
        return (
            "no surface"
            if m is None
            else f"{m['fscore']:.3f} (precision {m['precision']:.3f}, recall {m['recall']:.3f})"
        )

    return f"F-score at {threshold * 100:g} cm against the sensor depth: map {f(metrics['map'])}; MDE alone {f(metrics['mde'])}"
