"""The one durable-write helper of everything under data_dir (uploads, results, the job ledger, the token
secret, the embedded Redis's URL file).

Every write goes to a hidden temporary file beside its target (`.<name>.<uuid>.tmp`, which readers ignore),
and is then moved into place in one of three ways:
- `atomic_write_bytes`: fsync the file, rename it over the target, fsync the directory (replace, durable);
- `write_once`: fsync the file, hard-link it to the target (fails if the target exists), fsync the directory
  (create once: concurrent writers never overwrite each other);
- `replace_bytes`: rename without any fsync (live tiles, rewritten often and made again after a crash).
After a crash at any point a target holds its old content (or does not exist) or all of the new bytes.
`sync_filesystem` makes a batch written with `replace_bytes` durable at once (a version's tiles): one flush of the
filesystem instead of two fsyncs a file.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

_SYNCFS = getattr(ctypes.CDLL(None, use_errno=True), "syncfs", None)  # Linux; elsewhere sync(2)


def sync_filesystem(path: Path) -> None:
    """Make every file written so far on the filesystem holding `path` durable, renames and removals included:
    one syncfs(2) (sync(2) where the C library has none) instead of a fsync per file and directory."""
    if _SYNCFS is None:
        os.sync()
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        if _SYNCFS(fd) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err), str(path))
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    """Fsync a directory so a rename or creation inside it survives a power cut."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def directory_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive advisory lock on path/.lock (across processes) for the duration of the block."""
    with open(path / ".lock", "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


@contextlib.contextmanager
def try_lock(lock_path: Path) -> Iterator[bool]:
    """Try an exclusive advisory lock on lock_path without waiting: yield True while held, False if another
    process holds it. The kernel releases it when its holder dies, so a crashed holder never blocks anyone."""
    with open(lock_path, "a+b") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def temp_file(path: Path, data: bytes, fsync: bool = True, mode: int = 0o640) -> Path:
    """Return a new hidden temporary file beside `path` holding `data` (fsynced unless fsync=False)."""
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return tmp


def _move_over(tmp: Path, path: Path) -> None:
    try:
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` durably: temp file in the same directory, fsync, rename, fsync the directory.

    After a crash at any point `path` holds either its old content (or does not exist) or all of `data`,
    never a part; an interrupted write leaves at most a hidden `.<name>.*.tmp` file, which readers ignore.
    """
    path = Path(path)
    _move_over(temp_file(path, data), path)
    fsync_dir(path.parent)


def write_once(path: Path, data: bytes, mode: int = 0o640) -> bool:
    """Return True if this call created `path` with `data` durably (False when it exists already).

    The bytes go to a fsynced temporary file that is hard-linked into place (link fails if the target
    exists), so concurrent writers never overwrite each other and readers never see a partial file.
    """
    path = Path(path)
    tmp = temp_file(path, data, mode=mode)
    try:
        try:
            os.link(tmp, path)
        except FileExistsError:
            return False
        fsync_dir(path.parent)
        return True
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def replace_bytes(path: Path, data: bytes) -> None:
    """Write `path` atomically (temp file + rename) without fsync: readers see the old or the new file."""
    path = Path(path)
    _move_over(temp_file(path, data, fsync=False), path)
