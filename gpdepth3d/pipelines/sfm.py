"""Maps from an image folder alone (pycolmap SfM, metric scale from the network) or from given SfM / SLAM points.

`map_images` runs structure from motion on the images (`gpdepth3d.mapping.points.colmap_sfm`), fixes each
piece's metric scale from the network's depth at the SfM points (`gpdepth3d.mapping.points.sfm_scale`) and maps
each piece with the `Mapper`, its points given the calibrated sigma of `PointSigmaRule` widened by the
scale's uncertainty. `map_with_points` maps a posed sequence with given world points (a COLMAP model in
the poses' frame, or points with a stated sigma); a COLMAP model without poses goes through
`map_pieces` like an SfM run. A reconstruction in several pieces (a SLAM that lost tracking, an SfM
that could not chain every image) is mapped as separate maps, one per piece; a piece whose metric
scale is not to be trusted (`PieceRule`) is not mapped, and its result says why.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import PinholeCamera, transform_points
from ..datasets.posed import IMAGE_SUFFIXES, FileSpec, PosedSequence, list_files, read_intrinsics
from ..errors import EmptyInputError
from .mapping_run import MapResult, PosedInputs, map_sequence, piece_frames
from ..io import load_rgb
from ..mapping.points.colmap_sfm import SfMConfig, reconstruct_sequence
from ..mapping.points.given_points import GivenPoints, PointSigmaRule, read_given_points
from ..mapping.mapper import MDEFrontEnd
from ..mapping.mapper_config import MapperConfig
from ..mapping.points.sfm_scale import MetricScale, PieceRule, depth_ratios, focal_ratio, metric_scale
from ..io.poses import invert_pose


@dataclass
class PieceResult:
    """One piece of a reconstruction, mapped.

    Attributes:
        names: Image file names of the piece's frames, in sequence order.
        scale: Its metric scale (`MetricScale`), or None when the points were metric already.
        result: The map (`MapResult`), or None when the piece could not be mapped (``error`` says why).
        error: Why the piece was not mapped, or None.
    """

    names: list[str]
    scale: MetricScale | None
    result: MapResult | None
    error: str | None = None


@dataclass
class PiecesResult:
    """What `map_images` / `map_pieces` made: one map per piece, largest first.

    Attributes:
        pieces: `PieceResult` per piece.
        frames: Images given.
        registered: Distinct images in some piece (registered by SfM, or observed by the given model;
            pycolmap may register an image in two overlapping pieces).
        models: Folders of the SfM models (piece order), when SfM ran.
        timing: Seconds: ``sfm``, ``scale``, ``map`` and ``wall``.
    """

    pieces: list[PieceResult]
    frames: int
    registered: int
    models: list[Path] = field(default_factory=list)
    timing: dict = field(default_factory=dict)


def _scale_of(piece: GivenPoints, frames, files: list[Path], camera: PinholeCamera, mde: MDEFrontEnd) -> MetricScale:
    """The piece's metres per unit from the network's depth at its points (its training camera's view corrected)."""
    training = getattr(mde, "training_intrinsics", None)
    factor = 1.0 if training is None else focal_ratio(camera, training)
    ratios = []
    for i, image_id in frames:
        points = piece.points[piece.observed_by(image_id)]
        if len(points):
            depth = factor * np.asarray(mde(load_rgb(files[i])), dtype=np.float64)
            ratios.append(depth_ratios(points, piece.model.images[image_id].T_world_camera, camera, depth))
    return metric_scale(ratios)


def _scaled_inputs(
    piece: GivenPoints,
    frames,
    files: list[Path],
    camera: PinholeCamera,
    scale: MetricScale,
    rule: PointSigmaRule,
    depth_kw: dict,
) -> PosedInputs:
    """The piece's frames with metric poses, each with the points it observes and their sigma."""
    poses, points, sigmas = [], [], []
    s, rel = scale.scale, scale.relative_sigma
    for _, image_id in frames:
        T = piece.model.images[image_id].T_world_camera.copy()
        T[:3, 3] *= s
        rows = piece.observed_by(image_id)
        p = piece.points[rows] * s
        d = np.linalg.norm(transform_points(invert_pose(T), p), axis=1)
        sigma = rule.sigma(
            d, reprojection_error=piece.reprojection_error[rows], angle_deg=piece.angle_deg[rows], focal=camera.fx
        )
        poses.append(T)
        points.append(p)
        sigmas.append(np.sqrt(sigma**2 + (rel * d) ** 2))
    sequence = PosedSequence([files[i] for i, _ in frames], np.stack(poses), camera, **depth_kw)
    return PosedInputs(sequence, "sfm", points, sigmas)


def map_pieces(
    pieces: list[GivenPoints],
    files: list[Path],
    camera: PinholeCamera,
    *,
    mde: MDEFrontEnd,
    config: MapperConfig | None = None,
    sigma_rule: PointSigmaRule | None = None,
    depth: FileSpec | None = None,
    depth_kw: dict | None = None,
    map_kw: dict | None = None,
    piece_rule: PieceRule | None = None,
) -> PiecesResult:
    """Maps each piece of a reconstruction known up to scale: metric scale from ``mde``, then the `Mapper`.

    Args:
        pieces: COLMAP models (`read_given_points`), largest first.
        files: The sequence's image files (matched to the models' images by file name), in order.
        camera: The images' intrinsics.
        mde: Front-end ``rgb -> depth`` in metres; when it has ``training_intrinsics`` (fx, fy, width,
            height of its training camera), its depth is corrected by `focal_ratio` for the scale.
        config: Mapper options.
        sigma_rule: Depth sigma of the points (default `PointSigmaRule()`), widened by the scale's
            relative uncertainty times the distance.
        depth: Sensor depth for scoring only (folder, glob or files matched by name).
        depth_kw: ``depth_scale``, ``depth_invalid``, ``depth_intrinsics`` for `PosedSequence`.
        map_kw: Further arguments of `map_sequence` (``working_width``, ``threshold``, ...).
        piece_rule: When a piece's scale is not trusted (default `PieceRule()`): such a piece is not
            mapped (its geometry would be worse than the network's), its result says why.

    Returns:
        `PiecesResult`; a piece that cannot be mapped (no ratio for its scale, refused by
        ``piece_rule``, no frame fused) carries its error, the others go on.

    Raises:
        EmptyInputError: no piece could be mapped (naming why).
    """
    from ..errors import GPDepthError

    t0 = time.perf_counter()
    rule = sigma_rule or PointSigmaRule()
    trust = piece_rule or PieceRule()
    names = [f.name for f in files]
    depth_kw = dict(depth_kw or {})
    if depth is not None:
        depth_kw["depth"] = [str(p) for p in _matched_depth(files, depth)]
    out, registered, t_scale = [], set(), 0.0
    for piece in pieces:
        frames = piece_frames(piece, names)
        registered.update(i for i, _ in frames)
        piece_names = [names[i] for i, _ in frames]
        if len(frames) < 1:
            continue
        t1 = time.perf_counter()
        try:
            scale = _scale_of(piece, frames, files, camera, mde)
        except EmptyInputError as exc:
            out.append(PieceResult(piece_names, None, None, f"no metric scale: {exc}"))
            continue
        t_scale += time.perf_counter() - t1
        refusal = trust.refusal(len(frames), scale)
        if refusal is not None:
            out.append(PieceResult(piece_names, scale, None, refusal))
            continue
        kw = dict(depth_kw)
        if "depth" in kw:
            kw["depth"] = [kw["depth"][i] for i, _ in frames]
        inputs = _scaled_inputs(piece, frames, files, camera, scale, rule, kw)
        try:
            result = map_sequence(inputs, mde=mde, config=config, **(map_kw or {}))
        except GPDepthError as exc:
            out.append(PieceResult(piece_names, scale, None, f"{type(exc).__name__}: {exc}"))
            continue
        out.append(PieceResult(piece_names, scale, result))
    if not any(p.result is not None for p in out):
        why = "; ".join(p.error for p in out if p.error) or "no piece observes these images"
        raise EmptyInputError("images", "a piece of the reconstruction that can be mapped", why)
    wall = time.perf_counter() - t0
    return PiecesResult(
        out, len(files), len(registered), timing={"scale": t_scale, "map": wall - t_scale, "wall": wall}
    )


def _matched_depth(files: list[Path], depth: FileSpec) -> list[Path]:
    """One sensor-depth file per image (`gpdepth3d.datasets.posed.match_depth`)."""
    from ..datasets.posed import DEPTH_SUFFIXES, match_depth

    return match_depth(files, list_files(depth, DEPTH_SUFFIXES, "depth", "depth"))


def map_images(
    images: FileSpec,
    intrinsics: str | Path | PinholeCamera,
    workdir: str | Path,
    *,
    mde: MDEFrontEnd,
    sfm: SfMConfig | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    **kwargs: Any,
) -> PiecesResult:
    """A metric dense map from images and intrinsics alone: pycolmap SfM, scale from the network, the `Mapper`.

    Args:
        images: Image folder (its ``*.color.*`` files if any), glob pattern or list of files, in order.
        intrinsics: K file, ``"fx,fy,cx,cy"`` or a `PinholeCamera` of the images.
        workdir: Folder for pycolmap's database and models (``sparse/0`` is the largest piece).
        mde: Front-end ``rgb -> depth`` in metres (it fixes the metric scale and is refined).
        sfm: `SfMConfig` (default: settings for indoor walks).
        stride: Use every ``stride``-th image.
        max_frames: Use at most this many images (after the stride).
        **kwargs: Passed to `map_pieces` (``config``, ``sigma_rule``, ``depth``, ``depth_kw``, ``map_kw``).

    Raises:
        EmptyInputError: SfM registered no image.
    """
    from ..errors import InvalidInputError

    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise InvalidInputError("stride", "an integer >= 1", stride)
    files = list_files(images, IMAGE_SUFFIXES, "color", "images")[:: int(stride)][:max_frames]
    first = load_rgb(files[0])
    camera = intrinsics if isinstance(intrinsics, PinholeCamera) else read_intrinsics(intrinsics, *first.shape[1::-1])
    t0 = time.perf_counter()
    models = reconstruct_sequence(files, camera, workdir, config=sfm)
    t_sfm = time.perf_counter() - t0
    if not models:
        raise EmptyInputError("images", "images that structure from motion can chain", f"no model from {len(files)}")
    pieces = [p for folder in models for p in read_given_points(folder)]
    result = map_pieces(pieces, files, camera, mde=mde, **kwargs)
    result.models = models
    result.timing = {"sfm": t_sfm, **result.timing, "wall": time.perf_counter() - t0}
    return result


def write_pieces(
    result: PiecesResult, output: str | Path, *, summary: dict[str, Any], mesh_format: str = "ply"
) -> list[Path]:
    """Writes the largest piece's map into ``output`` and each further piece's into ``output/piece<k>``.

    Each map is one set of `write_map` (its ``metrics.json`` with the piece's frames and scale); the SfM
    models, when SfM ran, are copied to ``output/sparse/<k>`` (the piece order; ``gpdepth3d map --points``
    reads them back).

    Returns:
        The paths written.
    """
    import shutil

    from .mapping_run import map_summary, write_map

    written: list[Path] = []
    mapped = [p for p in result.pieces if p.result is not None]
    for k, piece in enumerate(mapped):
        folder = Path(output) if k == 0 else Path(output) / f"piece{k}"
        record = {**map_summary(piece.result), **summary, "piece": k, "pieces": pieces_summary(result)}
        written += write_map(piece.result, folder, mesh_format=mesh_format, summary=record)
    for k, model in enumerate(result.models):
        target = Path(output) / "sparse" / str(k)
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(model, target)
        written += sorted(target.iterdir())
    return written


def pieces_summary(result: PiecesResult) -> dict[str, Any]:
    """The JSON record of the pieces: frames, registered, per piece its frames, scale and F, timings."""
    from dataclasses import asdict

    rows = []
    for piece in result.pieces:
        metrics = piece.result.metrics if piece.result is not None else None
        rows.append(
            {
                "frames": len(piece.names),
                "first": piece.names[0] if piece.names else None,
                "last": piece.names[-1] if piece.names else None,
                "frames_fused": piece.result.frames_fused if piece.result is not None else 0,
                "scale": None if piece.scale is None else asdict(piece.scale),
                "fscore": None if not metrics or not metrics.get("map") else metrics["map"]["fscore"],
                "fscore_mde_only": None if not metrics or not metrics.get("mde") else metrics["mde"]["fscore"],
                "error": piece.error,
            }
        )
    return {"frames": result.frames, "registered": result.registered, "pieces": rows, "timing_s": result.timing}


def map_unposed(
    images: FileSpec,
    intrinsics: str | Path | None,
    *,
    mde: MDEFrontEnd,
    points: str | Path | None = None,
    workdir: str | Path | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    **kwargs: Any,
) -> PiecesResult:
    """Maps a sequence without poses: from a given COLMAP model (``points``), else from pycolmap SfM on the images.

    Args:
        images: Image folder, glob pattern or list of files, in order.
        intrinsics: K file or ``"fx,fy,cx,cy"``; optional with a COLMAP model of one camera.
        mde: Front-end ``rgb -> depth`` in metres.
        points: A COLMAP model folder, or a folder of numbered models (pieces); its poses and points
            are used, its scale fixed from ``mde``.
        workdir: Folder for pycolmap's database and models (default: a temporary folder, removed).
        stride: Use every ``stride``-th image.
        max_frames: Use at most this many images (after the stride).
        **kwargs: Passed to `map_pieces` (and ``sfm`` to `map_images`).

    Raises:
        InvalidInputError: ``points`` is not a COLMAP model, or no intrinsics with a model of several cameras.
    """
    import tempfile

    from ..errors import InvalidInputError

    if points is None:
        if intrinsics is None:
            raise InvalidInputError("intrinsics", "a K file or fx,fy,cx,cy (needed to run SfM)", None)
        if workdir is not None:
            return map_images(images, intrinsics, workdir, mde=mde, stride=stride, max_frames=max_frames, **kwargs)
        with tempfile.TemporaryDirectory(prefix="gpdepth3d-sfm-") as tmp:
            result = map_images(images, intrinsics, tmp, mde=mde, stride=stride, max_frames=max_frames, **kwargs)
            result.models = []  # removed with the folder
            return result
    kwargs.pop("sfm", None)
    pieces = read_given_points(points)
    if any(p.model is None for p in pieces):
        raise InvalidInputError("points", "a COLMAP model when no poses are given (world points need --poses)", points)
    files = list_files(images, IMAGE_SUFFIXES, "color", "images")[:: int(stride)][:max_frames]
    first = load_rgb(files[0])
    if intrinsics is None:
        cameras = {c for p in pieces for c in p.model.cameras.values()}
        if len(cameras) != 1:
            raise InvalidInputError("intrinsics", "a K file or fx,fy,cx,cy (the model has several cameras)", None)
        camera = cameras.pop()
    else:
        camera = read_intrinsics(intrinsics, *first.shape[1::-1])
    t0 = time.perf_counter()
    result = map_pieces(pieces, files, camera, mde=mde, **kwargs)
    result.timing["wall"] = time.perf_counter() - t0
    return result
