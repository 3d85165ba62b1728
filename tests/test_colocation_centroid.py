"""A colocation's centroids weigh every stretch of the wall alike (docs/ALGORITHM.md §I.15): two
passes over the same stretch of a wall, one of them piling its points at one end, must end on the
same stretch, not with the pile's end pulled to the middle."""

from __future__ import annotations

import numpy as np
import pytest

from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Interpretation, Mode
from hitl_slam.geometry import to_world
from hitl_slam.map import Map
from hitl_slam.pipeline import solve_all

WALL_Y = 2.0


def _world(seed: int, shift: float) -> tuple[Map, np.ndarray, np.ndarray, np.ndarray]:
    """A robot drives along a wall (y = 2, x in 0..4), turns away, and comes back along it. The
    first pass sees the stretch evenly; the second sees the same stretch but piles points on
    its first metre. The map's second pass is ``shift`` metres off along the wall (the odometry's
    error). Returns the map, the truth and the two passes' (pose, point) rows."""
    rng = np.random.default_rng(seed)
    out = [(x, 0.0, 0.0) for x in np.arange(0.0, 4.01, 0.25)]
    loop = [
        (4.5, -1.0, -np.pi / 2),
        (4.0, -2.5, np.pi),
        (0.0, -2.5, np.pi),
        (-0.5, -1.0, np.pi / 2),
    ]
    back = [(x, 0.0, 0.0) for x in np.arange(0.0, 4.01, 0.25)]
    truth = np.array(out + loop + back, dtype=np.float64)
    n1 = len(out)
    first_b = n1 + len(loop)
    scans, rows_a, rows_b = [], [], []
    for k, (x, y, th) in enumerate(truth):
        if k < n1:
            wx = np.linspace(0.0, 4.0, 81)
            wx = wx[np.abs(wx - x) < 1.5]
        elif k >= first_b:
            wx = np.concatenate([np.linspace(0.0, 1.0, 60), np.linspace(1.0, 4.0, 12)])
            wx = wx[np.abs(wx - x) < 2.5]
        else:
            wx = np.zeros(0)
        world = np.stack([wx, np.full(wx.shape, WALL_Y + rng.normal(0, 0.005, wx.shape))], 1)
        c, s = np.cos(th), np.sin(th)
        d = world - np.array([x, y])
        robot = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)
        scans.append(robot)
        target = rows_a if k < n1 else rows_b if k >= first_b else None
        if target is not None:
            target.extend((k, j) for j in range(robot.shape[0]))
    estimate = truth.copy()
    estimate[first_b:, 0] += shift
    m = Map.from_poses_and_scans(estimate, scans)
    return m, truth, np.array(rows_a, dtype=np.int64), np.array(rows_b, dtype=np.int64)


def _colocated(m: Map, rows_a: np.ndarray, rows_b: np.ndarray, even: bool) -> np.ndarray:
    h = Interpretation(
        mode=Mode.COLOCATION,
        line_a=((0.0, WALL_Y), (4.0, WALL_Y)),
        line_b=((0.0, WALL_Y), (4.0, WALL_Y)),
        s_a=rows_a,
        s_b=rows_b,
        x_a=np.unique(rows_a[:, 0]),
        x_b=np.unique(rows_b[:, 0]),
    )
    poses, _, _ = solve_all(m, [h], DEFAULT.replace(colocation_even_centroids=even))
    return poses


def _stretch(m: Map, poses: np.ndarray, rows: np.ndarray) -> tuple[float, float]:
    pts = to_world(poses, rows[:, 0], m.points[m.offsets[rows[:, 0]] + rows[:, 1]])
    return float(pts[:, 0].min()), float(pts[:, 0].max())


@pytest.mark.parametrize(("seed", "shift"), [(0, 0.6), (1, -0.4), (2, 0.0)])
def test_passes_over_one_stretch_end_on_it_whatever_their_density(seed: int, shift: float) -> None:
    m, truth, rows_a, rows_b = _world(seed, shift)
    even = _colocated(m, rows_a, rows_b, True)
    plain = _colocated(m, rows_a, rows_b, False)
    # Even centroids: the second pass's stretch lands on the first's (both saw x = 0..4).
    a_lo, a_hi = _stretch(m, even, rows_a)
    b_lo, b_hi = _stretch(m, even, rows_b)
    assert abs(b_lo - a_lo) < 0.1
    assert abs(b_hi - a_hi) < 0.1
    # Plain centroids: the pile on the second pass's first metre drags its stretch along the
    # wall by most of a metre, whatever the starting error.
    p_lo, _ = _stretch(m, plain, rows_b)
    q_lo, _ = _stretch(m, plain, rows_a)
    assert p_lo - q_lo > 0.5
    # And the map: the second pass's poses are back where they were driven.
    back = rows_b[:, 0].min()
    assert np.max(np.abs((even[back:, 0] - even[0, 0]) - (truth[back:, 0] - truth[0, 0]))) < 0.1
