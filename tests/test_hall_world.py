"""The hall world (issue 42): a large hall whose only long walls are its outer ones, seen far off
between booths, pillars and round stands; its layout drawn from a seed."""

from __future__ import annotations

import numpy as np
import pytest

from hitl_slam.errors import InputError
from hitl_slam.full_evaluation import FULL_MAPS, HALLS, damaged_scenario
from hitl_slam.sim import Scenario, hall
from hitl_slam.sim.hall_world import hall as hall_floorplan


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return hall(0)


def _distance_to_segments(p: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """Per point of ``p`` (N, 2), the distance to the nearest segment of ``seg`` (S, 4)."""
    a, b = seg[None, :, :2], seg[None, :, 2:]
    d = b - a
    t = np.clip(np.sum((p[:, None, :] - a) * d, axis=2) / np.sum(d * d, axis=2), 0.0, 1.0)
    near = a + t[..., None] * d
    return np.min(np.linalg.norm(p[:, None, :] - near, axis=2), axis=1)


def test_the_outer_walls_are_the_only_walls_and_are_seen_far_off(scenario: Scenario) -> None:
    world = scenario.floorplan
    assert world.wall_names == ("south", "east", "north", "west")
    assert len(world.clutter) > 100  # booths, pillars and stands
    labels = scenario.wall_of_point
    ranges = np.hypot(scenario.map.points[:, 0], scenario.map.points[:, 1])
    outer = labels >= 0
    # Most of what the lidar sees is clutter; some of the outer walls are seen beyond 20 m.
    assert 0.05 < outer.mean() < 0.5
    assert np.count_nonzero(outer & (ranges > 20.0)) > 1000
    # Every pose keeps clear of every surface: the tour runs in the aisles.
    surfaces = np.vstack([world.walls, world.clutter])
    assert _distance_to_segments(scenario.truth[::5, :2], surfaces).min() > 0.8


def test_the_layout_comes_from_its_seed_and_the_size_is_checked() -> None:
    a, b, c = hall_floorplan(0), hall_floorplan(0), hall_floorplan(1)
    assert np.array_equal(a.clutter, b.clutter)
    assert a.clutter.shape != c.clutter.shape or not np.allclose(a.clutter, c.clutter)
    small = hall_floorplan(3, 60.0, 30.0)
    assert np.allclose(small.walls[:, [0, 1]].min(axis=0), 0.0)
    assert small.walls[:, 2].max() == 60.0
    assert small.walls[:, 3].max() == 30.0
    with pytest.raises(InputError, match="60-120 m long"):
        hall_floorplan(0, 200.0, 50.0)


def test_the_full_evaluation_runs_the_hall_only_when_named() -> None:
    assert "hall" in HALLS
    assert "hall" not in FULL_MAPS
    damaged, _ = damaged_scenario("hall", "jump", 0.05, 1)
    assert damaged.name.startswith("hall")
    assert damaged.floorplan.name == "hall (layout 1)"
    assert len(damaged.faults) == 1
