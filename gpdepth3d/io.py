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
belong together (a posterior's ``.npz``, its PNGs and previews) are written as one set
(`output_set`, `atomic_write_set`): plain files, renamed into place together under a lock on the
folder after a small journal of the renames is on disk, so a kill, a full disk or a concurrent
writer leaves the old set or the new one (the next writer finishes an interrupted commit and
deletes what killed writers left). `write_together` defers the renames of a whole block of writes
(the CLI's ``eval``). A write that fails raises `OutputError` (an `OSError`) naming the path and
the cause (disk full, permission denied, a directory in the way, a name too long).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import json
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
# The `output_set` being written (per thread / task).
_SET: contextvars.ContextVar["_OutputSet | None"] = contextvars.ContextVar("gpdepth3d_output_set", default=None)


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
    _check_name_length(p)
    return p


_TEMP_EXTRA = len(".12345678.tmp") + 1  # what a temporary name adds to the file name (`atomic_path`)


def _check_name_length(path: Path) -> None:
    """Refuses a name (or a folder name) too long for the file system, its temporary name included."""
    existing = next((q for q in path.absolute().parents if q.exists()), Path("/"))
    try:
        limit = os.pathconf(existing, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    parts = [(part, 0) for part in path.parent.parts] + [(path.name, _TEMP_EXTRA)]
    for part, extra in parts:
        size = len(os.fsencode(part)) + extra
        if size > limit:
            raise OutputError(
                path,
                f"file name too long: {size} bytes with the temporary name's {extra}, the file system allows {limit}",
            )


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

    The temporary file (``.<stem>.<8 random>.tmp<suffix>``) is held under a lock until it is
    renamed, so a clean-up by another writer removes only those of killed writers. Inside an
    `output_set` of the same folder the rename waits for the set's commit; inside
    `write_together` until the whole block of writes succeeded.

    Raises:
        OutputError: when the folder cannot be created or written (read-only, full disk), when
            ``path`` is a directory, or when the block raises an `OSError` (the temporary file
            is removed; nothing appears under ``path``).
    """
    path = check_output_path(path)
    if _ANY_TEMP.match(path.name):  # already a temporary (a set's writer that itself writes atomically): fill it
        yield path
        return
    _make_parent(path)
    active = _SET.get()
    joins = active is not None and active.owns(path)
    try:
        with _folder_lock(path.parent):  # no clean-up sees the temporary before it is locked
            fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
            _flock(fd)
    except OSError as exc:
        raise _as_output_error(path, exc) from None
    tmp_path: Path | None = Path(tmp)
    pending = _PENDING.get()
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
            os.fsync(fd)  # the data is on disk before any rename can make it visible
            if joins:
                active.add(path, tmp_path, fd)
                tmp_path = None  # renamed (or removed) by the set's commit, which closes fd
            elif pending is not None:
                pending.append((tmp_path, path, fd))
                tmp_path = None  # renamed (or removed) by write_together, which closes fd
            else:
                os.replace(tmp_path, path)
                tmp_path = None
        except OSError as exc:
            raise _as_output_error(path, exc) from None
    finally:
        if tmp_path is not None:
            with contextlib.suppress(OSError):
                tmp_path.unlink()
        if tmp_path is not None or not (joins or pending is not None):
            with contextlib.suppress(OSError):
                os.close(fd)


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
    they renamed into place, folder by folder, each folder's renames one journalled commit as in
    `output_set` (a failure such as a full disk leaves none of the new files and the old files
    untouched; a kill during a commit is finished by the next `write_together` writing there).
    Used by the CLI so a command's outputs (``eval``'s tables and plots) do not come half-written.
    """
    pending: list[tuple[Path, Path, int]] = []
    token = _PENDING.set(pending)
    ok = False
    try:
        yield
        ok = True
    finally:
        _PENDING.reset(token)
        folders: dict[str, _OutputSet] = {}
        for tmp, final, fd in pending:
            key = os.path.abspath(final.parent)
            if key not in folders:
                folders[key] = _OutputSet(final.parent / TOGETHER_BASE, ())
            folders[key].add(final, tmp, fd)
        if ok:
            for i, s in enumerate(folders.values()):
                try:
                    s.commit()
                except BaseException:
                    for rest in list(folders.values())[i + 1 :]:
                        rest.discard()
                    raise
        else:
            for s in folders.values():
                s.discard()


TOGETHER_BASE = "gpdepth3d"
"""Name of the commit journals of `write_together` (``.gpdepth3d.<8 hex>.journal``, while a commit runs)."""


# ------------------------------------------------------------------------------ output sets
def _temp_pattern(name: str) -> re.Pattern:
    """Temporary files `atomic_path` makes for ``name``: ``.<stem>.<8 random>.tmp<suffix>``."""
    p = Path(name)
    return re.compile(rf"^\.{re.escape(p.stem)}\.[A-Za-z0-9_]{{8}}\.tmp{re.escape(p.suffix)}$")


def _journal_pattern(base_name: str) -> re.Pattern:
    """Commit journals of the set ``base_name``: ``.<base name>.<8 hex>.journal``."""
    return re.compile(rf"^\.{re.escape(base_name)}\.[0-9a-f]{{8}}\.journal$")


def _flock(fd: int, *, blocking: bool = True) -> bool:
    """An exclusive advisory lock (fcntl.flock) on ``fd``; True when taken (always without fcntl)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows: no advisory locks, writers do not take turns
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
    except BlockingIOError:
        return False
    except OSError:  # a file system without flock: nothing to wait for
        return True
    return True


@contextlib.contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    """Holds an exclusive lock on the folder itself (flock on its descriptor): no lock file is made.

    Taken only for short steps (making temporary files, a commit, a clean-up), never nested.
    Without ``fcntl`` (Windows) writers do not take turns.
    """
    try:
        import fcntl  # noqa: F401
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError as exc:
        raise OutputError(folder, write_problem(exc)) from None
    try:
        _flock(fd)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def _fsync_folder(folder: Path) -> None:
    """Makes the renames in ``folder`` durable (a no-op where folders cannot be opened)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class _OutputSet:
    """The files of one `output_set` call: final name -> temporary file (held locked until the commit)."""

    def __init__(self, base: Path, members: Sequence[str]):
        self.base = base
        self.folder = base.parent
        self.members: list[str] = list(members)
        self.temps: dict[str, tuple[Path, int]] = {}

    def owns(self, path: Path) -> bool:
        return os.path.abspath(path.parent) == os.path.abspath(self.folder)

    def add(self, path: Path, tmp: Path, fd: int) -> None:
        old = self.temps.pop(path.name, None)
        self.temps[path.name] = (tmp, fd)
        if old is not None:  # the same name written twice: the last write counts
            _drop_temp(*old)

    def discard(self) -> None:
        for tmp, fd in self.temps.values():
            _drop_temp(tmp, fd)
        self.temps.clear()

    def commit(self) -> None:
        """Renames every file into place under the folder lock, journalled so a kill rolls forward.

        Once the journal is on disk the commit is decided: a failure or an interruption after it
        leaves the journal and the temporaries for the next writer (or `clean_output_set`) to
        finish; before it, the temporaries are removed and the old files stay.
        """
        folder = self.folder
        names = list(dict.fromkeys([*self.temps, *self.members]))
        decided = False
        try:
            with _folder_lock(folder):
                _recover(self.base, names)
                renames = [[tmp.name, n] for n, (tmp, _) in self.temps.items()]
                remove = [n for n in self.members if n not in self.temps and os.path.lexists(folder / n)]
                journal = folder / f".{self.base.name}.{os.urandom(4).hex()}.journal"
                with open(journal, "w") as f:
                    f.write(json.dumps({"renames": renames, "remove": remove}))
                    f.flush()
                    os.fsync(f.fileno())
                _fsync_folder(folder)
                decided = True
                _apply_journal(folder, renames, remove)
                _fsync_folder(folder)
                journal.unlink()
                _fsync_folder(folder)
        except OSError as exc:
            raise _as_output_error(self.base, exc) from None
        finally:
            for tmp, fd in self.temps.values():
                if decided:
                    with contextlib.suppress(OSError):
                        os.close(fd)
                else:
                    _drop_temp(tmp, fd)
            self.temps.clear()


def _drop_temp(tmp: Path, fd: int) -> None:
    with contextlib.suppress(OSError):
        tmp.unlink()
    with contextlib.suppress(OSError):
        os.close(fd)


def _apply_journal(folder: Path, renames: Sequence[Sequence[str]], remove: Sequence[str]) -> None:
    """Carries out a commit: each temporary renamed onto its name, then the members not written removed.

    Idempotent, so an interrupted commit is finished by running it again (a temporary already
    renamed is no longer there).
    """
    for tmp, name in renames:
        if os.path.lexists(folder / tmp):
            os.replace(folder / tmp, folder / name)
    for name in remove:
        with contextlib.suppress(FileNotFoundError):
            (folder / name).unlink()


def _recover(base: Path, names: Sequence[str]) -> int:
    """Finishes commits of ``base`` a kill interrupted and removes what killed writers left.

    Called with the folder lock held. A journal is written only once all of its temporaries are
    complete, so it is rolled forward; a temporary whose writer is gone (its lock is free) is
    deleted. Sets of older versions (symbolic links into ``.<base>.set-*`` folders) become plain files.

    Returns:
        How many leftovers were removed or finished.
    """
    folder = base.parent
    if not folder.is_dir():
        return 0
    count = 0
    journal = _journal_pattern(base.name)
    temps = [_temp_pattern(n) for n in names]
    legacy_set = re.compile(rf"^\.{re.escape(base.name)}\.set-[A-Za-z0-9_]{{8}}$")
    legacy_files = {f".{base.name}.current", f".{base.name}.lock"}
    legacy_link = re.compile(
        rf"^\.({'|'.join(re.escape(x) for x in [f'{base.name}.current', *names])})\.[0-9a-f]{{8}}\.link$"
    )
    with os.scandir(folder) as it:  # every leftover is hidden: only those names are matched
        hidden = sorted(e.name for e in it if e.name.startswith("."))
    for n in hidden:
        if journal.match(n):
            entry = folder / n
            try:
                plan = json.loads(entry.read_text())
                _apply_journal(folder, plan["renames"], plan["remove"])
            except (ValueError, KeyError, TypeError):
                pass  # a journal cut while it was written: its commit never started
            entry.unlink()
            count += 1
    _fsync_folder(folder)
    if f".{base.name}.current" in hidden:  # an older version's set: each name a link into its set folder
        for n in names:
            link = folder / n
            if link.is_symlink():
                target = link.resolve()
                if target.is_file() and legacy_set.match(target.parent.name):
                    os.replace(target, link)
                else:
                    link.unlink()
                count += 1
    for n in hidden:
        entry = folder / n
        if any(p.match(n) for p in temps):
            with contextlib.suppress(OSError):
                fd = os.open(entry, os.O_RDONLY)
                try:
                    if _flock(fd, blocking=False):  # no writer holds it: a killed writer's leftover
                        entry.unlink()
                        count += 1
                finally:
                    os.close(fd)
        elif legacy_set.match(n) and entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
            count += 1
        elif n in legacy_files or legacy_link.match(n):
            with contextlib.suppress(OSError):
                entry.unlink()
                count += 1
    return count


def clean_output_set(base: str | Path, names: Sequence[str] = ()) -> int:
    """Finishes an interrupted commit of the set ``base`` and removes what killed writers left.

    Readers may call it before reading a set a killed writer may have left (each `output_set`
    commit calls it first). Writers still running are not disturbed (their temporaries are locked).

    Args:
        base: Path naming the set, e.g. ``out/frame0``.
        names: The file names of the set (in ``base``'s folder) whose temporaries to remove.

    Returns:
        How many leftovers were removed or finished.
    """
    base = Path(base)
    if not base.parent.is_dir():
        return 0
    with _folder_lock(base.parent):
        try:
            return _recover(base, list(names))
        except OSError as exc:
            raise _as_output_error(base, exc) from None


_ANY_JOURNAL = re.compile(r"^\..+\.[0-9a-f]{8}\.journal$")
_ANY_TEMP = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[^.]+)?$")


def clean_output_folder(folder: str | Path) -> int:
    """Finishes every interrupted commit in ``folder`` and deletes every temporary of a killed writer.

    For a folder a whole run writes (``batch``): like `clean_output_set` for every set in it.
    Writers still running are not disturbed (their temporaries are locked).

    Returns:
        How many leftovers were removed or finished.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    count = 0
    with _folder_lock(folder):
        try:
            with os.scandir(folder) as it:
                hidden = sorted(e.name for e in it if e.name.startswith("."))
            for n in hidden:
                if _ANY_JOURNAL.match(n):
                    base = folder / n[1:].rsplit(".", 2)[0]
                    count += _recover(base, [])
            for n in hidden:
                if _ANY_TEMP.match(n) and (folder / n).is_file():
                    fd = os.open(folder / n, os.O_RDONLY)
                    try:
                        if _flock(fd, blocking=False):
                            (folder / n).unlink()
                            count += 1
                    finally:
                        os.close(fd)
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise _as_output_error(folder, exc) from None
    return count


def _check_names(folder: Path, names: Sequence[str]) -> None:
    for n in names:
        if not isinstance(n, str) or Path(n).name != n or n in ("", ".", ".."):
            raise OutputError(folder / str(n), "a plain file name inside the set's folder expected")
        check_output_path(folder / n)


@contextlib.contextmanager
def output_set(base: str | Path, *, members: Sequence[str] = ()) -> Iterator[None]:
    """Makes every file written in the block in ``base``'s folder appear together, or none of them.

    Each `atomic_path` / `atomic_write` inside the block (any function that writes through them,
    such as `DepthPosterior.save` or `gpdepth3d.experiments.previews.write_previews`) writes a
    temporary file beside its target; when the block succeeds they are renamed into place under
    an exclusive lock on the folder, after a small journal listing the renames is made durable.
    A kill during the renames is rolled forward by the next writer (or `clean_output_set`); a
    kill before leaves the old files, and its temporaries are deleted by the next writer.
    Concurrent writers of one set take turns at the commit, the last one winning as a whole.
    The outputs are plain files: nothing hidden stays beside them.

    Args:
        base: Path naming the set (its folder and its name), e.g. ``out/frame0``.
        members: Every name the set may hold; those not written this time (say the error
            preview of an earlier call with ground truth) are removed in the same commit.

    Raises:
        OutputError: a file cannot be written; nothing of the new set is then visible.
    """
    base = check_output_path(base, "base")
    _check_names(base.parent, members)
    outer = _SET.get()
    if outer is not None and outer.owns(base):  # a set inside a set of the same folder joins it
        outer.members.extend(m for m in members if m not in outer.members)
        yield
        return
    _make_parent(base)
    current = _OutputSet(base, members)
    token = _SET.set(current)
    ok = False
    try:
        yield
        ok = True
    finally:
        _SET.reset(token)
        if ok:
            current.commit()
        else:
            current.discard()


def atomic_write_set(
    base: str | Path, writers: Mapping[str, Callable[[Path], None]], *, members: Sequence[str] = ()
) -> list[Path]:
    """Writes several files beside each other as one set: readers see the old set or the new one.

    Each ``write(path)`` of ``writers`` writes a temporary file; they are then renamed into
    place together (`output_set`). Inside an enclosing `output_set` of the same folder the files
    join that set instead.

    Args:
        base: Path naming the set (its folder and its name), e.g. ``out/frame0``.
        writers: File name (in ``base``'s folder) -> ``write(path)`` writing that file.
        members: Every name the set may hold (default: the names of ``writers``); those not
            written this time are removed in the same commit.

    Returns:
        The written paths, in the order of ``writers``.

    Raises:
        OutputError: if a file cannot be written; nothing of the new set is then visible.
    """
    base = check_output_path(base, "base")
    folder = base.parent
    _check_names(folder, list(writers))
    with output_set(base, members=list(dict.fromkeys([*writers, *members]))):
        for n, write in writers.items():
            with atomic_path(folder / n) as tmp:
                write(tmp)
                if not tmp.is_file() or tmp.stat().st_size == 0:
                    raise OutputError(folder / n, "the writer wrote no file")
    return [folder / n for n in writers]


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Writes arrays to a compressed ``.npz`` atomically."""
    return atomic_write(path, npz_writer(**arrays))


def npz_writer(**arrays: np.ndarray) -> Callable[[Path], None]:
    """A ``write(path)`` function storing ``arrays`` as a compressed ``.npz`` (for `atomic_write_set`)."""

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    return write


class PNGRangeWarning(UserWarning):
    """Depths beyond a 16-bit PNG's range were stored at its limit (the float outputs keep them)."""


def depth_png_values(
    depth: np.ndarray, png_scale: float = KITTI_PNG_SCALE, *, argument: str = "depth", saturate: bool = False
) -> np.ndarray:
    """The (H, W) uint16 values of a depth PNG, value = round(metres / png_scale).

    0 = no depth: pixels with depth <= 0, NaN or inf (a PNG holds no negative depths). The
    range is the format's (KITTI's 1/256: 256 m): beyond it a depth saturates at 65535 with
    ``saturate``, else it is refused. Everything is validated before anything is written.

    Raises:
        ShapeError: if ``depth`` is not 2-D.
        InvalidInputError: if ``png_scale`` is not a finite number > 0.
        InvalidDepthError: if a depth does not fit 16 bits at ``png_scale`` and not ``saturate``.

    Warns:
        PNGRangeWarning: with ``saturate``, naming how many pixels were stored at the limit.
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
    over = values > 65535
    n_over = int(np.count_nonzero(over))
    if n_over:
        limit = f"{65535 * png_scale:.1f} m for a 16-bit PNG with png_scale {png_scale}"
        if not saturate:
            raise InvalidDepthError(argument, f"depths up to {limit}", f"max {d[valid].max():.4g} m")
        warnings.warn(
            f"{argument}: {n_over} of {d.size} pixels beyond {limit} (max {d[valid].max():.4g} m) stored as "
            f"{65535 * png_scale:.1f} m; the float outputs keep the true values",
            PNGRangeWarning,
            stacklevel=2,
        )
        values[over] = 65535
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


def _read_npy_header(fp) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, header bytes) of the .npy stream ``fp``, read without touching its data."""
    start = fp.tell()
    version = np.lib.format.read_magic(fp)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
    else:
        shape, _, dtype = np.lib.format._read_array_header(fp, version)
    return tuple(int(s) for s in shape), np.dtype(dtype), fp.tell() - start


def check_stored_array(
    path: str | Path, member: str | None = None, *, copies: float = 2.0
) -> tuple[tuple[int, ...], np.dtype]:
    """Reads the header of an ``.npy`` file (or of ``member`` of an ``.npz``) and checks its size first.

    A header claiming more values than the file holds (a corrupt or forged file) is refused
    before NumPy allocates the array it claims, and so is an array whose ``copies`` (the array
    and its float64 copy) exceed `gpdepth3d.limits.memory_limit`.

    Returns:
        The stored (shape, dtype).

    Raises:
        DataFormatError: no such member, an unreadable header, or more data claimed than stored.
        ProblemTooLargeError: an array too large for the memory limit.
    """
    from .limits import check_array_size

    path = Path(path)
    try:
        if member is None:
            with open(path, "rb") as fp:
                shape, dtype, header = _read_npy_header(fp)
                stored = os.fstat(fp.fileno()).st_size - header
            label = str(path)
        else:
            with zipfile.ZipFile(path) as zf:
                name = member if member.endswith(".npy") else member + ".npy"
                info = zf.getinfo(name)
                with zf.open(info) as fp:
                    shape, dtype, header = _read_npy_header(fp)
                stored = info.file_size - header
            label = f"{path}[{member}]"
    except KeyError:
        raise DataFormatError(path, f"no array '{member}'") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFormatError(path, f"corrupt or unreadable array header: {exc}") from None
    claimed = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if claimed > stored:
        raise DataFormatError(
            label,
            f"corrupt: the header claims shape {shape} of {dtype} ({claimed} bytes), the file stores {max(stored, 0)}",
        )
    check_array_size(f"array {label}", shape, dtype, copies=copies * max(1.0, 8.0 / max(dtype.itemsize, 1)))
    return shape, dtype


def load_npz_arrays(path: str | Path, names: Sequence[str], what: str = "arrays") -> dict[str, np.ndarray]:
    """Reads the arrays ``names`` of an ``.npz``, each header checked first (`check_stored_array`).

    Raises:
        DataFormatError: a missing, corrupt or forged file (naming it), or a missing array.
        ProblemTooLargeError: an array too large for the memory limit.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, f"{what} not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise DataFormatError(path, f"{what}: an .npz archive expected (this is a single array)")
            missing = [n for n in names if n not in data.files]
            if missing:
                raise DataFormatError(path, f"{what}: no array {missing[0]!r} (has {data.files})")
            out = {}
            for n in names:
                check_stored_array(path, n)
                out[n] = data[n]
            return out
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        if isinstance(exc, GPDepthError):
            raise
        raise DataFormatError(path, f"{what}: corrupt or unreadable ({type(exc).__name__}: {exc})") from None


def check_image_header(path: str | Path, channels: int = 3) -> None:
    """Refuses a PNG (IHDR) or JPEG (start of frame) whose header claims more pixels than the memory limit allows.

    Other formats are left to the decoder (whose errors `load_rgb` / `load_depth` turn into
    `DataFormatError`).

    Raises:
        DataFormatError: a PNG signature with a header cut short.
        ProblemTooLargeError: the decoded image would exceed `gpdepth3d.limits.memory_limit`.
    """
    from .limits import check_array_size

    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(33)
        if head.startswith(b"\xff\xd8"):
            size = _jpeg_size(f)
            if size is not None:
                check_array_size(f"image {path}", (*size, channels), np.float64)
            return
    if not head.startswith(b"\x89PNG\r\n\x1a\n"):
        return
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise DataFormatError(path, "corrupt PNG: no IHDR header")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    check_array_size(f"image {path}", (height, width, channels), np.float64)


def _jpeg_size(f) -> tuple[int, int] | None:
    """(height, width) from a JPEG's start-of-frame marker, reading marker headers only (None: none found)."""
    f.seek(2)
    for _ in range(1000):  # the frame header comes after a few tables
        marker = f.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            return None
        if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:  # markers without a length
            continue
        length = f.read(2)
        if len(length) < 2:
            return None
        if 0xC0 <= marker[1] <= 0xCF and marker[1] not in (0xC4, 0xC8, 0xCC):  # SOFn
            frame = f.read(5)
            return (int.from_bytes(frame[1:3], "big"), int.from_bytes(frame[3:5], "big")) if len(frame) == 5 else None
        f.seek(int.from_bytes(length, "big") - 2, os.SEEK_CUR)
    return None


def _imread(path: Path, flags: int) -> np.ndarray | None:
    """cv2.imread with its size refusals and decoder errors as typed errors."""
    import cv2

    check_image_header(path)
    try:
        return cv2.imread(str(path), flags)
    except cv2.error as exc:
        raise DataFormatError(path, f"not a readable image: {str(exc).strip().splitlines()[-1]}") from None


def load_depth(
    path: str | Path, *, png_scale: float = KITTI_PNG_SCALE, key: str | None = None, invalid_value: int | None = None
) -> np.ndarray:
    """Reads a (H, W) depth map in metres from ``.npy``, ``.npz`` or 16-bit ``.png``.

    Invalid pixels (0, NaN, inf, ``invalid_value``) come back as 0.

    Raises:
        DataFormatError: for missing, unknown or corrupt files, and arrays that are not a
            real-valued (H, W) map (complex, strings, objects).
        InvalidInputError: if ``png_scale`` is not a finite number > 0.
    """
    path = _as_path(path)
    png_scale = check_png_scale(png_scale)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            check_stored_array(path)
            depth = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                member = _pick_key(path, list(data.keys()), key)
                check_stored_array(path, member)
                depth = data[member]
        elif suffix == ".png":
            import cv2

            raw = _imread(path, cv2.IMREAD_UNCHANGED)
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
    if depth.dtype == np.bool_ or not (
        np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)
    ):
        raise DataFormatError(path, f"expected a real-valued (float or integer) depth map, got dtype {depth.dtype}")
    depth = depth.astype(np.float64)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise DataFormatError(path, f"expected a 2-D depth map, got shape {depth.shape}")
    depth = np.where(np.isfinite(depth), depth, 0.0)
    return depth


def _as_path(path, argument: str = "path") -> Path:
    """``path`` as a `Path`; a value that is no path at all (None, a number) is refused by name."""
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise InvalidInputError(argument, "a file path", describe(path))
    return Path(path)


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
    path = _as_path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                if {"u", "v", "depth"} <= set(data.keys()):
                    if image_size is None:
                        raise ShapeError("image_size", "(height, width) for a point list", None)
                    for member in ("u", "v", "depth", "sigma"):
                        if member in data:
                            check_stored_array(path, member)
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

    path = _as_path(path)
    if not path.is_file():
        raise DataFormatError(path, "image not found")
    if path.suffix.lower() in (".jpg", ".jpeg"):
        _check_jpeg_complete(path)
    bgr = _imread(path, cv2.IMREAD_COLOR)
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
    bad = _jpeg_marker_problem(path.read_bytes())
    if bad is not None:
        raise DataFormatError(path, f"corrupt JPEG data ({bad}): OpenCV would decode it silently into a wrong image")


def _jpeg_marker_problem(data: bytes) -> str | None:
    """The first marker no JPEG may hold (a reserved code, a segment past the end), or None.

    The file is walked segment by segment; in the entropy-coded data after each start of scan an
    FF byte is always followed by 00 (stuffing) or a restart marker D0-D7, else it starts the next
    marker. Random bytes in a scan soon give an FF followed by a reserved code (02-BF).
    """
    at, n = 2, len(data)
    while at < n:
        if data[at] != 0xFF:
            return f"byte {at}: expected a marker"
        while at + 1 < n and data[at + 1] == 0xFF:  # fill bytes before a marker
            at += 1
        if at + 1 >= n:
            return None
        code = data[at + 1]
        if code == 0xD9:  # end of image
            return None
        if 0x02 <= code <= 0xBF:
            return f"byte {at}: reserved marker FF{code:02X}"
        if 0xD0 <= code <= 0xD7 or code == 0x01:  # no length
            at += 2
            continue
        if at + 4 > n:
            return f"byte {at}: marker FF{code:02X} cut short"
        end = at + 2 + int.from_bytes(data[at + 2 : at + 4], "big")
        if end > n:
            return f"byte {at}: segment FF{code:02X} runs past the end of the file"
        at = end
        if code == 0xDA:  # start of scan: skip its entropy-coded data to the next marker
            while True:
                at = data.find(b"\xff", at)
                if at < 0 or at + 1 >= n:
                    return None
                if data[at + 1] == 0x00 or 0xD0 <= data[at + 1] <= 0xD7:
                    at += 2
                    continue
                break
    return None


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
    path = _as_path(path)
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
    path = _as_path(path)
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
