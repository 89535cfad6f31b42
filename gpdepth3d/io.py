"""Reading and writing depth maps, sparse points and images; every write is atomic.

File conventions:

* ``.npy``: a (H, W) float array in metres.
* ``.npz``: the array under ``key`` (default: the only array, or ``depth``/``mean``).
* ``.png``: 16-bit depth; metres = value * ``png_scale``. KITTI stores value = metres * 256
  (``png_scale = 1/256``), 7-Scenes/TUM-style Kinect PNGs store millimetres (``1/1000``). Value 0
  (and 65535 for Kinect, see ``invalid_value``) means no depth.
* Sparse point lists: ``.npz`` with ``u``, ``v``, ``depth`` (and optional ``sigma``), or a text
  file with one ``u v depth [sigma]`` per line (pixels, metres).

Writes go to a temporary file in the destination folder and are renamed into place, so an
interrupted or failed write never leaves a partial file under the final name. Several files that
belong together (a posterior's ``.npz`` and PNGs) are written as one set (`atomic_write_set`:
hidden ``.<name>.set-*`` folder, ``.<name>.current`` pointer, ``.<name>.lock``), so a kill, a full
disk or a concurrent writer leaves the old set or the new one; `write_together` defers the renames
of a whole block of writes (the CLI's ``eval``). A write that fails raises `OutputError` (an
`OSError`) naming the path and the cause (disk full, permission denied, a directory in the way).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import re
import shutil
import tempfile
import warnings
import zipfile
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np

from .errors import (
    DataFormatError,
    GPDepthError,
    InvalidDepthError,
    InvalidInputError,
    OutputError,
    ShapeError,
    describe,
)
from .camera import check_pose
from .measurements import SparseDepth

KITTI_PNG_SCALE = 1.0 / 256.0
_UMASK = os.umask(0o022)  # read the process umask once (at import, before any threads) and restore it
os.umask(_UMASK)


_WRITE_PROBLEMS = {
    errno.ENOSPC: "no space left on the device (disk full)",
    errno.EDQUOT: "disk quota exceeded",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "read-only file system",
    errno.EISDIR: "a directory is in the way",
    errno.ENOTDIR: "a file is in the way of a folder of the path",
    errno.EEXIST: "a file is in the way of a folder of the path",
    errno.ENAMETOOLONG: "file name too long",
}

# Deferred renames of `write_together` (per thread / task).
_PENDING: contextvars.ContextVar[list | None] = contextvars.ContextVar("gpdepth3d_pending_writes", default=None)


def write_problem(exc: OSError) -> str:
    """A short description of why a write failed (disk full, permission denied, ...)."""
    return _WRITE_PROBLEMS.get(exc.errno or -1, exc.strerror or str(exc) or type(exc).__name__)


def _as_output_error(path: Path, exc: BaseException) -> GPDepthError:
    if isinstance(exc, GPDepthError):
        return exc
    if isinstance(exc, OSError):
        return OutputError(path, write_problem(exc))
    return OutputError(path, f"{type(exc).__name__}: {exc}")


def check_output_path(path: str | Path, argument: str = "path") -> Path:
    """Validates an output path before anything is computed or written; returns it as a `Path`.

    Raises:
        OutputError: if the name is empty, the path is an existing directory, or a component
            of its folder is an existing file.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise OutputError(path, f"{argument} must be a file path, got {type(path).__name__}")
    p = Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise OutputError(repr(str(path)), f"{argument} needs a file name")
    if p.is_dir():
        raise OutputError(p, "a directory is in the way")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(p, f"{parent} is a file, not a folder")
            break
    return p


def check_output_folder(folder: str | Path, argument: str = "output_dir") -> Path:
    """Checks that ``folder`` is (or can become) a writable folder, before any work; creates nothing.

    Raises:
        OutputError: empty name, a file in the way, or a folder that is not writable.
    """
    if not isinstance(folder, (str, os.PathLike)) or str(folder) == "":
        raise OutputError(repr(folder), f"{argument} needs a folder name")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(folder, f"{argument}: a file is in the way (expected a folder)")
    for parent in folder.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(folder, f"{argument}: {parent} is a file, not a folder")
            break
    existing = next((p for p in [folder.absolute(), *folder.absolute().parents] if p.exists()), None)
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(folder, f"{argument}: the folder {existing} is not writable")
    return folder


def _make_parent(path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(path, f"cannot create the folder {path.parent}: {write_problem(exc)}") from None


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yields a temporary path beside ``path``; renames it onto ``path`` only if the block succeeds.

    Inside `write_together` the rename waits until the whole block of writes succeeded.

    Raises:
        OutputError: when the folder cannot be created or written (read-only, full disk), when
            ``path`` is a directory, or when the block raises an `OSError` (the temporary file
            is removed; nothing appears under ``path``).
    """
    path = check_output_path(path)
    _make_parent(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    except OSError as exc:
        raise OutputError(path, write_problem(exc)) from None
    os.close(fd)
    tmp_path = Path(tmp)
    pending = _PENDING.get()
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
            if pending is not None:
                pending.append((tmp_path, path))
                tmp_path = None  # type: ignore[assignment]  # renamed (or removed) by write_together
            else:
                os.replace(tmp_path, path)
        except OSError as exc:
            raise _as_output_error(path, exc) from None
    finally:
        if tmp_path is not None and tmp_path.exists():
            tmp_path.unlink()


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Calls ``write(tmp_path)`` and moves the result onto ``path`` atomically."""
    with atomic_path(path) as tmp:
        write(tmp)
    return Path(path)


def to_jsonable(x):
    """A JSON-ready copy of ``x``: numpy scalars and arrays to Python numbers and lists, tuples to
    lists, paths to strings, NaN and +-inf to None (JSON has no such numbers); dict keys kept."""
    if isinstance(x, dict):
        return {k: to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, np.generic):
        return to_jsonable(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(path: str | Path, data, *, indent: int = 2) -> Path:
    """Writes ``data`` as indented JSON (`to_jsonable` first: NaN as null), atomically; returns the path.

    Raises:
        TypeError: ``data`` holds something JSON cannot represent (e.g. an object).
        OutputError: the file cannot be written.
    """
    import json

    text = json.dumps(to_jsonable(data), indent=indent, allow_nan=False)
    return atomic_write(path, lambda tmp: tmp.write_text(text + "\n"))


@contextlib.contextmanager
def write_together() -> Iterator[None]:
    """Defers the renames of every `atomic_path` write inside the block until the block succeeds.

    All files are first written under temporary names; only when the whole block succeeded are
    they renamed into place (a failure such as a full disk leaves none of the new files, and the
    old files untouched). Used by the CLI so a command's outputs do not come half-written.
    """
    pending: list[tuple[Path, Path]] = []
    token = _PENDING.set(pending)
    ok = False
    try:
        yield
        ok = True
    finally:
        _PENDING.reset(token)
        if ok:
            for i, (tmp, final) in enumerate(pending):
                try:
                    os.replace(tmp, final)
                except OSError as exc:
                    for t, _ in pending[i:]:
                        with contextlib.suppress(OSError):
                            t.unlink()
                    raise OutputError(final, write_problem(exc)) from None
        else:
            for tmp, _ in pending:
                with contextlib.suppress(OSError):
                    tmp.unlink()


# ------------------------------------------------------------------------------ output sets
def _temp_pattern(name: str) -> re.Pattern:
    """Temporary files `atomic_path` makes for ``name``: ``.<stem>.<8 random>.tmp<suffix>``."""
    p = Path(name)
    return re.compile(rf"^\.{re.escape(p.stem)}\.[A-Za-z0-9_]{{8}}\.tmp{re.escape(p.suffix)}$")


@contextlib.contextmanager
def _locked(lock_path: Path) -> Iterator[None]:
    """An exclusive advisory lock (fcntl.flock) on ``lock_path``, waited for; no-op without fcntl."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    try:
        fh = open(lock_path, "a")
    except OSError as exc:
        raise OutputError(lock_path, write_problem(exc)) from None
    with fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _replace_symlink(link: Path, target: str) -> None:
    """Points ``link`` at ``target`` atomically (a new link under a temporary name, renamed)."""
    tmp = link.with_name(f".{link.name}.{os.urandom(4).hex()}.link")
    os.symlink(target, tmp)
    try:
        os.replace(tmp, link)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def output_set_files(base: str | Path) -> dict[str, Path]:
    """The hidden files of the output set ``base`` (see `atomic_write_set`): lock, current, set folders."""
    base = Path(base)
    return {"lock": base.parent / f".{base.name}.lock", "current": base.parent / f".{base.name}.current"}


def clean_output_set(base: str | Path, names: Sequence[str] = ()) -> int:
    """Removes what killed writers of the set ``base`` left: set folders not in use, temporary files.

    Call with the set's lock held (`atomic_write_set` does). Returns how many entries were removed.
    """
    base = Path(base)
    folder = base.parent
    if not folder.is_dir():
        return 0
    current = output_set_files(base)["current"]
    live = os.readlink(current) if current.is_symlink() else None
    patterns = [_temp_pattern(n) for n in names]
    set_folder = re.compile(rf"^\.{re.escape(base.name)}\.set-[A-Za-z0-9_]{{8}}$")
    links = [re.compile(rf"^\.{re.escape(n)}\.[0-9a-f]{{8}}\.link$") for n in (current.name, *names)]
    removed = 0
    for entry in folder.iterdir():
        n = entry.name
        if set_folder.match(n) and n != live and entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
            removed += 1
        elif any(p.match(n) for p in (*patterns, *links)):
            with contextlib.suppress(OSError):
                entry.unlink()
                removed += 1
    return removed


def atomic_write_set(
    base: str | Path,
    writers: Mapping[str, Callable[[Path], None]],
    *,
    members: Sequence[str] = (),
) -> list[Path]:
    """Writes several files beside each other as one set: readers see the old set or the new one.

    The files ``base.parent / name`` for each ``name`` of ``writers`` are written as follows,
    holding the lock ``.<base name>.lock`` (so concurrent writers of one set take turns and the
    last one wins as a whole):

    1. every file is written into a new hidden folder ``.<base name>.set-<random>/``; a
       failure (full disk, read-only folder, a writer's error) removes that folder and leaves
       the old files untouched;
    2. each public name is a relative symlink ``name -> .<base name>.current/name`` and
       ``.<base name>.current`` a symlink to the set folder; the new set goes live by one atomic
       rename of ``.<base name>.current``, so a kill at any point leaves the old set or the new
       set, never a mix. ``members`` named but not written this time (say the PNGs of an
       earlier call) are removed from the set with the same rename.

    Folders of earlier killed writers and temporary files of the names are deleted first. A
    single file with no earlier set is written as a plain file (`atomic_write`). Plain files of
    the set left by older versions are moved into a set first, without a moment of mixing. On a
    file system without symbolic links the files are all written under temporary names and then
    renamed (a failure still leaves the old files; only a kill between the renames can mix).

    Args:
        base: Path naming the set (its folder and its name), e.g. ``out/frame0``.
        writers: File name (in ``base``'s folder) -> ``write(path)`` writing that file.
        members: Every name the set may hold (default: the names of ``writers``).

    Returns:
        The written paths, in the order of ``writers``.

    Raises:
        OutputError: if a file cannot be written; nothing of the new set is then visible.
    """
    base = check_output_path(base, "base")
    folder = base.parent
    names = list(writers)
    all_names = list(dict.fromkeys([*names, *members]))
    for n in all_names:
        if Path(n).name != n or n in ("", ".", ".."):
            raise OutputError(folder / str(n), "a plain file name inside the set's folder expected")
        check_output_path(folder / n)
    _make_parent(base)
    hidden = output_set_files(base)
    with _locked(hidden["lock"]):
        try:
            clean_output_set(base, all_names)
            present = [n for n in all_names if os.path.lexists(folder / n)]
            if len(names) == 1 and not hidden["current"].is_symlink() and present in ([], names):
                atomic_write(folder / names[0], writers[names[0]])
                return [folder / names[0]]
            if not _symlinks_work(folder):
                return _write_then_rename(folder, writers, all_names)
            return _swap_in_set(base, folder, writers, all_names, hidden["current"])
        except OSError as exc:
            raise _as_output_error(base, exc) from None


def _swap_in_set(
    base: Path, folder: Path, writers: Mapping[str, Callable[[Path], None]], all_names: list[str], current: Path
) -> list[Path]:
    link_target = {n: f"{current.name}/{n}" for n in all_names}
    # Plain files of an older writer: hard-link them into a set that goes live first, then turn each
    # name into a link resolving to the same content (no moment shows a mix).
    plain = [n for n in all_names if (folder / n).is_file() and not (folder / n).is_symlink()]
    if plain:
        old = Path(tempfile.mkdtemp(prefix=f".{base.name}.set-", dir=folder))
        if current.is_symlink() and (folder / os.readlink(current)).is_dir():
            for n in all_names:
                src = folder / os.readlink(current) / n
                if src.is_file() and n not in plain:
                    _link_or_copy(src, old / n)
        for n in plain:
            _link_or_copy(folder / n, old / n)
        _replace_symlink(current, old.name)
        for n in plain:
            _replace_symlink(folder / n, link_target[n])
    new = Path(tempfile.mkdtemp(prefix=f".{base.name}.set-", dir=folder))
    try:
        os.chmod(new, 0o777 & ~_UMASK)
        for n, write in writers.items():
            write(new / n)
            if (new / n).is_file():
                os.chmod(new / n, 0o666 & ~_UMASK)
            else:
                raise OutputError(folder / n, "the writer wrote no file")
        for n in writers:
            link = folder / n
            if not (link.is_symlink() and os.readlink(link) == link_target[n]):
                _replace_symlink(link, link_target[n])  # dangling or resolving to the old set until the swap
        previous = os.readlink(current) if current.is_symlink() else None
        _replace_symlink(current, new.name)  # the commit: one rename
    except BaseException as exc:
        shutil.rmtree(new, ignore_errors=True)
        if isinstance(exc, OSError) and not isinstance(exc, GPDepthError):
            raise _as_output_error(base, exc) from None
        raise
    if previous and previous != new.name:
        shutil.rmtree(folder / previous, ignore_errors=True)
    for n in all_names:
        if n not in writers and (folder / n).is_symlink():
            with contextlib.suppress(OSError):
                (folder / n).unlink()  # dangling now: a member of the old set only
    return [folder / n for n in writers]


_SYMLINKS: dict[int, bool] = {}


def _symlinks_work(folder: Path) -> bool:
    """Whether the file system of ``folder`` supports symbolic links (probed once per device)."""
    dev = folder.stat().st_dev
    if dev not in _SYMLINKS:
        probe = folder / f".gpdepth3d-probe.{os.urandom(4).hex()}.link"
        try:
            os.symlink("target", probe)
            probe.unlink()
            _SYMLINKS[dev] = True
        except (OSError, NotImplementedError):
            _SYMLINKS[dev] = False
    return _SYMLINKS[dev]


def _write_then_rename(folder: Path, writers: Mapping[str, Callable[[Path], None]], all_names: list[str]) -> list[Path]:
    """Fallback without symbolic links: every file to a temporary name first, then the renames.

    A failed write leaves the old files untouched; only a kill between the renames can mix sets.
    """
    with write_together():
        for n, write in writers.items():
            atomic_write(folder / n, write)
    for n in all_names:
        if n not in writers:
            with contextlib.suppress(FileNotFoundError):
                (folder / n).unlink()
    return [folder / n for n in writers]


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Writes arrays to a compressed ``.npz`` atomically."""
    return atomic_write(path, npz_writer(**arrays))


def npz_writer(**arrays: np.ndarray) -> Callable[[Path], None]:
    """A ``write(path)`` function storing ``arrays`` as a compressed ``.npz`` (for `atomic_write_set`)."""

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return write


def depth_png_values(depth: np.ndarray, png_scale: float = KITTI_PNG_SCALE, *, argument: str = "depth") -> np.ndarray:
    """The (H, W) uint16 values of a depth PNG, value = round(metres / png_scale).

    0 = no depth: pixels with depth <= 0, NaN or inf (a PNG holds no negative depths).

    Validates everything a depth PNG needs before anything is written.

    Raises:
        ShapeError: if ``depth`` is not 2-D.
        InvalidInputError: if ``png_scale`` is not a finite number > 0.
        InvalidDepthError: if a depth does not fit 16 bits at ``png_scale``
            (KITTI's 1/256: 256 m).
    """
    png_scale = check_png_scale(png_scale)
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ShapeError(argument, "a 2-D depth map", describe(d))
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise ShapeError(argument, "a real-valued depth map", describe(d))
    d = d.astype(np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0)
    values = np.zeros(d.shape, dtype=np.float64)
    values[valid] = np.rint(d[valid] / png_scale)
    if np.any(values > 65535):
        raise InvalidDepthError(
            argument,
            f"depths up to {65535 * png_scale:.1f} m for a 16-bit PNG with png_scale {png_scale}",
            f"max {d[valid].max():.4g} m",
        )
    return values.astype(np.uint16)


def png_writer(values: np.ndarray, path: str | Path) -> Callable[[Path], None]:
    """A ``write(path)`` function storing uint16 ``values`` as a PNG (errors name ``path``)."""

    def write(tmp: Path) -> None:
        import cv2

        target = tmp if tmp.suffix.lower() == ".png" else tmp.with_suffix(".png")
        if not cv2.imwrite(str(target), values):
            raise OutputError(path, "OpenCV could not write the PNG")
        if target != tmp:
            os.replace(target, tmp)

    return write


def save_depth_png(path: str | Path, depth: np.ndarray, png_scale: float = KITTI_PNG_SCALE) -> Path:
    """Writes a depth map (metres) as a 16-bit PNG, value = round(metres / png_scale); 0 = no depth."""
    values = depth_png_values(depth, png_scale)
    path = Path(path).with_suffix(".png")
    return atomic_write(path, png_writer(values, path))


def check_png_scale(png_scale: float, argument: str = "png_scale") -> float:
    """Validates metres per PNG unit: a finite real number > 0; returns it as float."""
    if isinstance(png_scale, (bool, np.bool_)) or not isinstance(png_scale, (int, float, np.integer, np.floating)):
        raise InvalidInputError(argument, "metres per PNG unit, a finite number > 0", describe(png_scale))
    if not np.isfinite(png_scale) or png_scale <= 0:
        raise InvalidInputError(argument, "metres per PNG unit, a finite number > 0", png_scale)
    return float(png_scale)


def load_depth(
    path: str | Path,
    *,
    png_scale: float = KITTI_PNG_SCALE,
    key: str | None = None,
    invalid_value: int | None = None,
) -> np.ndarray:
    """Reads a (H, W) depth map in metres from ``.npy``, ``.npz`` or 16-bit ``.png``.

    Invalid pixels (0, NaN, inf, ``invalid_value``) come back as 0.

    Raises:
        DataFormatError: for missing, unknown or corrupt files, and arrays that are not a
            real-valued (H, W) map (complex, strings, objects).
        InvalidInputError: if ``png_scale`` is not a finite number > 0.
    """
    path = Path(path)
    png_scale = check_png_scale(png_scale)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            depth = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                depth = data[_pick_key(path, list(data.keys()), key)]
        elif suffix == ".png":
            import cv2

            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise DataFormatError(path, "not a readable PNG")
            if raw.ndim != 2 or raw.dtype != np.uint16:
                raise DataFormatError(path, f"expected a single-channel 16-bit depth PNG, got {raw.dtype} {raw.shape}")
            depth = raw.astype(np.float64) * png_scale
            depth[raw == 0] = 0.0
            if invalid_value is not None:
                depth[raw == invalid_value] = 0.0
        else:
            raise DataFormatError(path, f"unknown depth format '{suffix}' (use .npy, .npz or .png)")
    except DataFormatError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFormatError(path, f"corrupt or unreadable: {exc}") from None
    depth = np.asarray(depth)
    if depth.dtype == np.bool_ or not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
        raise DataFormatError(path, f"expected a real-valued (float or integer) depth map, got dtype {depth.dtype}")
    depth = depth.astype(np.float64)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise DataFormatError(path, f"expected a 2-D depth map, got shape {depth.shape}")
    depth = np.where(np.isfinite(depth), depth, 0.0)
    return depth


def _pick_key(path: Path, keys: list[str], key: str | None) -> str:
    if key is not None:
        if key not in keys:
            raise DataFormatError(path, f"no array '{key}' (has {keys})")
        return key
    if len(keys) == 1:
        return keys[0]
    for k in ("depth", "mean", "velodyne_depth"):
        if k in keys:
            return k
    raise DataFormatError(path, f"several arrays {keys}: say which with key=")


def load_sparse(
    path: str | Path,
    image_size: tuple[int, int] | None = None,
    *,
    png_scale: float = KITTI_PNG_SCALE,
    drop_invalid: bool = False,
) -> SparseDepth:
    """Reads sparse measurements from a point list (``.npz`` u/v/depth, ``.txt``) or a sparse depth map.

    Args:
        path: The file.
        image_size: (height, width) the point coordinates refer to; required for point lists,
            taken from the map for depth images.
        png_scale: Metres per PNG unit for 16-bit PNG depth maps.
        drop_invalid: Point lists: drop rows with a NaN/inf/negative/zero depth, a non-finite
            coordinate or a pixel outside the image, with a warning that gives their count. By
            default such rows raise `InvalidDepthError` with the count.

    Raises:
        DataFormatError: missing, unknown or corrupt files.
        InvalidDepthError: invalid rows in a point list (unless ``drop_invalid``).
        ShapeError: a point list without ``image_size``.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                if {"u", "v", "depth"} <= set(data.keys()):
                    if image_size is None:
                        raise ShapeError("image_size", "(height, width) for a point list", None)
                    sigma = data["sigma"] if "sigma" in data else None
                    return _points(path, data["u"], data["v"], data["depth"], image_size, sigma, drop_invalid)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            if isinstance(exc, GPDepthError):
                raise
            raise DataFormatError(path, f"corrupt or unreadable point list: {exc}") from None
    if suffix in (".txt", ".csv"):
        if image_size is None:
            raise ShapeError("image_size", "(height, width) for a point list", None)
        try:
            table = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, ndmin=2)
        except (ValueError, UnicodeDecodeError) as exc:
            raise DataFormatError(path, f"expected lines 'u v depth [sigma]': {exc}") from None
        if table.shape[0] == 0:
            return SparseDepth.empty(image_size)
        if table.shape[1] not in (3, 4):
            raise DataFormatError(path, f"expected 3 or 4 columns (u v depth [sigma]), got {table.shape[1]}")
        sigma = table[:, 3] if table.shape[1] == 4 else None
        return _points(path, table[:, 0], table[:, 1], table[:, 2], image_size, sigma, drop_invalid)
    depth = load_depth(path, png_scale=png_scale)
    sparse = SparseDepth.from_depth_map(depth)
    if image_size is not None and tuple(image_size) != sparse.image_size:
        raise ShapeError("image_size", f"the size of the sparse map {sparse.image_size}", tuple(image_size))
    return sparse


def _points(path: Path, u, v, depth, image_size, sigma, drop_invalid: bool) -> SparseDepth:
    """Point-list rows as `SparseDepth`: invalid rows raise with their count, or are dropped with a warning."""
    arrays = []
    for name, a in (("u", u), ("v", v), ("depth", depth)) + ((("sigma", sigma),) if sigma is not None else ()):
        a = np.asarray(a)
        if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise DataFormatError(path, f"'{name}' must be real numbers, got dtype {a.dtype}")
        arrays.append(a.astype(np.float64).ravel())
    u, v, d = arrays[:3]
    if not (u.shape == v.shape == d.shape):
        raise DataFormatError(path, f"u, v, depth of different lengths {u.shape[0]}, {v.shape[0]}, {d.shape[0]}")
    full = SparseDepth.from_arrays(u, v, d, image_size, arrays[3] if sigma is not None else None)
    dropped = d.shape[0] - len(full)
    if dropped:
        h, w = full.image_size
        with np.errstate(invalid="ignore"):
            bad_depth = int(np.sum(~(np.isfinite(d) & (d > 0))))
        what = f"{dropped} of {d.shape[0]} rows ({bad_depth} with a NaN/inf/<= 0 depth, the others outside the {w}x{h} image)"
        if not drop_invalid:
            raise InvalidDepthError(
                f"{path}", "finite depths > 0 at pixels inside the image (or drop_invalid=True)", what + " invalid"
            )
        warnings.warn(f"{path}: dropped {what}", stacklevel=3)
    return full


def load_rgb(path: str | Path) -> np.ndarray:
    """Reads an image as (H, W, 3) uint8 RGB.

    Raises:
        DataFormatError: missing, unreadable, or truncated (JPEG) file.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "image not found")
    if path.suffix.lower() in (".jpg", ".jpeg"):
        _check_jpeg_complete(path)
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DataFormatError(path, "not a readable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _check_jpeg_complete(path: Path) -> None:
    """Refuses a truncated JPEG (OpenCV decodes one silently, greying the missing part).

    A complete JPEG starts with the SOI marker FFD8 and ends with the EOI marker FFD9 (trailing
    padding aside); inside the entropy-coded data an FF byte is always stuffed, so a file cut
    anywhere after its headers has no FFD9 at its end.
    """
    with open(path, "rb") as f:
        head = f.read(2)
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - 4096))
        tail = f.read().rstrip(b"\x00\r\n\t ")
    if head != b"\xff\xd8":
        raise DataFormatError(path, "not a JPEG file (no FFD8 start marker)")
    if not tail.endswith(b"\xff\xd9"):
        raise DataFormatError(path, f"truncated JPEG ({size} bytes, no FFD9 end marker)")


def read_matrix(path: Path, shape: tuple[int, ...], what: str) -> np.ndarray:
    """Reads a whitespace-separated text matrix and checks its shape; DataFormatError otherwise."""
    if not path.is_file():
        raise DataFormatError(path, f"{what} not found")
    try:
        m = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DataFormatError(path, f"{what}: not a numeric matrix ({exc})") from None
    if m.size != int(np.prod(shape)):
        raise DataFormatError(path, f"{what}: expected {shape} values, got shape {m.shape}")
    m = m.reshape(shape)
    if not np.all(np.isfinite(m)):
        raise DataFormatError(path, f"{what}: non-finite values")
    return m


def load_pose(path: str | Path) -> np.ndarray:
    """Reads a 4x4 ``T_world_camera`` from text: 4 rows of 4 numbers (7-Scenes/TUM) or 12 numbers (3x4)."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "pose file not found")
    try:
        values = np.loadtxt(path, ndmin=1).ravel()
    except ValueError as exc:
        raise DataFormatError(path, f"expected numbers of a 4x4 or 3x4 pose: {exc}") from None
    if values.size == 12:
        values = np.concatenate([values, [0.0, 0.0, 0.0, 1.0]])
    if values.size != 16:
        raise DataFormatError(path, f"expected 16 (4x4) or 12 (3x4) numbers, got {values.size}")
    return check_pose(values.reshape(4, 4), str(path))


def load_poses(path: str | Path) -> list[np.ndarray]:
    """Reads one pose per line (12 numbers, row-major 3x4, KITTI odometry style) as 4x4 matrices."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "pose file not found")
    try:
        table = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DataFormatError(path, f"expected lines of 12 numbers: {exc}") from None
    if table.shape[1] != 12:
        raise DataFormatError(path, f"expected 12 numbers per line (3x4 pose), got {table.shape[1]}")
    bottom = np.tile([0.0, 0.0, 0.0, 1.0], (table.shape[0], 1))
    return [check_pose(T.reshape(4, 4), f"{path} line {i + 1}") for i, T in enumerate(np.hstack([table, bottom]))]
