"""The odometry check matches a map's scans once: when a session starts on it (its outcome stored
with the map, so a reopen reads it), or never for a map the front end built (its chain edges are
its scan matches). No correction matches scans (issue 40)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam import _core
from hitl_slam.config import DEFAULT
from hitl_slam.errors import InputError
from hitl_slam.odometry_check import (
    STORED_STEPS,
    STORED_TURNS,
    check_odometry,
    checked_map,
    stored_check,
    unchecked_steps,
    with_stored_check,
)
from hitl_slam.session import Session
from hitl_slam.sim import HeadingJump, SimulatedHuman, lost_poses_room, parallel_corridors
from hitl_slam.sim.fault_models import damaged


@pytest.fixture
def matches(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The scan pairs matched (one entry per call into the core: its number of pairs)."""
    calls: list[int] = []
    real = _core.match_consecutive

    def counted(points: Any, offsets: Any, guesses: Any, **kw: Any) -> Any:
        calls.append(int(np.shape(guesses)[0]))
        return real(points, offsets, guesses, **kw)

    monkeypatch.setattr(_core, "match_consecutive", counted)
    return calls


def _jumped(seed: int) -> Any:
    base = parallel_corridors(seed, heading_jump_deg=0.0)
    return damaged(base, [HeadingJump(base.map.num_poses // 2, math.radians(20.0))], seed)


def test_a_session_matches_its_scans_when_it_starts_and_never_per_correction(
    tmp_path: Path, matches: list[int]
) -> None:
    scenario = _jumped(5)
    path = tmp_path / "s.hitl"
    with Session.new(scenario.map, path) as session:
        at_start = sum(matches)
        assert at_start >= scenario.map.num_poses - 1  # every step, once
        human = SimulatedHuman(scenario, 5)
        for _ in range(2):
            drawn = human.next_correction(np.array(session.poses))
            assert drawn is not None
            session.apply(drawn)
        assert sum(matches) == at_start  # nothing per correction
        after = np.array(session.poses)
    with Session.open(path) as reopened:
        assert np.array_equal(reopened.poses, after)
        drawn = SimulatedHuman(scenario, 6).next_correction(np.array(reopened.poses))
        assert drawn is not None
        reopened.apply(drawn)
        assert sum(matches) == at_start  # nor after a reopen
        # The stored outcome is the check's own, bit for bit.
        stored = stored_check(reopened.input_map, DEFAULT)
        assert stored is not None
        fresh = check_odometry(scenario.map)
        assert fresh.relaxed.size == 1  # the jump
        assert np.array_equal(stored[0].measurements, fresh.measurements)
        assert np.array_equal(stored[0].information, fresh.information)
        assert np.array_equal(stored[1], ~fresh.matched)


def test_a_front_end_map_is_never_matched_again(matches: list[int]) -> None:
    from hitl_slam.slam import StepKind, slam

    result = slam(lost_poses_room(0).map)
    m = result.map
    steps = m.metadata["front_end_steps"]
    assert steps.dtype == np.uint8
    assert np.array_equal(steps, result.steps)
    assert with_stored_check(m) is m  # nothing to store
    assert checked_map(m) is m  # its chain edges are its scan matches
    assert np.array_equal(unchecked_steps(m), steps[1:] == StepKind.FAILED)
    with Session.new(m) as session:
        scenario = lost_poses_room(0)
        drawn = SimulatedHuman(scenario, 0).next_correction(np.array(session.poses))
        assert drawn is not None
        session.apply(drawn)
    assert matches == []


def test_a_stored_check_of_other_scans_or_another_setting_is_not_used() -> None:
    scenario = _jumped(6)
    m = with_stored_check(scenario.map)
    assert m is not scenario.map
    assert stored_check(m) is not None
    moved = dataclasses.replace(m, points=m.points + 0.01)
    assert stored_check(moved) is None  # other scans: checked again
    assert stored_check(m, DEFAULT.replace(odometry_check=20.0)) is None
    assert with_stored_check(m) is m  # already there


def test_a_damaged_stored_check_is_refused_with_the_map_named() -> None:
    m = with_stored_check(_jumped(7).map)
    metadata = dict(m.metadata)
    metadata[STORED_TURNS] = np.zeros((np.size(metadata[STORED_STEPS]) + 1, 2))
    with pytest.raises(InputError, match="stored odometry check is malformed"):
        stored_check(dataclasses.replace(m, metadata=metadata))


def test_prepared_the_first_correction_makes_nothing_of_its_own(
    monkeypatch: pytest.MonkeyPatch, matches: list[int]
) -> None:
    """Session.prepare (serve calls it as the page opens) makes the scans in the core, the
    odometry check and the engine in the background: the first correction then builds none."""
    from hitl_slam import pipeline

    made: list[str] = []
    real_scans, real_engine = _core.MapScans, pipeline.new_engine

    def scans(*args: Any) -> Any:
        made.append("scans")
        return real_scans(*args)

    def engine(m: Any) -> Any:
        made.append("engine")
        return real_engine(m)

    monkeypatch.setattr(_core, "MapScans", scans)
    monkeypatch.setattr(pipeline, "new_engine", engine)
    scenario = _jumped(8)
    with Session.new(scenario.map) as session:
        thread = session.prepare()
        assert thread is not None
        thread.join(60)
        assert sorted(made) == ["engine", "scans"]
        drawn = SimulatedHuman(scenario, 8).next_correction(np.array(session.poses))
        assert drawn is not None
        before, checked = len(made), len(matches)  # (the simulated person reads the scans too)
        session.apply(drawn)
        assert len(made) == before  # nothing new for the correction
        assert len(matches) == checked
