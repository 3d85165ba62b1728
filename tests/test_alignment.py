"""Aligning a corrected map with its scans (docs/ALGORITHM.md §I.11): the guard, the session step
(journaled, undone and redone exactly, reopened), and what it does to a damaged real log."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.alignment import (
    OVERRULED_DEG,
    OVERRULED_M,
    AlignmentRefused,
    contradicted,
    contradicted_steps,
    overruled,
)
from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Interpretation, Mode
from hitl_slam.corrections_file import Apply, read_corrections
from hitl_slam.errors import InputError
from hitl_slam.full_evaluation import LASER, damaged_scenario, evaluate_run
from hitl_slam.journal import DamagedSession
from hitl_slam.map import Map
from hitl_slam.metrics import ate, inconsistency
from hitl_slam.session import AlignStep, EntryStatus, Session
from hitl_slam.sim import lost_poses_room
from hitl_slam.sim.fault_models import damaged, jump

DATA = Path(__file__).parent / "data"

needs_logs = pytest.mark.skipif(
    not (LASER / "orebro-corrected.log.gz").is_file(),
    reason="../shared/datasets/laser is not beside the repository",
)


def _events(path: Path, kind: str) -> int:
    with sqlite3.connect(path) as db:
        count: int = db.execute("SELECT count(*) FROM events WHERE kind = ?", (kind,)).fetchone()[0]
    return count


def test_contradicted_counts_the_steps_beyond_their_bound() -> None:
    m = lost_poses_room(0).map
    assert contradicted(m, m.poses) == (0, m.num_poses - 1)
    poses = m.poses.copy()
    poses[40:, 2] += math.radians(10.0)  # one step turned: the step into pose 40 only
    assert contradicted(m, poses) == (1, m.num_poses - 1)
    poses[41, :2] += 0.5  # pose 41 moved: the steps into it and out of it
    assert contradicted(m, poses) == (3, m.num_poses - 1)


def test_the_share_allowed_is_a_share() -> None:
    with pytest.raises(InputError, match="align_max_contradicted"):
        Config(align_max_contradicted=1.5)


def test_the_contradicted_steps_are_those_into_and_out_of_a_turned_pose() -> None:
    m = lost_poses_room(0).map
    n = m.num_poses - 1
    first, beyond = contradicted_steps(m, m.poses)
    assert np.array_equal(first, np.arange(n))
    assert not beyond.any()
    # A pose turned on its own contradicts the step into it and the step out of it.
    poses = m.poses.copy()
    turned = [*range(301, 325, 4), 21, 121, 451, n - 5]
    poses[turned, 2] += math.radians(10.0)
    first, beyond = contradicted_steps(m, poses)
    want = sorted(s for k in turned for s in (k - 1, k))
    assert np.flatnonzero(beyond).tolist() == want
    assert contradicted(m, poses) == (20, n)


def test_a_map_without_scans_is_refused_and_nothing_changes(tmp_path: Path) -> None:
    m = lost_poses_room(1).map
    bare = dataclasses.replace(
        m,
        points=m.points[:10].copy(),
        offsets=np.minimum(m.offsets, 10),
        normals=None if m.normals is None else m.normals[:10].copy(),
    )
    path = tmp_path / "bare.hitl"
    with Session.new(bare, path) as s:
        with pytest.raises(InputError, match="laser points over"):
            s.align()
        assert np.array_equal(s.poses, bare.poses)
        assert not s.can_undo
    assert _events(path, "align") == 0


@pytest.mark.parametrize("seed", [2, 5])
def test_the_guard_refuses_where_the_scans_contradict_the_odometry(
    seed: int, tmp_path: Path
) -> None:
    """The generated room's scans are too poor for the front end (docs §I.11): the aligned map
    would contradict a large share of the odometry steps, the front end keeps no loop closure
    between the passes (its group test sets the room's aside, docs/ALGORITHM.md §F.4), or the
    aligned map is less consistent with its scans than the map (since local ICP leaves a
    corridor's axis to the odometry, docs/ALGORITHM.md §F.1, the room's matches slide less and
    that guard is the one that answers), so it is refused with the figures and the session is
    left as it was."""
    base = lost_poses_room(seed)
    scenario = damaged(base, jump(base.truth, np.random.default_rng(seed)), seed)
    path = tmp_path / "room.hitl"
    refusal = (
        r"contradicts \d+ of the \d+ odometry steps|found 0 loop closures between the passes"
        r"|no more consistent with its scans than the map is: its inconsistency would go from"
    )
    with Session.new(scenario.map, path) as s:
        with pytest.raises(AlignmentRefused, match=refusal):
            s.align()
        assert np.array_equal(s.poses, scenario.map.poses)
        assert not s.can_undo
    assert _events(path, "align") == 0


def _aligned_run(tmp_path: Path, fault_seed: int) -> dict[str, Any]:
    """A damaged Orebro repaired by a few careful drawings, then aligned: the figures and a copy
    of the session file."""
    out: dict[str, Any] = {}

    def at_end(scenario: Any, session: Session) -> None:
        m, truth = scenario.map, scenario.truth
        first = inconsistency(m, m.poses, DEFAULT)

        def figures(poses: np.ndarray) -> tuple[float, float, float]:
            inc = inconsistency(m, poses, DEFAULT, like=first).total_m2
            return float(ate(poses, truth)), float(np.nanmean(scenario.errors(poses).angular)), inc

        before = np.array(session.poses)
        out["before"], out["before_poses"] = figures(before), before
        out["step"] = session.align()
        out["after"], out["after_poses"] = figures(np.array(session.poses)), np.array(session.poses)
        out["corrections"] = len(session.active)
        out["last"] = session.active[-1]
        session.write_journal(tmp_path / "orebro.hitl")

    evaluate_run(
        "Orebro", "jump", 0.05, seed=fault_seed, max_corrections=6, align=False, on_end=at_end
    )
    return out


@needs_logs
@pytest.mark.parametrize("fault_seed", [3, 4])
def test_aligning_a_repaired_real_log_closes_the_last_centimetres(
    fault_seed: int, tmp_path: Path
) -> None:
    run = _aligned_run(tmp_path, fault_seed)
    step = run["step"]
    assert isinstance(step, AlignStep)
    assert step.status is EntryStatus.APPLIED
    assert step.contradicted <= 0.05 * step.steps
    assert step.loop_closures > 0
    (ate0, angle0, inc0), (ate1, angle1, inc1) = run["before"], run["after"]
    # The scans resolve what the drawings could not: the map's overlaps agree much better, and
    # the walls do not turn.
    assert inc1 < 0.85 * inc0, (inc0, inc1)
    assert angle1 <= angle0 + 0.2, (angle0, angle1)
    assert ate1 < 1.0, (ate0, ate1)

    path = tmp_path / "orebro.hitl"
    assert _events(path, "align") == 1
    with Session.open(path) as s:
        assert np.array_equal(s.poses, run["after_poses"])
        assert s.solved_map().edges.shape[0] >= s.input_map.num_poses - 1
        assert s.solved_map() is not s.input_map
        assert len(s.lines) == 2 * run["corrections"]
        assert s.aligned
        s.undo()
        assert not s.aligned
        assert np.array_equal(s.poses, run["before_poses"])
        assert s.solved_map() is s.input_map
        s.redo()
        assert np.array_equal(s.poses, run["after_poses"])
        # A correction after the alignment solves over the aligned graph, every statement kept:
        # the last statement again, drawn along its walls where they are now.
        h = run["last"]
        segments = []
        for rows in (h.s_a, h.s_b):
            pts = s.input_map.observed_points(rows, s.poses)
            centre = pts.mean(axis=0)
            direction = np.linalg.svd(pts - centre)[2][0]
            t = (pts - centre) @ direction
            lo, hi = np.quantile(t, (0.05, 0.95))
            segments.append([list(centre + lo * direction), list(centre + hi * direction)])
        s.correct(segments[0], segments[1], h.mode)
        assert len(s.active) == run["corrections"] + 1
        moved = np.abs(s.poses[:, :2] - run["after_poses"][:, :2]).max()
        assert moved < 0.5  # the statement already holds there: a small step
    # Recomputed from scratch, the alignment is the same.
    with Session.open(path) as s:
        s.undo()
        s.undo()  # the correction, then back to the alignment's input
        s.redo()
        replayed, outcomes = s.replay()
        assert np.allclose(replayed, run["after_poses"], atol=1e-9)
        assert type(outcomes[-1]).__name__ == "Alignment"


@needs_logs
def test_a_damaged_alignment_event_names_the_last_good_checkpoint(tmp_path: Path) -> None:
    _aligned_run(tmp_path, 3)
    path = tmp_path / "orebro.hitl"
    with sqlite3.connect(path) as db:
        seq, payload = db.execute("SELECT seq, payload FROM events WHERE kind = 'align'").fetchone()
        data = json.loads(payload)
        data["graph"]["edges"][0] = [0, 10**6]
        db.execute("UPDATE events SET payload = ? WHERE seq = ?", (json.dumps(data), seq))
    with pytest.raises(DamagedSession, match=f"event {seq}"):
        Session.open(path)


def test_a_malformed_graph_is_damage_even_with_a_valid_checksum(tmp_path: Path) -> None:
    """The state machine checks an alignment's graph itself (a file written by another tool can
    carry a valid checksum over a bad value)."""
    from hitl_slam.journal import Event, EventKind
    from hitl_slam.session import _State

    m: Map = lost_poses_room(0).map
    state = _State.for_map(m)
    good = {
        "edges": [[0, 1]],
        "measurements": [[0.1, 0.0, 0.0]],
        "information": [[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]],
    }
    stats = {
        "iterations": 1,
        "initial_chi2": 1.0,
        "final_chi2": 1.0,
        "time_s": 0.1,
        "poses_moved": 0,
        "max_move_m": 0.0,
    }
    base = {
        "stats": stats,
        "lines": [],
        "loop_closures": 0,
        "loop_closures_rejected": 0,
        "steps": 1,
        "contradicted": 0,
    }
    for graph, why in (
        ({**good, "edges": [[0, 0]]}, "outside the map"),
        ({**good, "edges": [[0, m.num_poses]]}, "outside the map"),
        ({**good, "measurements": [[float("nan"), 0.0, 0.0]]}, "not finite"),
        ({**good, "information": [[1.0, 0.0]]}, "rows of 2, 3 and 9"),
    ):
        event = Event(7, 0.0, EventKind.ALIGN, {**base, "graph": graph}, m.poses.copy())
        problem = state.feed(event)
        assert problem is not None
        assert why in problem, problem
    for phi in (-1.0, float("nan"), "100", True, [100.0]):
        payload = {**base, "graph": good, "relation_dcs": phi}
        problem = state.feed(Event(7, 0.0, EventKind.ALIGN, payload, m.poses.copy()))
        assert problem is not None
        assert "relation_dcs" in problem, problem
    assert (
        state.feed(Event(8, 0.0, EventKind.ALIGN, {**base, "graph": good}, m.poses.copy())) is None
    )
    # An older file's event has no relation_dcs: the configured align_relation_dcs applies.
    older = state.alignment()
    assert older is not None
    assert older.config(DEFAULT).relation_dcs == DEFAULT.align_relation_dcs
    with_phi = {**base, "graph": good, "relation_dcs": 1000.0}
    assert state.feed(Event(9, 0.0, EventKind.ALIGN, with_phi, m.poses.copy())) is None
    newer = state.alignment()
    assert newer is not None
    assert newer.config(DEFAULT).relation_dcs == 1000.0


def _correct_align(m: Map, folder: Path, out: Path, hitl: Path) -> int:
    """`hitl-slam correct MAP --corrections (none) --align -o OUT --session HITL` on ``m``
    written as a .covars in ``folder``: the exit code."""
    from hitl_slam.cli import main
    from hitl_slam.io.export import export

    map_file = folder / "input.covars"
    export(m, m.poses, map_file)
    empty = folder / "none.jsonl"
    empty.write_text("")
    args = ["correct", str(map_file), "--corrections", str(empty), "--align", "-o", str(out)]
    return main([*args, "--session", str(hitl)])


def test_correct_align_refused_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = lost_poses_room(2)
    scenario = damaged(base, jump(base.truth, np.random.default_rng(2)), 2)
    out, hitl = tmp_path / "out.g2o", tmp_path / "out.hitl"
    assert _correct_align(scenario.map, tmp_path, out, hitl) == 2
    err = capsys.readouterr().err
    assert re.search(
        "--align: (the scans disagree with the odometry|the scans found 0 loop closures"
        "|the aligned map is no more consistent with its scans)",
        err,
    ), err
    assert "nothing was written" in err
    assert not out.exists()
    assert not hitl.exists()


@needs_logs
def test_correct_align_on_a_real_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A real log bent by slow heading drift: aligning alone (no drawing) takes most of it out."""
    from hitl_slam.full_evaluation import _base_scenario
    from hitl_slam.io.maps import load_map
    from hitl_slam.sim.fault_models import drift

    base = _base_scenario("Orebro", 1)
    scenario = damaged(base, drift(base.truth, np.random.default_rng(1)), 1)  # type: ignore[attr-defined]
    out, hitl = tmp_path / "aligned.covars", tmp_path / "aligned.hitl"
    assert _correct_align(scenario.map, tmp_path, out, hitl) == 0
    printed = capsys.readouterr().out
    assert "aligned with the scans:" in printed
    assert printed.splitlines()[-1].startswith("0 corrections applied, then aligned with the scans")
    with Session.open(hitl) as s:
        assert s.aligned
        assert np.allclose(load_map(out).poses, s.poses, atol=1e-6)
        before = ate(scenario.map.poses, scenario.truth)
        assert ate(s.poses, scenario.truth) < 0.5 * before


@needs_logs
def test_where_the_firm_solve_is_the_more_consistent_it_is_kept(
    tmp_path: Path,
) -> None:
    """Belgioioso with a 30-degree jump, repaired by a careful person with 15 cm endpoint noise
    (fault seed 0): of the two solves the alignment tries, the firm one (Phi 1000) leaves the
    scans the more consistent (ATE 0.170 -> 0.083 m; the yielding one alone, Phi 100, 0.089),
    and it is kept, journaled and used by later solves. The run this was first found on (Orebro,
    seed 1, where with the statements yielding the far part of the map turned about its one loop
    closure, ATE 0.60 -> 2.15 m) no longer folds now that solves start where the factors are
    least violated (docs/ALGORITHM.md §4.5)."""
    out: dict[str, Any] = {}

    def at_end(scenario: Any, session: Session) -> None:
        truth = scenario.truth

        def figures(poses: np.ndarray) -> tuple[float, float]:
            return float(ate(poses, truth)), float(np.nanmean(scenario.errors(poses).angular))

        out["before"] = figures(np.array(session.poses))
        out["step"] = session.align()
        out["after"] = figures(np.array(session.poses))
        out["poses"] = np.array(session.poses)
        out["alignment"] = session.alignment
        session.write_journal(tmp_path / "belgioioso.hitl")

    evaluate_run("Belgioioso", "jump", 0.15, seed=0, align=False, on_end=at_end)
    step = out["step"]
    assert step.relation_dcs == DEFAULT.relation_dcs != DEFAULT.align_relation_dcs
    assert out["alignment"].relation_dcs == step.relation_dcs
    (ate0, angle0), (ate1, angle1) = out["before"], out["after"]
    assert ate1 < ate0, (ate0, ate1)
    assert angle1 <= angle0 + 0.2, (angle0, angle1)
    with Session.open(tmp_path / "belgioioso.hitl") as s:
        assert s.alignment is not None
        assert s.alignment.relation_dcs == DEFAULT.relation_dcs
        replayed, outcomes = s.replay()  # recomputed from scratch: the same choice
        assert outcomes[-1].relation_dcs == DEFAULT.relation_dcs
        assert np.allclose(replayed, out["poses"], atol=1e-9)
        s.undo()
        assert s.alignment is None


def _statement(m: Map, mode: Mode) -> Interpretation:
    rows_a = np.array([[0, k] for k in range(8)], dtype=np.int64)
    rows_b = np.array([[60, k] for k in range(8)], dtype=np.int64)
    seg = ((0.0, 0.0), (1.0, 0.0))
    return Interpretation(mode, seg, seg, rows_a, rows_b, np.array([0]), np.array([60]))


@pytest.mark.parametrize("seed", [0, 3, 8])
def test_overruled_counts_statements_held_off_beyond_degrees_or_half_a_metre(seed: int) -> None:
    """A statement counts as overruled by a solve when its two lines end more than
    OVERRULED_DEG apart in angle (modulo the mode's right angle), or its observation sets'
    centres more than OVERRULED_M apart (across line a for collinear, anywhere for a
    colocation); a few tenths of a degree and centimetres are a statement yielding, not
    overruled."""
    m = lost_poses_room(seed).map
    rng = np.random.default_rng(seed)
    poses = m.poses
    ca, cb = (
        m.observed_points(r, poses).mean(axis=0)
        for r in (_statement(m, Mode.PARALLEL).s_a, _statement(m, Mode.PARALLEL).s_b)
    )
    d = cb - ca
    normal_along_d = math.atan2(d[1], d[0])  # a line with this normal has the centres across it
    small, large = math.radians(0.5 * OVERRULED_DEG), math.radians(1.5 * OVERRULED_DEG)

    def count(mode: Mode, phi_a: float, phi_b: float) -> int:
        lines = np.array([[phi_a, 0.0], [phi_b, 0.0]])
        return overruled(m, poses, lines, [_statement(m, mode)])

    for mode, right in ((Mode.PARALLEL, 0.0), (Mode.PERPENDICULAR, math.pi / 2)):
        phi = rng.uniform(-math.pi, math.pi)
        sign = rng.choice([-1.0, 1.0])
        assert count(mode, phi, phi + right + sign * small) == 0
        assert count(mode, phi, phi + right + sign * large) == 1
        assert count(mode, phi, phi + right + math.pi + sign * small) == 0  # undirected
    # Collinear: only the offset across line a counts.
    phi_across = normal_along_d + math.pi / 2  # normal across d: the centres on one line
    assert count(Mode.COLLINEAR, phi_across, phi_across + small) == 0
    assert count(Mode.COLLINEAR, phi_across, phi_across + large) == 1
    assert float(np.hypot(*d)) > 2 * OVERRULED_M  # the room's poses 0 and 60 are metres apart
    assert count(Mode.COLLINEAR, normal_along_d, normal_along_d) == 1
    assert count(Mode.COLOCATION, phi_across, phi_across) == 1  # apart along the line


@needs_logs
def test_where_a_wrong_scan_match_folded_the_map_the_alignment_is_refused_or_better(
    tmp_path: Path,
) -> None:
    """Orebro with two heading jumps (laps), repaired by a careful person with 15 cm endpoint
    noise (seed 2; found by the full evaluation at a seed it had never run). The front end,
    seeded from the corrected map, matched two steps wrongly by 8-17 degrees and kept two loop
    closures; with the statements yielding (Phi 100, and 1000) the map folded there, half of the
    person's twelve statements were held off by degrees and metres, and the map went from ATE
    0.88 m and 3.3 degrees to 2.45 m and 40 degrees, its inconsistency *lower* (172 -> 102
    m^2), every guard passing. Both solves are now set aside and the alignment refused with the
    figures: the map, the journal and the undo stack are left as they were.

    The state is rebuilt from that run's twelve drawings (tests/data/orebro-laps-15cm-seed2.jsonl,
    written by the person as they drew then, before §I.19 changed what they see), replayed on
    the same damaged map without the second reading of a near tie (docs/ALGORITHM.md §I.18),
    which would read the tenth drawing on the other line and leave the map repaired (0.21
    degrees) before any fold."""
    scenario, _ = damaged_scenario("Orebro", "laps", 0.15, seed=2)
    drawings = read_corrections(DATA / "orebro-laps-15cm-seed2.jsonl")
    out: dict[str, Any] = {}
    config = DEFAULT.replace(near_tie_reading=False)
    with Session.new(scenario.map, config=config) as session:
        for step in drawings:
            assert isinstance(step, Apply)
            session.apply(step.drawn)
        assert len(session.active) == 12
        out["poses"] = np.array(session.poses)
        out["undo"] = session.can_undo
        try:
            session.align()
            out["why"] = None
        except AlignmentRefused as refused:
            out["why"] = str(refused.value)
        out["after"] = np.array(session.poses)
        out["undo_after"] = session.can_undo
        out["aligned"] = session.aligned
        session.write_journal(tmp_path / "orebro.hitl")

    if out["why"] is None:
        # The front end of issue 39 (docs §F.4) no longer makes the wrong match here: the
        # alignment is kept, and it must leave the map better, not folded (measured: ATE 0.87 ->
        # 0.48 m, the largest heading error 15.9 -> 10.1 degrees).
        assert out["aligned"]
        assert ate(out["after"], scenario.truth) < ate(out["poses"], scenario.truth)
        assert _events(tmp_path / "orebro.hitl", "align") == 1
        return
    assert "contradict what you said" in out["why"], out["why"]
    assert np.array_equal(out["after"], out["poses"])
    assert out["undo_after"] == out["undo"]
    assert not out["aligned"]
    assert "of your 12 statements" in out["why"], out["why"]
    assert _events(tmp_path / "orebro.hitl", "align") == 0


def test_the_share_of_statements_overruled_is_a_share() -> None:
    with pytest.raises(InputError, match="align_max_overruled"):
        Config(align_max_overruled=2.0)
