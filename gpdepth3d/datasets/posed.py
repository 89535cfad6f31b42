"""A user's own posed image sequence: an image folder, one pose per image, intrinsics, optional depth.

The poses come already matched to the images (``T_world_camera``, one per image in order): the
pose formats and their association to images live one layer up, in
`gpdepth3d.io.poses` (`read_trajectory`, `associate_poses`). Intrinsics come from a
K file or four numbers (`read_intrinsics`). Depth, when given, is sensor depth for evaluation:
16-bit PNGs with their scale (metres per unit) and invalid value, or .npy / .npz in metres; it
may come from a second camera sharing the pose (``depth_camera``), and is then registered to
the colour camera as `gpdepth3d.datasets.sevenscenes.SevenScenes` does.

Everything that can be checked without reading the images is checked when the sequence is
opened (missing files, counts that do not match); a frame whose file turns out unreadable raises
`DataFormatError` naming the file when that frame is read, so a caller can skip it and go on.
"""

from __future__ import annotations

import glob as _glob
from pathlib import Path
from typing import Sequence

import numpy as np

from ..camera import PinholeCamera, check_pose
from ..errors import CalibrationError, DataFormatError, InvalidInputError, ShapeError, describe
from ..io import check_png_scale, load_depth, load_rgb, read_matrix
from ..measurements import project_points
from .base import DatasetReader, Frame

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""File endings of colour images in a folder."""
DEPTH_SUFFIXES = (".png", ".npy", ".npz")
"""File endings of depth maps in a folder (16-bit PNG with a scale, or arrays in metres)."""

FileSpec = str | Path | Sequence[str | Path]
"""A folder, a glob pattern (``'data/*.color.jpg'``) or a list of files."""


def list_files(spec: FileSpec, suffixes: tuple[str, ...], tag: str, argument: str) -> list[Path]:
    """The files of a folder, a glob pattern or a list, sorted by name.

    In a folder, files named ``*.<tag>.*`` (7-Scenes: ``frame-000000.color.jpg``, ``.depth.png``)
    are taken when there are any, else every file ending in one of ``suffixes``.

    Raises:
        DataFormatError: a missing folder or file, or nothing found.
    """
    if isinstance(spec, (list, tuple)):
        files = [Path(p) for p in spec]
        for f in files:
            if not f.is_file():
                raise DataFormatError(f, f"{argument}: file not found")
    else:
        path = Path(spec)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
            tagged = [p for p in found if f".{tag}." in p.name]
            files = tagged or found
        elif any(c in str(spec) for c in "*?["):
            files = sorted(Path(p) for p in _glob.glob(str(spec)) if Path(p).is_file())
        else:
            raise DataFormatError(path, f"{argument}: folder not found")
    if not files:
        raise DataFormatError(spec, f"{argument}: no files ({', '.join(suffixes)})")
    return files


def read_intrinsics(spec: str | Path | Sequence[float] | np.ndarray, width: int, height: int) -> PinholeCamera:
    """A `PinholeCamera` of a ``width`` x ``height`` image from a K file or ``fx,fy,cx,cy``.

    Args:
        spec: A text file holding a 3x3 K (9 numbers) or ``fx fy cx cy``; the string
            ``"fx,fy,cx,cy"`` (pixels); four numbers; or a 3x3 array.
        width: Image width, pixels.
        height: Image height, pixels.

    Raises:
        DataFormatError: a missing or malformed K file.
        CalibrationError: values that are no pinhole intrinsics (zero or negative focal length...).
    """
    values: np.ndarray
    if isinstance(spec, (str, Path)) and Path(spec).is_file():
        path = Path(spec)
        try:
            values = np.loadtxt(path, ndmin=1, delimiter=None).ravel()
        except ValueError as exc:
            raise DataFormatError(path, f"intrinsics: not numbers ({exc})") from None
        if values.size == 9:
            values = read_matrix(path, (3, 3), "intrinsics")
        elif values.size != 4:
            raise DataFormatError(
                path, f"intrinsics: expected a 3x3 K (9 numbers) or fx fy cx cy (4), got {values.size}"
            )
    elif isinstance(spec, (str, Path)):
        text = str(spec)
        try:
            values = np.array([float(x) for x in text.replace(",", " ").split()], dtype=np.float64)
        except ValueError:
            raise DataFormatError(text, "intrinsics: neither a K file nor 'fx,fy,cx,cy'") from None
        if values.size != 4:
            raise CalibrationError("intrinsics", "a K file or four numbers fx,fy,cx,cy", text)
    else:
        values = np.asarray(spec, dtype=np.float64)
    if values.shape == (4,):
        fx, fy, cx, cy = values
        values = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if values.shape != (3, 3) or not np.all(np.isfinite(values)):
        raise CalibrationError("intrinsics", "a finite 3x3 K or fx,fy,cx,cy", describe(values))
    return PinholeCamera.from_K(values, int(width), int(height))


def _time_of(path: Path) -> float | None:
    """The time a file is named by (``1305031102.175304.png``: a number with a fraction), or None."""
    stem = path.name.rsplit(".", 1)[0]
    if "." not in stem:
        return None
    try:
        t = float(stem)
    except ValueError:
        return None
    return t if np.isfinite(t) else None


def match_depth(images: list[Path], depth: list[Path], *, max_time_difference: float = 0.02) -> list[Path]:
    """Each image's depth file, matched by the first rule that gives every image one.

    1. the same name without its ending (``0001.png`` and ``0001.npy``);
    2. the same name up to the first dot (``frame-000000.color.jpg`` and ``frame-000000.depth.png``);
    3. both named by times (TUM RGB-D: ``1305031102.175304.png``): the nearest within ``max_time_difference`` s;
    4. as many depth files as images: by order.

    Raises:
        ShapeError: if no rule applies (naming the counts and the first image without depth).
    """
    for key in (lambda p: p.name.rsplit(".", 1)[0], lambda p: p.name.split(".", 1)[0]):
        table = {key(p): p for p in depth}
        if len(table) == len(depth) and all(key(p) in table for p in images):
            return [table[key(p)] for p in images]
    image_times = [_time_of(p) for p in images]
    depth_times = [_time_of(p) for p in depth]
    if None not in image_times and None not in depth_times:
        dt = np.array(depth_times)
        nearest = [int(np.argmin(np.abs(dt - t))) for t in image_times]
        if all(abs(dt[j] - t) <= max_time_difference for j, t in zip(nearest, image_times)):
            return [depth[j] for j in nearest]
    if len(depth) == len(images):
        return list(depth)
    keys = {p.name.split(".", 1)[0] for p in depth}
    lacking = next((p.name for p in images if p.name.split(".", 1)[0] not in keys), images[0].name)
    raise ShapeError(
        "depth",
        f"one depth file per image, matched by name, time or order ({len(images)} images; {lacking} has none)",
        f"{len(depth)} depth files",
    )


class PosedSequence(DatasetReader):
    """Frames of a posed image sequence (rgb, camera, pose, optional sensor depth), read lazily.

    Args:
        images: Colour images: a folder (its ``*.color.*`` files if any, else every image), a
            glob pattern or a list of files; sorted by name, that is the sequence order.
        poses: (N, 4, 4) ``T_world_camera`` of the N images, in their order
            (`gpdepth3d.io.poses.associate_poses` matches a trajectory to them).
        intrinsics: K file, ``"fx,fy,cx,cy"``, four numbers or a 3x3 K of the colour camera
            (`read_intrinsics`); or a `PinholeCamera`.
        depth: Sensor depth for evaluation, like ``images`` (a folder's ``*.depth.*`` files if
            any); matched to images by name, by time or by order (`match_depth`).
        depth_scale: Metres per unit of 16-bit PNG depth (0.001: millimetres; TUM RGB-D: 0.0002).
        depth_invalid: A PNG value that marks invalid pixels besides 0 (7-Scenes: 65535).
        depth_intrinsics: Intrinsics of the depth camera when it is not the colour camera (it
            shares the pose); its depth is registered to the colour camera (closest depth per pixel).

    Raises:
        DataFormatError: missing folders or files, a malformed K file.
        ShapeError: a number of poses or depth files that does not match the images.
        CalibrationError: a pose that is not a rigid transform (naming its image).
    """

    def __init__(
        self,
        images: FileSpec,
        poses: np.ndarray,
        intrinsics: str | Path | Sequence[float] | np.ndarray | PinholeCamera,
        *,
        depth: FileSpec | None = None,
        depth_scale: float = 1e-3,
        depth_invalid: int | None = None,
        depth_intrinsics: str | Path | Sequence[float] | np.ndarray | PinholeCamera | None = None,
    ):
        self.image_files = list_files(images, IMAGE_SUFFIXES, "color", "images")
        self.root = self.image_files[0].parent
        self.names = [p.name.split(".", 1)[0] for p in self.image_files]
        if len(set(self.names)) != len(self.names):
            self.names = [p.name for p in self.image_files]
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ShapeError("poses", "an (N, 4, 4) array of T_world_camera", describe(poses))
        if len(poses) != len(self.image_files):
            raise ShapeError("poses", f"one pose per image ({len(self.image_files)} images)", f"{len(poses)} poses")
        checked = []
        for name, T in zip(self.image_files, poses):
            try:
                checked.append(check_pose(T, f"pose of {name.name}"))
            except CalibrationError as exc:
                raise CalibrationError(f"pose of {name}", exc.expected, exc.got) from None
        self.poses = np.stack(checked)
        self.depth_scale = check_png_scale(depth_scale, "depth_scale")
        if depth_invalid is not None and (
            isinstance(depth_invalid, bool) or int(depth_invalid) != depth_invalid or not 0 < depth_invalid < 65536
        ):
            raise InvalidInputError("depth_invalid", "a 16-bit PNG value in 1..65535 (or None)", depth_invalid)
        self.depth_invalid = None if depth_invalid is None else int(depth_invalid)
        self.depth_files = (
            None
            if depth is None
            else match_depth(self.image_files, list_files(depth, DEPTH_SUFFIXES, "depth", "depth"))
        )
        first = load_rgb(self.image_files[0])
        h, w = first.shape[:2]
        self.camera = intrinsics if isinstance(intrinsics, PinholeCamera) else read_intrinsics(intrinsics, w, h)
        if self.camera.shape != (h, w):
            raise ShapeError(
                "intrinsics", f"a camera of the images' size {w}x{h}", f"{self.camera.width}x{self.camera.height}"
            )
        if depth_intrinsics is None or isinstance(depth_intrinsics, PinholeCamera):
            self.depth_camera = depth_intrinsics
            if depth_intrinsics is not None and self.depth_files is None:
                raise InvalidInputError("depth_intrinsics", "depth files to go with them", "no depth")
        elif self.depth_files is None:
            raise InvalidInputError("depth_intrinsics", "depth files to go with them", "no depth")
        else:
            dh, dw = load_depth(self.depth_files[0], png_scale=self.depth_scale).shape
            self.depth_camera = read_intrinsics(depth_intrinsics, dw, dh)

    def load(self, name: str) -> Frame:
        """The frame ``name`` (an image name up to its first dot; `names`)."""
        if name not in self.names:
            raise InvalidInputError(
                "name", f"the name of a frame of the sequence ({len(self.names)} frames)", describe(name)
            )
        return self.frame(self.names.index(name))

    def __getitem__(self, index: int) -> Frame:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            raise InvalidInputError("index", "an integer frame index", describe(index))
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame index {index} out of range for {len(self)} frames")
        return self.frame(int(index) % len(self))

    def frame(self, i: int) -> Frame:
        """Frame ``i``: rgb, camera, pose and depth (registered to the colour camera), read now.

        Raises:
            DataFormatError: an unreadable image or depth file, or one of another size (naming the file).
        """
        path = self.image_files[i]
        rgb = load_rgb(path)
        if rgb.shape[:2] != self.camera.shape:
            raise DataFormatError(
                path,
                f"image of {rgb.shape[1]}x{rgb.shape[0]}, the sequence's are {self.camera.width}x{self.camera.height}",
            )
        depth = None
        if self.depth_files is not None:
            dpath = self.depth_files[i]
            depth = load_depth(dpath, png_scale=self.depth_scale, invalid_value=self.depth_invalid)
            expected = (self.depth_camera or self.camera).shape
            if depth.shape != expected:
                raise DataFormatError(
                    dpath, f"depth of {depth.shape[1]}x{depth.shape[0]}, expected {expected[1]}x{expected[0]}"
                )
            if depth.max(initial=0.0) <= 0:
                raise DataFormatError(dpath, "no valid depth pixel (check --depth-scale and --depth-invalid)")
            if self.depth_camera is not None:
                points, _ = self.depth_camera.backproject(depth)
                depth = project_points(points, self.camera).to_depth_map()
        return Frame(name=self.names[i], rgb=rgb, camera=self.camera, depth=depth, pose=self.poses[i].copy())

    def __iter__(self):
        for i in range(len(self)):
            yield self.frame(i)
