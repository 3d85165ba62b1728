"""The session's folder as the only place the web UI writes: save names checked, every path
resolved (links followed) and kept inside the folder, write failures turned into clear errors.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable

from hitl_slam.errors import InputError

__all__ = ["SAVE_FORMATS", "OutsideFolder", "check_save_name", "contained", "inside", "write"]

SAVE_FORMATS = (".txt", ".g2o", ".pgm")
"""What ``POST /api/save`` writes (the ``.pgm`` brings its ``.yaml``)."""

_SAVE_NAME = re.compile(r"[A-Za-z0-9._-]{1,100}")


class OutsideFolder(InputError):
    """A save or export path that would leave the session's folder (HTTP 403)."""


def check_save_name(stem: str) -> str:
    """``stem`` if it is a plain file stem ([A-Za-z0-9._-], no leading dot, no ``..``)."""
    if not _SAVE_NAME.fullmatch(stem) or stem.startswith(".") or ".." in stem:
        raise InputError(
            f"cannot save as {stem!r}: give a plain file name of letters, digits, '.', '_' "
            "and '-' (up to 100, not starting with a dot), without a folder or extension"
        )
    return stem


def inside(folder: str, relative: str) -> str:
    """``relative`` resolved (links followed) inside ``folder``, or OutsideFolder."""
    if "\x00" in relative:
        raise InputError("the path contains a NUL byte; give a plain file name")
    parts = relative.replace("\\", "/").split("/")
    if not relative or os.path.isabs(relative) or relative.startswith("~") or ".." in parts:
        raise OutsideFolder(
            f"path outside the session folder: {relative!r}; give a file name relative to "
            "the session's folder, without '..'"
        )
    return contained(folder, os.path.join(folder, relative))


def contained(folder: str, path: str) -> str:
    """``path`` with every link resolved, if that stays inside ``folder``; else OutsideFolder
    (a link inside the folder may point anywhere)."""
    target = os.path.realpath(path)
    if os.path.commonpath([folder, target]) != folder or target == folder:
        raise OutsideFolder(
            f"path outside the session folder: {os.path.relpath(path, folder)!r} leads to "
            f"{target}; give a file name inside the session's folder"
        )
    return target


def write(work: Callable[[str], object], target: str) -> None:
    """``work(target)``, an OSError becoming an InputError that names the file."""
    try:
        work(target)
    except OSError as exc:
        raise InputError(
            f"{target}: cannot write the file ({exc.strerror or exc}); check that the folder "
            "exists and is writable"
        ) from None
