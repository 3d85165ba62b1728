"""Bad inputs found by fuzzing (a far-off pose, silent reader warnings, degenerate beam
geometry, maps without points, garbage ranges, huge tokens, smaller gaps): each gets a clear
error or a visible warning naming the file (and line), never an allocation blow-up or a panic."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bag_support import Bag, Scan, Transform, write_bag
from hitl_slam.cli import main
from hitl_slam.errors import InputError
from hitl_slam.io import load_graph
from hitl_slam.io.carmen import read_carmen
from hitl_slam.io.maps import load_map
from hitl_slam.io.rosbag import read_rosbag
from hitl_slam.slam import slam

SEC = 1_000_000_000


def room_ranges(n: int = 180) -> list[float]:
    """A 180-degree scan of a 4 x 6 m box from its middle (every beam a return)."""
    out = []
    for k in range(n):
        a = math.radians(-90.0 + k * 180.0 / n)
        c, s = math.cos(a), math.sin(a)
        t = min(2.0 / abs(c) if abs(c) > 1e-9 else 1e9, 3.0 / abs(s) if abs(s) > 1e-9 else 1e9)
        out.append(round(t, 3))
    return out


def flaser(
    ranges: list[float], pose: tuple[float, float, float] = (0.0, 0.0, 0.0), stamp: float = 1.0
) -> str:
    values = " ".join(repr(v) for v in [*ranges, *pose, *pose])
    return f"FLASER {len(ranges)} {values} {stamp!r} host {stamp!r}"


def carmen_log(tmp_path: Path, lines: list[str], name: str = "a.log") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def robotlaser(ranges: list[float], *, fov: float, resolution: float, stamp: float = 1.0) -> str:
    beams = " ".join(repr(r) for r in ranges)
    return (
        f"ROBOTLASER1 0 -1.5 {fov!r} {resolution!r} 30.0 0.01 0 {len(ranges)} {beams} 0 "
        f"0 0 0 0 0 0 0 0 0 0 0 {stamp!r} host {stamp!r}"
    )


# --- 1. a pose far from the others ------------------------------------------------------------


@pytest.mark.parametrize("far", [1e6, 1e9])
def test_slam_with_a_far_off_pose_is_refused_naming_the_scan_and_line(
    tmp_path: Path, far: float, capsys: pytest.CaptureFixture[str]
) -> None:
    ranges = room_ranges()
    poses = [(0.05 * k, 0.0, 0.0) for k in range(8)]
    poses[5] = (far, 0.0, 0.0)
    lines = [flaser(ranges, p, 1.0 + k) for k, p in enumerate(poses)]
    path = carmen_log(tmp_path, lines)
    with pytest.raises(InputError) as caught:
        slam(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:6: scan 6 of 8 is at ("), message
    assert "too large" in message
    assert "split it" in message
    out = tmp_path / "out.g2o"
    assert main(["slam", str(path), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hitl-slam: error: {path}:6: scan 6 of 8"), err
    assert "panicked" not in err
    assert not out.exists()


# --- 2. reader warnings reach the CLI's stderr ------------------------------------------------

G2O_CHAIN = [
    "VERTEX_SE2 0 0 0 0",
    "VERTEX_SE2 1 1 0 0",
    "VERTEX_SE2 2 2 0.1 0",
    "EDGE_SE2 0 1 1 0 0 100 0 0 100 0 1000",
    "EDGE_SE2 1 2 1 0 0 100 0 0 100 0 1000",
]


def test_cli_shows_skipped_tags_of_a_g2o_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "a.g2o"
    path.write_text("\n".join([*G2O_CHAIN, "VERTEX_XY 7 1 2"]) + "\n")
    assert main(["solve", str(path), "-o", str(tmp_path / "o.g2o"), "-q"]) == 0
    err = capsys.readouterr().err
    assert f"hitl-slam: {path}: ignored what the g2o reader does not use: VERTEX_XY x1" in err
    assert "line 6" in err


def test_cli_shows_skipped_tags_of_a_toro_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "a.graph"
    path.write_text(
        "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 100 0 100 1000 0 0\n"
        "VERTEX3 2 0 0 0 0 0 0\n"
    )
    assert main(["solve", str(path), "-o", str(tmp_path / "o.graph"), "-q"]) == 0
    assert "VERTEX3 x1 (first at line 4)" in capsys.readouterr().err


def test_lowercase_g2o_tags_are_reported_and_the_start_is_not_called_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # g2o's own reader matches tags exactly (its factory is a map from the tag string), so
    # `vertex_se2` is not a vertex there either: skipped, but said, with the likely meaning.
    path = tmp_path / "a.g2o"
    path.write_text("\n".join(line.lower() if line.startswith("V") else line for line in G2O_CHAIN))
    assert main(["solve", str(path), "-o", str(tmp_path / "o.g2o")]) == 0
    captured = capsys.readouterr()
    assert "vertex_se2 x3 (first at line 1; tags are case-sensitive: VERTEX_SE2?)" in captured.err
    assert "start: given, chained from the edges" in captured.out


def test_importing_the_library_stays_quiet(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "a.g2o"
    path.write_text("\n".join([*G2O_CHAIN, "VERTEX_XY 7 1 2"]) + "\n")
    load_graph(path)
    assert capsys.readouterr().err == ""


def test_cli_warns_about_covariances_that_are_not_positive_definite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rows = []
    for k in range(3):
        cov = [-1.0, 0, 0, 0, 0.01, 0, 0, 0, 0.01]
        for j in range(3):
            rows.append(", ".join(repr(float(v)) for v in [k, 0, 0, k + 1, j * 0.1, 0, 0, *cov]))
    path = tmp_path / "a.covars"
    path.write_text("room\n0.0\n" + "\n".join(rows) + "\n")
    out = tmp_path / "o.covars"
    assert main(["export", str(path), "-o", str(out), "-q"]) == 0
    err = capsys.readouterr().err
    assert f"hitl-slam: {path}:3: the covariance of 3 of 3 poses is not symmetric" in err


# --- 3. degenerate beam spacing ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("fov", "resolution", "expected"),
    [
        (3.0, 0.0, "beam spacing is 0 rad"),
        (3.0, 1e-30, "beam spacing is 1e-30 rad"),
        (1e6, 1e3, "more than a full turn"),
        (1e5, 0.01, "field of view is 100000 rad"),
    ],
)
def test_robotlaser_beam_geometry_is_checked(
    tmp_path: Path, fov: float, resolution: float, expected: str
) -> None:
    path = carmen_log(tmp_path, [robotlaser([1.0, 2.0, 3.0], fov=fov, resolution=resolution)])
    with pytest.raises(InputError) as caught:
        read_carmen(path)
    message = str(caught.value)
    assert message.startswith(f"{path}:1: ROBOTLASER1 angular_resolution"), message
    assert expected in message


def _bag(increment: float, ranges: list[float], n: int = 4, **scan: float) -> Bag:
    stamps = [100 * SEC + k * SEC for k in range(n)]
    return Bag(
        scans=[
            Scan(t, np.array(ranges), -1.0, increment, frame="base_link", **scan) for t in stamps
        ],
        tf=[[Transform(t, "odom", "base_link", (0.1 * k, 0.0, 0.0))] for k, t in enumerate(stamps)],
    )


@pytest.mark.parametrize("kind", ["ros1", "sqlite3"])
@pytest.mark.parametrize("increment", [0.0, 1e-30])
def test_laserscan_zero_angle_increment_is_refused(
    tmp_path: Path, kind: str, increment: float
) -> None:
    path = write_bag(_bag(increment, [1.0, 2.0, 3.0]), tmp_path / "b", kind)
    with pytest.raises(InputError, match=r"angle_increment .*beam spacing"):
        read_rosbag(path)


def test_laserscan_full_turn_with_rounding_is_accepted(tmp_path: Path) -> None:
    # A 360-degree driver: 360 beams of 1 degree, n * increment a hair over 2 pi.
    inc = 2 * math.pi / 359.5
    path = write_bag(_bag(inc, [2.0] * 360), tmp_path / "b", "ros1")
    assert read_rosbag(path).num_points == 4 * 360


# --- 4. maps without points -------------------------------------------------------------------


def test_metrics_refuses_a_map_without_points(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = carmen_log(tmp_path, [flaser([0.0] * 180, (0.3 * k, 0, 0), k + 1.0) for k in range(4)])
    assert main(["metrics", str(path)]) == 2
    err = capsys.readouterr().err
    assert "none of the 4 scans has a usable point" in err  # the reader's warning
    assert f"hitl-slam: error: {path}: the map has no points" in err
    assert "cannot be scored" in err


def test_slam_refuses_a_log_without_points(tmp_path: Path) -> None:
    path = carmen_log(tmp_path, [flaser([0.0] * 180, (0.3 * k, 0, 0), k + 1.0) for k in range(4)])
    with pytest.raises(InputError, match="none of the 4 scans has a usable point"):
        slam(path)


def test_laserscan_range_min_above_range_max_is_reported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write_bag(
        _bag(0.5, [1.0, 2.0, 3.0], range_min=50.0, range_max=10.0), tmp_path / "b", "ros1"
    )
    with caplog.at_level("WARNING", logger="hitl_slam"):
        m = load_map(path)
    assert m.num_points == 0
    assert "4 of 4 scans have range_min above range_max" in caplog.text
    assert "none of the 4 scans has a usable point" in caplog.text


# --- 5. absurd ranges do not fool the max-range inference -------------------------------------


def test_absurd_readings_are_ignored_when_inferring_the_maximum_range(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ranges = room_ranges()
    lines = []
    for k in range(30):
        r = list(ranges)
        r[10] = r[11] = 32.767  # the sensor's no-returns
        r[12] = r[13] = r[14] = 1e308 if k % 2 else 1e9  # garbage
        lines.append(flaser(r, (0.1 * k, 0, 0), k + 1.0))
    path = carmen_log(tmp_path, lines)
    with caplog.at_level("WARNING", logger="hitl_slam"):
        m = read_carmen(path)
    assert m.metadata["flaser_max_range"] == pytest.approx(32.767)
    assert "readings piled at 32.767 m" in m.metadata["max_range_source"]
    assert f"{path}:1: 0 readings are NaN/inf and 90 beyond 1000 m" in caplog.text
    assert "the first is on this line" in caplog.text
    assert m.num_points == 30 * (180 - 5)


# --- 6. long tokens are not echoed whole ------------------------------------------------------


def test_a_huge_token_is_shortened_in_the_error(tmp_path: Path) -> None:
    path = tmp_path / "a.g2o"
    path.write_text(f"VERTEX_SE2 0 {'1' * 100_000} 0 0\n")
    with pytest.raises(InputError) as caught:
        load_graph(path)
    message = str(caught.value)
    assert len(message) < 600, len(message)
    assert "(100002 characters)" in message


# --- 7. smaller gaps --------------------------------------------------------------------------


def test_backwards_timestamps_are_reported_with_the_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ranges = room_ranges()
    path = carmen_log(tmp_path, [flaser(ranges, (0.1 * k, 0, 0), 10.0 - k) for k in range(3)])
    with caplog.at_level("WARNING", logger="hitl_slam"):
        read_carmen(path)
    assert f"{path}:2: the timestamp goes backwards" in caplog.text
    assert "at 2 of 3 scans" in caplog.text


def test_scans_after_the_last_odometry_are_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bag = _bag(0.5, [1.0, 2.0, 3.0])
    bag.scans.append(Scan(104 * SEC, np.array([1.0, 2.0, 3.0]), -1.0, 0.5, frame="base_link"))
    path = write_bag(bag, tmp_path / "b", "ros1")
    with caplog.at_level("WARNING", logger="hitl_slam"):
        m = read_rosbag(path)
    assert m.num_poses == 4
    assert "1 of 5 scans of /scan dropped: before the first or after the last odometry" in (
        caplog.text
    )


def test_a_solve_that_does_not_converge_says_why_on_stderr(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "a.g2o"
    lines = [f"VERTEX_SE2 {k} {k}.0 0 0" for k in range(5)]
    lines[3] = "VERTEX_SE2 3 1e9 0 0"
    lines += [f"EDGE_SE2 {k} {k + 1} 1 0 0 100 0 0 100 0 1000" for k in range(4)]
    path.write_text("\n".join(lines) + "\n")
    code = main(["solve", str(path), "-o", str(tmp_path / "o.g2o"), "-q", "--max-iterations", "1"])
    assert code == 3
    err = capsys.readouterr().err
    assert f"hitl-slam: {path}: the solve did not converge" in err
    assert "edge 2 -> 3" in err or "edge 3 -> 4" in err


def test_match_range_nan_names_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = carmen_log(tmp_path, [flaser(room_ranges(), (0.1 * k, 0, 0), k + 1.0) for k in range(3)])
    assert main(["slam", str(path), "-o", str(tmp_path / "o.g2o"), "--match-range", "nan"]) == 2
    assert "--match-range must be a positive number, got nan" in capsys.readouterr().err


def test_fix_of_several_vertices_says_which_are_not_held(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "a.g2o"
    path.write_text("\n".join([*G2O_CHAIN, "FIX 0 1 2"]) + "\n")
    assert main(["solve", str(path), "-o", str(tmp_path / "o.g2o"), "-q"]) == 0
    err = capsys.readouterr().err
    assert "FIX x2 (first at line 6; only the first FIX'd vertex is held fixed" in err
