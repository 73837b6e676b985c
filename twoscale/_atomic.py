"""Atomic file writes: readers see either the old file or the whole new one, never a half file."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path


def current_umask() -> int:
    """The process umask (``os.umask`` can only be read by setting it: set, then restore)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def new_file_mode(path: Path) -> int:
    """Permissions for a written file: those of the file it replaces, else ``0o666 & ~umask``.

    (``tempfile.mkstemp`` creates its file ``0o600``; without this a replaced file would lose
    its permissions and a new one would be unreadable to other users.)
    """
    try:
        return path.stat().st_mode & 0o777
    except FileNotFoundError:
        return 0o666 & ~current_umask()


def write_atomic(path, chunks: Iterable[bytes | memoryview]) -> Path:
    """Write ``chunks`` to a temporary file beside ``path``, fsync it, then ``os.replace`` it."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            for chunk in chunks:
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, new_file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path, text: str) -> Path:
    """:func:`write_atomic` of UTF-8 text."""
    return write_atomic(path, [text.encode("utf-8")])
