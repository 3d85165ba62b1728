"""`hitl-slam correct` and `hitl-slam export` end to end with the real pipeline, on the generated
corridor loop (walls seen twice, the second pass off after a heading fault): the table, rejections
with and without --keep-going, undo, sessions, and replaying a session's exported corrections."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.cli import main
from hitl_slam.io.export import export
from hitl_slam.io.maps import load_map
from hitl_slam.session import EntryStatus, Session
from hitl_slam.sim.corridor import (
    INNER_BOTTOM,
    OUTER_BOTTOM,
    World,
    corridor_loop,
    drawn_segment,
)

CLI = (sys.executable, "-m", "hitl_slam.cli")
FAR_AWAY = {
    "mode": "collinear",
    "a": [[50.0, 50.0], [52.0, 50.0]],
    "b": [[60.0, 60.0], [62.0, 60.0]],
}


@pytest.fixture(scope="module")
def world() -> World:
    return corridor_loop(seed=1)


@pytest.fixture(scope="module")
def drawn(world: World) -> dict[str, Any]:
    """Two corrections a person would draw: the bottom wall seen on both passes is one wall
    (colocation), then the inner bottom wall of the second pass is parallel to it."""
    rng = np.random.default_rng(0)
    poses = world.map.poses
    first: dict[str, Any] = {
        "mode": "colocation",
        "a": drawn_segment(world, poses, OUTER_BOTTOM, (0, 60), rng),
        "b": drawn_segment(world, poses, OUTER_BOTTOM, (265, 325), rng),
    }
    with Session.new(world.map) as session:
        session.correct(first["a"], first["b"], first["mode"])
        after = session.poses
    second = {
        "mode": "parallel",
        "a": drawn_segment(world, after, OUTER_BOTTOM, (0, 60), rng),
        "b": drawn_segment(world, after, INNER_BOTTOM, (265, 325), rng),
        "sigma_h": 0.12,
    }
    return {"first": first, "second": second}


@pytest.fixture
def map_file(world: World, tmp_path: Path) -> Path:
    path = tmp_path / "corridor.covars"
    export(world.map, world.map.poses, path)
    return path


def write_jsonl(path: Path, *objects: dict[str, Any]) -> Path:
    path.write_text("".join(json.dumps(o) + "\n" for o in objects))
    return path


def test_correct_moves_the_second_pass_onto_the_first(
    world: World,
    drawn: dict[str, Any],
    map_file: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    c = write_jsonl(tmp_path / "c.jsonl", drawn["first"], drawn["second"])
    out = tmp_path / "fixed.covars"
    assert main(["correct", str(map_file), "--corrections", str(c), "-o", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "chi2 before" in lines[1]
    assert lines[2].split()[:2] == ["1", "colocation"]
    assert lines[3].split()[:2] == ["2", "parallel"]
    moved, chi2_before, chi2_after = lines[2].split()[2:5]
    assert int(moved) > 100
    assert float(chi2_after) < float(chi2_before)
    assert lines[-1].startswith("2 corrections applied in ")
    assert lines[-1].endswith(f"wrote {out}")
    before = np.hypot(*(world.map.poses[:, :2] - world.truth[:, :2]).T)
    after = np.hypot(*(load_map(out).poses[:, :2] - world.truth[:, :2]).T)
    assert after.max() < 0.7 * before.max()


def test_session_is_written_and_its_corrections_replay_to_the_same_map(
    drawn: dict[str, Any], map_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    c = write_jsonl(
        tmp_path / "c.jsonl",
        drawn["first"],
        drawn["second"],
        {"action": "undo"},
        {"action": "redo"},
    )
    out, hitl = tmp_path / "fixed.txt", tmp_path / "run.hitl"
    args = ["correct", str(map_file), "--corrections", str(c), "-o", str(out), "--quiet"]
    assert main([*args, "--session", str(hitl)]) == 0
    summary = capsys.readouterr().out.splitlines()
    assert len(summary) == 1
    assert summary[0].startswith("2 corrections applied, 1 undone, 1 redone")
    with Session.open(hitl) as session:
        assert [e.status for e in session.history] == [EntryStatus.APPLIED] * 2
        replayed, _ = session.replay()
        assert replayed.tobytes() == session.poses.tobytes()  # same build: bit for bit
        current = session.poses.copy()
    # The session is a map input too, and exports its corrections for replay by script.
    again_txt = tmp_path / "again.txt"
    assert main(["export", str(hitl), "-o", str(again_txt)]) == 0
    assert again_txt.read_bytes() == out.read_bytes()
    jsonl = tmp_path / "exported.jsonl"
    assert main(["export", str(hitl), "-o", str(jsonl)]) == 0
    assert len(jsonl.read_text().splitlines()) == 2
    replay_out = tmp_path / "replayed.txt"
    args = ["correct", str(map_file), "--corrections", str(jsonl), "-o", str(replay_out), "-q"]
    assert main(args) == 0
    assert replay_out.read_bytes() == out.read_bytes()
    assert load_map(hitl).poses.tobytes() == current.tobytes()
    # An existing session file is never overwritten.
    args = ["correct", str(map_file), "--corrections", str(c), "-o", str(out)]
    assert main([*args, "--session", str(hitl)]) == 2
    assert "already exists" in capsys.readouterr().err


def test_rejection_stops_the_run_and_writes_nothing(
    drawn: dict[str, Any], map_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    c = write_jsonl(tmp_path / "c.jsonl", drawn["first"], FAR_AWAY, drawn["second"])
    out, hitl = tmp_path / "fixed.covars", tmp_path / "run.hitl"
    args = ["correct", str(map_file), "--corrections", str(c), "-o", str(out)]
    assert main([*args, "--session", str(hitl)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"hitl-slam: error: {c}:2: collinear correction rejected: ")
    assert "no observations" in err
    assert not out.exists()
    assert not hitl.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.jsonl", map_file.name]


def test_keep_going_applies_the_rest_and_lists_rejections(
    drawn: dict[str, Any], map_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    c = write_jsonl(tmp_path / "c.jsonl", drawn["first"], FAR_AWAY, drawn["second"])
    out, hitl = tmp_path / "fixed.txt", tmp_path / "run.hitl"
    args = ["correct", str(map_file), "--corrections", str(c), "-o", str(out), "--keep-going"]
    assert main([*args, "--session", str(hitl)]) == 0
    text = capsys.readouterr().out
    assert f"{c}:2: collinear correction rejected" in text
    assert text.splitlines()[-1].startswith("2 corrections applied, 1 rejected (line 2) in ")
    with Session.open(hitl) as session:
        statuses = [e.status for e in session.history]
        assert statuses == [EntryStatus.APPLIED, EntryStatus.REJECTED, EntryStatus.APPLIED]
    # Skipping the rejected line gives the same map as never having written it.
    clean = write_jsonl(tmp_path / "clean.jsonl", drawn["first"], drawn["second"])
    clean_out = tmp_path / "clean.txt"
    assert main(["correct", str(map_file), "--corrections", str(clean), "-o", str(clean_out)]) == 0
    assert clean_out.read_bytes() == out.read_bytes()


def test_undo_in_a_script_restores_the_input_map(
    drawn: dict[str, Any], map_file: Path, tmp_path: Path
) -> None:
    c = write_jsonl(tmp_path / "c.jsonl", drawn["first"], {"action": "undo"})
    out = tmp_path / "same.txt"
    assert main(["correct", str(map_file), "--corrections", str(c), "-o", str(out), "-q"]) == 0
    plain = tmp_path / "plain.txt"
    assert main(["export", str(map_file), "-o", str(plain)]) == 0
    assert out.read_bytes() == plain.read_bytes()


@pytest.mark.parametrize("suffix", [".covars", ".g2o", ".txt", ".pgm"])
def test_export_formats(map_file: Path, tmp_path: Path, suffix: str) -> None:
    out = tmp_path / f"out{suffix}"
    assert main(["export", str(map_file), "-o", str(out), "-q"]) == 0
    assert out.stat().st_size > 0


def test_bad_input_as_a_real_process(map_file: Path, tmp_path: Path) -> None:
    c = tmp_path / "c.jsonl"
    c.write_text('{"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]], "x": 1}\n')
    run = subprocess.run(
        [*CLI, "correct", str(map_file), "--corrections", str(c), "-o", str(tmp_path / "o.covars")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 2
    assert run.stderr == f"hitl-slam: error: {c}:1: unknown key 'x'; the keys are mode, a, b, " + (
        "sigma_h, version (a typo must not become a default)\n"
    )
    assert not (tmp_path / "o.covars").exists()
    unknown = subprocess.run(
        [*CLI, "export", str(tmp_path / "m.xyz"), "-o", str(tmp_path / "o.g2o")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert unknown.returncode == 2
    assert "supported: .covars, .clf, .log, .bag, .db3, .mcap, .hitl" in unknown.stderr
