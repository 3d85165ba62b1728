"""The odometry checked against the scans (hitl_slam.odometry_check): a heading fault is found
at the step where it happened and nowhere else, across seeds, sizes and signs; slow drift is not
mistaken for a fault; the faulty step is re-measured from the scans; and a correction across the
fault puts the turn there."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hitl_slam.config import DEFAULT
from hitl_slam.odometry_check import check_odometry, checked_map
from hitl_slam.sim import HeadingDrift, HeadingJump, parallel_corridors
from hitl_slam.sim.fault_models import damaged
from hitl_slam.sim.odometry import relative_motions
from hitl_slam.workspace import Workspace
from reference import wrap


@pytest.mark.parametrize(
    ("seed", "degrees", "at"), [(1, 20.0, 0.35), (2, -12.0, 0.5), (3, 30.0, 0.6)]
)
def test_a_heading_jump_is_found_at_its_step_and_only_there(
    seed: int, degrees: float, at: float
) -> None:
    base = parallel_corridors(seed, heading_jump_deg=0.0)
    n = base.map.num_poses
    pose = int(at * n)
    scenario = damaged(base, [HeadingJump(pose, math.radians(degrees))], seed + 10)
    check = check_odometry(scenario.map)
    assert check.matched.mean() > 0.8
    steps = scenario.map.edges[check.relaxed, 0].tolist()
    assert steps == [pose - 1]
    # The step's turn is now the scans': within a degree and a half of the true turn (it was off
    # by the whole jump), with the scan match's variance; its translation stays the odometry's.
    row = int(check.relaxed[0])
    true_turn = float(relative_motions(base.truth)[pose - 1, 2])
    off = math.degrees(math.remainder(float(check.measurements[row, 2]) - true_turn, 2 * math.pi))
    assert abs(off) < 1.5
    was = math.degrees(
        math.remainder(float(scenario.map.measurements[row, 2]) - true_turn, 2 * math.pi)
    )
    assert abs(was - degrees) < 1.5
    sigma = math.degrees(math.sqrt(np.linalg.inv(check.information[row])[2, 2]))
    assert 0.5 <= sigma < 5.0
    assert np.array_equal(check.measurements[row, :2], scenario.map.measurements[row, :2])
    others = np.delete(np.arange(scenario.map.edges.shape[0]), row)
    assert np.array_equal(check.measurements[others], scenario.map.measurements[others])


def test_slow_drift_widens_nothing_and_the_check_can_be_turned_off() -> None:
    base = parallel_corridors(4, heading_jump_deg=0.0)
    n = base.map.num_poses
    scenario = damaged(base, [HeadingDrift(0, n, math.radians(0.3))], 7)
    assert check_odometry(scenario.map).relaxed.size == 0
    jumped = damaged(base, [HeadingJump(n // 2, math.radians(25.0))], 7)
    off = dataclasses.replace(DEFAULT, odometry_check=0.0)
    assert checked_map(jumped.map, off) is jumped.map
    checked = checked_map(jumped.map)
    assert checked is not jumped.map
    held = Workspace(jumped.map)  # what a session keeps: the check, made once
    assert held.checked(jumped.map)[0] is held.checked(jumped.map)[0]
    assert np.array_equal(held.checked(jumped.map)[0].information, checked.information)
    assert np.array_equal(checked.poses, jumped.map.poses)
    assert not np.array_equal(checked.information, jumped.map.information)
    assert not np.array_equal(checked.measurements, jumped.map.measurements)


@pytest.mark.parametrize("seed", [5, 6])
def test_a_correction_across_the_jump_turns_the_map_at_the_jump(seed: int) -> None:
    from hitl_slam.sim import SimulatedHuman, repair

    base = parallel_corridors(seed, heading_jump_deg=0.0)
    n = base.map.num_poses
    pose = n // 2
    scenario = damaged(base, [HeadingJump(pose, math.radians(20.0))], seed)
    result = repair(scenario, SimulatedHuman(scenario, seed), max_corrections=2)
    assert result.used >= 1
    est = relative_motions(result.poses)[:, 2]
    odo = relative_motions(scenario.map.poses)[:, 2]
    change = np.degrees(wrap(est - odo))
    # The jump's 20 degrees are taken out at the step where they came in ...
    assert abs(change[pose - 1] + 20.0) < 2.0
    # ... and no other step is turned by more than a degree for it.
    assert np.max(np.abs(np.delete(change, pose - 1))) < 1.0
