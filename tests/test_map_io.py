"""Map file I/O: .covars round trips and errors, CARMEN logs (FLASER, ROBOTLASER1, PARAM, max-range
beams, compression, the public datasets), ground-truth relations, and the exports (TUM, g2o,
occupancy grid), all written atomically.
"""

from __future__ import annotations

import bz2
import gzip
import math
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.io import load_graph
from hitl_slam.io.carmen import PoseSource, infer_max_range, read_carmen
from hitl_slam.io.covars import read_covars, write_covars
from hitl_slam.io.export import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    export,
    occupancy_grid,
    write_g2o_map,
    write_occupancy,
    write_tum,
)
from hitl_slam.io.relations import Relations, match_relations, read_relations
from hitl_slam.map import InformationSource, Map
from reference import wrap

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
LASER = SHARED / "datasets" / "laser"
needs_shared = pytest.mark.skipif(
    not LASER.is_dir(),
    reason=f"public laser datasets not found at {LASER} (the project's ../shared folder)",
)


def assert_error(message: str, path: Path, line: int | None, *phrases: str) -> None:
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert message.startswith(prefix), message
    assert "; " in message[len(prefix) :], f"no advice in: {message}"
    for phrase in phrases:
        assert phrase in message, f"{phrase!r} not in: {message}"


def error_of(function: object, *args: object, **kwargs: object) -> str:
    assert callable(function)
    with pytest.raises(InputError) as excinfo:
        function(*args, **kwargs)
    return str(excinfo.value)


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------------
# .covars


def synthetic_map() -> Map:
    """Five poses: scans with and without normals, one pose without a scan (index 2)."""
    rng = np.random.default_rng(7)
    poses = np.array(
        [[0.0, 0.0, 0.0], [1.0, 0.2, 0.3], [2.1, 0.5, 0.6], [3.0, 1.5, 2.9], [2.5, 3.0, -2.8]]
    )
    counts = [5, 3, 0, 4, 2]
    scans = [rng.uniform(-4, 4, size=(k, 2)) for k in counts]
    normals = []
    for k, scan in zip(counts, scans, strict=True):
        angle = rng.uniform(-math.pi, math.pi, size=k)
        nrm = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        if k == 3:
            nrm[:] = 0.0  # a scan without normals
        normals.append(nrm if len(scan) else np.zeros((0, 2)))
    covariances = np.zeros((5, 3, 3))
    for i in (0, 1, 3, 4):  # pose 2's covariance is unknown
        a = rng.normal(size=(3, 3))
        covariances[i] = a @ a.T + 0.01 * np.eye(3)
    result = Map.from_poses_and_scans(
        poses,
        scans,
        covariances=covariances,
        normals=normals,
        timestamps=np.arange(5, dtype=np.float64) * 0.5 + 100.0,
        name="synthetic room",
    )
    result.metadata["pose_covariances"] = covariances
    return result


def test_covars_round_trip_reproduces_poses_points_normals_and_covariances(
    tmp_path: Path,
) -> None:
    original = synthetic_map()
    moved = original.poses + np.array([0.3, -0.2, 0.1])  # as after a correction
    path = tmp_path / "room.covars"
    write_covars(original, moved, path)
    lines = path.read_text().splitlines()
    assert lines[0] == "synthetic room"
    assert float(lines[1]) == 100.0  # no covars timestamp: the first pose's
    assert len(lines) == 2 + 5 + 3 + 1 + 4 + 2
    assert all(len(line.split(",")) == 16 for line in lines[2:])

    back = read_covars(path)
    assert back.name == "synthetic room"
    assert back.source == str(path)
    assert back.num_poses == 5
    np.testing.assert_allclose(back.poses[:, :2], moved[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap(back.poses[:, 2] - moved[:, 2]), 0.0, atol=1e-12)
    assert back.offsets.tolist() == original.offsets.tolist()
    assert back.offsets[3] - back.offsets[2] == 0  # the pose without a scan stays without
    np.testing.assert_allclose(back.points, original.points, atol=1e-12)
    np.testing.assert_allclose(back.world_points(), original.world_points(moved), atol=1e-12)
    assert back.normals is not None
    assert original.normals is not None
    np.testing.assert_allclose(back.normals, original.normals, atol=1e-12)
    assert np.all(back.normals[5:8] == 0.0)  # "no normal" survives
    cov = back.metadata["pose_covariances"]
    assert np.array_equal(cov, original.metadata["pose_covariances"])
    # Edges 1-2 and 2-3 touch the pose of unknown covariance: motion model; the rest from input.
    assert back.information_source.tolist() == [
        InformationSource.INPUT,
        InformationSource.MOTION_MODEL,
        InformationSource.MOTION_MODEL,
        InformationSource.INPUT,
    ]
    np.testing.assert_allclose(back.information[0], np.linalg.inv(cov[0] + cov[1]), rtol=1e-12)

    # Reading and writing again gives the same file, up to the last bits of the points.
    again = tmp_path / "again.covars"
    write_covars(back, back.poses, again)
    first, second = path.read_text().splitlines(), again.read_text().splitlines()
    assert first[:2] == second[:2]
    a = np.array([[float(v) for v in line.split(",")] for line in first[2:]])
    b = np.array([[float(v) for v in line.split(",")] for line in second[2:]])
    assert np.array_equal(a[:, 7:], b[:, 7:])
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_covars_pose_without_scan_is_one_self_observation(tmp_path: Path) -> None:
    original = synthetic_map()
    path = tmp_path / "m.covars"
    write_covars(original, original.poses, path)
    line = path.read_text().splitlines()[2 + 5 + 3]
    values = [float(v) for v in line.split(",")]
    assert values[:3] == original.poses[2].tolist()
    assert values[3:5] == values[:2]
    assert values[5:7] == [0.0, 0.0]


def test_covars_identical_consecutive_poses_stay_two_poses(tmp_path: Path) -> None:
    poses = np.array([[1.0, 2.0, 0.5], [1.0, 2.0, 0.5], [1.5, 2.0, 0.5]])
    scans = [np.array([[1.0, 0.0]]), np.array([[2.0, 0.0], [2.0, 1.0]]), np.zeros((0, 2))]
    original = Map.from_poses_and_scans(poses, scans)
    path = tmp_path / "still.covars"
    write_covars(original, poses, path)
    back = read_covars(path)
    assert back.num_poses == 3
    assert back.offsets.tolist() == [0, 1, 3, 3]
    np.testing.assert_allclose(back.poses, poses, atol=1e-12)
    assert back.normals is None
    assert np.all(back.metadata["pose_covariances"] == 0)
    assert np.all(back.information_source == InformationSource.MOTION_MODEL)


def test_covars_reader_accepts_spaces_and_converts_to_the_robot_frame(tmp_path: Path) -> None:
    text = (
        "hand written\n12.5\n"
        "1, 0, 1.5707963267948966, 1, 2, 0, 3, 0,0,0, 0,0,0, 0,0,0\n"
        " 1 , 0 , 1.5707963267948966 , 1 , 3 , 0 , 0 , 0,0,0, 0,0,0, 0,0,0 \n\n"
    )
    back = read_covars(write(tmp_path, "h.covars", text))
    assert back.name == "hand written"
    assert back.metadata["covars_timestamp"] == 12.5
    assert back.num_poses == 1
    # Robot facing +y: the world point 2 m ahead is (2, 0) in the robot frame.
    np.testing.assert_allclose(back.points, [[2.0, 0.0], [3.0, 0.0]], atol=1e-15)
    assert back.normals is not None
    np.testing.assert_allclose(back.normals, [[1.0, 0.0], [0.0, 0.0]], atol=1e-15)


COVARS_ROW = "0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1"


@pytest.mark.parametrize(
    ("text", "line", "phrases"),
    [
        ("", None, ("empty file",)),
        ("name only\n", 2, ("missing the timestamp",)),
        ("m\nyesterday\n" + COVARS_ROW + "\n", 2, ("timestamp", "'yesterday'")),
        ("m\n1\n", None, ("no observation lines",)),
        ("m\n1\n" + COVARS_ROW + "\n" + COVARS_ROW + ", 5\n", 4, ("16 comma-separated", "got 17")),
        ("m\n1\n0, 0, 0, 1, 0\n", 3, ("got 5 fields",)),
        ("m\n1\n" + COVARS_ROW.replace("1, 0, 0, 0, 1", "x, 0, 0, 0, 1", 1) + "\n", 3, ("'x'",)),
        ("m\n1\n" + COVARS_ROW.replace("0, 0, 0, 1", "0, nan, 0, 1", 1) + "\n", 3, ("NaN",)),
        ("m\n1\n" + COVARS_ROW.replace("0, 0, 0, 1", "0, 0, 0, inf", 1) + "\n", 3, ("obs_x",)),
        # An empty field next to a field with two numbers must not shift the values.
        ("m\n1\n" + COVARS_ROW.replace("0, 0, 0, 1", "0, 0 0, , 1", 1) + "\n", 3, ("pose_y",)),
    ],
)
def test_covars_errors_name_file_and_line(
    tmp_path: Path, text: str, line: int | None, phrases: tuple[str, ...]
) -> None:
    path = write(tmp_path, "bad.covars", text)
    assert_error(error_of(read_covars, path), path, line, *phrases)


def test_covars_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.covars"
    assert_error(error_of(read_covars, path), path, None, "no such file")


def test_write_covars_rejects_poses_of_the_wrong_shape(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"shape \(5, 3\)"):
        write_covars(synthetic_map(), np.zeros((4, 3)), tmp_path / "x.covars")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# CARMEN


def flaser(
    ranges: list[float],
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    odom: tuple[float, float, float] | None = None,
    stamp: float = 1.0,
) -> str:
    odom = pose if odom is None else odom
    values = " ".join(repr(v) for v in [*ranges, *pose, *odom])
    return f"FLASER {len(ranges)} {values} {stamp!r} host {stamp + 0.01!r}"


def robotlaser(
    ranges: list[float],
    *,
    start: float,
    step: float,
    max_range: float,
    laser_pose: tuple[float, float, float],
    robot_pose: tuple[float, float, float],
    remissions: int = 2,
    stamp: float = 5.0,
) -> str:
    head = f"ROBOTLASER1 0 {start!r} {step * (len(ranges) - 1)!r} {step!r} {max_range!r} 0.01 0"
    beams = " ".join(repr(r) for r in ranges)
    rem = " ".join(["0.5"] * remissions)
    poses = " ".join(repr(v) for v in [*laser_pose, *robot_pose])
    return (
        f"{head} {len(ranges)} {beams} {remissions} {rem} {poses} 0.1 0.2 0.3 0.4 0.5 "
        f"{stamp!r} host {stamp + 0.01!r}"
    )


def angles_of(points: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.degrees(np.arctan2(points[:, 1], points[:, 0]))


@pytest.mark.parametrize(
    ("n", "last_degrees"), [(180, 89.0), (181, 90.0), (360, 89.5), (361, 90.0)]
)
def test_flaser_beam_angles(tmp_path: Path, n: int, last_degrees: float) -> None:
    path = write(tmp_path, "a.clf", flaser([2.0] * n) + "\n")
    result = read_carmen(path)
    assert result.num_points == n
    angles = angles_of(result.points)
    assert angles[0] == pytest.approx(-90.0)
    assert angles[-1] == pytest.approx(last_degrees)
    np.testing.assert_allclose(np.diff(angles), (last_degrees + 90.0) / (n - 1))
    np.testing.assert_allclose(np.hypot(*result.points.T), 2.0)


def test_flaser_poses_timestamps_chain_and_skipped_tags(tmp_path: Path) -> None:
    text = "\n".join(
        [
            "# CARMEN Logfile",
            "ODOM 0 0 0 0 0 0 0.5 host 0.5",
            flaser([1.0] * 180, pose=(1.0, 2.0, 0.5), stamp=10.0),
            "ODOM 0 0 0 0 0 0 10.5 host 10.5",
            "SYNC x 11 host 11",
            flaser([1.0] * 180, pose=(2.0, 2.0, 4.0), stamp=11.0),
            "",
        ]
    )
    result = read_carmen(write(tmp_path, "p.log", text))
    np.testing.assert_allclose(result.poses, [[1.0, 2.0, 0.5], [2.0, 2.0, 4.0 - 2 * math.pi]])
    assert result.timestamps is not None
    assert result.timestamps.tolist() == [10.0, 11.0]
    assert result.edges.tolist() == [[0, 1]]
    assert result.name == "p"
    assert result.metadata["skipped_lines"] == {"ODOM": 2, "SYNC": 1}
    assert result.metadata["scan_lines"].tolist() == [3, 6]
    # A point in the robot (laser) frame lands at pose * point in the world.
    ahead = result.world_points()[90]
    np.testing.assert_allclose(ahead, [1.0 + math.cos(0.5), 2.0 + math.sin(0.5)], atol=1e-12)


def test_max_range_and_invalid_beams_are_not_points(tmp_path: Path) -> None:
    ranges = [1.0, 79.99, 80.0, 81.83, 0.0, -1.0, float("nan"), float("inf"), 79.998] + [3.0] * 171
    path = write(tmp_path, "m.clf", flaser(ranges) + "\n")
    kept = np.hypot(*read_carmen(path).points.T)
    assert kept[:4].tolist() == pytest.approx([1.0, 79.99, 79.998, 3.0])
    assert len(kept) == 3 + 171
    # The PARAM sets the FLASER maximum range; the keyword overrides everything.
    with_param = write(
        tmp_path, "p.clf", "PARAM robot_front_laser_max 50.0 0 h 0\n" + flaser(ranges)
    )
    assert len(read_carmen(with_param).points) == 1 + 171
    assert len(read_carmen(path, max_range=2.0).points) == 1
    assert len(read_carmen(path, max_range=100.0).points) == 5 + 171


def _room_log(no_return: float, scans: int = 40, seed: int = 0, param: str = "") -> str:
    """A robot turning in a 6 m room whose door lets some beams out: those read `no_return`
    (the sensor's value for no echo), spread by rounding over a few centimetres."""
    rng = np.random.default_rng(seed)
    lines = [param] if param else []
    for k in range(scans):
        theta = 0.1 * k
        ranges = 2.0 + 1.0 * np.abs(np.sin(np.linspace(0, 3, 180) + theta))
        ranges += rng.normal(0, 0.01, 180)
        door = slice(60 + k % 20, 75 + k % 20)
        ranges[door] = no_return - rng.choice([0.0, 0.01, 0.02], ranges[door].size)
        lines.append(flaser(ranges.tolist(), pose=(0.0, 0.0, theta), stamp=1.0 + k))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("no_return", [50.0, 32.767, 8.191])
@pytest.mark.parametrize("seed", [0, 3])
def test_no_returns_of_a_silent_log_are_inferred_and_dropped(
    tmp_path: Path, no_return: float, seed: int
) -> None:
    path = write(tmp_path, "silent.clf", _room_log(no_return, seed=seed))
    result = read_carmen(path)
    ranges = np.hypot(*result.points.T)
    assert ranges.max() < 3.2  # no phantom ring at the sensor's maximum
    assert result.metadata["max_range_source"].startswith("inferred: 600 readings piled at")
    assert result.metadata["flaser_max_range"] == pytest.approx(no_return - 0.02)
    # A PARAM or --max-range wins over the inference.
    with_param = write(
        tmp_path,
        "param.clf",
        _room_log(no_return, seed=seed, param="PARAM robot_front_laser_max 80.0 0 h 0"),
    )
    kept = read_carmen(with_param)
    assert kept.metadata["max_range_source"] == "PARAM robot_front_laser_max"
    assert np.hypot(*kept.points.T).max() > no_return - 0.1
    given = read_carmen(path, max_range=2.5)
    assert given.metadata["max_range_source"] == "given (--max-range)"
    assert np.hypot(*given.points.T).max() < 2.5


def test_far_real_returns_are_not_mistaken_for_no_returns(tmp_path: Path) -> None:
    # A long hall: the farthest readings spread over metres, they do not pile at one value.
    rng = np.random.default_rng(1)
    lines = [
        flaser(rng.uniform(1.0, 40.0, 180).tolist(), pose=(0.0, 0.0, 0.1 * k), stamp=1.0 + k)
        for k in range(50)
    ]
    result = read_carmen(write(tmp_path, "hall.clf", "\n".join(lines) + "\n"))
    assert result.num_points == 50 * 180
    assert result.metadata["max_range_source"].startswith("default 80 m")


def test_infer_max_range_needs_a_pile() -> None:
    assert infer_max_range(np.array([1.0, 2.0, 3.0])) is None
    assert infer_max_range(np.array([np.nan, -1.0, 0.0])) is None
    piled = np.concatenate([np.linspace(0.5, 20.0, 500), np.full(30, 25.0)])
    assert infer_max_range(piled) == (25.0, 30)


def test_laser_offset_param_and_pose_source(tmp_path: Path) -> None:
    robot = (1.0, 2.0, 0.5)
    forward, side, turn = -0.04, 0.1, 0.2
    c, s = math.cos(robot[2]), math.sin(robot[2])
    laser = (robot[0] + c * forward - s * side, robot[1] + s * forward + c * side, robot[2] + turn)
    text = (
        f"PARAM robot_frontlaser_offset {forward} 0 h 0\n"
        f"PARAM robot_frontlaser_side_offset {side} 0 h 0\n"
        f"PARAM robot_frontlaser_angular_offset {turn} 0 h 0\n"
        + flaser([1.0] * 180, pose=(9.0, 9.0, 0.0), odom=robot)
        + "\n"
    )
    path = write(tmp_path, "o.clf", text)
    logged = read_carmen(path)
    odometry = read_carmen(path, pose_source=PoseSource.ODOMETRY)
    np.testing.assert_allclose(logged.poses, [[9.0, 9.0, 0.0]])
    np.testing.assert_allclose(odometry.poses, [laser], atol=1e-15)
    assert odometry.metadata["laser_offset"] == [forward, side, turn]
    assert odometry.metadata["pose_source"] == "odometry"
    # The sensor origin is the pose position: points are in the laser frame either way.
    np.testing.assert_allclose(logged.points, odometry.points)


def test_robotlaser1_uses_its_own_geometry_and_laser_pose(tmp_path: Path) -> None:
    ranges = [1.0, 2.0, 9.9995, 3.0, 12.0]
    text = "\n".join(
        [
            flaser([5.0] * 180, stamp=4.0),  # the same scan in the old format: skipped
            robotlaser(
                ranges,
                start=-1.0,
                step=0.25,
                max_range=10.0,
                laser_pose=(1.0, 1.0, 0.3),
                robot_pose=(0.9, 1.0, 0.3),
            ),
        ]
    )
    result = read_carmen(write(tmp_path, "r.log", text))
    assert result.num_poses == 1
    assert result.metadata["laser"] == "ROBOTLASER1"
    assert result.metadata["skipped_lines"] == {"FLASER": 1}
    np.testing.assert_allclose(result.poses, [[1.0, 1.0, 0.3]])
    assert result.timestamps is not None
    assert result.timestamps.tolist() == [5.0]
    np.testing.assert_allclose(np.hypot(*result.points.T), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(angles_of(result.points), np.degrees([-1.0, -0.75, -0.25]))


def test_robotlaser1_without_remissions(tmp_path: Path) -> None:
    line = robotlaser(
        [1.0, 1.0],
        start=0.0,
        step=0.5,
        max_range=4.0,
        laser_pose=(0.0, 0.0, 0.0),
        robot_pose=(0.0, 0.0, 0.0),
        remissions=0,
    )
    assert read_carmen(write(tmp_path, "r0.log", line + "\n")).num_points == 2


@pytest.mark.parametrize("suffix", [".gz", ".bz2"])
def test_compressed_logs(tmp_path: Path, suffix: str) -> None:
    data = (flaser([1.0] * 180) + "\n" + flaser([2.0] * 180, stamp=2.0) + "\n").encode()
    path = tmp_path / f"log.clf{suffix}"
    path.write_bytes(gzip.compress(data) if suffix == ".gz" else bz2.compress(data))
    result = read_carmen(path)
    assert result.num_poses == 2
    assert result.num_points == 360
    assert result.name == "log"


def test_min_travel_subsampling(tmp_path: Path) -> None:
    lines = [flaser([1.0] * 180, pose=(0.1 * k, 0.0, 0.0), stamp=float(k)) for k in range(10)]
    lines.append(flaser([1.0] * 180, pose=(0.9, 0.0, 1.0), stamp=10.0))
    path = write(tmp_path, "s.clf", "\n".join(lines))
    assert read_carmen(path).num_poses == 11
    kept = read_carmen(path, min_travel=0.25)
    assert kept.timestamps is not None
    assert kept.timestamps.tolist() == [0.0, 3.0, 6.0, 9.0]
    turned = read_carmen(path, min_travel=0.25, min_rotation=0.5)
    assert turned.timestamps is not None
    assert turned.timestamps.tolist() == [0.0, 3.0, 6.0, 9.0, 10.0]


GOOD = flaser([1.0] * 180)


@pytest.mark.parametrize(
    ("text", "line", "phrases"),
    [
        ("", None, ("empty log",)),
        ("# only a comment\n\n", None, ("empty log",)),
        ("ODOM 0 0 0 0 0 0 1 h 1\nODOM 0 0 0 0 0 0 2 h 2\n", None, ("no laser lines", "ODOM x2")),
        (GOOD + "\n" + GOOD.replace("FLASER 180", "FLASER 181"), 2, ("181 beams", "got 190")),
        (GOOD + "\n" + GOOD.replace("FLASER 180", "FLASER 179"), 2, ("179 beams", "got 190")),
        ("FLASER x " + GOOD[11:], 1, ("'x'", "number of beams")),
        ("FLASER 0 0 0 0 0 0 0 1 h 1", 1, ("number of beams of FLASER is 0",)),
        ("FLASER", 1, ("without a number of beams",)),
        (GOOD.replace(" 1.0 ", " 1.0x ", 1), 1, ("'1.0x'", "range 1", "field 2")),
        (flaser([1.0] * 180, pose=(0.0, float("nan"), 0.0)), 1, ("y is 'nan'", "NaN")),
        (flaser([1.0] * 180, stamp=float("inf")), 1, ("ipc_timestamp", "NaN/inf")),
        ("PARAM robot_frontlaser_offset abc 0 h 0\n" + GOOD, 1, ("'abc'",)),
        ("PARAM robot_front_laser_max -3 0 h 0\n" + GOOD, 1, ("not a positive range",)),
        ("ROBOTLASER1 0 0 3.14 0.01 80", 1, ("too short",)),
        ("ROBOTLASER1 0 0 3.14 0.01 80 0.01 0 3 1 2", 1, ("declares 3 beams",)),
        ("ROBOTLASER1 0 0 3.14 0.01 80 0.01 0 2 1 2 0 1 2 3", 1, ("needs 25 fields", "got 14")),
    ],
)
def test_carmen_errors_name_file_and_line(
    tmp_path: Path, text: str, line: int | None, phrases: tuple[str, ...]
) -> None:
    path = write(tmp_path, "bad.clf", text)
    assert_error(error_of(read_carmen, path), path, line, *phrases)


def test_carmen_argument_errors(tmp_path: Path) -> None:
    path = write(tmp_path, "ok.clf", GOOD)
    for kwargs in ({"max_range": 0.0}, {"min_travel": -1.0}, {"min_rotation": float("nan")}):
        with pytest.raises(InputError):
            read_carmen(path, **kwargs)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# The public laser datasets

_CACHE: dict[str, Map] = {}


def dataset(name: str) -> Map:
    if name not in _CACHE:
        _CACHE[name] = read_carmen(LASER / name)
    return _CACHE[name]


@needs_shared
@pytest.mark.parametrize(
    ("name", "scans", "beams"),
    [
        ("freiburg-079-corrected.log.gz", 4791, 360),
        ("intel-corrected.log.gz", 910, 180),
        ("fr079.clf.bz2", 4934, 360),
        ("intel.clf.bz2", 13631, 180),
    ],
)
def test_public_logs_load_with_their_scan_counts(name: str, scans: int, beams: int) -> None:
    start = time.perf_counter()
    result = dataset(name)
    elapsed = time.perf_counter() - start
    assert result.num_poses == scans
    assert result.metadata["scans_in_log"] == scans
    assert result.timestamps is not None
    assert np.all(np.isfinite(result.timestamps))  # not monotonic: intel.clf steps back once
    counts = np.diff(result.offsets)
    assert counts.max() <= beams
    assert counts.max() > beams // 2
    # The beams of the first scan sit on the log's angular grid starting at -90 degrees.
    steps = (angles_of(result.points[: counts[0]]) + 90.0) / (180.0 / beams)
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    if name in ("fr079.clf.bz2", "freiburg-079-corrected.log.gz"):
        assert elapsed < 6.0, f"{name} took {elapsed:.2f} s"


@needs_shared
def test_freiburg_079_corrected_map_is_the_building() -> None:
    result = dataset("freiburg-079-corrected.log.gz")
    world = result.world_points()
    low, high = world.min(axis=0), world.max(axis=0)
    width, height = high - low
    assert 40.0 < width < 50.0, (low, high)  # Freiburg building 079: about 45 m x 17 m
    assert 14.0 < height < 20.0, (low, high)
    assert np.all(np.abs(result.poses[:, :2] - (low + high) / 2) < (high - low) / 2)
    assert result.metadata["flaser_max_range"] == 80.99  # from its PARAM lines
    assert result.num_points > 1_500_000


@needs_shared
def test_fr079_logged_pose_is_odometry_composed_with_the_laser_offset() -> None:
    logged = dataset("fr079.clf.bz2")
    odometry = read_carmen(LASER / "fr079.clf.bz2", pose_source=PoseSource.ODOMETRY)
    assert odometry.metadata["laser_offset"] == [-0.04, 0.0, 0.0]
    difference = logged.poses - odometry.poses
    difference[:, 2] = wrap(difference[:, 2])
    assert np.abs(difference).max() < 5e-6  # the log prints 6 decimals


@needs_shared
@pytest.mark.parametrize(("log", "relations"), [("fr079.clf.bz2", "fr079.relations")])
def test_relations_match_the_scans_of_their_log(log: str, relations: str) -> None:
    result = dataset(log)
    truth = read_relations(LASER / relations)
    assert len(truth) == sum(1 for line in (LASER / relations).open() if line.strip())
    assert result.timestamps is not None
    pairs = match_relations(truth, result.timestamps, tolerance=1e-5)
    assert pairs.shape == (len(truth), 2)
    assert pairs.dtype == np.int64
    np.testing.assert_allclose(result.timestamps[pairs[:, 0]], truth.t1, atol=1e-5)
    np.testing.assert_allclose(result.timestamps[pairs[:, 1]], truth.t2, atol=1e-5)


@needs_shared
def test_intel_relations_match_intel_clf() -> None:
    result = dataset("intel.clf.bz2")
    truth = read_relations(LASER / "intel.relations")
    assert result.timestamps is not None
    pairs = match_relations(truth, result.timestamps, tolerance=1e-5)
    np.testing.assert_allclose(
        result.timestamps[pairs], np.stack([truth.t1, truth.t2], 1), atol=1e-5
    )


@needs_shared
def test_occupancy_grid_of_freiburg_079(tmp_path: Path) -> None:
    result = dataset("freiburg-079-corrected.log.gz")
    start = time.perf_counter()
    grid = write_occupancy(result, result.poses, tmp_path / "fr079.pgm")
    elapsed = time.perf_counter() - start
    assert elapsed < 10.0
    values, counts = np.unique(grid.image, return_counts=True)
    share = dict(zip(values.tolist(), (counts / grid.image.size).tolist(), strict=True))
    assert share[OCCUPIED] > 0.02
    assert share[FREE] > 0.4


# ---------------------------------------------------------------------------------------------
# .relations


def test_relations_read_and_match(tmp_path: Path) -> None:
    text = (
        "# t1 t2 dx dy dz roll pitch yaw\n10.0 11.0 0.5 -0.1 0 0 0 0.2\n\n11.0 12.5 1 2 0 0 0 4\n"
    )
    path = write(tmp_path, "r.relations", text)
    truth = read_relations(path)
    assert isinstance(truth, Relations)
    assert len(truth) == 2
    assert truth.t1.tolist() == [10.0, 11.0]
    assert truth.t2.tolist() == [11.0, 12.5]
    np.testing.assert_allclose(truth.relative, [[0.5, -0.1, 0.2], [1.0, 2.0, 4.0 - 2 * math.pi]])
    assert truth.lines.tolist() == [2, 4]
    stamps = np.array([12.5004, 9.0, 11.00002, 10.0])  # any order
    assert match_relations(truth, stamps).tolist() == [[3, 2], [2, 0]]
    message = error_of(match_relations, truth, stamps, tolerance=1e-4)
    assert_error(message, path, 4, "relation 2", "t2 = 12.5", "12.5004")


@pytest.mark.parametrize(
    ("text", "line", "phrases"),
    [
        ("", None, ("no relations",)),
        ("1 2 3 4 5 6 7\n", 1, ("expected 8 numbers", "got 7")),
        ("1 2 3 4 5 6 7 8\n1 2 3 4 5 6 7 x\n", 2, ("'x'", "yaw")),
        ("1 2 nan 4 5 6 7 8\n", 1, ("'nan'", "dx")),
    ],
)
def test_relations_errors(
    tmp_path: Path, text: str, line: int | None, phrases: tuple[str, ...]
) -> None:
    path = write(tmp_path, "bad.relations", text)
    assert_error(error_of(read_relations, path), path, line, *phrases)


def test_match_relations_needs_timestamps(tmp_path: Path) -> None:
    truth = read_relations(write(tmp_path, "r.relations", "1 2 0 0 0 0 0 0\n"))
    with pytest.raises(InputError, match="no usable timestamps"):
        match_relations(truth, np.zeros(0))
    assert match_relations(truth, np.array([1.5]), tolerance=1.0).tolist() == [[0, 0]]


# ---------------------------------------------------------------------------------------------
# Exports


def test_tum_export_values(tmp_path: Path) -> None:
    original = synthetic_map()
    path = tmp_path / "t.txt"
    write_tum(original, original.poses, path)
    rows = np.loadtxt(path)
    assert rows.shape == (5, 8)
    assert original.timestamps is not None
    assert rows[:, 0].tolist() == original.timestamps.tolist()
    assert rows[:, 1:3].tolist() == original.poses[:, :2].tolist()
    assert np.all(rows[:, 3:6] == 0.0)
    theta = 2 * np.arctan2(rows[:, 6], rows[:, 7])
    np.testing.assert_allclose(wrap(theta - original.poses[:, 2]), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(rows[:, 4:8], axis=1), 1.0)
    # Without timestamps the pose index is the time.
    plain = Map.from_poses_and_scans(original.poses, [np.zeros((0, 2))] * 5)
    write_tum(plain, plain.poses, path)
    assert np.loadtxt(path)[:, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_g2o_export_keeps_the_original_factors(tmp_path: Path) -> None:
    original = synthetic_map()
    moved = original.poses + 0.25
    path = tmp_path / "m.g2o"
    write_g2o_map(original, moved, path)
    graph = load_graph(path)
    np.testing.assert_allclose(graph.poses[:, :2], moved[:, :2])
    np.testing.assert_allclose(wrap(graph.poses[:, 2] - moved[:, 2]), 0.0, atol=1e-15)
    assert graph.edges.tolist() == original.edges.tolist()
    np.testing.assert_allclose(graph.measurements, original.measurements, atol=1e-15)
    np.testing.assert_allclose(graph.information, original.information, rtol=1e-12)


HALF = 2.01  # the room's walls sit at x, y = +-2.01 m, inside 5 cm cells


def room_scan(pose: NDArray[np.float64], beams: int, fov: float) -> NDArray[np.float64]:
    """Robot-frame points of a laser at ``pose`` inside the square room, ray cast exactly."""
    angles = -fov / 2 + fov * np.arange(beams) / beams
    world_angles = angles + pose[2]
    d = np.stack([np.cos(world_angles), np.sin(world_angles)], axis=1)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (HALF - pose[:2]) / d, np.where(d < 0, (-HALF - pose[:2]) / d, np.inf))
    r = t.min(axis=1)
    return np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)


def room_map() -> Map:
    poses = np.array([[0.0, 0.0, 0.0], [0.5, -0.6, 1.2], [-0.8, 0.7, 2.8], [1.0, 1.0, -2.0]])
    scans = [room_scan(p, 360, 2 * math.pi) for p in poses[:2]]
    scans += [room_scan(p, 181, math.pi) for p in poses[2:]]
    return Map.from_poses_and_scans(poses, scans, name="room")


def test_occupancy_grid_of_a_square_room() -> None:
    room = room_map()
    grid = occupancy_grid(room, room.poses, resolution=0.05)
    assert grid.resolution == 0.05
    inside = np.linspace(-1.9, 1.9, 39)
    free = [grid.value_at(x, y) == FREE for x in inside for y in inside]
    assert np.mean(free) > 0.97
    wall = np.linspace(-1.95, 1.95, 40)
    walls = [grid.value_at(HALF, y) for y in wall] + [grid.value_at(x, -HALF) for x in wall]
    walls += [grid.value_at(-HALF, y) for y in wall] + [grid.value_at(x, HALF) for x in wall]
    assert np.mean(np.array(walls) == OCCUPIED) > 0.97
    for x, y in [(2.2, 0.0), (0.0, -2.3), (3.0, 3.0), (-2.15, 1.0)]:
        assert grid.value_at(x, y) == UNKNOWN
    # Free space stops a cell before the wall; the wall is not cleared by grazing beams.
    assert grid.value_at(HALF - 0.1, 0.3) == FREE
    row, column = grid.cell(0.3, HALF)
    assert grid.free_counts[row, column] == 0
    assert grid.hit_counts[row, column] >= 1


def test_occupancy_grid_orientation_origin_and_unseen_grid() -> None:
    room = room_map()
    grid = occupancy_grid(room, room.poses, resolution=0.1)
    height, width = grid.image.shape
    # Row 0 is the top (largest y): the top wall is near row 0, the bottom wall near the end.
    assert grid.cell(0.0, HALF)[0] < 4
    assert grid.cell(0.0, -HALF)[0] > height - 5
    ox, oy = grid.origin
    assert ox == pytest.approx(-2.3)
    assert oy == pytest.approx(-2.3)
    assert ox + width * 0.1 > HALF
    assert oy + height * 0.1 > HALF


def brute_force_free_counts(room: Map, res: float, margin: float) -> NDArray[np.int64]:
    """The free-space definition cell by cell: centres inside a cut-back fan triangle."""
    grid = occupancy_grid(room, room.poses, resolution=res, surface_margin=margin)
    height, width = grid.image.shape
    ox, oy = grid.origin
    xs = ox + (np.arange(width) + 0.5) * res
    ys = oy + (np.arange(height)[::-1] + 0.5) * res
    cx, cy = np.meshgrid(xs, ys)
    counts = np.zeros((height, width), dtype=np.int64)
    for i in range(room.num_poses):
        pts = room.points[room.offsets[i] : room.offsets[i + 1]]
        order = np.argsort(np.arctan2(pts[:, 1], pts[:, 0]))
        pts = pts[order]
        angle = np.arctan2(pts[:, 1], pts[:, 0])
        gaps = np.diff(angle)
        median = np.sort(gaps)[(len(gaps) - 1) // 2]
        pairs = [(k, k + 1) for k in range(len(pts) - 1) if gaps[k] <= 5.5 * median]
        if angle[0] + 2 * math.pi - angle[-1] <= 5.5 * median:
            pairs.append((len(pts) - 1, 0))
        x, y, th = room.poses[i]
        c, s = math.cos(th), math.sin(th)
        lx, ly = c * (cx - x) + s * (cy - y), -s * (cx - x) + c * (cy - y)
        inside = np.zeros_like(cx, dtype=bool)
        for a_idx, b_idx in pairs:
            a, b = pts[a_idx], pts[b_idx]
            depth = (a[0] * b[1] - a[1] * b[0]) / np.hypot(*(b - a))
            if depth <= margin:
                continue
            a, b = a * (1 - margin / depth), b * (1 - margin / depth)
            # Inside the triangle (0, a, b), counter-clockwise.
            e1 = a[0] * ly - a[1] * lx >= 0
            e2 = (b[0] - a[0]) * (ly - a[1]) - (b[1] - a[1]) * (lx - a[0]) >= 0
            e3 = -b[0] * (ly - b[1]) + b[1] * (lx - b[0]) >= 0
            inside |= e1 & e2 & e3
        counts += inside
    return counts


@pytest.mark.parametrize(("res", "margin"), [(0.1, 0.05), (0.07, 0.0), (0.05, 0.2)])
def test_free_space_rasterization_matches_the_definition(res: float, margin: float) -> None:
    rng = np.random.default_rng(3)
    room = room_map()
    # Jitter the ranges so no cell centre sits exactly on a triangle edge.
    room.points = room.points * rng.uniform(0.9, 1.0, size=(room.num_points, 1))
    grid = occupancy_grid(room, room.poses, resolution=res, surface_margin=margin)
    expected = brute_force_free_counts(room, res, margin)
    mismatch = np.count_nonzero(grid.free_counts != expected)
    assert mismatch <= 0.001 * expected.size, mismatch


def parse_yaml(path: Path) -> dict[str, str]:
    entries = {}
    for line in path.read_text().splitlines():
        key, _, value = line.partition(":")
        entries[key.strip()] = value.strip()
    return entries


def test_occupancy_files_for_map_server(tmp_path: Path) -> None:
    room = room_map()
    pgm = tmp_path / "room.pgm"
    grid = write_occupancy(room, room.poses, pgm, resolution=0.05)
    data = pgm.read_bytes()
    lines = data.split(b"\n", 3)
    assert lines[0] == b"P5"
    assert lines[1].startswith(b"#")
    width, height = (int(v) for v in lines[2].split())
    assert (height, width) == grid.image.shape
    header_end = data.index(b"\n255\n") + 5
    pixels = np.frombuffer(data[header_end:], dtype=np.uint8).reshape(height, width)
    assert np.array_equal(pixels, grid.image)
    assert set(np.unique(pixels).tolist()) == {FREE, OCCUPIED, UNKNOWN}

    yaml = parse_yaml(tmp_path / "room.yaml")
    assert yaml["image"] == "room.pgm"
    assert float(yaml["resolution"]) == 0.05
    origin = [float(v) for v in yaml["origin"].strip("[]").split(",")]
    assert origin == [grid.origin[0], grid.origin[1], 0.0]
    assert yaml["negate"] == "0"
    assert float(yaml["occupied_thresh"]) == 0.65
    assert float(yaml["free_thresh"]) == 0.196
    assert yaml["mode"] == "trinary"
    # map_server's reading: a world point maps back to the pixel the grid says.
    x, y = HALF, 0.3
    column = math.floor((x - origin[0]) / 0.05)
    row = height - 1 - math.floor((y - origin[1]) / 0.05)
    assert pixels[row, column] == OCCUPIED


def test_occupancy_yaml_quotes_an_awkward_image_name(tmp_path: Path) -> None:
    room = room_map()
    write_occupancy(room, room.poses, tmp_path / "my map: v2.pgm", resolution=0.1)
    assert parse_yaml(tmp_path / "my map: v2.yaml")["image"] == '"my map: v2.pgm"'


def test_export_dispatches_on_extension_and_leaves_no_temporary_files(tmp_path: Path) -> None:
    room = room_map()
    for name in ("m.covars", "m.clf", "m.g2o", "m.txt", "m.pgm"):
        export(room, room.poses, tmp_path / name)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "m.clf",
        "m.covars",
        "m.g2o",
        "m.pgm",
        "m.txt",
        "m.yaml",
    ]
    assert read_covars(tmp_path / "m.covars").num_points == room.num_points
    path = tmp_path / "m.bmp"
    message = error_of(export, room, room.poses, path)
    assert_error(message, path, None, "'.bmp'", ".covars, .clf, .g2o, .txt, .pgm, .png, .svg")
    assert not path.exists()


def test_a_failed_export_keeps_the_old_file(tmp_path: Path) -> None:
    room = room_map()
    path = tmp_path / "keep.txt"
    path.write_text("old\n")
    with pytest.raises(InputError):
        export(room, np.full((room.num_poses, 3), np.nan), path)
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
