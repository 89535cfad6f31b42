"""Structure from motion on an image sequence with pycolmap: poses and points up to scale, in one or more pieces.

`reconstruct_sequence` runs pycolmap's SIFT extraction, sequential matching and incremental mapping on
the images of a sequence whose intrinsics are known (COLMAP camera model PINHOLE, held fixed). The
settings of `SfMConfig` are chosen for hand-held indoor walks with little texture: more, weaker SIFT
keypoints, a smaller triangulation angle and fewer inliers to start a model or register an image than
COLMAP's defaults (which are tuned for photo collections with wide baselines); SIFT runs on the images
upsampled twice (COLMAP's default: the most points to fix the metric scale with), or, with
``SfMConfig(upsample=False)``, at their own size first and upsampled only when there they give too few
keypoints (`SfMConfig.min_keypoints`) or register too few images (`SfMConfig.min_registered`). Where the images do
not chain (a blank wall, a fast turn) pycolmap starts a new model; every model is one piece, with its
own frame and scale. See https://colmap.github.io/pycolmap/index.html.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...camera import PinholeCamera
from ...checks import Bool, Int, Real, check_fields, positive
from ...errors import InvalidInputError


@dataclass(frozen=True)
class SfMConfig:
    """Settings of `reconstruct_sequence` (pycolmap's extraction, sequential matching and incremental mapping).

    Attributes:
        max_features: SIFT keypoints per image at most.
        peak_threshold: SIFT's contrast threshold (COLMAP's default 0.0067; lower finds keypoints on
            weak texture).
        upsample: SIFT on the images upsampled twice (SIFT's first octave -1, COLMAP's default): several
            times the points at their own size, which fix the metric scale more closely (`sfm_scale`), at
            several times the time of extraction and matching. False: at their own size first
            (``min_keypoints``, ``min_registered`` decide whether to upsample after all).
        min_keypoints: Without ``upsample``: when the median image has fewer keypoints than this at its
            own size, SIFT runs again on the images upsampled twice.
        min_registered: Without ``upsample``: share of the images the pieces must register between them
            with keypoints at the images' own size; below it, SfM runs again on the upsampled images and
            the run that registers more images is kept.
        overlap: Sequential matching: image ``i`` is matched with images ``i + 1, i + 2, i + 4, ...,
            i + 2 ** (overlap - 1)`` (pycolmap's quadratic overlap: near neighbours for the chain, a few
            far ones for a walk that comes back).
        init_min_num_inliers: Inlier matches a pair needs to start a model (COLMAP: 100).
        init_min_tri_angle: Median triangulation angle a starting pair needs, degrees (COLMAP: 16; the
            frames of a walk are close together).
        abs_pose_min_num_inliers: 2-D / 3-D inliers an image needs to be registered (COLMAP: 30).
        abs_pose_min_inlier_ratio: Their share of the image's matches (COLMAP: 0.25).
        max_reg_trials: Times an image that failed to register is tried again as the model grows
            (COLMAP: 3; after a turn the next images see few of the model's points until more are
            triangulated).
        min_tri_angle: Smallest angle between two rays of a point kept, degrees (COLMAP: 1.5).
        two_view_tracks: Triangulate points seen in two images only (COLMAP ignores them; in a walk
            they are what registers the next image).
        min_model_size: Registered images a piece needs to be kept.
        threads: CPU threads pycolmap may use.
        seed: pycolmap's random seed. Runs are repeatable with the same seed and one thread; with more,
            pycolmap's extraction, matching and mapping may differ from run to run.
    """

    max_features: int = 4096
    peak_threshold: float = 0.002
    upsample: bool = True
    min_keypoints: int = 500
    min_registered: float = 0.9
    overlap: int = 8
    init_min_num_inliers: int = 30
    init_min_tri_angle: float = 4.0
    abs_pose_min_num_inliers: int = 6
    abs_pose_min_inlier_ratio: float = 0.08
    max_reg_trials: int = 10
    min_tri_angle: float = 0.5
    two_view_tracks: bool = True
    min_model_size: int = 3
    threads: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        rules = {n: Int(low) for n, low in (("max_features", 64), ("min_keypoints", 0), ("overlap", 1))}
        rules.update(init_min_num_inliers=Int(8), abs_pose_min_num_inliers=Int(6), max_reg_trials=Int(1))
        rules.update(min_model_size=Int(2), threads=Int(1), seed=Int(0), upsample=Bool())
        rules.update({n: positive() for n in ("peak_threshold", "init_min_tri_angle", "min_tri_angle")})
        rules.update(min_registered=Real(0.0, 1.0, unit="a share"))
        rules.update(abs_pose_min_inlier_ratio=Real(0.0, 1.0, high_open=True, unit="a share"))
        check_fields(self, rules)


def _extract(images: list[Path], camera: PinholeCamera, database: Path, config: SfMConfig, first_octave: int) -> None:
    """SIFT keypoints of every image into a new ``database`` (one PINHOLE camera, fixed)."""
    import pycolmap

    database.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"  # COLMAP puts the first pixel's centre at 0.5
    reader.camera_params = f"{camera.fx},{camera.fy},{camera.cx + 0.5},{camera.cy + 0.5}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = config.threads
    extraction.sift.max_num_features = config.max_features
    extraction.sift.peak_threshold = config.peak_threshold
    extraction.sift.first_octave = first_octave
    pycolmap.extract_features(
        database,
        images[0].parent,
        image_names=[p.name for p in images],
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


def median_keypoints(database: Path) -> float:
    """The median number of keypoints per image in a COLMAP database (0 when it has none)."""
    import sqlite3

    with sqlite3.connect(database) as db:
        counts = [row[0] for row in db.execute("SELECT rows FROM keypoints")]
    return float(np.median(counts)) if counts else 0.0


def _extract_and_match(
    images: list[Path], camera: PinholeCamera, database: Path, config: SfMConfig, *, upsample: bool | None = None
) -> bool:
    """SIFT keypoints of every image, then sequential matches; returns whether the images were upsampled.

    ``upsample`` None: at the images' own size, upsampled twice when the median image has fewer than
    ``config.min_keypoints`` there; True: upsampled at once.
    """
    import pycolmap

    if not upsample:
        _extract(images, camera, database, config, first_octave=0)
        upsample = median_keypoints(database) < config.min_keypoints
    if upsample:
        _extract(images, camera, database, config, first_octave=-1)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = config.overlap
    pairing.quadratic_overlap = True
    pairing.num_threads = config.threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.threads
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    return upsample


def _mapping_options(config: SfMConfig):
    """pycolmap's incremental mapping options: intrinsics fixed, thresholds of `SfMConfig`."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.threads
    options.random_seed = config.seed
    options.min_model_size = config.min_model_size
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.mapper.init_min_num_inliers = config.init_min_num_inliers
    options.mapper.init_min_tri_angle = config.init_min_tri_angle
    options.mapper.abs_pose_min_num_inliers = config.abs_pose_min_num_inliers
    options.mapper.abs_pose_min_inlier_ratio = config.abs_pose_min_inlier_ratio
    options.mapper.max_reg_trials = config.max_reg_trials
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    options.mapper.filter_min_tri_angle = config.min_tri_angle
    options.triangulation.min_angle = config.min_tri_angle
    options.triangulation.ignore_two_view_tracks = not config.two_view_tracks
    return options


def registered_images(models: dict) -> int:
    """Distinct images registered by pycolmap's models (an image may be registered in two of them)."""
    return len({model.images[i].name for model in models.values() for i in model.reg_image_ids()})


def reconstruct_sequence(
    images: Sequence[str | Path], camera: PinholeCamera, workdir: str | Path, *, config: SfMConfig | None = None
) -> list[Path]:
    """Runs pycolmap's SfM on an image sequence with known intrinsics; returns the model folders, largest first.

    Args:
        images: Image files of ``camera``'s size, in temporal order, in one folder.
        camera: Pinhole intrinsics shared by the images (held fixed).
        workdir: Folder for ``database.db`` and the models (``sparse/0``, ``sparse/1``, ...); an
            earlier run there is replaced.
        config: `SfMConfig` (default: settings for indoor walks). When the keypoints at the images' own
            size register fewer than ``config.min_registered`` of the images, SfM runs again on the
            upsampled images and the run registering more images is kept.

    Returns:
        One folder per piece (`gpdepth3d.mapping.trajectories.read_colmap_model` reads it), the piece
        with the most registered images first; empty when no pair of images started a model.

    Raises:
        InvalidInputError: fewer than two images, or images from several folders.
    """
    import shutil

    import pycolmap

    config = config or SfMConfig()
    images = [Path(p) for p in images]
    if len(images) < 2:
        raise InvalidInputError("images", "two or more image files", len(images))
    if len({p.parent.resolve() for p in images}) != 1:
        raise InvalidInputError("images", "files of one folder", sorted({str(p.parent) for p in images}))
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    database, sparse, raw = workdir / "database.db", workdir / "sparse", workdir / "incremental"
    database.unlink(missing_ok=True)
    for folder in (sparse, raw):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
    upsampled = _extract_and_match(images, camera, database, config, upsample=True if config.upsample else None)
    models = pycolmap.incremental_mapping(database, images[0].parent, raw, options=_mapping_options(config))
    if not upsampled and registered_images(models) < config.min_registered * len(images):
        shutil.rmtree(raw, ignore_errors=True)
        raw.mkdir()
        _extract_and_match(images, camera, database, config, upsample=True)
        again = pycolmap.incremental_mapping(database, images[0].parent, raw, options=_mapping_options(config))
        models = again if registered_images(again) >= registered_images(models) else models
    shutil.rmtree(raw, ignore_errors=True)
    order = sorted(models, key=lambda k: (-models[k].num_reg_images(), k))
    folders = []
    for rank, key in enumerate(order):
        folder = sparse / str(rank)
        folder.mkdir()
        models[key].write(folder)
        folders.append(folder)
    return folders
