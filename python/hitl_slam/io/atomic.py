"""Atomic file output: write a temporary file next to the target, fsync it, then rename it over
the target, so an interrupted or failed write never leaves a half-written file in its place.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from typing import TextIO

__all__ = ["atomic_write_text", "atomic_writer", "fsync_directory"]


def _create_temp(target: str) -> tuple[int, str]:
    directory, name = os.path.split(target)
    while True:
        # Not tempfile.mkstemp: its 0600 mode would replace the target's permissions; os.open with
        # 0o666 lets the umask decide, as a plain open() would.
        temp = os.path.join(directory, f".{name}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), temp
        except FileExistsError:
            continue


def fsync_directory(directory: str) -> None:
    # Makes the rename itself durable on POSIX; not possible (nor needed) everywhere.
    try:
        fd = os.open(directory or ".", os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_writer(
    path: str | os.PathLike[str], *, encoding: str = "utf-8", newline: str = "\n"
) -> Iterator[TextIO]:
    """Open a text file for writing that replaces ``path`` only if the ``with`` block succeeds.

    On any exception (in the block, the fsync or the rename) the temporary file is removed, the
    old ``path`` (if any) is untouched, and the exception propagates.
    """
    target = os.fspath(path)
    fd, temp = _create_temp(target)
    try:
        file = os.fdopen(fd, "w", encoding=encoding, newline=newline)
    except BaseException:
        os.close(fd)
        os.unlink(temp)
        raise
    try:
        with file as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(FileNotFoundError):
            os.chmod(temp, os.stat(target).st_mode & 0o7777)
        os.replace(temp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temp)
        raise
    fsync_directory(os.path.dirname(target))


def atomic_write_text(path: str | os.PathLike[str], text: str, *, encoding: str = "utf-8") -> None:
    """Replace ``path`` with ``text`` atomically (see :func:`atomic_writer`)."""
    with atomic_writer(path, encoding=encoding) as f:
        f.write(text)
