"""`hitl-slam serve BAG` on a bag with its own SLAM (issue 39, point 6): with /tf map -> odom the
session starts from the SLAM's trajectory map -> base_link (its factors the chain of steps
between its poses, no loop closures) and says so; --slam rebuilds the map with the front end from
the bag's odometry and compares the two by their inconsistency; a bag without a map frame runs the
front end as before; --no-slam serves the bag's own poses; the session beside the bag is reopened
only when it holds the poses asked for. The bag is made from the corrected Orebro log (Radish):
its logged poses are the SLAM's trajectory, a drifting odometry under it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the [ros] extra (rosbags) is not installed")
pytest.importorskip("fastapi", reason="the [web] extra is not installed")

from bag_support import slam_bag_of_log, write_bag
from hitl_slam.cli import main
from hitl_slam.errors import InputError
from hitl_slam.geometry import chain_steps
from hitl_slam.io.covars import write_covars
from hitl_slam.io.rosbag import BagOptions
from hitl_slam.map import InformationSource, motion_model_information
from hitl_slam.metrics import inconsistency
from hitl_slam.sim import lost_poses_room
from hitl_slam.web import SessionHost
from hitl_slam.web.server import open_session
from reference import wrap

LOG = Path(__file__).resolve().parents[1].parent / "shared/datasets/laser/orebro-corrected.log.gz"


def _bag(folder: Path, *, map_frame: bool = True, kind: str = "ros1") -> tuple[Path, np.ndarray]:
    if not LOG.is_file():
        pytest.skip("../shared/datasets/laser is not beside the repository")
    folder.mkdir(parents=True, exist_ok=True)
    bag, trajectory = slam_bag_of_log(LOG, 3, map_frame=map_frame)
    return write_bag(bag, folder / "run", kind), trajectory


def _angle(a: np.ndarray) -> np.ndarray:
    return np.abs(wrap(a))


def test_a_bag_with_its_own_slam_is_served_from_its_trajectory(tmp_path: Path) -> None:
    path, trajectory = _bag(tmp_path)
    session, how = open_session(path)
    with session:
        assert how.startswith(
            f"{path}: starting from the bag's own SLAM trajectory (map -> base_link, "
            f"{len(trajectory)} scans); --slam rebuilds it with the front end; created the "
            f"session {tmp_path / 'run.hitl'}"
        ), how
        m = session.input_map
        np.testing.assert_allclose(m.poses[:, :2], trajectory[:, :2], rtol=0, atol=1e-9)
        assert _angle(m.poses[:, 2] - trajectory[:, 2]).max() <= 1e-9
        np.testing.assert_array_equal(session.poses, m.poses)
        # Its factors: the chain of steps between its own poses, as for a corrected log; no
        # loop closures (the reader's chain is the odometry's, which would undo the SLAM's).
        n = m.num_poses
        np.testing.assert_array_equal(m.edges, np.stack([np.arange(n - 1), np.arange(1, n)], 1))
        np.testing.assert_allclose(m.measurements, chain_steps(trajectory), atol=1e-9)
        np.testing.assert_allclose(m.information, motion_model_information(m.measurements))
        assert np.all(m.information_source == InformationSource.MOTION_MODEL)
        assert session.loop_closures == []
        assert m.metadata["trajectory"] == "slam (map -> base_link)"
        info = SessionHost(session, metrics=False).map_info()
    assert info["poses"] == "own_slam"
    assert info["description"] == "the bag's own SLAM trajectory (map -> base_link)"
    assert info["comparison"] is None
    assert info["front_end_verdict"] is None
    assert info["front_end_doubtful"] == []
    # Served again: the same session, saying what it holds; --no-slam asks for the same poses.
    for front_end in (None, False):
        session, how = open_session(path, front_end=front_end)
        with session:
            assert how.startswith(
                f"reopened the session {tmp_path / 'run.hitl'} of {path} (the bag's own SLAM "
                "trajectory (map -> base_link); "
            ), how
    # --slam is not served this session, nor is the front end's map from --map-frame ''.
    with pytest.raises(InputError, match=r"holds the bag's own SLAM trajectory .* without --slam"):
        open_session(path, front_end=True)
    with pytest.raises(InputError, match=r"--map-frame '' asks for the front end's map"):
        open_session(path, bag=BagOptions(map_frame=None))
    with pytest.raises(InputError, match=r"--map-frame '' asks for the odometry"):
        open_session(path, front_end=False, bag=BagOptions(map_frame=None))


def test_slam_rebuilds_it_with_the_front_end_and_compares_the_two(tmp_path: Path) -> None:
    path, trajectory = _bag(tmp_path)
    session, how = open_session(path, front_end=True)
    with session:
        assert how.startswith(
            f"ran the front end over {path} from the bag's odometry, in place of its own SLAM "
            "trajectory ("
        ), how
        m = session.input_map
        assert m.metadata["front_end"] == "hitl-slam"
        assert m.metadata["trajectory"] == "odometry (odom -> base_link)"
        assert m.metadata["replaced_trajectory"] == "slam (map -> base_link)"
        assert "odometry_poses" not in m.metadata
        assert m.num_poses == len(trajectory)
        # The front end's map, with its loop closures, not the SLAM's trajectory.
        assert len(session.loop_closures) >= 1
        assert len(m.metadata["loop_closure_edges"]) == len(session.loop_closures)
        assert np.hypot(*(m.poses[:, :2] - trajectory[:, :2]).T).max() > 0.01
        compared = m.metadata["trajectory_comparison"]
        # Both measured as `hitl-slam metrics` would, over the same scans.
        assert compared["bag_slam_m2"] == pytest.approx(inconsistency(m, trajectory).total_m2)
        assert compared["front_end_m2"] == pytest.approx(inconsistency(m).total_m2)
        assert compared["bag_slam_m2"] > 0
        assert compared["front_end_m2"] > 0
        assert (
            f"inconsistency: the bag's own SLAM trajectory {compared['bag_slam_m2']:.2f} m^2, "
            f"the front end's map {compared['front_end_m2']:.2f} m^2"
        ) in how
        info = SessionHost(session, metrics=False).map_info()
    assert info["poses"] == "front_end"
    assert info["comparison"] == {
        "trajectory": "slam (map -> base_link)",
        "bag_slam_m2": compared["bag_slam_m2"],
        "front_end_m2": compared["front_end_m2"],
    }
    assert "in place of the bag's own trajectory (map -> base_link)" in info["description"]
    # Reopened with --slam only: without it the bag's own trajectory comes first.
    session, how = open_session(path, front_end=True)
    with session:
        assert how.startswith("reopened the session"), how
        assert session.input_map.metadata["trajectory_comparison"] == compared
    with pytest.raises(InputError, match=r"made with --slam.*serve it with --slam"):
        open_session(path)
    with pytest.raises(InputError, match=r"holds the front end's map of the log; serve it with"):
        open_session(path, front_end=False)


def test_a_bag_without_a_map_frame_runs_the_front_end_as_before(tmp_path: Path) -> None:
    path, trajectory = _bag(tmp_path / "plain", map_frame=False, kind="mcap")
    session, how = open_session(path)
    with session:
        assert how.startswith(f"ran the front end over {path} ("), how
        m = session.input_map
        assert m.metadata["front_end"] == "hitl-slam"
        assert "replaced_trajectory" not in m.metadata
        assert "trajectory_comparison" not in m.metadata
        assert session.loop_closures
    session, how = open_session(path, front_end=True)  # --slam: the same, reopened
    with session:
        assert how.startswith("reopened the session"), how
    with pytest.raises(InputError, match="holds the front end's map of the log; serve it without"):
        open_session(path, front_end=False)
    # --no-slam: the odometry as recorded.
    path, trajectory = _bag(tmp_path / "odometry", map_frame=False, kind="sqlite3")
    session, how = open_session(path, front_end=False)
    with session:
        assert "the bag's odometry (odom -> base_link), as recorded" in how, how
        assert session.loop_closures == []
        assert np.hypot(*(session.poses[:, :2] - trajectory[:, :2]).T).max() > 0.01
    with pytest.raises(InputError, match="made with --no-slam"):
        open_session(path)
    with pytest.raises(InputError, match="made with --no-slam"):
        open_session(path, front_end=True)


def test_slam_and_no_slam_are_one_line_errors_where_they_do_not_apply(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    covars = tmp_path / "lab.covars"
    room = lost_poses_room(0).map
    write_covars(room, room.poses, covars)
    cases = [
        (["serve", "run.bag", "--slam", "--no-slam"], "give --slam"),
        (["serve", str(covars), "--slam"], "--slam applies to raw logs"),
        (["serve", "--demo", "--slam"], "--slam chooses how a raw log becomes a map"),
        (["serve", "--demo", "--no-slam"], "--no-slam chooses how a raw log becomes a map"),
    ]
    for argv, message in cases:
        assert main([*argv, "--port", "0"]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        assert message in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lab.covars"]


def test_serve_help_teaches_the_bags_own_slam(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["serve", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for needle in (
        "--slam",
        "map -> odom",
        "starts from the SLAM's own trajectory",
        "side by side",
        "--slam and --no-slam together are an error",
        "doubts",
    ):
        assert needle in out, needle


def test_the_command_says_where_the_map_comes_from(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`hitl-slam serve BAG` in a subprocess: the line on stdout, the page's map info and poses;
    then `--slam` on the same session: one line on stderr, exit 2, the session untouched."""
    from web_support import serve

    path, trajectory = _bag(tmp_path)
    with serve(tmp_path, str(path)) as server:
        info = server.api("GET", "/api/map/info").json()
        poses = server.poses()
    said = (
        f"hitl-slam serve: {path}: starting from the bag's own SLAM trajectory (map -> "
        f"base_link, {len(trajectory)} scans); --slam rebuilds it with the front end"
    )
    assert any(line.startswith(said) for line in server.output), server.output
    assert info["poses"] == "own_slam"
    np.testing.assert_allclose(poses[:, :2], trajectory[:, :2], atol=1e-4)
    session = tmp_path / "run.hitl"
    before = session.read_bytes()
    assert main(["serve", str(path), "--slam", "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "holds the bag's own SLAM trajectory (map -> base_link), not the front end's" in err[0]
    assert session.read_bytes() == before
