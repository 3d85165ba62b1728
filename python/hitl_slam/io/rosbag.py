"""ROS bags into a :class:`Map`: ROS 1 ``.bag``, ROS 2 ``.db3`` / ``.mcap`` files or a ROS 2 bag
directory (with ``metadata.yaml``), read without ROS by the ``rosbags`` library (the ``[ros]``
extra). Laser scans with odometry from ``/tf`` or ``nav_msgs/Odometry``, and the SLAM's own
trajectory when ``/tf`` has ``map -> odom``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.extras import require
from hitl_slam.geometry import compose_rows
from hitl_slam.io.bag_scans import _points, _Scan
from hitl_slam.io.textfile import MAX_COORDINATE, PathLike, check_regular_file, sci
from hitl_slam.io.tf_tree import (
    _checked,
    _frame_name,
    _interpolate,
    _se2,
    _seconds,
    _series,
    _stamps_array,
    _Transforms,
    _Tree,
)
from hitl_slam.map import Map

__all__ = ["BAG_EXTENSIONS", "DEFAULT_BAG_OPTIONS", "BagOptions", "is_rosbag", "read_rosbag"]

_log = logging.getLogger(__name__)

BAG_EXTENSIONS = (".bag", ".db3", ".mcap")
"""ROS bag files :func:`read_rosbag` reads; a ROS 2 bag directory (``metadata.yaml``) too."""

_LASER_SCAN = "sensor_msgs/msg/LaserScan"
_ODOMETRY = "nav_msgs/msg/Odometry"
_TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
_TF, _TF_STATIC = "/tf", "/tf_static"
_MAGIC = {
    ".bag": (b"#ROSBAG V2.0\n", "a ROS 1 bag (format 2.0)"),
    ".db3": (b"SQLite format 3\x00", "a ROS 2 bag (SQLite 3)"),
    ".mcap": (b"\x89MCAP0\r\n", "an MCAP file"),
}
_DAMAGED = (
    "the bag may be truncated (a recording that did not end cleanly) or damaged; "
    "re-record or repair it (`rosbag reindex` for ROS 1, `ros2 bag reindex` for ROS 2)"
)


@dataclass(frozen=True)
class BagOptions:
    """What to read from a bag: topic and frame names (ROS conventions by default).

    Attributes:
        scan_topic: the ``sensor_msgs/LaserScan`` topic; None: the bag's only one.
        odom_topic: a ``nav_msgs/Odometry`` topic to take the odometry from; None: ``/tf``
            (``odom_frame -> base_frame``) when it has that transform, else the bag's only
            Odometry topic.
        odom_frame, base_frame: the odometry frame and the robot's frame (REP 105).
        map_frame: the SLAM's map frame: when ``/tf`` has ``map_frame -> odom_frame``, the map's
            poses are the SLAM's trajectory ``map_frame -> base_frame``; None or "": always the
            odometry.
    """

    scan_topic: str | None = None
    odom_topic: str | None = None
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    map_frame: str | None = "map"


DEFAULT_BAG_OPTIONS = BagOptions()


def is_rosbag(path: PathLike) -> bool:
    """Whether ``path`` names a ROS bag by its form: a ``.bag``, ``.db3`` or ``.mcap`` file, or a
    directory with a ``metadata.yaml`` (a ROS 2 bag)."""
    name = os.fspath(path)
    if os.path.splitext(name)[1].lower() in BAG_EXTENSIONS:
        return True
    return os.path.isdir(name) and os.path.isfile(os.path.join(name, "metadata.yaml"))


# ---------------------------------------------------------------------------------------------
# What the bag holds, as plain arrays


@dataclass
class _Contents:
    ros_version: int
    storage: str
    scan_topic: str
    scans: list[_Scan]
    tf: _Transforms
    tf_static: _Transforms
    odometry: _Transforms | None  # the Odometry topic's poses, when one is read
    odometry_topics: list[str]


def _stamp(header_stamp: Any, bag_time: int) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time``; the bag's record time when it is zero (a
    driver that does not stamp its messages)."""
    ns = int(header_stamp.sec) * 1_000_000_000 + int(header_stamp.nanosec)
    return int(bag_time) if ns == 0 else ns


def _pose_values(position: Any, orientation: Any) -> tuple[float, ...]:
    return (
        float(position.x),
        float(position.y),
        float(position.z),
        float(orientation.x),
        float(orientation.y),
        float(orientation.z),
        float(orientation.w),
    )


# ---------------------------------------------------------------------------------------------
# The reader


def read_rosbag(
    path: PathLike,
    options: BagOptions = DEFAULT_BAG_OPTIONS,
    *,
    max_range: float | None = None,
    config: Config = DEFAULT,
) -> Map:
    """Read a ROS bag into a :class:`Map` with one pose per laser scan.

    Scans: the ``sensor_msgs/LaserScan`` topic (``options.scan_topic``, or the bag's only one).
    As the message definition says, beam ``i`` is at ``angle_min + i * angle_increment`` and a
    range is a point when it is finite and within ``[range_min, range_max]`` (NaN, +inf and -inf,
    REP 117's "no return" and "too close", are not points, nor is a range <= 0); ``max_range``
    (m) lowers ``range_max`` for every scan. Points are in the robot frame (``base_frame``): the
    laser's mounting (``base_frame -> the scan's frame_id``, from ``/tf_static``, else from
    ``/tf`` taken as rigid) moves them there, in 3D (an upside-down laser is mirrored), then they
    are projected on the plane. Intensities, when a scan has one per range, are kept per point in
    ``map.metadata["intensities"]`` (NaN for scans without); an empty array means none.

    Poses: the robot's (``base_frame``) at each scan's ``header.stamp``. Odometry comes from
    ``/tf`` (``odom_frame -> base_frame``, through any chain of frames) or from a
    ``nav_msgs/Odometry`` topic (see :class:`BagOptions`), interpolated at each stamp in SE(2):
    linearly in x and y, along the shorter arc in heading; a scan outside the odometry's time
    span is dropped (``metadata["scans_dropped"]``). When ``/tf`` also has ``map_frame ->
    odom_frame`` (slam_toolbox, Cartographer, gmapping, AMCL), the poses are the SLAM's
    trajectory ``map_frame -> base_frame`` at each stamp, and ``metadata["odometry_poses"]``
    keeps the odometry. Either way the chain edges are the odometry's consecutive steps with the
    motion-model information (docs/ALGORITHM.md §1.3), as for a CARMEN log. Timestamps are the
    scans' stamps in seconds.

    Frames: the map's robot frame is ``base_frame``, not the laser's: where the laser is mounted
    off the base's origin (``metadata["laser_mount"]``, ``(x, y, yaw)``), the sensor is there,
    not at the pose's position.

    Raises:
        MissingExtra: ``rosbags`` (the ``[ros]`` extra) is not installed.
        InputError: ``{path}: what; what to do``: not a bag, a truncated or damaged bag, no
            LaserScan topic or several (the message lists them), a topic of another type, no
            odometry, a frame missing from the transforms, a bad number in a message.
    """
    name = os.fspath(path)
    _check_options(name, options, max_range)
    storage = _check_form(name)
    require("ros", f"{name}: reading a ROS bag")
    contents = _read_contents(name, storage, options)
    return _build_map(name, contents, options, max_range, config)


def _check_options(name: str, options: BagOptions, max_range: float | None) -> None:
    if not isinstance(options, BagOptions):
        raise InputError(f"{name}: options must be a BagOptions, got {options!r}")
    if max_range is not None and not (
        isinstance(max_range, int | float) and math.isfinite(max_range) and max_range > 0
    ):
        raise InputError(
            f"{name}: max_range must be a finite number > 0 (metres), got {max_range!r}; give "
            "the laser's maximum range"
        )
    if max_range is not None and max_range > MAX_COORDINATE:
        raise InputError(
            f"{name}: max_range {max_range!r} is beyond {sci(MAX_COORDINATE)} m, larger than "
            "any laser reaches; give the laser's maximum range in metres"
        )
    for label, frame in (("odom_frame", options.odom_frame), ("base_frame", options.base_frame)):
        if not _frame_name(frame):
            raise InputError(f"{name}: {label} is empty; give the frame's name, e.g. 'odom'")
    if _frame_name(options.odom_frame) == _frame_name(options.base_frame):
        raise InputError(
            f"{name}: odom_frame and base_frame are both {options.odom_frame!r}; the odometry "
            "is the pose of the robot's frame in the odometry frame: give two frames"
        )
    map_frame = _frame_name(options.map_frame or "")
    if map_frame in (_frame_name(options.odom_frame), _frame_name(options.base_frame)):
        raise InputError(
            f"{name}: map_frame {options.map_frame!r} is also the odometry's or the robot's "
            "frame; give the SLAM's map frame, or '' to load the odometry"
        )


def _check_form(name: str) -> str:
    """The storage kind (``bag``, ``sqlite3``, ``mcap``, ``directory``) after checking that the
    file is what its name says, before the library opens it."""
    if os.path.isdir(name):
        if not os.path.isfile(os.path.join(name, "metadata.yaml")):
            raise InputError(
                f"{name}: a directory without metadata.yaml is not a ROS 2 bag; give the bag's "
                "directory (the one holding metadata.yaml) or one of its .db3/.mcap files"
            )
        return "directory"
    check_regular_file(name)
    extension = os.path.splitext(name)[1].lower()
    if extension not in _MAGIC:
        raise InputError(
            f"{name}: not a ROS bag name; give a .bag (ROS 1), .db3 or .mcap file (ROS 2) or a "
            "ROS 2 bag directory"
        )
    magic, what = _MAGIC[extension]
    try:
        with open(name, "rb") as f:
            head = f.read(len(magic))
    except OSError as exc:
        raise InputError(f"{name}: cannot be read ({exc}); check the file") from None
    if not head:
        raise InputError(f"{name}: empty file; give a recorded bag")
    if head != magic:
        raise InputError(
            f"{name}: not {what}: it does not start as one ({head!r}); give a bag recorded by "
            "rosbag/ros2 bag, or check the file's extension"
        )
    return {".bag": "bag", ".db3": "sqlite3", ".mcap": "mcap"}[extension]


def _topic_list(topics: dict[str, str]) -> str:
    shown = [f"{t} ({k})" for t, k in sorted(topics.items())]
    if len(shown) > 12:
        shown = [*shown[:12], f"... {len(shown) - 12} more"]
    return ", ".join(shown) if shown else "none"


def _pick_scan_topic(name: str, topics: dict[str, str], wanted: str | None) -> str:
    scans = sorted(t for t, kind in topics.items() if kind == _LASER_SCAN)
    if wanted is not None:
        if wanted not in topics:
            raise InputError(
                f"{name}: no topic {wanted!r} in the bag; its LaserScan topics: "
                f"{', '.join(scans) or 'none'}; pass one of them as --scan-topic"
            )
        if topics[wanted] != _LASER_SCAN:
            raise InputError(
                f"{name}: topic {wanted} is {topics[wanted]}, not sensor_msgs/LaserScan; pass "
                f"one of its LaserScan topics as --scan-topic: {', '.join(scans) or 'none'}"
            )
        return wanted
    if not scans:
        raise InputError(
            f"{name}: no sensor_msgs/LaserScan topic in the bag (topics: {_topic_list(topics)}); "
            "a map needs 2D laser scans: record the laser's scan topic (a 3D point cloud must "
            "first be turned into LaserScan, e.g. by pointcloud_to_laserscan)"
        )
    if len(scans) > 1:
        raise InputError(
            f"{name}: {len(scans)} LaserScan topics ({', '.join(scans)}); pick one with "
            "--scan-topic (scan_topic=)"
        )
    return scans[0]


def _pick_odom_topic(name: str, topics: dict[str, str], wanted: str | None) -> str | None:
    if wanted is None:
        return None
    odometry = sorted(t for t, kind in topics.items() if kind == _ODOMETRY)
    if wanted not in topics:
        raise InputError(
            f"{name}: no topic {wanted!r} in the bag; its nav_msgs/Odometry topics: "
            f"{', '.join(odometry) or 'none'}; pass one of them as --odom-topic"
        )
    if topics[wanted] != _ODOMETRY:
        raise InputError(
            f"{name}: topic {wanted} is {topics[wanted]}, not nav_msgs/Odometry; pass one of "
            f"its Odometry topics as --odom-topic: {', '.join(odometry) or 'none'}"
        )
    return wanted


def _read_contents(name: str, storage: str, options: BagOptions) -> _Contents:
    """Every message the map needs, decoded into plain values. The library's own exceptions
    (any kind: it does not reduce a damaged file to one) become one InputError."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    where = "the bag"
    try:
        # ROS 2 bags may carry no message definitions (before Iron): the standard ones then.
        with AnyReader([Path(name)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            topics = {
                topic: info.msgtype
                for topic, info in reader.topics.items()
                if isinstance(info.msgtype, str)
            }
            scan_topic = _pick_scan_topic(name, topics, options.scan_topic)
            odom_topic = _pick_odom_topic(name, topics, options.odom_topic)
            odometry_topics = sorted(t for t, kind in topics.items() if kind == _ODOMETRY)
            if odom_topic is None and len(odometry_topics) == 1:
                odom_topic = odometry_topics[0]  # read in case /tf has no odometry
            contents = _Contents(
                ros_version=2 if reader.is2 else 1,
                storage=storage,
                scan_topic=scan_topic,
                scans=[],
                tf=_Transforms(_TF),
                tf_static=_Transforms(_TF_STATIC),
                odometry=None if odom_topic is None else _Transforms(f"topic {odom_topic}"),
                odometry_topics=odometry_topics,
            )
            handlers: dict[str, Callable[[Any, int], None]] = {
                scan_topic: lambda m, t: contents.scans.append(_scan_of(m, t))
            }
            for topic, tf in ((_TF, contents.tf), (_TF_STATIC, contents.tf_static)):
                if topics.get(topic) in _TF_TYPES:
                    handlers[topic] = _tf_handler(tf)
            if odom_topic is not None and contents.odometry is not None:
                handlers[odom_topic] = _odometry_handler(contents.odometry)
            connections = [c for c in reader.connections if c.topic in handlers]
            counts: dict[str, int] = {}
            where = "the bag's first message"
            for connection, bag_time, raw in reader.messages(connections=connections):
                topic = connection.topic
                counts[topic] = counts.get(topic, 0) + 1
                where = f"message {counts[topic]} on {topic}"
                handlers[topic](reader.deserialize(raw, connection.msgtype), bag_time)
                where = f"the message after {where}"
    except InputError:
        raise
    except Exception as exc:
        detail = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise InputError(
            f"{name}: cannot read {where} ({type(exc).__name__}: {detail}); {_DAMAGED}"
        ) from None
    return contents


def _scan_of(message: Any, bag_time: int) -> _Scan:
    with np.errstate(invalid="ignore"):  # a signalling NaN sets "invalid" when widened
        ranges = np.asarray(message.ranges, dtype=np.float64).reshape(-1)
        intensities = np.asarray(message.intensities, dtype=np.float64).reshape(-1)
    return _Scan(
        stamp=_stamp(message.header.stamp, bag_time),
        frame=_frame_name(str(message.header.frame_id)),
        angle_min=float(message.angle_min),
        angle_increment=float(message.angle_increment),
        range_min=float(message.range_min),
        range_max=float(message.range_max),
        ranges=ranges,
        intensities=intensities,
    )


def _tf_handler(into: _Transforms) -> Callable[[Any, int], None]:
    def handle(message: Any, bag_time: int) -> None:
        for transform in message.transforms:
            into.add(
                _stamp(transform.header.stamp, bag_time),
                str(transform.header.frame_id),
                str(transform.child_frame_id),
                _pose_values(transform.transform.translation, transform.transform.rotation),
            )

    return handle


def _odometry_handler(into: _Transforms) -> Callable[[Any, int], None]:
    def handle(message: Any, bag_time: int) -> None:
        into.add(
            _stamp(message.header.stamp, bag_time),
            str(message.header.frame_id),
            str(message.child_frame_id),
            _pose_values(message.pose.pose.position, message.pose.pose.orientation),
        )

    return handle


# ---------------------------------------------------------------------------------------------
# The map


def _build_map(
    name: str,
    contents: _Contents,
    options: BagOptions,
    max_range: float | None,
    config: Config,
) -> Map:
    scans = contents.scans  # in the bag's (record) order, as CARMEN keeps the log's
    if not scans:
        raise InputError(
            f"{name}: the topic {contents.scan_topic} has no messages; give a bag with laser "
            "scans recorded"
        )
    tree = _Tree(
        name,
        _series(name, contents.tf, static=False),
        _series(name, contents.tf_static, static=True),
    )
    odom_frame, base_frame = _frame_name(options.odom_frame), _frame_name(options.base_frame)
    when = _stamps_array(
        name, f"topic {contents.scan_topic}", np.array([s.stamp for s in scans], dtype=object)
    )
    odometry, valid, odometry_source = _odometry(name, contents, options, tree, when)
    map_frame = _frame_name(options.map_frame or "")
    slam: NDArray[np.float64] | None = None
    if map_frame and map_frame in tree.frames and tree.connects(map_frame, odom_frame):
        map_odom, ok = tree.se2(map_frame, odom_frame, when)
        slam = compose_rows(map_odom, odometry)
        valid &= ok
    kept = np.flatnonzero(valid)
    if kept.size == 0:
        raise InputError(
            f"{name}: no scan of {contents.scan_topic} lies within the time span of the "
            f"odometry ({odometry_source}"
            + (f" and {map_frame} -> {odom_frame}" if slam is not None else "")
            + "); the scans' stamps and the transforms' do not overlap: check that they come "
            "from one clock (use_sim_time)"
        )
    poses = (odometry if slam is None else slam)[kept]
    if not (
        np.all(np.abs(poses[:, :2]) <= MAX_COORDINATE)
        and np.all(np.abs(odometry[kept, :2]) <= MAX_COORDINATE)
    ):
        raise InputError(
            f"{name}: a robot pose beyond {sci(MAX_COORDINATE)} m from the origin; the "
            "transforms are damaged: re-record the bag"
        )
    used = [scans[k] for k in kept]
    points, counts, intensities, mounts = _points(name, contents, used, tree, base_frame, max_range)
    split = np.split(points, np.cumsum(counts)[:-1])
    stamps = np.array([_seconds(s.stamp) for s in used])
    result = Map.from_poses_and_scans(
        odometry[kept], split, timestamps=stamps, config=config, name=_stem(name), source=name
    )
    if slam is not None:
        result = dataclasses.replace(result, poses=poses)
    dropped = len(scans) - len(kept)
    if dropped:
        _log.warning(
            "%s: %d of %d scans of %s dropped: before the first or after the last odometry (%s) "
            "message, where it cannot place them",
            name,
            dropped,
            len(scans),
            contents.scan_topic,
            odometry_source,
        )
    result.metadata.update(
        {
            "format": "rosbag",
            "ros_version": contents.ros_version,
            "storage": contents.storage,
            "scan_topic": contents.scan_topic,
            "odometry": odometry_source,
            "trajectory": (
                f"slam ({map_frame} -> {base_frame})"
                if slam is not None
                else f"odometry ({odom_frame} -> {base_frame})"
            ),
            "pose_frame": base_frame,
            "laser_frames": sorted(mounts),
            "laser_mount": next(iter(mounts.values())) if len(mounts) == 1 else mounts,
            "max_range": max_range,
            "scans_in_bag": len(scans),
            "scans_dropped": dropped,
        }
    )
    if slam is not None:
        result.metadata["odometry_poses"] = odometry[kept]
    if intensities is not None:
        result.metadata["intensities"] = intensities
    return result


def _stem(name: str) -> str:
    base = os.path.basename(os.path.normpath(name))
    root, extension = os.path.splitext(base)
    return root if extension.lower() in BAG_EXTENSIONS else base


def _odometry(
    name: str,
    contents: _Contents,
    options: BagOptions,
    tree: _Tree,
    when: NDArray[np.int64],
) -> tuple[NDArray[np.float64], NDArray[np.bool_], str]:
    """``T_odom_base`` at every scan stamp, where it is defined, and where it came from."""
    odom_frame, base_frame = _frame_name(options.odom_frame), _frame_name(options.base_frame)
    if options.odom_topic is None and tree.connects(odom_frame, base_frame):
        poses, valid = tree.se2(odom_frame, base_frame, when)
        return poses, valid, f"/tf {odom_frame} -> {base_frame}"
    records = contents.odometry
    if records is None or (options.odom_topic is None and len(contents.odometry_topics) > 1):
        raise _no_odometry(name, contents, options, tree)
    topic = records.where
    if not records.stamps:
        raise InputError(
            f"{name}: {topic} has no messages and /tf has no {odom_frame} -> {base_frame}; "
            "record the odometry, or pass --odom-topic"
        )
    values = _checked(name, records)
    child = {c for c in records.children}
    if len(child) > 1:
        raise InputError(
            f"{name}: {topic} gives poses of several frames ({', '.join(sorted(child))}); "
            "give the topic of one robot's odometry with --odom-topic"
        )
    frame = child.pop() or base_frame
    times = _stamps_array(name, topic, np.array(records.stamps, dtype=object))
    order = np.argsort(times, kind="stable")
    times, values = times[order], values[order]
    last = np.append(times[1:] != times[:-1], True)
    poses, valid = _interpolate(times[last], _se2(values[last]), when)
    if frame != base_frame:
        if not tree.connects(frame, base_frame):
            raise InputError(
                f"{name}: {topic} gives the pose of {frame!r}, and the transforms do not "
                f"connect it to {base_frame!r}; pass --base-frame {frame}, or record the "
                "robot's static transforms (/tf_static)"
            )
        mount, ok = tree.se2(frame, base_frame, when)
        poses, valid = compose_rows(poses, mount), valid & ok
    return poses, valid, topic


def _no_odometry(name: str, contents: _Contents, options: BagOptions, tree: _Tree) -> InputError:
    odom_frame, base_frame = _frame_name(options.odom_frame), _frame_name(options.base_frame)
    if len(contents.odometry_topics) > 1:
        return InputError(
            f"{name}: /tf has no {odom_frame} -> {base_frame} and there are "
            f"{len(contents.odometry_topics)} nav_msgs/Odometry topics "
            f"({', '.join(contents.odometry_topics)}); pick one with --odom-topic"
        )
    frames = sorted(tree.frames)
    shown = ", ".join(frames[:12]) + (f", ... {len(frames) - 12} more" if len(frames) > 12 else "")
    return InputError(
        f"{name}: no odometry: no nav_msgs/Odometry topic, and /tf has no {odom_frame} -> "
        f"{base_frame} (its frames: {shown or 'none'}); record the odometry (/odom or /tf), or "
        "name the robot's frames with --odom-frame and --base-frame"
    )
