"""The CARMEN log writer (``.clf`` outputs of ``slam`` and ``export``): a log the map was read
from is copied with only its pose fields changed; any other map gets one ROBOTLASER1 line per
scan; either reads back with the poses written and the map's points."""

from __future__ import annotations

import bz2
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hitl_slam.cli import main
from hitl_slam.io.carmen import read_carmen
from hitl_slam.io.carmen_writer import write_carmen
from hitl_slam.map import Map
from hitl_slam.sim import lost_poses_room
from reference import wrap

ROOT = Path(__file__).resolve().parents[1]
LASER = ROOT.parent / "shared" / "datasets" / "laser"
HITL_SLAM = str(ROOT / ".venv" / "bin" / "hitl-slam")


def _box_scans(poses: list[tuple[float, float, float]], beams: int) -> list[np.ndarray]:
    """Exact ranges to the walls of a 4 x 4 m box from each pose, beams over 180 degrees."""
    out = []
    for x, y, th in poses:
        angles = th + np.radians(-90.0 + 180.0 / beams * np.arange(beams))
        d = np.column_stack([np.cos(angles), np.sin(angles)])
        with np.errstate(divide="ignore"):
            tx = np.where(d[:, 0] > 0, (4.0 - x) / d[:, 0], -x / d[:, 0])
            ty = np.where(d[:, 1] > 0, (4.0 - y) / d[:, 1], -y / d[:, 1])
        out.append(np.minimum(np.abs(tx), np.abs(ty)))
    return out


def _robotlaser_log(path: Path, offset: float) -> list[tuple[float, float, float]]:
    """A ROBOTLASER1 log (laser ``offset`` m ahead of the robot) with the FLASER copies of its
    scans and an ODOM line between, as CARMEN's logger writes them; returns the laser poses."""
    robots = [(1.0, 1.0, 0.1), (1.5, 1.2, 0.5), (2.0, 1.6, 1.2), (2.1, 2.2, 2.0)]
    lasers = [(x + offset * math.cos(t), y + offset * math.sin(t), t) for x, y, t in robots]
    lines = [f"PARAM robot_frontlaser_offset {offset}\n", "PARAM robot_front_laser_max 20\n"]
    for k, (ranges, laser, robot) in enumerate(
        zip(_box_scans(lasers, 180), lasers, robots, strict=True)
    ):
        r = " ".join(f"{v:.4f}" for v in ranges)
        t = 10.0 + k
        lp = " ".join(map(repr, laser))
        rp = " ".join(map(repr, robot))
        lines.append(f"ODOM {rp} 0 0 0 {t - 0.5} host {t - 0.5}\n")
        lines.append(
            f"ROBOTLASER1 0 {-math.pi / 2!r} {math.pi!r} {math.pi / 180!r} 20.0 0.01 0 180 {r} "
            f"0 {lp} {rp} 0 0 0 0 0 {t} host {t}\n"
        )
        lines.append(f"FLASER 180 {r} {lp} {rp} {t} host {t}\n")
    path.write_text("".join(lines))
    return lasers


def _moved(poses: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = poses + rng.normal(0.0, [0.2, 0.2, 0.1], poses.shape)
    out[:, 2] = wrap(out[:, 2])
    return out


@pytest.mark.parametrize("offset", [0.0, 0.12])
def test_a_robotlaser_log_is_copied_with_only_its_poses_changed(
    tmp_path: Path, offset: float
) -> None:
    log = tmp_path / "in.clf"
    _robotlaser_log(log, offset)
    m = read_carmen(log)
    new = _moved(m.poses, seed=int(offset * 100))
    out = tmp_path / "out.clf"
    write_carmen(m, new, out)
    back = read_carmen(out)
    np.testing.assert_allclose(back.poses, new, rtol=0, atol=1e-12)  # heading re-wrapped on read
    np.testing.assert_array_equal(back.points, m.points)
    np.testing.assert_array_equal(back.timestamps, m.timestamps)
    # Every other line is kept as it was; the robot pose is the laser pose without the offset,
    # so the robot poses read back through the offset give the laser poses again.
    lines = out.read_text().splitlines()
    assert [ln for ln in lines if ln.startswith(("PARAM", "ODOM"))] == [
        ln.rstrip("\n")
        for ln in log.read_text().splitlines(keepends=True)
        if ln.startswith(("PARAM", "ODOM"))
    ]
    from hitl_slam.io.carmen import PoseSource

    via_robot = read_carmen(out, pose_source=PoseSource.ODOMETRY)
    np.testing.assert_allclose(via_robot.poses, new, atol=1e-12)
    # The FLASER copies of the scans carry the same laser poses.
    flaser = [ln.split() for ln in lines if ln.startswith("FLASER")]
    assert len(flaser) == 4
    for tokens, pose in zip(flaser, new, strict=True):
        np.testing.assert_array_equal([float(v) for v in tokens[182:185]], pose)


def test_a_subsampled_map_leaves_out_the_scans_it_does_not_hold(tmp_path: Path) -> None:
    log = tmp_path / "in.clf"
    _robotlaser_log(log, 0.0)
    m = read_carmen(log, min_travel=0.6)
    assert 1 < m.num_poses < 4
    out = tmp_path / "out.clf"
    write_carmen(m, m.poses, out)
    back = read_carmen(out)
    np.testing.assert_allclose(back.poses, m.poses, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(back.timestamps, m.timestamps)
    assert out.read_text().count("ROBOTLASER1") == m.num_poses


def test_a_map_without_its_log_gets_robotlaser_lines_from_its_points(tmp_path: Path) -> None:
    world = lost_poses_room(seed=3)
    m = world.map
    new = _moved(m.poses, seed=5)
    out = tmp_path / "room.clf"
    write_carmen(m, new, out)
    back = read_carmen(out)
    np.testing.assert_allclose(back.poses, new, rtol=0, atol=1e-12)  # heading re-wrapped on read
    assert back.num_points == m.num_points
    # The same points per scan, up to half a beam of bearing (the room's beams are evenly
    # spaced, so in fact to rounding).
    for k in range(m.num_poses):
        a = m.points[m.offsets[k] : m.offsets[k + 1]]
        b = back.points[back.offsets[k] : back.offsets[k + 1]]
        order = lambda p: p[np.argsort(np.arctan2(p[:, 1], p[:, 0]))]  # noqa: E731
        np.testing.assert_allclose(order(b), order(a), atol=1e-9)


def test_a_log_moved_away_since_reading_is_written_from_the_points(tmp_path: Path) -> None:
    log = tmp_path / "in.clf"
    _robotlaser_log(log, 0.0)
    m = read_carmen(log)
    log.unlink()
    out = tmp_path / "out.clf"
    write_carmen(m, m.poses, out)
    back = read_carmen(out)
    np.testing.assert_allclose(back.poses, m.poses, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.points, m.points, atol=1e-9)


def test_scans_of_uneven_bearings_read_back_within_half_a_beam(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    scans = [
        np.column_stack([r * np.cos(b), r * np.sin(b)])
        for r, b in (
            (rng.uniform(0.5, 5.0, 60), np.sort(rng.uniform(-2.0, 2.0, 60))) for _ in range(3)
        )
    ]
    m = Map.from_poses_and_scans(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), scans)
    out = tmp_path / "uneven.clf"
    write_carmen(m, m.poses, out)
    back = read_carmen(out)
    for k in range(3):
        a, b = scans[k], back.points[back.offsets[k] : back.offsets[k + 1]]
        assert 0 < len(b) <= len(a)
        ra, rb = np.hypot(*a.T), np.hypot(*b.T)
        # Each point read back is one of the scan's points, moved along its beam at most by
        # half the beam spacing (the nearer of two points sharing a beam is kept).
        for p, r in zip(b, rb, strict=True):
            i = int(np.argmin(np.abs(ra - r)))
            assert abs(ra[i] - r) < 1e-9
            gap = abs(wrap(np.arctan2(p[1], p[0]) - np.arctan2(*a[i][::-1])))
            assert gap <= 0.5 * math.radians(4.0 / 59 * 180 / math.pi) + 1e-9


def test_slam_and_export_write_clf_that_metrics_scores(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source = LASER / "intel.clf.bz2"
    if not source.is_file():
        pytest.skip("../shared/datasets/laser is not beside the repository")
    # The first 600 scans of the Intel log, and the relations between them.
    with bz2.open(source, "rt") as f:
        lines = f.read().splitlines(keepends=True)
    cut, scans = [], 0
    for line in lines:
        if line.startswith("FLASER"):
            scans += 1
            if scans > 600:
                break
        cut.append(line)
    log = tmp_path / "intel600.clf"
    log.write_text("".join(cut))
    stamps = read_carmen(log).timestamps
    assert stamps is not None
    rel = [
        ln
        for ln in (LASER / "intel.relations").read_text().splitlines(keepends=True)
        if ln.strip() and float(ln.split()[1]) <= stamps[-1]
    ]
    relations = tmp_path / "intel600.relations"
    relations.write_text("".join(rel))
    out = tmp_path / "intel600-slam.clf"
    run = subprocess.run(
        [HITL_SLAM, "slam", str(log), "-o", str(out), "-q"], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    back = read_carmen(out)
    assert back.num_poses == 600
    capsys.readouterr()
    assert main(["metrics", str(out), "--relations", str(relations), "-q"]) == 0
    scored = capsys.readouterr().out
    assert main(["metrics", str(log), "--relations", str(relations), "-q"]) == 0
    raw = capsys.readouterr().out

    def rotation(text: str) -> float:
        line = next(ln for ln in text.splitlines() if ln.startswith("relations:"))
        return float(line.split("rotation ")[1].split()[0])

    # The front end's log scores far better than the raw odometry it started from (on these
    # short relations the odometry's error is mostly in heading).
    assert rotation(scored) < 0.5 < 1.0 < rotation(raw), (scored, raw)
    # `export` writes the same kind of file from a session.
    session = tmp_path / "intel600.hitl"
    assert main(["slam", str(log), "-o", str(session), "-q"]) == 0
    exported = tmp_path / "exported.clf"
    assert main(["export", str(session), "-o", str(exported)]) == 0
    np.testing.assert_allclose(read_carmen(exported).poses, back.poses, rtol=0, atol=1e-12)
