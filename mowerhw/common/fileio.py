"""Crash-safe file writing.

``write_atomic`` writes to a temporary file in the same directory, flushes and fsyncs it,
renames it over the target (atomic on POSIX) and fsyncs the directory, so a reader sees the
old file or the new one, never half of either, whatever happens in between (power loss,
SIGKILL, a full disk).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

FileStamp = tuple[int, int, int]


def file_stamp(path: str | Path) -> FileStamp | None:
    """(mtime, size, inode) of ``path``, None if it cannot be read: a change means reload
    (the daemon's map file, the status page's copy of it)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def write_atomic(path: str | Path, data: bytes, mode: int = 0o644, durable: bool = True) -> None:
    """Replace ``path`` with ``data`` atomically and (``durable``) durably. Without
    ``durable`` nothing is fsynced: still never half a file, but a power loss may keep the
    previous one (for state rewritten many times a second)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if not durable:
        return
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
