"""ROS bag input (hitl_slam.io.rosbag): bags written with rosbags' own writers (ROS 1, ROS 2 sqlite3
and MCAP, as a directory or a lone storage file) from the shared CARMEN logs load to the poses,
points and timestamps read_carmen reads from the same scans, in TF, Odometry and SLAM (map -> odom)
layouts; interpolation, range limits, mounts and frame chains on hand-made bags; every bad input an
InputError naming the file; the map loader and the CLI.

Data: the Freiburg 079 and Intel lab CARMEN logs (Kuemmerle et al. 2009 / D. Haehnel, via Radish;
CC-BY) and the corrected Seattle log (Radish), in ../shared/datasets/laser.
"""

from __future__ import annotations

import bz2
import gzip
import math
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

pytest.importorskip("rosbags", reason="the [ros] extra (rosbags) is not installed")

import hitl_slam
from bag_support import KINDS, Bag, Scan, Transform, seconds_to_ns, write_bag
from hitl_slam.cli import main
from hitl_slam.errors import InputError
from hitl_slam.io.carmen import read_carmen
from hitl_slam.io.maps import load_map
from hitl_slam.io.rosbag import BagOptions, is_rosbag, read_rosbag
from hitl_slam.map import Map, motion_model_information
from reference import compose, inverse, transform_points, wrap

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
LASER = SHARED / "datasets" / "laser"
needs_shared = pytest.mark.skipif(
    not LASER.is_dir(),
    reason=f"public laser datasets not found at {LASER} (the project's ../shared folder)",
)
FloatArray = NDArray[np.float64]
SCANS = 300  # per bag made from a log: enough to mean something, fast to write and read


def world(m: Map, poses: FloatArray | None = None) -> FloatArray:
    p = m.poses if poses is None else poses
    return transform_points(p[m.pose_of_point()], m.points)


def assert_poses(actual: FloatArray, expected: FloatArray, atol: float = 1e-9) -> None:
    assert actual.shape == expected.shape
    np.testing.assert_allclose(actual[:, :2], expected[:, :2], rtol=0, atol=atol)
    assert np.abs(wrap(actual[:, 2] - expected[:, 2])).max(initial=0) <= atol


def float32_bound(ranges: FloatArray) -> FloatArray:
    """How far a point may move when its range and beam angle are stored as float32, as the
    LaserScan message stores them: 2^-24 of the range for the range, and the angle's rounding
    (angle_min and angle_increment, each 2^-24 relative, times up to 361 beams) times the range;
    1e-6 m on top."""
    return 1e-6 + ranges * 1.3e-7


# --- the shared logs, cut to their first scans -------------------------------------------------


@dataclass
class LogHead:
    """``count`` FLASER lines of a CARMEN log from line ``start`` (with the log's PARAM lines),
    written to ``path``, their raw fields, and read_carmen's map of them."""

    path: Path
    ranges: list[FloatArray]
    steps: list[float]
    stamps: list[float]
    reference: Map

    @property
    def max_range(self) -> float:
        return float(self.reference.metadata["flaser_max_range"])


_HEADS: dict[tuple[str, int], LogHead] = {}


@pytest.fixture(scope="module")
def heads(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str, int], LogHead]:
    folder = tmp_path_factory.mktemp("heads")

    def head(name: str, start: int) -> LogHead:
        key = (name, start)
        if key not in _HEADS:
            opener = bz2.open if name.endswith(".bz2") else gzip.open
            kept: list[str] = []
            count = 0
            with opener(LASER / name, "rt") as f:
                for line in f:
                    tag = line.split(None, 1)[0] if line.strip() else ""
                    if tag == "FLASER":
                        count += 1
                        if count > start + SCANS:
                            break
                        if count > start:
                            kept.append(line)
                    elif tag == "PARAM":
                        kept.append(line)
            path = folder / f"{name.split('.')[0]}-{start}.clf"
            path.write_text("".join(kept))
            ranges, steps, stamps = [], [], []
            for line in kept:
                tokens = line.split()
                if tokens[0] != "FLASER":
                    continue
                n = int(tokens[1])
                ranges.append(np.array(tokens[2 : 2 + n], dtype=np.float64))
                steps.append(math.pi / (n - 1) if n in (181, 361) else math.pi / n)
                stamps.append(float(tokens[8 + n]))
            _HEADS[key] = LogHead(path, ranges, steps, stamps, read_carmen(path))
        return _HEADS[key]

    return head


# --- a log's scans as a bag ---------------------------------------------------------------------

LAYOUTS = ("tf", "tf-laser-is-base", "odometry-topic", "slam")
LOGS = ("fr079.clf.bz2", "intel.clf.bz2", "seattle-corrected.log.gz")


@dataclass
class Expected:
    poses: FloatArray  # what the map's poses must be (the robot's, in the odometry or map frame)
    odometry: FloatArray  # the odometry at each scan (the chain edges' source)
    mount: FloatArray  # (x, y, yaw) of the laser on the robot
    intensities: FloatArray | None  # per point, for the points read_carmen keeps
    options: BagOptions


def random_pose(rng: np.random.Generator, xy: float, yaw: float) -> FloatArray:
    return np.array([rng.uniform(-xy, xy), rng.uniform(-xy, xy), rng.uniform(-yaw, yaw)])


def bag_of_log(head: LogHead, layout: str, seed: int, ros1: bool) -> tuple[Bag, Expected]:
    """The log's scans as a bag in ``layout``; the laser poses are read_carmen's."""
    rng = np.random.default_rng(seed)
    laser = head.reference.poses
    n = len(laser)
    slash = "/" if rng.random() < 0.5 and ros1 else ""  # ROS 1's tf accepted "/odom"
    odom, base = rng.choice([("odom", "base_link"), ("odom_combined", "base_footprint")])
    options = BagOptions(odom_frame=str(odom), base_frame=str(base))
    mount = np.zeros(3) if layout == "tf-laser-is-base" else random_pose(rng, 0.3, 0.6)
    laser_frame = str(base) if layout == "tf-laser-is-base" else "laser"
    robot = compose(laser, inverse(mount))
    # Invalid CARMEN beams (<= 0, at the maximum range) written as REP 117 says, or left as read
    # with range_max below them.
    mode = rng.choice(["inf", "nan", "beyond"])
    limit = head.max_range - 1e-3
    range_max = head.max_range if mode != "beyond" else limit - 1e-5
    kind = rng.choice(["none", "per-range", "mismatched"])
    scans, intensities = [], []
    for k in range(n):
        r = head.ranges[k]
        valid = np.isfinite(r) & (r > 0) & (r < limit)
        if mode == "beyond":
            assert not np.any(valid & (r > range_max - 1e-4)), "a valid range at the limit"
            written = np.where(r > 0, r, -np.inf)
        else:
            written = np.where(valid, r, np.inf if mode == "inf" else np.nan)
        values = rng.uniform(0, 1000, len(r)).astype(np.float32).astype(np.float64)
        if kind == "per-range":
            intensities.append(values[valid])
        record = 10**18 + k * 10**7  # the bag's order is the log's (Intel's stamps are not)
        scans.append(
            Scan(
                stamp=seconds_to_ns(head.stamps[k]),
                ranges=written,
                angle_min=-math.pi / 2,
                angle_increment=head.steps[k],
                range_min=0.0,
                range_max=range_max,
                frame=slash + laser_frame,
                intensities=(
                    values if kind == "per-range" else values[:-1] if kind == "mismatched" else []
                ),
                record=record,
            )
        )
    bag = Bag(scans=scans)
    static = []
    if layout != "tf-laser-is-base":
        static.append(Transform(0, base, "laser", tuple(mount), z=rng.uniform(0, 0.5)))
    odometry = robot
    if layout == "slam":
        # Odometry that drifts away from the SLAM's poses; map -> odom makes up the difference.
        drift = np.cumsum(rng.normal(0, [0.01, 0.01, 0.003], (n, 3)), axis=0)
        odometry = compose(robot, drift)
        map_odom = compose(robot, inverse(odometry))
    stamps = [s.stamp for s in scans]
    if layout == "odometry-topic":
        bag.odometry = [
            Transform(stamps[k], slash + odom, slash + base, tuple(odometry[k]), record=s.record)
            for k, s in enumerate(scans)
        ]
        if rng.random() < 0.5:  # a second Odometry topic: the right one is named
            bag.more_odometry["/odom_filtered"] = [
                Transform(t, "odom", "base_link", (0.0, 0.0, 0.0)) for t in stamps[:3]
            ]
            bag.odom_topic = "/wheel_odom"
            options = BagOptions(
                odom_topic="/wheel_odom", odom_frame=str(odom), base_frame=str(base)
            )
    else:
        for k, s in enumerate(scans):
            group = [Transform(stamps[k], slash + odom, slash + base, tuple(odometry[k]))]
            if layout == "slam":
                group.append(Transform(stamps[k], slash + "map", slash + odom, tuple(map_odom[k])))
            for t in group:
                t.record = s.record
            bag.tf.append(group)
    bag.tf_static = static
    if rng.random() < 0.5:  # another LaserScan topic: the right one is named
        bag.more_scans["/scan_rear"] = [
            Scan(t, np.ones(4), 0.0, 0.1, frame="rear_laser") for t in stamps[:5]
        ]
        bag.scan_topic = "/front/scan"
        options = BagOptions(
            scan_topic="/front/scan",
            odom_topic=options.odom_topic,
            odom_frame=options.odom_frame,
            base_frame=options.base_frame,
        )
    expected = Expected(
        poses=robot,
        odometry=odometry,
        mount=mount,
        intensities=np.concatenate(intensities) if kind == "per-range" else None,
        options=options,
    )
    return bag, expected


def check_same_as_log(loaded: Map, head: LogHead, expected: Expected) -> None:
    reference = head.reference
    assert loaded.num_poses == reference.num_poses >= min(SCANS, 241)  # Seattle has 241
    assert_poses(loaded.poses, expected.poses)
    assert_poses(compose(loaded.poses, expected.mount), reference.poses)  # the laser's poses
    assert loaded.timestamps is not None
    assert reference.timestamps is not None
    np.testing.assert_allclose(loaded.timestamps, reference.timestamps, rtol=4.5e-16, atol=1e-9)
    np.testing.assert_array_equal(loaded.offsets, reference.offsets)
    reach = np.hypot(reference.points[:, 0], reference.points[:, 1])
    assert np.all(np.hypot(*(world(loaded) - world(reference)).T) <= float32_bound(reach))
    in_robot = transform_points(expected.mount, reference.points)
    assert np.all(np.hypot(*(loaded.points - in_robot).T) <= float32_bound(reach))
    steps = compose(inverse(expected.odometry[:-1]), expected.odometry[1:])
    assert_poses(loaded.measurements, steps)
    np.testing.assert_allclose(
        loaded.information, motion_model_information(loaded.measurements), rtol=1e-12
    )
    np.testing.assert_array_equal(loaded.edges, reference.edges)
    np.testing.assert_allclose(loaded.metadata["laser_mount"], expected.mount, atol=1e-12)
    if expected.intensities is None:
        assert "intensities" not in loaded.metadata
    else:
        np.testing.assert_array_equal(loaded.metadata["intensities"], expected.intensities)


CASES = [
    (kind, layout, LOGS[(k + j) % len(LOGS)], 10 * k + j)
    for k, kind in enumerate(KINDS)
    for j, layout in enumerate(LAYOUTS)
]


@needs_shared
@pytest.mark.parametrize(("kind", "layout", "log", "seed"), CASES)
def test_a_bag_made_from_a_log_loads_as_the_log(
    tmp_path: Path,
    heads: Callable[[str, int], LogHead],
    kind: str,
    layout: str,
    log: str,
    seed: int,
) -> None:
    start = 0 if log.startswith("seattle") else int(np.random.default_rng(seed).integers(0, 200))
    head = heads(log, start)
    bag, expected = bag_of_log(head, layout, seed, ros1=kind == "ros1")
    path = write_bag(bag, tmp_path / "run", kind)
    loaded = read_rosbag(path, expected.options)
    check_same_as_log(loaded, head, expected)
    assert loaded.metadata["ros_version"] == (1 if kind == "ros1" else 2)
    assert loaded.metadata["scan_topic"] == bag.scan_topic
    assert loaded.name == "run" if kind in ("ros1", "sqlite3", "mcap") else "run-lone"
    assert loaded.source == str(path)
    if layout == "slam":
        assert loaded.metadata["trajectory"].startswith("slam (map -> ")
        assert_poses(loaded.metadata["odometry_poses"], expected.odometry)
        # Without the map frame the same bag gives its odometry.
        plain = read_rosbag(path, BagOptions(**{**vars(expected.options), "map_frame": None}))
        assert_poses(plain.poses, expected.odometry)
        np.testing.assert_array_equal(plain.measurements, loaded.measurements)
    else:
        assert loaded.metadata["trajectory"].startswith("odometry (")
        assert "odometry_poses" not in loaded.metadata
    source = loaded.metadata["odometry"]
    assert source.startswith("topic /") if layout == "odometry-topic" else source.startswith("/tf")
    # Through the map loader: by extension, or a ROS 2 bag's directory.
    assert is_rosbag(path)
    again = load_map(path, bag=expected.options)
    np.testing.assert_array_equal(again.poses, loaded.poses)
    np.testing.assert_array_equal(again.points, loaded.points)


@needs_shared
def test_ros1_and_ros2_bags_of_one_log_are_the_same_map(
    tmp_path: Path, heads: Callable[[str, int], LogHead]
) -> None:
    head = heads("intel.clf.bz2", 0)
    maps = []
    for kind in KINDS:
        bag, expected = bag_of_log(head, "slam", 7, ros1=kind == "ros1")
        maps.append(read_rosbag(write_bag(bag, tmp_path / kind, kind), expected.options))
    for other in maps[1:]:
        np.testing.assert_array_equal(other.poses, maps[0].poses)
        np.testing.assert_array_equal(other.points, maps[0].points)
        np.testing.assert_array_equal(other.measurements, maps[0].measurements)
        assert other.timestamps is not None
        assert maps[0].timestamps is not None
        np.testing.assert_array_equal(other.timestamps, maps[0].timestamps)


# --- hand-made bags: interpolation, ranges, mounts, frames ------------------------------------

SEC = 1_000_000_000


def simple_bag(
    n: int = 5,
    ranges: FloatArray | None = None,
    *,
    stamps: list[int] | None = None,
    frame: str = "laser",
    mount: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
    odometry: str = "tf",
) -> Bag:
    """n scans one second apart of ``ranges`` (angle_min -1, 0.5 rad apart), the robot at
    (k, 0, 0.1 k) in odom, on /tf or an Odometry topic; the laser mounted at ``mount``."""
    beams = np.array([1.0, 2.0, 3.0]) if ranges is None else ranges
    stamps = [100 * SEC + k * SEC for k in range(n)] if stamps is None else stamps
    scans = [Scan(t, beams, -1.0, 0.5, 0.1, 10.0, frame) for t in stamps]
    poses = [
        Transform(t, "odom", "base_link", (float(k), 0.0, 0.1 * k)) for k, t in enumerate(stamps)
    ]
    bag = Bag(scans=scans)
    if odometry == "tf":
        bag.tf = [[p] for p in poses]
    elif odometry == "topic":
        bag.odometry = poses
    if mount is not None and frame != "base_link":
        bag.tf_static = [Transform(0, "base_link", frame, mount)]
    return bag


def test_odometry_is_interpolated_in_se2_at_each_scan(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    scans = [int(t) for t in np.sort(rng.uniform(10, 20, 30)) * SEC]
    # Odometry at its own times: 1 s apart from 9.5 s to 19.5 s; the heading crosses +-pi.
    times = [int((9.5 + k) * SEC) for k in range(11)]
    values = np.array([[0.3 * k, -0.2 * k, 2.9 + 0.15 * k] for k in range(11)])
    values[:, 2] = wrap(values[:, 2])
    bag = Bag(
        scans=[Scan(t, np.array([1.0]), 0.0, 0.0, 0.0, 5.0, "base_link") for t in scans],
        tf=[
            [Transform(t, "odom", "base_link", tuple(v))]
            for t, v in zip(times, values, strict=True)
        ],
    )
    m = read_rosbag(write_bag(bag, tmp_path / "interp", "sqlite3"))
    inside = [t for t in scans if times[0] <= t <= times[-1]]
    assert m.num_poses == len(inside)
    assert m.metadata["scans_dropped"] == len(scans) - len(inside)
    expected = []
    for t in inside:
        k = min(int((t - times[0]) // SEC), 9)
        f = (t - times[k]) / (times[k + 1] - times[k])
        a, b = values[k], values[k + 1]
        turn = wrap(np.array([b[2] - a[2]]))[0]  # the shorter arc: 0.15 rad, never 2 pi - 0.15
        expected.append([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * turn])
    assert_poses(m.poses, np.array(expected), atol=1e-12)
    assert np.all(m.poses[:, 2] > -math.pi)
    assert np.all(m.poses[:, 2] <= math.pi)
    assert m.timestamps is not None
    np.testing.assert_allclose(m.timestamps, np.array(inside) / SEC, rtol=1e-15)


def test_map_to_odom_is_interpolated_too(tmp_path: Path) -> None:
    bag = simple_bag(9, mount=None, frame="base_link")
    # map -> odom every 4 s: a rotation about the origin that grows linearly.
    for k in (0, 4, 8):
        bag.tf[k].append(Transform(bag.tf[k][0].stamp, "map", "odom", (0.0, 0.5 * k, 0.05 * k)))
    m = read_rosbag(write_bag(bag, tmp_path / "slam", "mcap"))
    odometry = np.array([[float(k), 0.0, 0.1 * k] for k in range(9)])
    map_odom = np.array([[0.0, 0.5 * k, 0.05 * k] for k in range(9)])
    assert_poses(m.poses, compose(map_odom, odometry), atol=1e-12)
    assert_poses(m.metadata["odometry_poses"], odometry, atol=1e-12)


def test_range_limits_no_returns_and_intensities(tmp_path: Path) -> None:
    # Beams at -1, -0.5, 0, ... rad; range_min 0.1, range_max 10.
    ranges = np.array([np.nan, np.inf, -np.inf, 0.0, 0.05, 0.1, 5.0, 10.0, 10.5, -3.0, 2.0])
    bag = simple_bag(2, ranges, frame="base_link")
    bag.scans[0].intensities = np.arange(len(ranges), dtype=np.float64)
    bag.scans[1].intensities = np.zeros(3)  # not one per range: ignored
    path = write_bag(bag, tmp_path / "limits", "ros1")
    m = read_rosbag(path)
    kept = [5, 6, 7, 10]  # 0.1 (= range_min), 5, 10 (= range_max), 2
    angles = -1.0 + 0.5 * np.array(kept)
    expected = ranges[kept, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    np.testing.assert_allclose(m.points[:4], expected, rtol=1e-7)
    np.testing.assert_allclose(m.points[4:], expected, rtol=1e-7)
    np.testing.assert_array_equal(m.offsets, [0, 4, 8])
    np.testing.assert_array_equal(m.metadata["intensities"][:4], kept)
    assert np.all(np.isnan(m.metadata["intensities"][4:]))
    # --max-range lowers every scan's range_max; beyond the message's it changes nothing.
    lowered = read_rosbag(path, max_range=6.0)
    np.testing.assert_array_equal(lowered.offsets, [0, 3, 6])
    np.testing.assert_array_equal(read_rosbag(path, max_range=50.0).points, m.points)


def test_an_upside_down_laser_is_mirrored_and_moved_in_3d(tmp_path: Path) -> None:
    bag = simple_bag(3, np.array([1.0, 2.0, 3.0]))
    # Rolled by pi (x, y, z, w) = (1, 0, 0, 0), 0.2 m ahead and 0.3 m up, turned by nothing.
    bag.tf_static = [
        Transform(0, "base_link", "laser", (0.2, 0.0, 0.0), z=0.3, quaternion=(1.0, 0.0, 0.0, 0.0))
    ]
    m = read_rosbag(write_bag(bag, tmp_path / "flip", "sqlite3"))
    angles = np.array([-1.0, -0.5, 0.0])
    r = np.array([1.0, 2.0, 3.0])
    expected = np.stack([0.2 + r * np.cos(angles), -r * np.sin(angles)], axis=1)
    np.testing.assert_allclose(m.points[:3], expected, atol=1e-12)
    assert m.metadata["laser_mount"] == pytest.approx([0.2, 0.0, 0.0], abs=1e-12)


def test_frame_chains_and_an_odometry_topic_of_another_frame(tmp_path: Path) -> None:
    mount = np.array([0.1, -0.05, 0.2])
    footprint = np.array([0.05, 0.0, 0.0])
    # odom -> base_footprint on /tf, base_footprint -> base_link -> mount -> laser static.
    bag = simple_bag(4, mount=None)
    for group in bag.tf:
        group[0].child = "base_footprint"
    bag.tf_static = [
        Transform(0, "base_footprint", "base_link", tuple(footprint)),
        Transform(0, "base_link", "laser_mount", (0.1, 0.0, 0.0)),
        Transform(0, "laser_mount", "laser", (0.0, -0.05, 0.2)),
    ]
    m = read_rosbag(write_bag(bag, tmp_path / "chain", "ros1"))
    robot = compose(np.array([[float(k), 0.0, 0.1 * k] for k in range(4)]), footprint)
    assert_poses(m.poses, robot, atol=1e-12)
    assert m.metadata["laser_mount"] == pytest.approx(list(mount), abs=1e-12)
    # The same from an Odometry topic whose child frame is base_footprint.
    bag.odometry = [g[0] for g in bag.tf]
    bag.tf = []
    topic = read_rosbag(write_bag(bag, tmp_path / "topic", "mcap"))
    assert_poses(topic.poses, robot, atol=1e-12)
    assert topic.metadata["odometry"] == "topic /odom"


def test_zero_stamps_take_the_record_time(tmp_path: Path) -> None:
    bag = simple_bag(3, frame="base_link")
    for k, scan in enumerate(bag.scans):
        scan.record, scan.stamp = scan.stamp, 0
        bag.tf[k][0].record = scan.record
    m = read_rosbag(write_bag(bag, tmp_path / "zero", "ros1"))
    assert m.timestamps is not None
    np.testing.assert_allclose(m.timestamps, [100.0, 101.0, 102.0])


def test_the_bag_order_is_kept_when_stamps_go_back(tmp_path: Path) -> None:
    stamps = [100 * SEC, 102 * SEC, 101 * SEC, 103 * SEC]
    bag = simple_bag(4, stamps=stamps, frame="base_link")
    for k, scan in enumerate(bag.scans):
        scan.record = bag.tf[k][0].record = 10 * SEC + k
    m = read_rosbag(write_bag(bag, tmp_path / "order", "sqlite3"))
    assert m.timestamps is not None
    assert m.timestamps.tolist() == [100.0, 102.0, 101.0, 103.0]
    assert_poses(m.poses, np.array([[k, 0.0, 0.1 * k] for k in range(4)]), atol=1e-12)


# --- bad input ----------------------------------------------------------------------------------


def error_of(path: Path, options: BagOptions | None = None) -> str:
    with pytest.raises(InputError) as excinfo:
        read_rosbag(path, options or BagOptions())
    message = str(excinfo.value)
    assert message.startswith(f"{path}: "), message
    assert "; " in message[len(str(path)) + 2 :], f"no advice in: {message}"
    assert "\n" not in message
    return message


@pytest.mark.parametrize("kind", KINDS)
def test_bad_bags_are_input_errors_naming_the_file(tmp_path: Path, kind: str) -> None:
    def bag_at(name: str, bag: Bag) -> Path:
        return write_bag(bag, tmp_path / name, kind)

    # No LaserScan topic: the topics are listed.
    no_scans = simple_bag(3)
    no_scans.scans = []
    message = error_of(bag_at("noscan", no_scans))
    assert "no sensor_msgs/LaserScan topic" in message
    assert "/tf (tf2_msgs/msg/TFMessage)" in message
    # Several LaserScan topics: pick one.
    two = simple_bag(3)
    two.more_scans["/scan_rear"] = [
        Scan((100 + k) * SEC, np.array([1.0, 2.0]), 0.0, 0.1, frame="base_link") for k in range(2)
    ]
    path = bag_at("two", two)
    assert "2 LaserScan topics (/scan, /scan_rear); pick one with --scan-topic" in error_of(path)
    assert read_rosbag(path, BagOptions(scan_topic="/scan_rear")).num_points == 2 * 2
    # A topic of the wrong type, or none of that name.
    odom = simple_bag(3, odometry="topic")
    path = bag_at("wrongtype", odom)
    message = error_of(path, BagOptions(scan_topic="/odom"))
    assert "topic /odom is nav_msgs/msg/Odometry, not sensor_msgs/LaserScan" in message
    assert "LaserScan topics as --scan-topic: /scan" in message
    assert "no topic '/front'" in error_of(path, BagOptions(scan_topic="/front"))
    assert "is sensor_msgs/msg/LaserScan, not nav_msgs/Odometry" in error_of(
        path, BagOptions(odom_topic="/scan")
    )
    # Missing TF frames: the laser's mounting, the odometry's frames.
    no_mount = simple_bag(3, mount=None)
    message = error_of(bag_at("nomount", no_mount))
    assert "no transform from 'base_link' to the laser's frame 'laser'" in message
    message = error_of(bag_at("frames", simple_bag(3)), BagOptions(base_frame="base_footprint"))
    assert "no odometry" in message
    assert "--odom-frame and --base-frame" in message
    # No odometry at all.
    message = error_of(bag_at("noodom", simple_bag(3, odometry="none")))
    assert "no odometry: no nav_msgs/Odometry topic, and /tf has no odom -> base_link" in message
    # Odometry whose time span misses every scan.
    late = simple_bag(3)
    for k, group in enumerate(late.tf):
        group[0].stamp = group[0].record = (500 + k) * SEC
    assert "no scan of /scan lies within the time span of the odometry" in error_of(
        bag_at("late", late)
    )
    # A range_max that is no maximum, a NaN angle, a NaN transform.
    bad = simple_bag(3)
    bad.scans[1].range_max = math.inf
    assert "pass --max-range" in error_of(bag_at("inf", bad))
    assert read_rosbag(bag_at("inf2", bad), max_range=8.0).num_poses == 3
    bad = simple_bag(3)
    bad.scans[2].angle_increment = math.nan
    assert "angle_increment nan" in error_of(bag_at("nan", bad))
    bad = simple_bag(3)
    bad.tf[1][0].pose = (math.nan, 0.0, 0.0)
    assert "/tf: the transform odom -> base_link" in error_of(bag_at("nantf", bad))
    bad = simple_bag(3)
    bad.tf[1][0].quaternion = (0.0, 0.0, 0.0, 0.0)
    assert "quaternion of norm 0" in error_of(bag_at("zeroq", bad))


@pytest.mark.parametrize("kind", KINDS)
def test_truncated_and_damaged_bags_are_input_errors(tmp_path: Path, kind: str) -> None:
    path = write_bag(simple_bag(20), tmp_path / "cut", kind)
    storage = (
        path if path.is_file() else next(p for p in path.iterdir() if p.name != "metadata.yaml")
    )
    data = storage.read_bytes()
    rng = np.random.default_rng(len(kind))
    intact = read_rosbag(path)
    for keep in (0.2, 0.6, 0.95, (len(data) - 1) / len(data)):
        storage.write_bytes(data[: int(len(data) * keep)])
        if keep > 0.99 and storage.suffix == ".db3":
            # SQLite reads whole pages: a last page it does not use, cut short, loses nothing.
            np.testing.assert_array_equal(read_rosbag(path).poses, intact.poses)
            continue
        assert "truncated" in error_of(path)
    # Structure overwritten with junk: the ROS 1 bag's header and index, the MCAP header and
    # footer, SQLite's header and its first page's b-tree header. (A damaged message payload
    # reads as other numbers: bags carry no checksums.)
    places = (20, 100) if storage.suffix == ".db3" else (20, len(data) - 40)
    for at in places:
        damaged = bytearray(data)
        damaged[at : at + 16] = rng.integers(0, 256, 16, dtype=np.uint8).tobytes()
        storage.write_bytes(bytes(damaged))
        with pytest.raises(InputError, match="^" + str(path).replace(".", r"\.")):
            read_rosbag(path)


def test_what_is_not_a_bag_says_so(tmp_path: Path) -> None:
    for name, data, phrase in [
        ("text.bag", b"FLASER 3 1 2 3\n", "not a ROS 1 bag (format 2.0)"),
        ("v12.bag", b"#ROSBAG V1.2\n" + bytes(100), "not a ROS 1 bag (format 2.0)"),
        ("empty.db3", b"", "empty file"),
        ("text.db3", b"hello", "not a ROS 2 bag (SQLite 3)"),
        ("zip.mcap", b"PK\x03\x04" + bytes(20), "not an MCAP file"),
    ]:
        path = tmp_path / name
        path.write_bytes(data)
        assert phrase in error_of(path)
    folder = tmp_path / "folder"
    folder.mkdir()
    assert "a directory without metadata.yaml is not a ROS 2 bag" in error_of(folder)
    assert "no such file" in error_of(tmp_path / "missing.bag")
    assert not is_rosbag(folder)
    assert not is_rosbag(tmp_path / "x.clf")
    # A ROS 2 bag directory whose metadata is not YAML.
    bag = write_bag(simple_bag(3), tmp_path / "meta", "sqlite3")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    assert "cannot read the bag" in error_of(bag)


def test_options_are_checked(tmp_path: Path) -> None:
    path = write_bag(simple_bag(3), tmp_path / "ok", "ros1")
    assert "give two frames" in error_of(path, BagOptions(odom_frame="base_link"))
    assert "base_frame is empty" in error_of(path, BagOptions(base_frame="/"))
    for frame in ("odom", "/base_link"):
        assert "give the SLAM's map frame" in error_of(path, BagOptions(map_frame=frame))
    with pytest.raises(InputError, match="max_range must be a finite number"):
        read_rosbag(path, max_range=-1.0)


# --- the map loader and the command line --------------------------------------------------------


def test_load_map_reads_bags_and_refuses_bag_options_elsewhere(tmp_path: Path) -> None:
    path = write_bag(simple_bag(3), tmp_path / "run", "mcap")
    assert load_map(path).num_poses == 3
    assert load_map(next(path.glob("*.mcap"))).num_poses == 3  # the storage file alone
    log = tmp_path / "box.clf"
    log.write_text("FLASER 3 1 2 3 0 0 0 0 0 0 1.0 h 1.0\n")
    with pytest.raises(InputError, match="apply to ROS bags"):
        load_map(log, bag=BagOptions(scan_topic="/scan"))
    assert load_map(log, bag=BagOptions()).num_poses == 1


def test_cli_commands_take_bags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = simple_bag(4)
    bag.more_scans["/rear"] = [
        Scan(s.stamp, np.array([4.0]), 0.0, 0.1, 0.1, 10.0, "base_link") for s in bag.scans
    ]
    path = write_bag(bag, tmp_path / "run", "sqlite3")
    assert main(["metrics", str(path), "--scan-topic", "/rear", "-q"]) == 0
    assert capsys.readouterr().out.startswith(f"{path}: 4 poses, 4 points")
    out = tmp_path / "run.g2o"
    assert main(["export", str(path), "--scan-topic", "/scan", "-o", str(out), "-q"]) == 0
    assert out.read_text().count("VERTEX_SE2") == 4
    capsys.readouterr()
    # Bad input: one line, exit 2, nothing written.
    out2 = tmp_path / "none.g2o"
    assert main(["export", str(path), "-o", str(out2)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"hitl-slam: error: {path}: 2 LaserScan topics (/rear, /scan)")
    assert not out2.exists()
    assert main(["metrics", str(path), "--scan-topic", "/odom_missing"]) == 2
    assert "no topic '/odom_missing'" in capsys.readouterr().err
    log = tmp_path / "box.clf"
    log.write_text("FLASER 3 1 2 3 0 0 0 0 0 0 1.0 h 1.0\n")
    assert main(["metrics", str(log), "--scan-topic", "/scan"]) == 2
    assert "apply to ROS bags" in capsys.readouterr().err


def test_a_missing_ros_extra_is_one_line(tmp_path: Path) -> None:
    path = write_bag(simple_bag(3), tmp_path / "run", "ros1")
    code = (
        "import sys\n"
        "sys.modules['rosbags'] = None\n"
        "from hitl_slam.cli import main\n"
        f"sys.exit(main(['metrics', {str(path)!r}]))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(hitl_slam.__file__).resolve().parents[1])}
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
        env=env,
    )
    assert result.returncode == 2
    assert result.stderr == (
        f"hitl-slam: error: {path}: reading a ROS bag needs the ros extra: "
        "pip install 'rosbags>=0.11' (or, in a clone of hitl-slam: pip install '.[ros]')\n"
    )
    assert result.stdout == ""


def test_a_signalling_nan_range_is_no_point_and_no_warning(tmp_path: Path) -> None:
    import warnings

    path = write_bag(
        simple_bag(2, np.array([1.0, 2.0, 3.0]), frame="base_link"), tmp_path / "s", "ros1"
    )
    data = bytearray(path.read_bytes())
    three = np.float32(3.0).tobytes()
    at = data.index(three)  # the first scan's third range
    data[at : at + 4] = b"\x01\x00\x80\x7f"  # float32 signalling NaN (found by make fuzz)
    path.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = read_rosbag(path)
    np.testing.assert_array_equal(m.offsets, [0, 2, 5])


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
@pytest.mark.parametrize("output", ["run.hitl", "run.clf", "run.g2o"])
def test_slam_on_a_bad_bag_is_one_line_exit_2_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, output: str
) -> None:
    """Issue 14's bad inputs through `hitl-slam slam`: no LaserScan topic, a topic of the wrong
    type, missing TF frames, no odometry, a truncated bag."""
    no_scans = simple_bag(6)
    no_scans.scans = []
    cases: list[tuple[str, Bag, list[str], str]] = [
        ("noscan", no_scans, [], "no sensor_msgs/LaserScan topic"),
        ("wrongtype", simple_bag(6, odometry="topic"), ["--scan-topic", "/odom"], "not sensor"),
        ("nomount", simple_bag(6, mount=None), [], "no transform from 'base_link'"),
        ("noodom", simple_bag(6, odometry="none"), [], "no odometry"),
        ("frames", simple_bag(6), ["--base-frame", "base_footprint"], "no odometry"),
        ("cut", simple_bag(30), [], "truncated"),
    ]
    for name, bag, options, expected in cases:
        path = write_bag(bag, tmp_path / name, kind)
        if name == "cut":
            storage = (
                path
                if path.is_file()
                else next(p for p in path.iterdir() if p.name != "metadata.yaml")
            )
            storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
        out = tmp_path / output
        before = sorted(p.name for p in tmp_path.iterdir())
        assert main(["slam", str(path), "-o", str(out), *options]) == 2, name
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert err.startswith(f"hitl-slam: error: {path}: "), err
        assert expected in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == before, name


def test_serve_reads_the_named_topics_of_a_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`hitl-slam serve BAG` takes the bag options (--scan-topic ...) as the other commands do:
    a bag with two LaserScan topics is refused without one (one line, exit 2, nothing written)
    and served with it."""
    pytest.importorskip("fastapi")
    from hitl_slam.web.server import open_session

    bag = simple_bag(4)
    bag.more_scans["/rear"] = [
        Scan(s.stamp, np.array([4.0]), 0.0, 0.1, 0.1, 10.0, "base_link") for s in bag.scans
    ]
    path = write_bag(bag, tmp_path / "run", "ros1")
    assert main(["serve", str(path), "--no-slam", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "2 LaserScan topics (/rear, /scan)" in err, err
    assert main(["serve", str(path), "--no-slam", "--scan-topic", "/nope", "--port", "0"]) == 2
    assert "no topic '/nope'" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.bag"]
    session, how = open_session(path, front_end=False, bag=BagOptions(scan_topic="/rear"))
    try:
        assert session.input_map.num_poses == 4
        assert session.input_map.num_points == 4  # one beam per /rear scan, not /scan's three
        assert "created the session" in how
    finally:
        session.close()
