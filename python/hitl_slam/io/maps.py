"""Load a map with observations from any supported file, choosing the reader by extension:
``.covars`` (the original tool's format), CARMEN logs (``.clf``/``.log``, optionally ``.gz`` or
``.bz2``), or a session (``.hitl``, its current map).
"""

from __future__ import annotations

import os

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.io.textfile import check_regular_file
from hitl_slam.map import Map

__all__ = ["MAP_EXTENSIONS", "load_map"]

MAP_EXTENSIONS = (".covars", ".clf", ".log", ".hitl")
"""What :func:`load_map` reads; CARMEN logs may also end in ``.gz`` or ``.bz2``."""

_COMPRESSED = (".gz", ".bz2")
_POSE_GRAPHS = (".g2o", ".graph")


def _extensions(name: str) -> tuple[str, str]:
    """(format extension, compression extension or "")."""
    base, extension = os.path.splitext(name.lower())
    if extension in _COMPRESSED:
        return os.path.splitext(base)[1], extension
    return extension, ""


def load_map(
    path: str | os.PathLike[str], config: Config = DEFAULT, *, max_range: float | None = None
) -> Map:
    """The map in ``path``: ``.covars``, ``.clf``/``.log`` (+ ``.gz``/``.bz2``), or ``.hitl``
    (the session's current poses; ``config`` does not apply, the session has its own).

    ``max_range`` (m, CARMEN logs only) overrides the laser's maximum range: readings at or
    beyond it are no-returns, not points. Without it the log's ``PARAM`` is used, or the maximum
    is inferred from readings piled at the largest value (``map.metadata["max_range_source"]``
    says which).

    Raises:
        InputError: an unsupported extension (the message lists the supported ones), or any
            problem the format's reader finds.
    """
    name = os.fspath(path)
    extension, compression = _extensions(name)
    if extension in (".clf", ".log"):
        from hitl_slam.io.carmen import read_carmen

        return read_carmen(name, config=config, max_range=max_range)
    if max_range is not None:
        raise InputError(
            f"{name}: --max-range applies to CARMEN laser logs (.clf/.log); this map's points "
            "are already filtered"
        )
    if not compression and extension == ".covars":
        from hitl_slam.io.covars import read_covars

        return read_covars(name, config)
    if not compression and extension == ".hitl":
        from hitl_slam.session import Session

        check_regular_file(name, missing_ok=True)
        with Session.open(name) as session:
            return session.current_map()
    supported = ", ".join(MAP_EXTENSIONS)
    shown = extension + compression or "no extension"
    if extension in _POSE_GRAPHS:
        raise InputError(
            f"{name}: a pose graph ({extension}) has no laser observations to draw on; "
            f"give a map with observations ({supported}), or optimize it with `hitl-slam solve`"
        )
    raise InputError(
        f"{name}: cannot read a map from {shown!r}; supported: {supported} "
        "(CARMEN logs also as .gz or .bz2)"
    )
