"""Write ROS bags for tests with rosbags' own writers: ROS 1 (``.bag``), ROS 2 sqlite3 and MCAP
(a bag directory, or its lone storage file). A bag is described as plain values (:class:`Bag`):
scans, odometry or tf transforms, static transforms, each with a stamp in nanoseconds.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from reference import compose, inverse, wrap

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
KINDS = ("ros1", "sqlite3", "mcap", "db3-file", "mcap-file")
"""``ros1``: a .bag; ``sqlite3``/``mcap``: a ROS 2 bag directory; ``db3-file``/``mcap-file``:
the storage file of such a directory, on its own."""

_STORES = {1: get_typestore(Stores.ROS1_NOETIC), 2: get_typestore(Stores.ROS2_HUMBLE)}
# rosbags' ROS 1 store lacks tf2_msgs (a ROS 1 bag carries its definitions: write them).
_STORES[1].register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))


@dataclass
class Scan:
    stamp: int  # [ns]
    ranges: NDArray[np.float64]
    angle_min: float
    angle_increment: float
    range_min: float = 0.0
    range_max: float = 80.0
    frame: str = "laser"
    intensities: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    record: int | None = None  # [ns] the bag's record time (its order); default: the stamp


@dataclass
class Transform:
    stamp: int  # [ns]
    parent: str
    child: str
    pose: tuple[float, float, float]  # x y yaw (planar)
    z: float = 0.0
    quaternion: tuple[float, float, float, float] | None = None  # x y z w; default from yaw
    record: int | None = None  # [ns] the bag's record time (its order); default: the stamp


@dataclass
class Bag:
    scans: list[Scan] = field(default_factory=list)
    scan_topic: str = "/scan"
    tf: list[list[Transform]] = field(default_factory=list)  # one TFMessage per inner list
    tf_static: list[Transform] = field(default_factory=list)
    odometry: list[Transform] = field(default_factory=list)  # parent = header, child frame
    odom_topic: str = "/odom"
    more_scans: dict[str, list[Scan]] = field(default_factory=dict)  # other LaserScan topics
    more_odometry: dict[str, list[Transform]] = field(default_factory=dict)  # other Odometry


def seconds_to_ns(t: float) -> int:
    """A float time [s] as ROS's (sec, nanosec), in nanoseconds."""
    sec = math.floor(t)
    nsec = round((t - sec) * 1e9)
    return sec * 1_000_000_000 + nsec


def _time(store: Any, ns: int) -> Any:
    return store.types["builtin_interfaces/msg/Time"](
        sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
    )


def _header(version: int, ns: int, frame: str) -> Any:
    store = _STORES[version]
    header = store.types["std_msgs/msg/Header"]
    if version == 1:
        return header(seq=0, stamp=_time(store, ns), frame_id=frame)
    return header(stamp=_time(store, ns), frame_id=frame)


def _quaternion(t: Transform) -> tuple[float, float, float, float]:
    if t.quaternion is not None:
        return t.quaternion
    with np.errstate(invalid="ignore"):  # a hostile yaw (inf) gives a NaN quaternion
        half = np.float64(t.pose[2]) / 2
        return (0.0, 0.0, float(np.sin(half)), float(np.cos(half)))


def _float32(value: float) -> float:
    with np.errstate(over="ignore"):
        return float(np.float32(value))


def _scan_message(version: int, scan: Scan) -> Any:
    store = _STORES[version]
    n = len(scan.ranges)
    with np.errstate(over="ignore", invalid="ignore"):  # hostile values: inf as float32 has it
        angle_max = _float32(scan.angle_min + max(n - 1, 0) * scan.angle_increment)
    return store.types[LASER_SCAN](
        header=_header(version, scan.stamp, scan.frame),
        angle_min=_float32(scan.angle_min),
        angle_max=angle_max,
        angle_increment=_float32(scan.angle_increment),
        time_increment=0.0,
        scan_time=0.0,
        range_min=_float32(scan.range_min),
        range_max=_float32(scan.range_max),
        ranges=np.asarray(scan.ranges, dtype=np.float32),
        intensities=np.asarray(scan.intensities, dtype=np.float32),
    )


def _transform_message(version: int, t: Transform) -> Any:
    store = _STORES[version]
    qx, qy, qz, qw = _quaternion(t)
    return store.types["geometry_msgs/msg/TransformStamped"](
        header=_header(version, t.stamp, t.parent),
        child_frame_id=t.child,
        transform=store.types["geometry_msgs/msg/Transform"](
            translation=store.types["geometry_msgs/msg/Vector3"](x=t.pose[0], y=t.pose[1], z=t.z),
            rotation=store.types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )


def _tf_message(version: int, transforms: list[Transform]) -> Any:
    store = _STORES[version]
    return store.types[TF_MESSAGE](transforms=[_transform_message(version, t) for t in transforms])


def _odometry_message(version: int, t: Transform) -> Any:
    store = _STORES[version]
    qx, qy, qz, qw = _quaternion(t)
    types = store.types
    covariance = np.zeros(36)
    pose = types["geometry_msgs/msg/PoseWithCovariance"](
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=t.pose[0], y=t.pose[1], z=t.z),
            orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
        covariance=covariance,
    )
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = types["geometry_msgs/msg/TwistWithCovariance"](
        twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=covariance
    )
    return types[ODOMETRY](
        header=_header(version, t.stamp, t.parent), child_frame_id=t.child, pose=pose, twist=twist
    )


def _record(item: Scan | Transform) -> int:
    return item.stamp if item.record is None else item.record


def _messages(bag: Bag, version: int) -> list[tuple[str, str, int, Any]]:
    """(topic, type, bag time, message) in time order."""
    out: list[tuple[str, str, int, Any]] = []
    for scan in bag.scans:
        out.append((bag.scan_topic, LASER_SCAN, _record(scan), _scan_message(version, scan)))
    for group in bag.tf:
        out.append(("/tf", TF_MESSAGE, _record(group[0]), _tf_message(version, group)))
    if bag.tf_static:
        out.append(("/tf_static", TF_MESSAGE, 0, _tf_message(version, bag.tf_static)))
    for t in bag.odometry:
        out.append((bag.odom_topic, ODOMETRY, _record(t), _odometry_message(version, t)))
    for topic, scans in bag.more_scans.items():
        out += [(topic, LASER_SCAN, _record(s), _scan_message(version, s)) for s in scans]
    for topic, poses in bag.more_odometry.items():
        out += [(topic, ODOMETRY, _record(t), _odometry_message(version, t)) for t in poses]
    out.sort(key=lambda item: item[2])
    return out


def write_bag(bag: Bag, path: Path, kind: str) -> Path:
    """Write ``bag`` as ``kind`` (see :data:`KINDS`) at ``path`` (its name without extension);
    returns what to read: the .bag file, the directory, or the lone storage file."""
    if kind == "ros1":
        out = path.with_suffix(".bag")
        store = _STORES[1]
        with Writer1(out) as writer:
            connections: dict[str, Any] = {}
            for topic, msgtype, stamp, message in _messages(bag, 1):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
                data = store.serialize_ros1(message, msgtype)
                writer.write(connections[topic], max(stamp, 1), data)
        return out
    plugin = StoragePlugin.MCAP if kind.startswith("mcap") else StoragePlugin.SQLITE3
    store = _STORES[2]
    with Writer2(path, version=9, storage_plugin=plugin) as writer2:
        connections = {}
        for topic, msgtype, stamp, message in _messages(bag, 2):
            if topic not in connections:
                connections[topic] = writer2.add_connection(topic, msgtype, typestore=store)
            writer2.write(connections[topic], max(stamp, 1), store.serialize_cdr(message, msgtype))
    if kind.endswith("-file"):
        (storage,) = [p for p in path.iterdir() if p.suffix in (".db3", ".mcap")]
        lone = path.parent / f"{path.name}-lone{storage.suffix}"
        shutil.move(storage, lone)
        shutil.rmtree(path)
        return lone
    return path


def slam_bag_of_log(
    log: Path, seed: int = 0, *, map_frame: bool = True
) -> tuple[Bag, NDArray[np.float64]]:
    """A bag as a SLAM (slam_toolbox, Cartographer) records it, made from the FLASER lines of a
    CARMEN log whose logged poses are a good map (a corrected log): the logged poses are the
    SLAM's trajectory ``map -> base_link`` (the laser is the robot's frame), the odometry
    ``odom -> base_link`` drifts away from it (a random walk), and ``map -> odom`` (when
    ``map_frame``) makes up the difference, on /tf at each scan's stamp (100 s + 0.2 s per scan:
    corrected logs often carry one timestamp for every scan). Readings at the log's maximum range
    are no-returns (inf). Returns the bag and the trajectory ``(N, 3)``."""
    import gzip

    opener = gzip.open if log.name.endswith(".gz") else open
    with opener(log, "rt") as f:
        lines = [line.split() for line in f if line.startswith(("FLASER", "PARAM"))]
    params = {t[1]: float(t[2]) for t in lines if t[0] == "PARAM" and len(t) > 2}
    limit = params.get("robot_front_laser_max", 80.0) - 1e-3
    rng = np.random.default_rng(seed)
    scans, slam, stamps = [], [], []
    for t in (t for t in lines if t[0] == "FLASER"):
        n = int(t[1])
        r = np.array(t[2 : 2 + n], dtype=np.float64)
        slam.append([float(v) for v in t[2 + n : 5 + n]])
        stamps.append((500 + len(stamps)) * 200_000_000)
        step = math.pi / (n - 1) if n in (181, 361) else math.pi / n
        ranges = np.where((r > 0) & (r < limit), r, np.inf)
        scans.append(Scan(stamps[-1], ranges, -math.pi / 2, step, 0.0, 80.0, "base_link"))
    trajectory = np.array(slam)
    trajectory[:, 2] = wrap(trajectory[:, 2])
    drift = np.cumsum(rng.normal(0, [0.01, 0.01, 0.004], trajectory.shape), axis=0)
    odometry = compose(trajectory, drift)
    map_odom = compose(trajectory, inverse(odometry))
    bag = Bag(scans=scans)
    for k, stamp in enumerate(stamps):
        group = [Transform(stamp, "odom", "base_link", tuple(odometry[k]))]
        if map_frame:
            group.append(Transform(stamp, "map", "odom", tuple(map_odom[k])))
        bag.tf.append(group)
    return bag, trajectory
