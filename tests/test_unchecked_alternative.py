"""A correction across chain steps the scans could not check is also solved with a robust kernel
on the odometry, and the more consistent map is kept (docs/ALGORITHM.md §I.12)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hitl_slam.config import DEFAULT
from hitl_slam.errors import InputError
from hitl_slam.full_evaluation import evaluate_run
from hitl_slam.odometry_check import check_odometry, unchecked_steps
from hitl_slam.session import Session
from hitl_slam.sim import SimulatedHuman, lost_poses_room, parallel_corridors

OFF = DEFAULT.replace(unchecked_alternative="")
NOTE = "could not be checked by the scans"


def test_unchecked_steps_are_the_steps_the_check_did_not_match() -> None:
    m = lost_poses_room(0).map
    u = unchecked_steps(m)
    assert u.shape == (m.num_poses - 1,)
    assert np.array_equal(u, ~check_odometry(m).matched)
    assert 0 < u.sum() < u.size  # the room's 1.5 m scans match about half of its steps
    assert not u.flags.writeable
    off = DEFAULT.replace(odometry_check=0.0)
    assert not unchecked_steps(m, off).any()


def test_the_alternative_is_a_robust_specification() -> None:
    with pytest.raises(InputError, match="unknown edge class"):
        DEFAULT.replace(unchecked_alternative="wheels=dcs:1")


def _final(config: Any) -> tuple[float, float, list[str]]:
    """The lost-poses room with a 30-degree heading jump at step 316, inside a stretch its scans
    cannot check (steps 310-319 unmatched), repaired by the careful person (15 cm endpoint noise,
    seed 0): the final inconsistency and ATE, and the notes of the corrections in effect."""
    notes: list[str] = []

    def at_end(_scenario: Any, session: Session) -> None:
        notes.extend(n for h in session.active for n in h.notes)

    run = evaluate_run(
        "lost poses room", "jump", 0.15, seed=0, config=config, align=False, on_end=at_end
    )
    return run.inconsistency[1], run.ate[1], notes


def test_a_jump_the_scans_cannot_see_is_kept_where_it_happened() -> None:
    inc_off, ate_off, notes_off = _final(OFF)
    inc_on, ate_on, notes_on = _final(DEFAULT)
    # Spread over the stretch between the passes, the jump turned the walls seen from it: the
    # map ended more inconsistent than the damaged one (32.8 m^2 before the first drawing).
    assert inc_off > 100.0, inc_off
    assert inc_on < 0.5 * inc_off, (inc_on, inc_off)
    assert ate_on < ate_off, (ate_on, ate_off)
    assert not any(NOTE in n for n in notes_off)
    assert any(NOTE in n for n in notes_on), notes_on


def test_where_the_scans_checked_every_step_nothing_changes() -> None:
    scenario = parallel_corridors(0)
    assert not unchecked_steps(scenario.map).any()
    results = []
    for config in (DEFAULT, OFF):
        with Session.new(scenario.map, config=config) as session:
            human = SimulatedHuman(scenario, 0)
            for _ in range(3):
                drawn = human.next_correction(np.array(session.poses))
                assert drawn is not None
                session.apply(drawn)
            results.append(np.array(session.poses))
            assert not any(NOTE in n for h in session.active for n in h.notes)
    assert np.array_equal(results[0], results[1])
