"""Files written whole or not at all: a capture, its clip, its JSON side file on a disk that
can fill up. Each is written into a hidden temporary file beside its name, flushed to the
disk, then given its name in one step; on any error (OSError: a full disk, ENOSPC) the
temporary file is removed and nothing is left."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from pathlib import Path

_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK}


def _temporary(path: Path, data: bytes | memoryview, mode: int) -> str:
    """``data`` in a new hidden file beside ``path``, on the disk; its path."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return tmp


def write_new(path: Path, data: bytes | memoryview, mode: int = 0o644) -> None:
    """Write the new file ``path`` whole or not at all; FileExistsError if it exists (never
    overwritten), OSError when it cannot be written (nothing left)."""
    tmp = _temporary(path, data, mode)
    try:
        try:
            os.link(tmp, path)  # one step, and refuses to replace an existing file
        except OSError as exc:
            if exc.errno not in _NO_HARD_LINKS:
                raise
            if path.exists():  # a file system without hard links: check, then rename
                raise FileExistsError(errno.EEXIST, "exists, not overwritten", str(path)) from None
            os.rename(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def replace_whole(path: Path, data: bytes | memoryview, mode: int = 0o644) -> None:
    """Replace (or create) ``path`` with ``data`` in one step: a reader sees the old file
    or the new one, never part of it; OSError when it cannot be written (the old kept)."""
    tmp = _temporary(path, data, mode)
    try:
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
