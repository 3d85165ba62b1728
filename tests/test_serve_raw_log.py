"""`hitl-slam serve LOG` on a raw log (issue 14, part 3): the front end runs first and its map,
with its loop closures, is served; the session beside the log is reopened only when it is this
log's, made the same way; --no-slam serves the log as logged; bad logs are one line, exit 2,
nothing written. The real log is the corrected Orebro log (Radish), copied to a temporary folder
(the session goes beside it)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hitl_slam.cli import main
from hitl_slam.errors import InputError
from hitl_slam.io.covars import write_covars
from hitl_slam.sim import lost_poses_room
from hitl_slam.web.server import is_raw_log, open_session

LASER = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "laser"
BEAMS = " ".join(["2.0"] * 181)


def _orebro(folder: Path, name: str = "orebro.log.gz") -> Path:
    source = LASER / "orebro-corrected.log.gz"
    if not source.is_file():
        pytest.skip("../shared/datasets/laser is not beside the repository")
    target = folder / name
    shutil.copyfile(source, target)
    return target


def test_raw_logs_are_told_from_maps(tmp_path: Path) -> None:
    for name in ("run.clf", "run.log", "run.clf.gz", "RUN.LOG.BZ2", "run.bag", "run.mcap"):
        assert is_raw_log(tmp_path / name), name
    for name in ("run.covars", "run.hitl", "run.g2o", "run.gz"):
        assert not is_raw_log(tmp_path / name), name


def test_serve_runs_the_front_end_and_reopens_only_this_logs_session(tmp_path: Path) -> None:
    log = _orebro(tmp_path)
    seen: list[tuple[int, int]] = []
    session, how = open_session(log, progress=lambda done, total, _rtf: seen.append((done, total)))
    with session:
        assert how.startswith(f"ran the front end over {log}")
        assert "loop closures" in how
        assert session.path == str(tmp_path / "orebro.hitl")
        loops = session.loop_closures
        assert len(loops) >= 2
        assert session.input_map.metadata["front_end"] == "hitl-slam"
        session.set_loop_closure(next(c.index for c in loops if not c.rejected), True)
        rejected = session.rejected_loop_closures
    assert seen
    assert seen[-1][0] == seen[-1][1] == session.input_map.num_poses
    # Served again: the same session, not a new front end run.
    session, how = open_session(log)
    with session:
        assert how.startswith("reopened the session")
        assert session.rejected_loop_closures == rejected
    # Asked for the log's own poses, the front end's session is refused, and the other way.
    with pytest.raises(InputError, match="holds the front end's map of the log"):
        open_session(log, front_end=False)
    (tmp_path / "plain").mkdir()
    plain = _orebro(tmp_path / "plain")
    session, how = open_session(plain, front_end=False)
    with session:
        assert how.startswith("created the session")
        assert session.loop_closures == []
    with pytest.raises(InputError, match=r"made with --no-slam"):
        open_session(plain)
    # A session beside the log made from another file is not this log's.
    other = tmp_path / "other"
    other.mkdir()
    shutil.copyfile(tmp_path / "orebro.hitl", other / "orebro.hitl")
    renamed = _orebro(other, "orebro.clf.gz")
    with pytest.raises(InputError, match=r"made from orebro\.log\.gz, not orebro\.clf\.gz"):
        open_session(renamed)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("nolaser.clf", f"PARAM robot_front_laser_max 80\nRAWLASER1 181 {BEAMS}\n", "no laser"),
        ("broken.clf.gz", "garbage", "cannot be decompressed"),
        ("one.clf", "FLASER 3 1 1 1 0 0 0 0 0 0 1 host 1\n", "one laser scan"),
        ("empty.log", "", "empty"),
    ],
)
def test_serve_on_a_bad_log_is_one_line_and_writes_nothing(
    name: str,
    content: str,
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = tmp_path / name
    log.write_text(content)
    assert main(["serve", str(log), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if line.startswith("hitl-slam: error")]
    assert len(errors) == 1, err
    assert name in errors[0]
    assert message in errors[0], errors[0]
    assert all(line.startswith("hitl-slam") for line in err)  # progress lines, then the error
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_no_slam_applies_to_raw_logs_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    covars = tmp_path / "lab.covars"
    room = lost_poses_room(0).map
    write_covars(room, room.poses, covars)
    assert main(["serve", str(covars), "--no-slam", "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "--no-slam applies to raw logs" in err[0]
    assert not (tmp_path / "lab.hitl").exists()


def test_serve_help_says_when_the_front_end_runs(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["serve", "--help"])
    out = capsys.readouterr().out
    for needle in ("--no-slam", "raw log", "front end", "Every .clf/.log is taken as raw"):
        assert needle in out, needle
