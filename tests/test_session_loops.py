"""Loop closures in a session (issue 14, part 4): rejecting or reinstating one re-solves the map
without (or with) its edge, is journaled, undone and redone exactly like a correction, survives
later corrections and a reopened file; maps without loop closures, and old session files, behave
as before. On a generated room with planted loop closures (tests/loop_support.py), and on the
front end's map of the Orebro log."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.errors import InputError
from hitl_slam.journal import DamagedSession
from hitl_slam.loop_closures import (
    AUTO_REJECTED,
    EDGES,
    WEIGHT,
    LoopClosureTable,
    effective_map,
)
from hitl_slam.map import Map
from hitl_slam.pipeline import CorrectionResult, apply_correction, solve_all
from hitl_slam.session import EntryStatus, Session, StepRefused
from hitl_slam.sim import SimulatedHuman
from loop_support import FALSE_LOOP, TRUE_PAIRS, map_with_loops, room

ROOT = Path(__file__).resolve().parents[1]
LASER = ROOT.parent / "shared" / "datasets" / "laser"
OLD_SESSION = ROOT / "tests" / "data" / "session_schema1.hitl"


@pytest.fixture(scope="module")
def loops_map() -> Map:
    return map_with_loops()


def _without(m: Map, rows: Sequence[int]) -> Map:
    """``m`` without edge ``rows``, built by hand (no metadata): what a solve without them uses."""
    keep = np.ones(m.edges.shape[0], dtype=bool)
    keep[list(rows)] = False
    return Map(
        poses=m.poses,
        points=m.points,
        offsets=m.offsets,
        edges=m.edges[keep],
        measurements=m.measurements[keep],
        information=m.information[keep],
        information_source=m.information_source[keep],
        anchor=m.anchor,
    )


def test_a_new_session_starts_with_the_front_ends_rejections(loops_map: Map) -> None:
    with Session.new(loops_map) as s:
        loops = s.loop_closures
        assert [c.pair for c in loops[:-1]] == list(TRUE_PAIRS)
        assert [c.rejected for c in loops] == [False] * FALSE_LOOP + [True]
        assert loops[FALSE_LOOP].auto_rejected
        assert loops[2].weight == pytest.approx(0.7)
        assert s.rejected_loop_closures == frozenset({FALSE_LOOP})
        # The map solved is the map without the false loop closure.
        solved = s.solved_map()
        assert solved.edges.shape[0] == loops_map.edges.shape[0] - 1
        assert not any(tuple(e) == (60, 420) for e in solved.edges.tolist())


def test_rejecting_re_solves_without_the_edge_and_undo_redo_are_exact(
    loops_map: Map, tmp_path: Path
) -> None:
    path = tmp_path / "loops.hitl"
    with Session.new(loops_map, path) as s:
        before = s.poses.copy()
        step = s.set_loop_closure(1, True)
        after = s.poses.copy()
        assert step.loop == 1
        assert step.rejected
        assert step.status is EntryStatus.APPLIED
        assert s.rejected_loop_closures == frozenset({1, FALSE_LOOP})
        assert np.abs(after - before).max() > 1e-4  # the map moved
        # Exactly the solve of the graph without the two rejected loop closures' edges.
        table = LoopClosureTable.of(loops_map)
        assert table is not None
        by_hand = _without(loops_map, [int(table.edges[1]), int(table.edges[FALSE_LOOP])])
        expected, _, _ = solve_all(by_hand, [], start=before)
        np.testing.assert_array_equal(after, expected)
        assert s.can_undo
        s.undo()
        np.testing.assert_array_equal(s.poses, before)
        assert s.rejected_loop_closures == frozenset({FALSE_LOOP})
        s.redo()
        np.testing.assert_array_equal(s.poses, after)
        assert s.rejected_loop_closures == frozenset({1, FALSE_LOOP})
        # Reinstating the false one pulls poses 60 and 420 towards its (wrong) measurement.
        gap = np.hypot(*(after[60, :2] - after[420, :2]))
        s.set_loop_closure(FALSE_LOOP, False)
        assert s.rejected_loop_closures == frozenset({1})
        assert np.hypot(*(s.poses[60, :2] - s.poses[420, :2])) > gap + 0.3
        final = s.poses.copy()
    with Session.open(path) as s:
        np.testing.assert_array_equal(s.poses, final)
        assert s.rejected_loop_closures == frozenset({1})
        assert [(t.loop, t.rejected, t.status) for t in s.loop_closure_steps] == [
            (1, True, EntryStatus.APPLIED),
            (FALSE_LOOP, False, EntryStatus.APPLIED),
        ]
        s.undo()
        np.testing.assert_array_equal(s.poses, after)
        s.undo()
        np.testing.assert_array_equal(s.poses, before)
        assert not s.can_undo
        # A new step after an undo discards the redo stack, as for corrections.
        s.set_loop_closure(3, True)
        assert not s.can_redo
        assert [t.status for t in s.loop_closure_steps] == [
            EntryStatus.DISCARDED,
            EntryStatus.DISCARDED,
            EntryStatus.APPLIED,
        ]
        replayed, _ = s.replay()
        np.testing.assert_array_equal(replayed, s.poses)


def test_refusals_change_nothing(loops_map: Map, tmp_path: Path) -> None:
    path = tmp_path / "r.hitl"
    with Session.new(loops_map, path) as s:
        events = _event_count(path)
        with pytest.raises(StepRefused, match="already rejected"):
            s.set_loop_closure(FALSE_LOOP, True)
        with pytest.raises(StepRefused, match="already in the solve"):
            s.set_loop_closure(0, False)
        with pytest.raises(InputError, match="no loop closure 6: the map has 6"):
            s.set_loop_closure(6, True)
        with pytest.raises(InputError, match="index"):
            s.set_loop_closure(True, True)  # type: ignore[arg-type]
        assert _event_count(path) == events
        assert not s.can_undo
    room_map = room().map
    with Session.new(room_map) as s:
        assert s.loop_closures == []
        assert s.solved_map() is s.input_map
        with pytest.raises(InputError, match="no loop closures"):
            s.set_loop_closure(0, True)


def _event_count(path: Path) -> int:
    with sqlite3.connect(path) as db:
        count: int = db.execute("SELECT count(*) FROM events").fetchone()[0]
    return count


class _Recording:
    """The real applier, recording the map each correction was computed on."""

    def __init__(self) -> None:
        self.maps: list[Map] = []

    def __call__(
        self,
        map: Map,
        poses: NDArray[np.float64],
        drawn: Correction,
        active: Sequence[Interpretation],
        config: Config,
    ) -> CorrectionResult:
        self.maps.append(map)
        return apply_correction(map, poses, drawn, active, config)


def test_corrections_after_a_rejection_solve_without_it_and_keep_it_rejected(
    loops_map: Map, tmp_path: Path
) -> None:
    scenario = room()
    human = SimulatedHuman(scenario, 0)
    recording = _Recording()
    path = tmp_path / "c.hitl"
    table = LoopClosureTable.of(loops_map)
    assert table is not None
    rejected_edge = tuple(loops_map.edges[table.edges[0]].tolist())
    with Session.new(loops_map, path, applier=recording) as s:
        s.set_loop_closure(0, True)
        for _ in range(2):
            drawn = human.next_correction(s.poses)
            assert drawn is not None
            s.apply(drawn)
        assert s.rejected_loop_closures == frozenset({0, FALSE_LOOP})
        assert len(s.active) == 2
        for m in recording.maps:
            pairs = {tuple(e) for e in m.edges.tolist()}
            assert rejected_edge not in pairs
            assert (60, 420) not in pairs
        # Both corrections were computed on the same map object (one engine for the set).
        assert recording.maps[0] is recording.maps[1]
        # Reinstating it re-solves every correction in effect jointly, with its edge back.
        lines_before = s.lines.copy()
        s.set_loop_closure(0, False)
        assert s.lines.shape == lines_before.shape == (4, 2)
        assert len(s.active) == 2
        s.undo()  # the reinstatement
        np.testing.assert_array_equal(s.lines, lines_before)
        poses = s.poses.copy()
        assert [h.status for h in s.history] == [EntryStatus.APPLIED, EntryStatus.APPLIED]
    with Session.open(path) as s:
        np.testing.assert_array_equal(s.poses, poses)
        assert s.rejected_loop_closures == frozenset({0, FALSE_LOOP})
        assert s.can_redo
        s.undo()
        s.undo()
        assert s.rejected_loop_closures == frozenset({0, FALSE_LOOP})
        s.undo()  # the rejection itself
        assert s.rejected_loop_closures == frozenset({FALSE_LOOP})
        np.testing.assert_array_equal(s.poses, loops_map.poses)


def test_the_current_map_and_a_save_leave_rejected_loop_closures_out(
    loops_map: Map, tmp_path: Path
) -> None:
    with Session.new(loops_map, tmp_path / "m.hitl") as s:
        s.set_loop_closure(2, True)
        s.set_loop_closure(FALSE_LOOP, False)
        current = s.current_map()
        assert current.edges.shape[0] == loops_map.edges.shape[0] - 1
        np.testing.assert_array_equal(current.poses, s.poses)
        table = LoopClosureTable.of(current)
        assert table is not None
        assert table.count == 5
        assert not table.auto_rejected.any()  # a session from it starts where this one is
        pairs = [tuple(p) for p in table.pairs.tolist()]
        assert TRUE_PAIRS[2] not in pairs
        assert (60, 420) in pairs
        with Session.new(current) as again:
            assert again.rejected_loop_closures == frozenset()
        s.save(tmp_path / "m.g2o")
    edges = [
        line.split()[1:3]
        for line in (tmp_path / "m.g2o").read_text().splitlines()
        if line.startswith("EDGE_SE2")
    ]
    assert len(edges) == loops_map.edges.shape[0] - 1
    assert [str(TRUE_PAIRS[2][0]), str(TRUE_PAIRS[2][1])] not in edges


def test_effective_maps_are_made_once_per_set_and_share_the_observations(loops_map: Map) -> None:
    from hitl_slam.workspace import Workspace

    assert effective_map(loops_map, frozenset()) is loops_map
    held = Workspace(loops_map)  # what a session keeps: each set's map, made once
    a = held.graph(frozenset({1, FALSE_LOOP}))
    assert held.graph(frozenset({FALSE_LOOP, 1})) is a
    assert np.array_equal(a.edges, effective_map(loops_map, frozenset({1, FALSE_LOOP})).edges)
    assert np.shares_memory(a.points, loops_map.points)
    assert a.edges.shape[0] == loops_map.edges.shape[0] - 2
    with pytest.raises(InputError, match="no loop closure 9"):
        effective_map(loops_map, frozenset({9}))


def test_malformed_loop_closure_metadata_is_one_clear_error(loops_map: Map, tmp_path: Path) -> None:
    for key, value, message in [
        (EDGES, np.array([0, 0, 1, 2, 3, 4]), "listed twice"),
        (EDGES, np.array([10**6] * 6), "not an edge of the map"),
        (WEIGHT, np.array([1.0, np.nan, 1, 1, 1, 0]), "not finite"),
        (AUTO_REJECTED, np.array([1, 0, 0, 0, 0, 1]), "rejection flags"),
    ]:
        bad = dataclasses.replace(loops_map, metadata={**loops_map.metadata, key: value})
        target = tmp_path / f"{key}-{message[:4]}.hitl"
        with pytest.raises(InputError, match=message):
            Session.new(bad, target)
        assert not target.exists()  # refused before anything was written
    partial = {k: v for k, v in loops_map.metadata.items() if k != WEIGHT}
    with pytest.raises(InputError, match="incomplete"):
        Session.new(dataclasses.replace(loops_map, metadata=partial))


def test_a_damaged_loop_closure_event_names_the_last_good_checkpoint(
    loops_map: Map, tmp_path: Path
) -> None:
    path = tmp_path / "d.hitl"
    with Session.new(loops_map, path) as s:
        s.set_loop_closure(1, True)
        s.set_loop_closure(2, True)
    with sqlite3.connect(path) as db:
        seq, payload = db.execute(
            "SELECT seq, payload FROM events WHERE kind = 'loop_closure' ORDER BY seq DESC"
        ).fetchone()
        data = json.loads(payload)
        data["loop"] = 1  # already rejected: not a valid step
        db.execute("UPDATE events SET payload = ? WHERE seq = ?", (json.dumps(data), seq))
    with pytest.raises(DamagedSession, match="last good checkpoint is the map after rejecting"):
        Session.open(path)


def test_old_sessions_open_unchanged() -> None:
    with Session.open(OLD_SESSION) as s:
        assert s.loop_closures == []
        assert s.rejected_loop_closures == frozenset()
        assert s.solved_map() is s.input_map


def test_the_front_end_lists_every_loop_closure_of_orebro(tmp_path: Path) -> None:
    log = LASER / "orebro-corrected.log.gz"
    if not log.is_file():
        pytest.skip("../shared/datasets/laser is not beside the repository")
    from hitl_slam.slam import slam

    result = slam(log)
    loops = result.loop_closures
    m = result.map
    n = m.num_poses
    assert loops.pairs.shape[0] >= 2
    # Whether the front end rejects one of them varies with its settings (one was rejected
    # before issue 39's loop closure floor, none since); the session lists what it rejected
    # either way (below), and tests/loop_support.py's maps hold rejected ones on purpose.
    # Every loop closure is an edge of the map; the accepted map is today's graph.
    assert m.edges.shape[0] == n - 1 + loops.pairs.shape[0]
    kept = result.accepted_map()
    assert kept.edges.shape[0] == n - 1 + int(loops.accepted.sum())
    with Session.new(m, tmp_path / "o.hitl") as s:
        listed = s.loop_closures
        assert [c.pair for c in listed] == [tuple(p) for p in loops.pairs.tolist()]
        np.testing.assert_allclose([c.weight for c in listed], np.clip(loops.weights, 0, 1))
        assert s.rejected_loop_closures == frozenset(
            int(k) for k in np.flatnonzero(~loops.accepted)
        )
        accepted = int(np.flatnonzero(loops.accepted)[0])
        before = s.poses.copy()
        s.set_loop_closure(accepted, True)
        assert not np.array_equal(s.poses, before)
    with Session.open(tmp_path / "o.hitl") as s:
        assert accepted in s.rejected_loop_closures
