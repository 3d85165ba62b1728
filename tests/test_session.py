"""The session and its journal, with a fake applier (so they are tested apart from the pipeline):
journal before memory, rejections, undo/redo of any depth against a from-scratch model, reopening
bit for bit, schema refusal, interrupted corrections, durability under SIGKILL, and the `correct`
and `export` commands with the map reader and the exporter replaced by fakes."""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import time
import types
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.corrections_file import Apply, read_corrections
from hitl_slam.errors import CorrectionRejected, InputError, SolverError
from hitl_slam.journal import SCHEMA_VERSION, EventKind, Journal, read_journal
from hitl_slam.map import Map
from hitl_slam.odometry_check import STORED_KEYS
from hitl_slam.session import EntryStatus, Session

TESTS = Path(__file__).resolve().parent

# -- the fake pipeline ------------------------------------------------------------------------


@dataclass(frozen=True)
class FakeResult:
    poses: NDArray[np.float64]
    interpretation: Interpretation
    iterations: int
    initial_chi2: float
    final_chi2: float
    time_s: float


def tiny_map(n: int = 24) -> Map:
    """A short trajectory along x, a few points per pose."""
    t = np.arange(n, dtype=np.float64)
    poses = np.stack([0.5 * t, 0.1 * np.sin(t), 0.05 * np.cos(t)], axis=1)
    scans = [np.array([[1.0, 0.5 * k], [1.0, -0.5 * k], [2.0, 0.1]]) for k in range(n)]
    return Map.from_poses_and_scans(poses, scans, name="tiny", source="tiny.covars")


def fake_applier(
    map: Map,
    poses: NDArray[np.float64],
    drawn: Correction,
    active: Sequence[Interpretation],
    config: Config,
) -> FakeResult:
    """Deterministic stand-in for the pipeline: rotates and shifts the poses after an index
    derived from the drawing (and from how many corrections are active); rejects a segment of
    zero length. Never mutates its inputs (they are read-only when the session calls it)."""
    (ax0, ay0), (ax1, ay1) = drawn.a
    (bx0, by0), (bx1, by1) = drawn.b
    length_a, length_b = math.hypot(ax1 - ax0, ay1 - ay0), math.hypot(bx1 - bx0, by1 - by0)
    if length_a == 0.0:
        raise CorrectionRejected("no observations under segment a; draw along a wall")
    if length_b == 0.0:
        raise CorrectionRejected("no observations under segment b; draw along a wall")
    n = poses.shape[0]
    k = 1 + int(abs(ax0 * 13.0 + by1 * 7.0)) % (n - 1)
    angle = 0.01 * math.sin(length_a - length_b + len(active))
    shift = 0.01 * np.array([(bx0 + bx1 - ax0 - ax1) / 2, (by0 + by1 - ay0 - ay1) / 2])
    out = np.array(poses)
    c, s = math.cos(angle), math.sin(angle)
    rel = out[k:, :2] - out[k, :2]
    out[k:, 0] = out[k, 0] + c * rel[:, 0] - s * rel[:, 1] + shift[0]
    out[k:, 1] = out[k, 1] + s * rel[:, 0] + c * rel[:, 1] + shift[1]
    out[k:, 2] = np.mod(out[k:, 2] + angle + math.pi, 2 * math.pi) - math.pi
    interpretation = Interpretation(
        mode=drawn.mode,
        line_a=drawn.a,
        line_b=drawn.b,
        s_a=np.array([[k - 1, 0]], dtype=np.int64),
        s_b=np.array([[k, 0]], dtype=np.int64),
        x_a=np.arange(k, dtype=np.int64),
        x_b=np.arange(k, n, dtype=np.int64),
        notes=(f"active={len(active)}",),
    )
    return FakeResult(out, interpretation, len(active) + 1, length_a, 1e-3 * length_b, 1e-3)


def drawing(seed: float, mode: Mode | str = Mode.COLLINEAR) -> Correction:
    return Correction.make(
        [[seed, 1.0], [seed + 2.0, 1.5]], [[seed + 0.3, -1.0], [seed + 1.0, 2.0 * seed]], mode
    )


REJECTED = Correction.make([[1.0, 1.0], [1.0, 1.0]], [[0.0, 0.0], [1.0, 0.0]], "colocation")


def from_scratch(map: Map, corrections: Sequence[Correction]) -> NDArray[np.float64]:
    """The model: apply the corrections in order, without any session code."""
    poses = np.array(map.poses)
    active: list[Interpretation] = []
    for drawn in corrections:
        result = fake_applier(map, poses, drawn, list(active), DEFAULT)
        poses, active = result.poses, [*active, result.interpretation]
    return poses


def same(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def rows(path: Path, sql: str) -> list[tuple[Any, ...]]:
    """Read with a second, independent connection (what another process would see)."""
    connection = sqlite3.connect(path)
    try:
        return connection.execute(sql).fetchall()
    finally:
        connection.close()


def reseal(path: Path) -> None:
    """Recompute every row's checksum, as if the file had been written that way (to test the
    checks behind the checksums: a tampered value that a checksum does not give away). A file
    without checksums (schema 1) is left as it is."""
    connection = sqlite3.connect(path)
    if "sha256" not in {row[1] for row in connection.execute("PRAGMA table_info(events)")}:
        connection.close()
        return
    from hitl_slam.journal import row_digest

    for table, key, columns in (
        ("map", "id", ("name", "source", "anchor", "metadata")),
        ("map_arrays", "name", ("name", "npy")),
        ("config", "id", ("json",)),
        ("events", "seq", ("seq", "time", "kind", "payload", "poses")),
    ):
        rows = connection.execute(f"SELECT {key}, {', '.join(columns)} FROM {table}").fetchall()
        connection.executemany(
            f"UPDATE {table} SET sha256 = ? WHERE {key} = ?",
            [(row_digest(table, *row[1:]), row[0]) for row in rows],
        )
    connection.commit()
    connection.close()


def kinds(path: Path) -> list[str]:
    return [kind for (kind,) in rows(path, "SELECT kind FROM events ORDER BY seq")]


@pytest.fixture
def session_file(tmp_path: Path) -> Iterator[tuple[Session, Path]]:
    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=fake_applier) as session:
        yield session, path


# -- basics -----------------------------------------------------------------------------------


def test_new_session_stores_the_map_and_config_exactly(tmp_path: Path) -> None:
    the_map = tiny_map()
    the_map.metadata["origin"] = {"robot": "cobot", "when": 3}
    config = DEFAULT.replace(sigma_h=0.07, k1=2e6)
    path = tmp_path / "s.hitl"
    with Session.new(the_map, path, config, applier=fake_applier) as session:
        assert session.path == str(path)
        assert same(session.poses, the_map.poses)
        assert not session.poses.flags.writeable
        assert session.history == []
        assert not session.can_undo
        assert not session.can_redo
    stored, stored_config, events = read_journal(path)
    assert stored_config == config
    assert [e.kind for e in events] == [EventKind.LOAD]
    assert events[0].payload["poses"] == the_map.num_poses
    for name in ("poses", "points", "offsets", "edges", "measurements", "information"):
        assert same(getattr(stored, name), getattr(the_map, name)), name
    assert stored.information_source.tobytes() == the_map.information_source.tobytes()
    assert stored.normals is None
    assert (stored.name, stored.source, stored.anchor) == ("tiny", "tiny.covars", 0)
    # The map's own metadata, and the outcome of the odometry check made as the session started
    # (stored with the map so that no reopen matches the scans again).
    own = {k: v for k, v in stored.metadata.items() if k not in STORED_KEYS}
    assert own == {"origin": {"robot": "cobot", "when": 3}}
    assert sorted(set(stored.metadata) - set(own)) == sorted(STORED_KEYS)
    assert rows(path, "PRAGMA user_version") == [(SCHEMA_VERSION,)]
    assert rows(path, "PRAGMA journal_mode") == [("delete",)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.hitl"]


def test_optional_arrays_round_trip(tmp_path: Path) -> None:
    base = tiny_map(5)
    the_map = Map(
        poses=base.poses,
        points=base.points,
        offsets=base.offsets,
        edges=base.edges,
        measurements=base.measurements,
        information=base.information,
        information_source=base.information_source,
        normals=np.tile([[0.0, 1.0]], (base.num_points, 1)),
        timestamps=np.linspace(100.0, 101.0, 5),
        anchor=2,
        metadata={
            "pose_covariances": np.arange(45, dtype=np.float64).reshape(5, 3, 3) / 7.0,
            "count": np.int64(3),
            "nested": {"list": np.array([1.5, 2.5])},
        },
    )
    Session.new(the_map, tmp_path / "s.hitl").close()
    stored, _, _ = read_journal(tmp_path / "s.hitl")
    covariances = stored.metadata["pose_covariances"]
    assert same(covariances, the_map.metadata["pose_covariances"])  # arrays kept exactly
    assert stored.metadata["count"] == 3
    assert stored.metadata["nested"] == {"list": [1.5, 2.5]}
    assert stored.normals is not None
    assert stored.timestamps is not None
    assert the_map.normals is not None
    assert the_map.timestamps is not None
    assert same(stored.normals, the_map.normals)
    assert same(stored.timestamps, the_map.timestamps)
    assert stored.anchor == 2


def test_correct_updates_poses_history_and_active(session_file: tuple[Session, Path]) -> None:
    session, path = session_file
    drawn = drawing(0.7)
    result = session.correct(drawn.a, drawn.b, "collinear")
    assert same(result.poses, from_scratch(session.input_map, [drawn]))
    assert same(session.poses, result.poses)
    assert not session.poses.flags.writeable
    [entry] = session.history
    assert entry.index == 0
    assert entry.status is EntryStatus.APPLIED
    assert entry.mode is Mode.COLLINEAR
    assert entry.drawn == drawn
    assert entry.stats is not None
    assert entry.stats.iterations == 1
    assert entry.stats.poses_moved > 0
    assert entry.interpretation is not None
    assert len(session.active) == 1
    assert session.active[0].notes == ("active=0",)
    assert session.can_undo
    assert kinds(path) == ["load", "request", "correction"]


def test_bad_drawing_is_refused_before_anything_is_journaled(
    session_file: tuple[Session, Path],
) -> None:
    session, path = session_file
    with pytest.raises(InputError, match="unknown mode"):
        session.correct([[0, 0], [1, 0]], [[0, 1], [1, 1]], "diagonal")
    with pytest.raises(InputError, match="segment a"):
        session.correct([[0, 0]], [[0, 1], [1, 1]], "collinear")
    assert kinds(path) == ["load"]


# -- the journal is written before memory changes ---------------------------------------------


def test_request_is_committed_before_the_computation(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    seen: list[tuple[Any, ...]] = []
    holder: list[Session] = []

    def spy(
        map: Map,
        poses: NDArray[np.float64],
        drawn: Correction,
        active: Sequence[Interpretation],
        config: Config,
    ) -> FakeResult:
        session = holder[0]
        [last] = rows(path, "SELECT kind, payload FROM events ORDER BY seq DESC LIMIT 1")
        seen.append(last)
        assert same(session.poses, map.poses)  # memory not changed yet
        assert session.history[-1].status is EntryStatus.PENDING
        assert not poses.flags.writeable  # the applier cannot change the session's map
        return fake_applier(map, poses, drawn, active, config)

    with Session.new(tiny_map(), path, applier=spy) as session:
        holder.append(session)
        drawn = drawing(1.1, "colocation")
        session.apply(drawn)
        assert seen[0][0] == "request"
        assert json.loads(seen[0][1]) == {"correction": drawn.to_json()}
        [(kind, blob)] = rows(path, "SELECT kind, poses FROM events ORDER BY seq DESC LIMIT 1")
        assert kind == "correction"
        stored = np.load(__import__("io").BytesIO(blob))
        assert same(stored, session.poses)


def test_every_event_is_committed_before_the_state_changes(
    session_file: tuple[Session, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    session, path = session_file
    journal = session._journal
    original = journal.append
    seen: list[tuple[EventKind, bytes, list[EntryStatus]]] = []

    def spying_append(
        kind: EventKind, payload: dict[str, Any], poses: NDArray[np.float64] | None = None
    ) -> Any:
        seen.append((kind, session.poses.tobytes(), [e.status for e in session.history]))
        event = original(kind, payload, poses)
        [(last,)] = rows(path, "SELECT max(seq) FROM events")
        assert last == event.seq  # committed: visible to another connection
        return event

    monkeypatch.setattr(journal, "append", spying_append)
    applied, undone, pending = EntryStatus.APPLIED, EntryStatus.UNDONE, EntryStatus.PENDING
    expected: list[tuple[Callable[..., object], tuple[Any, ...], list[Any], list[Any]]] = [
        (session.apply, (drawing(0.3),), [[], [pending]], [applied]),
        (session.apply, (drawing(2.9),), [[applied], [applied, pending]], [applied, applied]),
        (session.undo, (), [[applied, applied]], [applied, undone]),
        (session.undo, (), [[applied, undone]], [undone, undone]),
        (session.redo, (), [[undone, undone]], [applied, undone]),
    ]
    for operation, args, during, after in expected:
        before = session.poses.tobytes()
        seen.clear()
        operation(*args)
        assert [statuses for _, _, statuses in seen] == during
        assert all(poses == before for _, poses, _ in seen)  # memory unchanged while journaling
        assert [e.status for e in session.history] == after
        assert session.poses.tobytes() != before


# -- rejections and failures ------------------------------------------------------------------


def dump(path: Path) -> dict[str, list[tuple[Any, ...]]]:
    tables = ("meta", "map", "map_arrays", "config", "events")
    return {t: rows(path, f"SELECT * FROM {t} ORDER BY 1") for t in tables}


def test_rejection_changes_nothing_but_the_journal(session_file: tuple[Session, Path]) -> None:
    session, path = session_file
    session.apply(drawing(0.5))
    (path.parent / "keep.txt").write_text("untouched")
    before = dump(path)
    poses = session.poses.copy()
    files = sorted((p.name, p.stat().st_mtime_ns) for p in path.parent.iterdir() if p != path)
    with pytest.raises(CorrectionRejected, match="segment a"):
        session.apply(REJECTED)
    after = dump(path)
    for table in ("meta", "map", "map_arrays", "config"):
        assert after[table] == before[table], table
    assert after["events"][: len(before["events"])] == before["events"]
    new = after["events"][len(before["events"]) :]
    assert [row[2] for row in new] == ["request", "rejection"]
    payload = json.loads(new[1][3])
    assert payload["correction"] == REJECTED.to_json()
    assert "segment a" in payload["reason"]
    assert new[1][4] is None  # no checkpoint
    assert same(session.poses, poses)
    assert len(session.active) == 1
    assert session.history[-1].status is EntryStatus.REJECTED
    assert session.history[-1].reason is not None
    assert files == sorted(
        (p.name, p.stat().st_mtime_ns) for p in path.parent.iterdir() if p != path
    )
    # The rejection does not disturb undo: it undoes the last APPLIED correction.
    session.undo()
    assert same(session.poses, session.input_map.poses)


@pytest.mark.parametrize(
    ("error", "expected"),
    [
        (SolverError("singular system"), SolverError),
        (KeyboardInterrupt(), KeyboardInterrupt),
        (RuntimeError("bug"), RuntimeError),
    ],
)
def test_failed_computation_is_journaled_as_interrupted(
    tmp_path: Path, error: BaseException, expected: type[BaseException]
) -> None:
    def failing(*args: Any) -> FakeResult:
        raise error

    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=failing) as session:
        with pytest.raises(expected):
            session.apply(drawing(0.2))
        assert session.history[-1].status is EntryStatus.INTERRUPTED
        assert type(error).__name__ in (session.history[-1].reason or "")
        assert same(session.poses, session.input_map.poses)
    assert kinds(path) == ["load", "request", "interrupted"]
    with Session.open(path) as again:
        assert again.history[-1].status is EntryStatus.INTERRUPTED


def test_bad_poses_from_the_applier_are_a_solver_error(tmp_path: Path) -> None:
    def wrong_shape(*args: Any) -> FakeResult:
        result = fake_applier(*args)
        return FakeResult(result.poses[:-1], result.interpretation, 1, 0.0, 0.0, 0.0)

    def not_finite(*args: Any) -> FakeResult:
        result = fake_applier(*args)
        poses = result.poses.copy()
        poses[3, 1] = np.nan
        return FakeResult(poses, result.interpretation, 1, 0.0, 0.0, 0.0)

    with Session.new(tiny_map(), applier=wrong_shape) as session:
        with pytest.raises(SolverError, match="shape"):
            session.apply(drawing(0.2))
        assert not session.can_undo
    with Session.new(tiny_map(), applier=not_finite) as session:
        with pytest.raises(SolverError, match="non-finite"):
            session.apply(drawing(0.2))
        assert session.history[-1].status is EntryStatus.INTERRUPTED


# -- undo / redo --------------------------------------------------------------------------------


def test_undo_redo_any_depth_and_discarding(session_file: tuple[Session, Path]) -> None:
    session, _ = session_file
    input_poses = session.input_map.poses
    drawings = [drawing(s) for s in (0.4, 1.7, 2.2, 3.9)]
    states = [input_poses]
    for d in drawings:
        session.apply(d)
        states.append(session.poses.copy())
    for depth in range(4, 0, -1):
        session.undo()
        assert same(session.poses, states[depth - 1])
    assert same(session.poses, input_poses)  # bit for bit
    assert not session.can_undo
    with pytest.raises(InputError, match="nothing to undo"):
        session.undo()
    for depth in range(1, 3):
        session.redo()
        assert same(session.poses, states[depth])
    assert [e.status for e in session.history] == [
        EntryStatus.APPLIED,
        EntryStatus.APPLIED,
        EntryStatus.UNDONE,
        EntryStatus.UNDONE,
    ]
    session.apply(drawing(5.5))  # drops the redo stack
    assert not session.can_redo
    with pytest.raises(InputError, match="nothing to redo"):
        session.redo()
    assert [e.status for e in session.history] == [
        EntryStatus.APPLIED,
        EntryStatus.APPLIED,
        EntryStatus.DISCARDED,
        EntryStatus.DISCARDED,
        EntryStatus.APPLIED,
    ]
    assert session.corrections == [drawings[0], drawings[1], drawing(5.5)]
    expected = from_scratch(session.input_map, session.corrections)
    assert same(session.poses, expected)


Op = tuple[str, float, bool]
ops = st.lists(
    st.one_of(
        st.tuples(st.just("correct"), st.floats(-5.0, 5.0), st.booleans()),
        st.tuples(st.just("undo"), st.just(0.0), st.just(False)),
        st.tuples(st.just("redo"), st.just(0.0), st.just(False)),
    ),
    max_size=14,
)


@settings(max_examples=40, deadline=None)
@given(ops)
def test_any_sequence_equals_the_surviving_corrections_from_scratch(sequence: list[Op]) -> None:
    the_map = tiny_map(16)
    applied: list[Correction] = []
    redo: list[Correction] = []
    with Session.new(the_map, applier=fake_applier) as session:
        for op, seed, reject in sequence:
            if op == "undo":
                if applied:
                    session.undo()
                    redo.append(applied.pop())
                else:
                    with pytest.raises(InputError):
                        session.undo()
            elif op == "redo":
                if redo:
                    session.redo()
                    applied.append(redo.pop())
                else:
                    with pytest.raises(InputError):
                        session.redo()
            elif reject:
                with pytest.raises(CorrectionRejected):
                    session.apply(REJECTED)
            else:
                session.apply(drawing(seed))
                applied.append(drawing(seed))
                redo.clear()
        expected = from_scratch(the_map, applied)
        assert same(session.poses, expected)
        assert session.corrections == applied
        undone = [e.drawn for e in session.history if e.status is EntryStatus.UNDONE]
        assert undone == redo[::-1]
        assert session.can_undo == bool(applied)
        assert session.can_redo == bool(redo)
        replayed, outcomes = session.replay()
        assert same(replayed, expected)
        assert len(outcomes) == len(applied)
        with tempfile.TemporaryDirectory() as directory:
            copy = Path(directory) / "copy.hitl"
            session.write_journal(copy)
            with Session.open(copy, applier=fake_applier) as reopened:
                assert same(reopened.poses, session.poses)
                assert [(e.seq, e.status, e.drawn) for e in reopened.history] == [
                    (e.seq, e.status, e.drawn) for e in session.history
                ]
                # The stacks came back too: redo everything, then undo everything.
                while reopened.can_redo:
                    reopened.redo()
                    applied.append(redo.pop())
                assert same(reopened.poses, from_scratch(the_map, applied))
                while reopened.can_undo:
                    reopened.undo()
                assert same(reopened.poses, the_map.poses)


def test_reopen_gives_identical_poses_and_stacks(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=fake_applier) as session:
        for s in (0.1, 1.3, 2.6, 3.3):
            session.apply(drawing(s))
        with pytest.raises(CorrectionRejected):
            session.apply(REJECTED)
        session.undo()
        session.undo()
        session.redo()
        poses = session.poses.copy()
        history = session.history
        active = [h.to_json() for h in session.active]
    with Session.open(path, applier=fake_applier) as again:
        assert same(again.poses, poses)
        assert not again.poses.flags.writeable
        assert [(e.index, e.seq, e.time, e.status, e.drawn, e.reason) for e in again.history] == [
            (e.index, e.seq, e.time, e.status, e.drawn, e.reason) for e in history
        ]
        assert [e.stats for e in again.history] == [e.stats for e in history]
        assert [h.to_json() for h in again.active] == active
        assert again.can_undo
        assert again.can_redo
        again.redo()
        assert same(again.poses, from_scratch(again.input_map, again.corrections))
        again.apply(drawing(4.4))  # the session continues in the same file
    assert kinds(path)[-3:] == ["redo", "request", "correction"]


def test_export_corrections_replays_to_the_same_map(
    session_file: tuple[Session, Path], tmp_path: Path
) -> None:
    session, _ = session_file
    for s in (0.9, 2.1, 3.4):
        session.apply(drawing(s, Mode.PARALLEL))
    session.undo()
    out = tmp_path / "c.jsonl"
    assert session.export_corrections(out) == 2
    steps = read_corrections(out)
    drawn = [s.drawn for s in steps if isinstance(s, Apply)]
    assert drawn == session.corrections
    assert same(from_scratch(session.input_map, drawn), session.poses)


# -- interrupted corrections, refusals, damage ----------------------------------------------------


def test_request_without_outcome_reads_back_as_interrupted(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=fake_applier) as session:
        session.apply(drawing(0.6))
        after_first = session.poses.copy()
    with Journal.open(path) as journal:  # a process that died mid-solve left only this
        journal.append(EventKind.REQUEST, {"correction": drawing(1.6).to_json()})
    with Session.open(path, applier=fake_applier) as session:
        statuses = [e.status for e in session.history]
        assert statuses == [EntryStatus.APPLIED, EntryStatus.INTERRUPTED]
        assert "ended" in (session.history[-1].reason or "")
        assert same(session.poses, after_first)
        assert len(session.active) == 1
        session.apply(drawing(2.5))
        session.undo()
        session.undo()
        assert same(session.poses, session.input_map.poses)
    with Session.open(path) as session:
        assert [e.status for e in session.history] == [
            EntryStatus.UNDONE,
            EntryStatus.INTERRUPTED,
            EntryStatus.UNDONE,
        ]


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    Session.new(tiny_map(), path).close()
    connection = sqlite3.connect(path)
    connection.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    connection.close()
    with pytest.raises(InputError) as info:
        Session.open(path)
    message = str(info.value)
    assert f"this session was written by a newer hitl-slam (schema {SCHEMA_VERSION + 1}); " in (
        message
    )
    assert "upgrade" in message
    assert message.startswith(str(path))


def test_a_session_saved_with_a_removed_option_opens_and_says_it_is_ignored(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An option measured and not kept is deleted from Config; a session saved before that names
    it in its stored configuration. The file opens with its history as it was left, and a warning
    names each option this version does not have, with its stored value; the rest of the
    configuration is kept."""
    path = tmp_path / "s.hitl"
    config = DEFAULT.replace(sigma_h=0.07)
    with Session.new(tiny_map(), path, config, applier=fake_applier) as session:
        drawn = drawing(0.7)
        session.correct(drawn.a, drawn.b, "collinear")
        before = session.poses.copy()
    (stored,) = rows(path, "SELECT json FROM config WHERE id = 1")[0]
    # The seven deleted by issue 41, as sessions of that time stored them (one set on).
    deleted = {
        "sigma_scan": 0.01,
        "points_yield": False,
        "pass_by_pass": False,
        "colocation_even_centroids": False,
        "colocation_length_rule": False,
        "align_max_contradicted_local": 1.0,
        "odometry_fuse": 0.0,
    }
    connection = sqlite3.connect(path)
    connection.execute(
        "UPDATE config SET json = ? WHERE id = 1", (json.dumps({**json.loads(stored), **deleted}),)
    )
    connection.commit()
    connection.close()
    reseal(path)
    with (
        caplog.at_level(logging.WARNING, logger="hitl_slam.journal"),
        Session.open(path, applier=fake_applier) as session,
    ):
        assert session.config == config
        np.testing.assert_array_equal(session.poses, before)
        assert [entry.drawn for entry in session.history] == [drawn]
    (record,) = [r for r in caplog.records if "does not have" in r.getMessage()]
    message = record.getMessage()
    assert message.startswith(str(path))
    for name, value in deleted.items():
        assert f"{name}={value!r}" in message
    assert "ignored" in message
    # A wrong value for a key this version has is still refused, naming the file.
    bad = {**json.loads(stored), "sigma_h": "wide"}
    connection = sqlite3.connect(path)
    connection.execute("UPDATE config SET json = ? WHERE id = 1", (json.dumps(bad),))
    connection.commit()
    connection.close()
    reseal(path)
    with pytest.raises(InputError, match="the configuration is invalid"):
        Session.open(path)


def test_files_that_are_not_sessions_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        Session.open(tmp_path / "missing.hitl")
    assert not (tmp_path / "missing.hitl").exists()  # opening never creates
    text = tmp_path / "text.hitl"
    text.write_text("hello, this is not a database at all, not even close" * 10)
    with pytest.raises(InputError, match="not a hitl-slam session"):
        Session.open(text)
    other = tmp_path / "other.hitl"
    connection = sqlite3.connect(other)
    connection.execute("CREATE TABLE t (x)")
    connection.commit()
    connection.close()
    with pytest.raises(InputError, match="not a hitl-slam session"):
        Session.open(other)
    empty = tmp_path / "empty.hitl"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="not a hitl-slam session"):
        Session.open(empty)


def test_new_never_overwrites(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    path.write_text("precious")
    with pytest.raises(InputError, match="already exists"):
        Session.new(tiny_map(), path)
    assert path.read_text() == "precious"
    with pytest.raises(InputError, match="cannot create"):
        Session.new(tiny_map(), tmp_path / "no" / "such" / "dir.hitl")


def test_damaged_journal_is_reported(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=fake_applier) as session:
        session.apply(drawing(0.6))
    connection = sqlite3.connect(path)
    connection.execute("UPDATE events SET poses = NULL WHERE kind = 'correction'")
    connection.commit()
    connection.close()
    with pytest.raises(InputError, match=r"damaged \(event 3 does not match its checksum\)"):
        Session.open(path)
    reseal(path)
    with pytest.raises(InputError, match=r"damaged.*event 3"):
        Session.open(path)
    connection = sqlite3.connect(path)
    connection.execute("DELETE FROM events WHERE seq = 2")
    connection.commit()
    connection.close()
    with pytest.raises(InputError, match="event 2 is missing"):
        Session.open(path)


def test_two_sessions_on_one_file_cannot_interleave(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    Session.new(tiny_map(), path).close()
    with (
        Session.open(path, applier=fake_applier) as first,
        Session.open(path, applier=fake_applier) as second,
    ):
        first.apply(drawing(0.3))
        with pytest.raises(InputError, match="changed by another program"):
            second.apply(drawing(0.4))
        assert not second.can_undo
    assert kinds(path) == ["load", "request", "correction"]


def test_closed_session_refuses_work(tmp_path: Path) -> None:
    session = Session.new(tiny_map(), applier=fake_applier)
    session.close()
    session.close()
    assert session.closed
    with pytest.raises(InputError, match="closed"):
        session.apply(drawing(0.3))


def test_write_journal_refuses_an_existing_file(tmp_path: Path) -> None:
    with Session.new(tiny_map(), applier=fake_applier) as session:
        session.apply(drawing(0.3))
        target = tmp_path / "copy.hitl"
        target.write_text("precious")
        with pytest.raises(InputError, match="already exists"):
            session.write_journal(target)
        assert target.read_text() == "precious"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["copy.hitl"]


# -- durability under SIGKILL ---------------------------------------------------------------------

_CHILD = """
import sys, time
sys.path.insert(0, {tests!r})
import test_session as t
from hitl_slam.session import Session

calls = []

def applier(*args):
    calls.append(1)
    if len(calls) == 3:
        open({marker!r}, "w").close()
        time.sleep(60)
    return t.fake_applier(*args)

session = Session.new(t.tiny_map(), {path!r}, applier=applier)
session.apply(t.drawing(0.8))
session.apply(t.drawing(2.3))
session.apply(t.drawing(3.1))
"""


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_sigkill_during_a_solve_loses_nothing_committed(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    marker = tmp_path / "solving"
    code = _CHILD.format(tests=str(TESTS), marker=str(marker), path=str(path))
    child = subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)])
    try:
        deadline = time.monotonic() + 60
        while not marker.exists():
            assert child.poll() is None, "the child exited early"
            assert time.monotonic() < deadline, "the child never reached the third solve"
            time.sleep(0.02)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
    assert child.returncode == -signal.SIGKILL
    with Session.open(path, applier=fake_applier) as session:
        statuses = [e.status for e in session.history]
        assert statuses == [EntryStatus.APPLIED, EntryStatus.APPLIED, EntryStatus.INTERRUPTED]
        assert session.history[2].drawn == drawing(3.1)
        expected = from_scratch(session.input_map, [drawing(0.8), drawing(2.3)])
        assert same(session.poses, expected)
        assert len(session.active) == 2


# -- load_map on sessions -------------------------------------------------------------------------


def test_load_map_reads_a_sessions_current_map(session_file: tuple[Session, Path]) -> None:
    from hitl_slam.io.maps import load_map

    session, path = session_file
    session.apply(drawing(1.2))
    loaded = load_map(path)
    assert same(loaded.poses, session.poses)
    assert same(loaded.points, session.input_map.points)
    assert loaded.name == "tiny"


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("map.xyz", "supported: .covars, .clf, .log, .bag, .db3, .mcap, .hitl"),
        ("map", "no extension"),
        ("graph.g2o", "hitl-slam solve"),
        ("map.hitl.gz", "supported"),
    ],
)
def test_load_map_names_the_supported_formats(tmp_path: Path, name: str, message: str) -> None:
    from hitl_slam.io.maps import load_map

    path = tmp_path / name
    path.write_text("x")
    with pytest.raises(InputError, match=message.replace(".", r"\.")):
        load_map(path)


# -- the `correct` and `export` commands, with the map reader and exporter replaced -------------


@pytest.fixture
def fakes(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, bytes]]:
    """Map files are read as tiny_map(); exports are recorded (and written as the poses' bytes);
    the pipeline is the fake applier."""
    import hitl_slam.io.maps
    import hitl_slam.session

    written: list[tuple[str, bytes]] = []

    def export(map: Map, poses: NDArray[np.float64], path: Any) -> None:
        from hitl_slam.io.atomic import atomic_write_text

        written.append((str(path), np.asarray(poses).tobytes()))
        atomic_write_text(path, "poses\n")

    module = types.ModuleType("hitl_slam.io.export")
    module.export = export  # type: ignore[attr-defined]
    module.EXPORT_EXTENSIONS = (".covars", ".g2o", ".txt", ".pgm")  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "hitl_slam.io.export", module)
    real_load = hitl_slam.io.maps.load_map

    def load(
        path: Any, config: Config = DEFAULT, *, max_range: float | None = None, bag: Any = None
    ) -> Map:
        return real_load(path) if str(path).endswith(".hitl") else tiny_map()

    monkeypatch.setattr(hitl_slam.io.maps, "load_map", load)
    monkeypatch.setattr(hitl_slam.session, "_default_applier", lambda _workspace: fake_applier)
    return written


def corrections_file(tmp_path: Path, *items: Correction | str) -> Path:
    path = tmp_path / "c.jsonl"
    lines = [
        json.dumps({"action": i}) if isinstance(i, str) else json.dumps(i.to_json()) for i in items
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_correct_applies_steps_in_order_and_writes_a_session(
    tmp_path: Path, fakes: list[tuple[str, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    from hitl_slam.cli import main

    c = corrections_file(tmp_path, drawing(0.5), drawing(1.5), "undo", "redo", drawing(2.5))
    out, hitl = tmp_path / "out.covars", tmp_path / "run.hitl"
    args = ["correct", "in.covars", "--corrections", str(c), "-o", str(out), "--session", str(hitl)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "chi2 before" in text
    assert "undo" in text
    assert "redo" in text
    assert text.strip().splitlines()[-1].startswith("3 corrections applied, 1 undone, 1 redone")
    expected = from_scratch(tiny_map(), [drawing(0.5), drawing(1.5), drawing(2.5)])
    assert fakes == [(str(out), expected.tobytes())]
    with Session.open(hitl) as session:
        assert same(session.poses, expected)
        assert [e.status for e in session.history] == [EntryStatus.APPLIED] * 3
    assert kinds(hitl)[-1] == "save"
    # Exporting the session's corrections and running them again gives the same map.
    jsonl = tmp_path / "again.jsonl"
    assert main(["export", str(hitl), "-o", str(jsonl)]) == 0
    assert "3 corrections" in capsys.readouterr().out
    assert main(["correct", "in.covars", "--corrections", str(jsonl), "-o", str(out), "-q"]) == 0
    assert capsys.readouterr().out.count("\n") == 1
    assert fakes[-1] == (str(out), expected.tobytes())


def test_correct_stops_at_a_rejection_and_writes_nothing(
    tmp_path: Path, fakes: list[tuple[str, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    from hitl_slam.cli import main

    c = corrections_file(tmp_path, drawing(0.5), REJECTED, drawing(2.5))
    out, hitl = tmp_path / "out.covars", tmp_path / "run.hitl"
    args = ["correct", "in.covars", "--corrections", str(c), "-o", str(out), "--session", str(hitl)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"hitl-slam: error: {c}:2: colocation correction rejected")
    assert "--keep-going" in err
    assert fakes == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.jsonl"]


def test_correct_keep_going_lists_rejections(
    tmp_path: Path, fakes: list[tuple[str, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    from hitl_slam.cli import main

    c = corrections_file(tmp_path, "undo", drawing(0.5), REJECTED, drawing(2.5), "redo")
    out, hitl = tmp_path / "out.covars", tmp_path / "run.hitl"
    args = ["correct", "in.covars", "--corrections", str(c), "-o", str(out)]
    assert main([*args, "--session", str(hitl), "--keep-going"]) == 0
    text = capsys.readouterr().out
    assert f"{c}:1: nothing to undo" in text
    assert f"{c}:3: colocation correction rejected" in text
    assert f"{c}:5: nothing to redo" in text
    assert "3 rejected (lines 1, 3, 5)" in text.splitlines()[-1]
    expected = from_scratch(tiny_map(), [drawing(0.5), drawing(2.5)])
    assert fakes == [(str(out), expected.tobytes())]
    with Session.open(hitl) as session:
        statuses = [e.status for e in session.history]
        assert statuses == [EntryStatus.APPLIED, EntryStatus.REJECTED, EntryStatus.APPLIED]


def test_correct_refuses_bad_arguments_before_any_work(
    tmp_path: Path, fakes: list[tuple[str, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    from hitl_slam.cli import main

    c = corrections_file(tmp_path, drawing(0.5))
    out = tmp_path / "out.covars"
    existing = tmp_path / "old.hitl"
    existing.write_text("precious")
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"mode": "collinear"}\n')
    cases = [
        (["--session", str(existing)], "already exists"),
        (["--session", str(tmp_path / "s.db")], "must end in .hitl"),
    ]
    for extra, message in cases:
        assert main(["correct", "m.covars", "--corrections", str(c), "-o", str(out), *extra]) == 2
        assert message in capsys.readouterr().err
    assert main(["correct", "m.covars", "--corrections", str(bad), "-o", str(out)]) == 2
    assert f"{bad}:1: missing" in capsys.readouterr().err
    assert main(["correct", "m.covars", "--corrections", str(c), "-o", str(tmp_path / "o.x")]) == 2
    assert "unsupported output extension" in capsys.readouterr().err
    assert existing.read_text() == "precious"
    assert fakes == []
    assert not out.exists()


def test_export_command(
    tmp_path: Path, fakes: list[tuple[str, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    from hitl_slam.cli import main

    hitl = tmp_path / "s.hitl"
    with Session.new(tiny_map(), hitl, applier=fake_applier) as session:
        session.apply(drawing(0.5))
        poses = session.poses.copy()
    before = kinds(hitl)
    assert main(["export", str(hitl), "-o", str(tmp_path / "m.g2o")]) == 0
    assert fakes == [(str(tmp_path / "m.g2o"), poses.tobytes())]
    assert kinds(hitl) == before  # exporting reads the session, never writes to it
    assert main(["export", "m.covars", "-o", str(tmp_path / "m.jsonl")]) == 2
    assert "come from a session" in capsys.readouterr().err
    assert main(["export", str(hitl), "-o", str(tmp_path / "m.csv")]) == 2
    assert ".jsonl" in capsys.readouterr().err
