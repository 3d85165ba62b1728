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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.extras import require
from hitl_slam.geometry import between, compose_rows, invert, wrap
from hitl_slam.io.textfile import (
    MAX_ANGLE,
    MAX_COORDINATE,
    PathLike,
    beam_spacing_problem,
    check_regular_file,
    sci,
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
_STAMP_LIMIT = 2**62  # [ns] about 146 years: differences of two stamps stay within int64
_MIN_QUATERNION_NORM = 1e-6
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
class _Scan:
    stamp: int  # [ns]
    frame: str
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: NDArray[np.float64]
    intensities: NDArray[np.float64]  # empty: none


@dataclass
class _Transforms:
    """TransformStamped-like records of one source: ``parent -> child`` at ``stamp``."""

    where: str  # e.g. "/tf" or "topic /odom", for messages
    stamps: list[int] = field(default_factory=list)
    parents: list[str] = field(default_factory=list)
    children: list[str] = field(default_factory=list)
    values: list[tuple[float, ...]] = field(default_factory=list)  # x y z qx qy qz qw

    def add(self, stamp: int, parent: str, child: str, values: tuple[float, ...]) -> None:
        self.stamps.append(stamp)
        self.parents.append(_frame_name(parent))
        self.children.append(_frame_name(child))
        self.values.append(values)


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


def _frame_name(name: str) -> str:
    """tf2 ignores a leading slash (ROS 1's ``/odom`` is ``odom``)."""
    return name.lstrip("/")


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
# Transforms: checked arrays, the frame tree, lookups at the scans' stamps


@dataclass
class _Series:
    """One edge ``parent -> child``: its samples sorted by stamp (one per stamp, the last)."""

    parent: str
    stamps: NDArray[np.int64]
    se2: NDArray[np.float64]  # (S, 3)
    matrix: NDArray[np.float64]  # (4, 4): the first sample in 3D, for rigid mounts
    static: bool

    def at(self, when: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """SE(2) at ``when`` (linear in x, y; shorter arc in heading), and which stamps lie
        within the samples' span (a static edge holds at every time)."""
        if self.static:
            return np.repeat(self.se2[:1], len(when), axis=0), np.ones(len(when), dtype=bool)
        return _interpolate(self.stamps, self.se2, when)


def _interpolate(
    stamps: NDArray[np.int64], poses: NDArray[np.float64], when: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    last = len(stamps) - 1
    left = np.clip(np.searchsorted(stamps, when, side="right") - 1, 0, last)
    right = np.minimum(left + 1, last)
    valid = (when >= stamps[0]) & (when <= stamps[last])
    span = (stamps[right] - stamps[left]).astype(np.float64)
    offset = (when - stamps[left]).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(span > 0, offset / np.where(span > 0, span, 1.0), 0.0)
    fraction = np.where(valid, np.clip(fraction, 0.0, 1.0), 0.0)
    a, b = poses[left], poses[right]
    turn = wrap(b[:, 2] - a[:, 2])
    out = np.stack(
        [
            a[:, 0] + fraction * (b[:, 0] - a[:, 0]),
            a[:, 1] + fraction * (b[:, 1] - a[:, 1]),
            wrap(a[:, 2] + fraction * turn),
        ],
        axis=1,
    )
    return out, valid


def _checked(name: str, records: _Transforms) -> NDArray[np.float64]:
    """``(K, 7)`` ``x y z qx qy qz qw`` with unit quaternions, or an InputError for a value
    that is not finite, a translation beyond the readers' limit, or a zero quaternion."""
    values = np.array(records.values, dtype=np.float64).reshape(-1, 7)
    finite = np.asarray(np.isfinite(values).all(axis=1), dtype=bool)
    safe = np.where(finite[:, None], values, 0.0)
    norm = np.sqrt(np.sum(np.clip(safe[:, 3:], -1e6, 1e6) ** 2, axis=1))
    within = np.asarray(
        (np.abs(safe[:, :3]) <= MAX_COORDINATE).all(axis=1)
        & (np.abs(safe[:, 3:]) <= 1e6).all(axis=1),
        dtype=bool,
    )
    bad = ~finite | ~within | (norm < _MIN_QUATERNION_NORM)
    if bad.any():
        k = int(np.argmax(bad))
        shown = ", ".join(f"{v!r}" for v in records.values[k])
        raise InputError(
            f"{name}: {records.where}: the transform {records.parents[k] or '?'} -> "
            f"{records.children[k] or '?'} at {_seconds(records.stamps[k]):.9f} s is "
            f"({shown}): a NaN/inf, a translation beyond {sci(MAX_COORDINATE)} m or a quaternion "
            "of norm 0 or beyond 1e6; the bag is damaged: re-record it or drop that message"
        )
    values[:, 3:] /= norm[:, None]  # tf2 wants unit quaternions; a rounded one is normalized
    return values


def _yaw(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Heading of unit quaternions ``(K, 4)`` ``x y z w`` (the rotation's z-y-x yaw)."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _matrix(row: NDArray[np.float64]) -> NDArray[np.float64]:
    """4x4 homogeneous transform of ``x y z qx qy qz qw`` (unit quaternion)."""
    x, y, z, w = row[3:7]
    out = np.eye(4)
    out[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    out[:3, 3] = row[:3]
    return out


def _se2(rows: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.stack([rows[:, 0], rows[:, 1], _yaw(rows[:, 3:7])], axis=1)


def _series(name: str, records: _Transforms, static: bool) -> dict[tuple[str, str], _Series]:
    """The records grouped by edge ``(parent, child)``."""
    if not records.stamps:
        return {}
    values = _checked(name, records)
    stamps = np.array(records.stamps, dtype=object)
    out: dict[tuple[str, str], _Series] = {}
    edges: dict[tuple[str, str], list[int]] = {}
    for k, edge in enumerate(zip(records.parents, records.children, strict=True)):
        edges.setdefault(edge, []).append(k)
    for (parent, child), rows in edges.items():
        if static:
            rows = rows[-1:]  # a later static transform replaces an earlier one
        picked = np.array(rows, dtype=np.int64)
        times = _stamps_array(name, records.where, stamps[picked])
        order = np.argsort(times, kind="stable")
        times, chosen = times[order], values[picked[order]]
        last = np.append(times[1:] != times[:-1], True)  # one sample per stamp: the last
        out[(parent, child)] = _Series(
            parent=parent,
            stamps=times[last],
            se2=_se2(chosen[last]),
            matrix=_matrix(chosen[0]),
            static=static,
        )
    return out


def _stamps_array(name: str, where: str, stamps: NDArray[Any]) -> NDArray[np.int64]:
    for stamp in stamps:
        if not -_STAMP_LIMIT < int(stamp) < _STAMP_LIMIT:
            raise InputError(
                f"{name}: {where}: a stamp of {int(stamp)} ns, beyond the year 2116; the bag is "
                "damaged: re-record it"
            )
    return np.array([int(s) for s in stamps], dtype=np.int64)


def _seconds(ns: int) -> float:
    return ns // 1_000_000_000 + (ns % 1_000_000_000) / 1e9


class _Tree:
    """The frames of ``/tf`` and ``/tf_static``: each child's edge to its parent."""

    def __init__(
        self,
        name: str,
        dynamic: dict[tuple[str, str], _Series],
        static: dict[tuple[str, str], _Series],
    ) -> None:
        self.edges: dict[str, _Series] = {}
        for (parent, child), series in [*dynamic.items(), *static.items()]:
            known = self.edges.get(child)
            if known is not None and known.parent != parent:
                raise InputError(
                    f"{name}: frame {child!r} has two parents in the transforms, "
                    f"{known.parent!r} and {parent!r}; a tf tree gives each frame one parent: "
                    "drop one of the publishers"
                )
            self.edges[child] = series  # static after dynamic: /tf_static wins

    @property
    def frames(self) -> set[str]:
        return set(self.edges) | {s.parent for s in self.edges.values()}

    def ancestry(self, frame: str) -> list[str]:
        """``frame``, its parent, ... up to the root (a cycle stops the walk)."""
        out = [frame]
        seen = {frame}
        while (edge := self.edges.get(out[-1])) is not None and edge.parent not in seen:
            out.append(edge.parent)
            seen.add(edge.parent)
        return out

    def path(self, target: str, source: str) -> tuple[list[str], list[str]] | None:
        """The frames from ``source`` and from ``target`` up to their first common ancestor
        (excluded), or None when they are not connected."""
        up_source = self.ancestry(source)
        up_target = self.ancestry(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            return None
        return up_source[: up_source.index(common)], up_target[: up_target.index(common)]

    def connects(self, target: str, source: str) -> bool:
        return self.path(target, source) is not None

    def se2(
        self, target: str, source: str, when: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """``T_target_source`` in SE(2) at ``when``, and where every edge on the way is defined."""
        found = self.path(target, source)
        assert found is not None  # callers check connects() first
        valid = np.ones(len(when), dtype=bool)

        def up(frames: list[str]) -> NDArray[np.float64] | None:
            nonlocal valid
            total: NDArray[np.float64] | None = None
            for frame in frames:
                step, ok = self.edges[frame].at(when)
                valid &= ok
                total = step if total is None else compose_rows(step, total)
            return total

        from_source, from_target = up(found[0]), up(found[1])
        if from_target is None:
            result = from_source
        elif from_source is None:
            result = invert(from_target)
        else:
            result = between(from_target, from_source)
        if result is None:
            result = np.zeros((len(when), 3))
        return result, valid

    def rigid(self, target: str, source: str) -> NDArray[np.float64] | None:
        """``T_target_source`` in 3D from each edge's first sample (a rigid mount), or None."""
        found = self.path(target, source)
        if found is None:
            return None

        def up(frames: list[str]) -> NDArray[np.float64]:
            total = np.eye(4)
            for frame in frames:
                total = self.edges[frame].matrix @ total
            return total

        return np.linalg.inv(up(found[1])) @ up(found[0])

    def only_static(self, target: str, source: str) -> bool:
        found = self.path(target, source)
        return found is not None and all(self.edges[f].static for f in found[0] + found[1])


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


def _mount(
    name: str, tree: _Tree, base_frame: str, laser_frame: str
) -> tuple[NDArray[np.float64], bool]:
    """``T_base_laser`` (4x4) and whether it came from /tf_static alone."""
    if not laser_frame or laser_frame == base_frame:
        return np.eye(4), True
    matrix = tree.rigid(base_frame, laser_frame)
    if matrix is None:
        frames = sorted(tree.frames)
        shown = ", ".join(frames[:12]) + (
            f", ... {len(frames) - 12} more" if len(frames) > 12 else ""
        )
        raise InputError(
            f"{name}: no transform from {base_frame!r} to the laser's frame {laser_frame!r} in "
            f"/tf_static or /tf (frames: {shown or 'none'}); record the robot's static "
            "transforms (robot_state_publisher), or pass --base-frame if the robot's frame has "
            "another name"
        )
    if not np.all(np.isfinite(matrix)) or not np.all(np.abs(matrix[:3, 3]) <= MAX_COORDINATE):
        raise InputError(
            f"{name}: the laser's mounting {base_frame} -> {laser_frame} is beyond "
            f"{sci(MAX_COORDINATE)} m; the transforms are damaged: re-record the bag"
        )
    static = tree.only_static(base_frame, laser_frame)
    if not static:
        _log.info(
            "%s: %s -> %s is not in /tf_static; its first value in /tf is taken as rigid",
            name,
            base_frame,
            laser_frame,
        )
    return matrix, static


def _points(
    name: str,
    contents: _Contents,
    scans: list[_Scan],
    tree: _Tree,
    base_frame: str,
    max_range: float | None,
) -> tuple[
    NDArray[np.float64],
    NDArray[np.int64],
    NDArray[np.float64] | None,
    dict[str, list[float]],
]:
    """Every scan's points in the base frame at once; per-scan counts, per-point intensities
    (None when no scan has any), and each laser frame's mounting ``(x, y, yaw)``."""
    topic = contents.scan_topic
    fields = np.array(
        [[s.angle_min, s.angle_increment, s.range_min, s.range_max] for s in scans]
    ).reshape(-1, 4)
    beams = np.array([len(s.ranges) for s in scans], dtype=np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        limit = fields[:, 3] if max_range is None else np.minimum(fields[:, 3], max_range)
        last_angle = fields[:, 0] + np.maximum(beams - 1, 0) * fields[:, 1]
        bad = (
            ~np.isfinite(fields[:, :3]).all(axis=1)
            | ~(np.abs(fields[:, 0]) <= MAX_ANGLE)
            | ~(np.abs(fields[:, 1]) <= MAX_ANGLE)
            | ~(np.abs(last_angle) <= MAX_ANGLE)
        )
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(
            f"{name}: {topic}: the scan at {_seconds(scans[k].stamp):.9f} s has angle_min "
            f"{float(fields[k, 0])!r}, angle_increment {float(fields[k, 1])!r}, range_min "
            f"{float(fields[k, 2])!r} over {beams[k]} beams: a NaN/inf or angles beyond "
            f"{sci(MAX_ANGLE)} rad; the message is damaged: re-record the bag or drop it"
        )
    for k in np.unique(np.stack([beams, fields[:, 1]], axis=1), axis=0, return_index=True)[1]:
        problem = beam_spacing_problem(int(beams[k]), float(fields[k, 1]))
        if problem:
            raise InputError(
                f"{name}: {topic}: the scan at {_seconds(scans[k].stamp):.9f} s has "
                f"angle_increment {float(fields[k, 1])!r}: "
                f"{problem}; the message is damaged: re-record the bag or drop it"
            )
    with np.errstate(invalid="ignore"):
        inverted = fields[:, 2] > limit
    if inverted.any():
        k = int(np.argmax(inverted))
        _log.warning(
            "%s: %s: %d of %d scans have range_min above range_max%s (first at %.9f s: %g > "
            "%g m); none of their readings can be a point: check the laser driver's range "
            "settings",
            name,
            topic,
            int(inverted.sum()),
            len(scans),
            "" if max_range is None else " (or --max-range)",
            _seconds(scans[k].stamp),
            float(fields[k, 2]),
            float(limit[k]),
        )
    with np.errstate(invalid="ignore"):
        unusable = ~(limit <= MAX_COORDINATE)  # NaN, inf or absurd: no usable maximum
    if unusable.any():
        k = int(np.argmax(unusable))
        raise InputError(
            f"{name}: {topic}: the scan at {_seconds(scans[k].stamp):.9f} s has range_max "
            f"{float(fields[k, 3])!r}, not a usable maximum range; pass --max-range M (the laser's "
            "maximum range in metres)"
        )
    mounts: dict[str, tuple[NDArray[np.float64], bool]] = {}
    for frame in {s.frame for s in scans}:
        mounts[frame] = _mount(name, tree, base_frame, frame)
    total = int(beams.sum())
    if total == 0:
        empty = np.zeros((0, 2))
        return empty, np.zeros(len(scans), dtype=np.int64), None, _mount_table(mounts)
    r = np.concatenate([s.ranges for s in scans])
    index = np.arange(total) - np.repeat(np.cumsum(beams) - beams, beams)
    owner = np.repeat(np.arange(len(scans)), beams)
    angle = fields[owner, 0] + index * fields[owner, 1]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0) & (r >= fields[owner, 2]) & (r <= limit[owner])
    rv, av, ov = r[valid], angle[valid], owner[valid]
    local = np.stack([rv * np.cos(av), rv * np.sin(av)], axis=1)
    points = np.empty_like(local)
    frame_of = np.array([s.frame for s in scans], dtype=object)[ov]
    for frame, (matrix, _) in mounts.items():
        rows = frame_of == frame
        points[rows] = local[rows] @ matrix[:2, :2].T + matrix[:2, 3]
    counts = np.bincount(ov, minlength=len(scans)).astype(np.int64)
    intensities = None
    if any(len(s.intensities) and len(s.intensities) == len(s.ranges) for s in scans):
        per_beam = np.concatenate(
            [
                s.intensities
                if len(s.intensities) == len(s.ranges)
                else np.full(len(s.ranges), np.nan)
                for s in scans
            ]
        )
        intensities = per_beam[valid]
    mismatched = sum(1 for s in scans if len(s.intensities) not in (0, len(s.ranges)))
    if mismatched:
        _log.info(
            "%s: %d scans of %s have intensities, but not one per range; theirs are ignored",
            name,
            mismatched,
            topic,
        )
    return points, counts, intensities, _mount_table(mounts)


def _mount_table(mounts: dict[str, tuple[NDArray[np.float64], bool]]) -> dict[str, list[float]]:
    return {
        frame: [float(m[0, 3]), float(m[1, 3]), math.atan2(float(m[1, 0]), float(m[0, 0]))]
        for frame, (m, _) in mounts.items()
    }
