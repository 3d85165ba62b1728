"""Which poses a served session holds (the front end's map, a bag's own SLAM trajectory, or the
input's own poses as they are) and whether that is what ``hitl-slam serve`` was asked for: a
session beside a raw log is reopened only when the two agree, so that a session of one kind is
never served as the other.

What is asked (``front_end``): True (``--slam``) the front end's map; False (``--no-slam``) the
input's own poses (a bag's own SLAM trajectory when it has one); None (neither) a bag's own SLAM
trajectory when it has one, else the front end's map.
"""

from __future__ import annotations

import enum
from pathlib import Path

from hitl_slam.errors import InputError
from hitl_slam.io.rosbag import is_rosbag
from hitl_slam.map import Map
from hitl_slam.own_slam import REPLACED, trajectory_of
from hitl_slam.session import Session

__all__ = ["FRONT_END_MARK", "Held", "check_session_of", "describe", "held"]

FRONT_END_MARK = "hitl-slam"
"""``map.metadata["front_end"]`` of a map the front end built."""


class Held(enum.Enum):
    """Which poses a map holds."""

    FRONT_END = "front_end"  # the front end's map (with its loop closures)
    OWN_SLAM = "own_slam"  # a bag's own SLAM trajectory (map -> base_link)
    AS_INPUT = "as_input"  # the input's own poses as they are (logged, odometry, a map's)


def held(m: Map) -> Held:
    """Which poses ``m`` holds."""
    if m.metadata.get("front_end") == FRONT_END_MARK or m.name.endswith("(hitl-slam front end)"):
        return Held.FRONT_END
    # The bag reader's word on the poses, which the session file keeps with the map.
    if trajectory_of(m).startswith("slam ("):
        return Held.OWN_SLAM
    return Held.AS_INPUT


def describe(m: Map) -> str:
    """What ``m``'s poses are, for the user: "the front end's map", "the bag's own SLAM
    trajectory (map -> base_link)", "the log's own poses", ..."""
    kind = held(m)
    if kind is Held.FRONT_END:
        replaced = m.metadata.get(REPLACED)
        return "the front end's map" + (
            f", in place of the bag's own trajectory ({replaced.removeprefix('slam (')}"
            if isinstance(replaced, str) and replaced
            else ""
        )
    if kind is Held.OWN_SLAM:
        return f"the bag's own SLAM trajectory ({trajectory_of(m).removeprefix('slam (')}"
    what = m.metadata.get("format")
    if what == "rosbag":
        return f"the bag's {trajectory_of(m) or 'odometry'}, as recorded"
    if what == "carmen":
        return "the log's own poses, as logged"
    return "the map's own poses"


def check_session_of(
    session: Session,
    path: Path,
    source: Path,
    *,
    raw: bool,
    front_end: bool | None,
    map_frame: str | None,
) -> None:
    """Refuses a session beside ``source`` that is not its session as asked for: made from a
    file of another name, or (``raw``: ``source`` is a raw log) holding other poses than
    ``front_end`` asks for (see the module). ``map_frame``: the bag option (None or "": a bag's
    SLAM trajectory is not read, so the default is the front end's map, as for a CARMEN log).

    Raises:
        InputError: which poses the session holds, how to serve it, and how to start over.
    """
    stored = session.input_map.source
    if stored is not None and Path(stored).name != source.name:
        raise InputError(
            f"{path}: this session was made from {Path(stored).name}, not {source.name}; "
            f"serve {path} itself, or move it away to start a session of {source.name}"
        )
    if not raw:
        return
    m = session.input_map
    kind = held(m)
    bag = is_rosbag(source)
    slam_first = bag and bool(map_frame)  # a bag's own SLAM trajectory comes first, if it has one
    if front_end is True:
        if kind is Held.FRONT_END:
            return
        if kind is Held.OWN_SLAM:
            raise InputError(
                f"{path}: this session holds {describe(m)}, not the front end's map; serve it "
                "without --slam, or move it away to rebuild the map with the front end"
            )
        raise InputError(
            f"{path}: this session holds the log's own poses (made with --no-slam); serve it "
            "with --no-slam, or move it away to run the front end over the log"
        )
    if front_end is False:
        if kind is Held.FRONT_END:
            again = "with --slam" if m.metadata.get(REPLACED) else "without --no-slam"
            raise InputError(
                f"{path}: this session holds the front end's map of the log; serve it {again}, "
                "or move it away to serve the log's own poses"
            )
        if kind is Held.OWN_SLAM and not map_frame:
            raise InputError(
                f"{path}: this session holds {describe(m)}, and --map-frame '' asks for the "
                "odometry; drop --map-frame '', or move the session away to serve the odometry"
            )
        return
    # Neither flag: a bag's own SLAM trajectory when it has one, else the front end's map.
    if kind is Held.OWN_SLAM:
        if slam_first:
            return
        raise InputError(
            f"{path}: this session holds {describe(m)}, and --map-frame '' asks for the front "
            "end's map from the odometry; drop --map-frame '', or move the session away"
        )
    if kind is Held.FRONT_END:
        if slam_first and m.metadata.get(REPLACED):
            raise InputError(
                f"{path}: this session holds the front end's map of the bag (made with --slam), "
                "not the bag's own SLAM trajectory, which comes first without --slam; serve it "
                "with --slam, or move it away to serve the bag's own trajectory"
            )
        return
    raise InputError(
        f"{path}: this session holds the log's own poses (made with --no-slam); serve it "
        "with --no-slam, or move it away to run the front end over the log"
    )
