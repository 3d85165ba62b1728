"""Load a map with observations from any supported file, choosing the reader by extension:
``.covars`` (the original tool's format), CARMEN logs (``.clf``/``.log``, optionally ``.gz`` or
``.bz2``), ROS bags (``.bag``, ``.db3``, ``.mcap``, or a ROS 2 bag directory with its
``metadata.yaml``), or a session (``.hitl``, its current map).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.io.rosbag import BAG_EXTENSIONS, DEFAULT_BAG_OPTIONS, BagOptions, is_rosbag
from hitl_slam.io.textfile import check_regular_file
from hitl_slam.map import Map

__all__ = ["MAP_EXTENSIONS", "load_map", "looks_like_carmen", "map_kind"]

MAP_EXTENSIONS = (".covars", ".clf", ".log", *BAG_EXTENSIONS, ".hitl")
"""What :func:`load_map` reads; CARMEN logs may also end in ``.gz`` or ``.bz2``, and a ROS 2 bag
may be its directory."""

_log = logging.getLogger(__name__)
_COMPRESSED = (".gz", ".bz2")
_POSE_GRAPHS = (".g2o", ".graph")


def _extensions(name: str) -> tuple[str, str]:
    """(format extension, compression extension or "")."""
    base, extension = os.path.splitext(name.lower())
    if extension in _COMPRESSED:
        return os.path.splitext(base)[1], extension
    return extension, ""


def load_map(
    path: str | os.PathLike[str],
    config: Config = DEFAULT,
    *,
    max_range: float | None = None,
    bag: BagOptions | None = None,
) -> Map:
    """The map in ``path``: ``.covars``, ``.clf``/``.log`` (+ ``.gz``/``.bz2``), a ROS bag
    (``.bag``, ``.db3``, ``.mcap`` or a ROS 2 bag directory; :func:`~hitl_slam.io.rosbag.
    read_rosbag`, which needs the ``[ros]`` extra), or ``.hitl`` (the session's current poses;
    ``config`` does not apply, the session has its own).

    ``max_range`` (m, CARMEN logs and ROS bags only) overrides the laser's maximum range: readings
    at or beyond it are no-returns, not points. Without it a CARMEN log's ``PARAM`` is used, or
    the maximum is inferred from readings piled at the largest value
    (``map.metadata["max_range_source"]`` says which); a bag's scans carry their ``range_max``.
    ``bag`` (ROS bags only): the topics and frames to read (default: the bag's only LaserScan
    topic, ``odom``, ``base_link``, ``map``).

    Raises:
        InputError: an unsupported extension (the message lists the supported ones), or any
            problem the format's reader finds.
    """
    name = os.fspath(path)
    extension, compression = _extensions(name)
    if not compression and is_rosbag(name):
        from hitl_slam.io.rosbag import read_rosbag

        return _warn_if_empty(
            read_rosbag(name, bag or DEFAULT_BAG_OPTIONS, max_range=max_range, config=config)
        )
    if bag is not None and bag != DEFAULT_BAG_OPTIONS:
        raise InputError(
            f"{name}: topic and frame options (--scan-topic, --odom-topic, --odom-frame, "
            "--base-frame, --map-frame) apply to ROS bags (.bag, .db3, .mcap); this is not one"
        )
    if extension in (".clf", ".log"):
        from hitl_slam.io.carmen import read_carmen

        return _warn_if_empty(read_carmen(name, config=config, max_range=max_range))
    if max_range is not None:
        raise InputError(
            f"{name}: --max-range applies to laser logs (CARMEN .clf/.log, ROS bags); this "
            "map's points are already filtered"
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
        "(CARMEN logs also as .gz or .bz2; a ROS 2 bag also as its directory)"
    )


def map_kind(path: str | os.PathLike[str]) -> str | None:
    """What kind of map ``path`` names by its extension (one of :data:`MAP_EXTENSIONS`, also
    under ``.gz``/``.bz2``), as words for a message: ``"a CARMEN log"``,
    ``"a ROS bag"``, ``"a .covars map"`` or ``"a session"``; None for anything else (a pose
    graph, no extension). Only the name is looked at."""
    extension, _ = _extensions(Path(os.fspath(path)).name)
    if extension not in MAP_EXTENSIONS:
        return None
    if extension in BAG_EXTENSIONS:
        return "a ROS bag"
    return {".covars": "a .covars map", ".hitl": "a session"}.get(extension, "a CARMEN log")


_CARMEN_WORDS = (b"PARAM", b"ODOM", b"FLASER", b"RLASER", b"ROBOTLASER1", b"RAWLASER", b"TRUEPOS")


def looks_like_carmen(path: str | os.PathLike[str]) -> bool:
    """Whether the first data line of the (uncompressed) file ``path`` starts with a CARMEN
    message name, whatever its extension; False when it cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return False
    for line in head.splitlines():
        words = line.split()
        if words and not words[0].startswith(b"#"):
            return words[0] in _CARMEN_WORDS
    return False


def _warn_if_empty(laser_map: Map) -> Map:
    """A laser log whose scans have no usable point is read (its poses may still be wanted) but
    said loudly: a map without points draws nothing, matches nothing and scores nothing."""
    n = laser_map.num_poses
    empty = int(np.count_nonzero(np.diff(laser_map.offsets) == 0))
    where = laser_map.source or laser_map.name
    if laser_map.num_points == 0:
        _log.warning(
            "%s: none of the %d scans has a usable point (every reading is a no-return, NaN, "
            "or outside the laser's range); check the laser's range fields or --max-range",
            where,
            n,
        )
    elif 2 * empty > n:
        _log.warning(
            "%s: %d of %d scans have no usable point (every reading a no-return, NaN, or outside "
            "the laser's range); check the laser's range fields or --max-range",
            where,
            empty,
            n,
        )
    return laser_map
