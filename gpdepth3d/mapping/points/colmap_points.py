"""Map points from COLMAP: SIFT features, matching and triangulation with the poses held fixed (pycolmap).

`triangulate_with_colmap` writes the posed frames' images to a work folder, runs pycolmap's
feature extraction, sequential matching and point triangulation on a model whose cameras sit at
the given ``T_world_camera`` poses (COLMAP's ``point_triangulator``: poses and intrinsics are not
refined), and writes the sparse model there. Read it with
`gpdepth3d.io.poses.read_colmap_model` and give its points to `Mapper.add_frame` as
SLAM map points. See https://colmap.github.io/pycolmap/index.html.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ...camera import PinholeCamera, check_pose
from ...errors import InvalidInputError
from ...io.poses import invert_pose


def _write_images(rgbs: Sequence[np.ndarray], camera: PinholeCamera, folder: Path) -> list[str]:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, rgb in enumerate(rgbs):
        camera.check_image(np.asarray(rgb), f"rgbs[{i}]")
        names.append(f"{i:05d}.png")
        cv2.imwrite(str(folder / names[-1]), cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR))
    return names


def _posed_model(database: Path, names: list[str], poses: list[np.ndarray]):
    """A pycolmap Reconstruction with the database's camera and images at the given poses (no points)."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        cameras, images = db.read_all_cameras(), db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for cam in cameras:
        rec.add_camera_with_trivial_rig(cam)
    index = {name: i for i, name in enumerate(names)}
    for image in images:
        T_cw = invert_pose(poses[index[image.name]])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(T_cw[:3, :3]), T_cw[:3, 3])
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id), pose
        )
    return rec


def triangulate_with_colmap(
    rgbs: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    workdir: str | Path,
    *,
    max_features: int = 4000,
    overlap: int = 8,
    threads: int = 2,
) -> Path:
    """Runs pycolmap's features, matching and triangulation on posed frames; returns the model folder.

    Args:
        rgbs: (H, W, 3) uint8 RGB images of ``camera``'s size, in temporal order.
        poses: Their 4x4 ``T_world_camera`` (held fixed).
        camera: Pinhole intrinsics shared by the images (COLMAP model PINHOLE, not refined).
        workdir: Folder for the images, ``database.db`` and the model (``sparse/``).
        max_features: SIFT keypoints per image.
        overlap: Each image is matched with this many following ones (sequential matching).
        threads: CPU threads pycolmap may use.

    Returns:
        The model folder (``workdir/sparse``), for `gpdepth3d.io.poses.read_colmap_model`.
    """
    import pycolmap

    if len(rgbs) < 2 or len(poses) != len(rgbs):
        raise InvalidInputError("rgbs, poses", "two or more images with one pose each", (len(rgbs), len(poses)))
    poses = [check_pose(T, f"poses[{i}]") for i, T in enumerate(poses)]
    workdir = Path(workdir)
    image_dir, database, model = workdir / "images", workdir / "database.db", workdir / "sparse"
    names = _write_images(rgbs, camera, image_dir)
    database.unlink(missing_ok=True)
    with _pycolmap_quiet(pycolmap):
        return _triangulate(pycolmap, database, image_dir, model, names, poses, camera, threads, max_features, overlap)


def _pycolmap_quiet(pycolmap):
    """COLMAP's INFO log (hundreds of lines a run) held back; its warnings and errors still print."""
    import contextlib

    @contextlib.contextmanager
    def quiet():
        logging = getattr(pycolmap, "logging", None)
        before = getattr(logging, "minloglevel", None)
        if before is not None:
            logging.minloglevel = max(int(before), 1)  # 0 INFO, 1 WARNING
        try:
            yield
        finally:
            if before is not None:
                logging.minloglevel = before

    return quiet()


def _triangulate(pycolmap, database, image_dir, model, names, poses, camera, threads, max_features, overlap) -> Path:
    """Features, sequential matches and points triangulated with the poses held fixed (`triangulate_with_colmap`)."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"  # COLMAP puts the first pixel's centre at 0.5
    reader.camera_params = f"{camera.fx},{camera.fy},{camera.cx + 0.5},{camera.cy + 0.5}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = int(threads)
    extraction.sift.max_num_features = int(max_features)
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = int(overlap)
    pairing.num_threads = int(threads)
    pycolmap.match_sequential(database, pairing_options=pairing, device=pycolmap.Device.cpu)
    rec = _posed_model(database, names, poses)
    model.mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = int(threads)
    rec = pycolmap.triangulate_points(rec, database, image_dir, model, options=options)
    rec.write(model)
    return model
