"""Durable writes: every write is atomic, and files that belong together are written as one set.

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
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np

from ..errors import GPDepthError, OutputError

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
    errno.EFBIG: "file too large: the file size limit (ulimit -f) was reached",
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
    such as `DepthPosterior.save` or `gpdepth3d.pipelines.previews.write_previews`) writes a
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
