"""A generated world with known walls: a rectangular corridor loop driven one or more times, a
simulated 2D lidar, noisy odometry and an injected heading fault, so that later passes see the
first pass's walls in the wrong place. Deterministic under a seed; used by tests and benchmarks.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.geometry import between, compose, principal_axes
from hitl_slam.map import Map

__all__ = ["WALLS", "World", "corridor_loop", "drawn_segment"]

FloatArray = NDArray[np.float64]

# Walls (x0, y0, x1, y1): an outer 20 x 10 m rectangle and an inner 16 x 6 m one, a 2 m corridor.
WALLS = np.array(
    [
        [0, 0, 20, 0],
        [20, 0, 20, 10],
        [20, 10, 0, 10],
        [0, 10, 0, 0],
        [2, 2, 18, 2],
        [18, 2, 18, 8],
        [18, 8, 2, 8],
        [2, 8, 2, 2],
    ],
    dtype=np.float64,
)
OUTER_BOTTOM, OUTER_RIGHT, OUTER_TOP, OUTER_LEFT = 0, 1, 2, 3
INNER_BOTTOM, INNER_RIGHT, INNER_TOP, INNER_LEFT = 4, 5, 6, 7


@dataclass
class World:
    map: Map
    truth: FloatArray  # (N, 3) true poses
    wall_of_point: NDArray[np.int64]  # (P,) which wall each point hit


def _path(step: float, laps: float) -> FloatArray:
    corners = np.array([[1.0, 1.0], [19.0, 1.0], [19.0, 9.0], [1.0, 9.0], [1.0, 1.0]])
    pts = []
    for a, b in itertools.pairwise(corners):
        n = round(float(np.linalg.norm(b - a)) / step)
        for k in range(n):
            pts.append(a + (b - a) * k / n)
    loop = np.array(pts)
    total = int(len(loop) * laps)
    xy = loop[np.arange(total) % len(loop)]
    nxt = loop[(np.arange(total) + 1) % len(loop)]
    theta = np.arctan2(nxt[:, 1] - xy[:, 1], nxt[:, 0] - xy[:, 0])
    return np.column_stack([xy, theta])


def _scan(
    pose: FloatArray, beams: int, max_range: float, rng: np.random.Generator, noise: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    angles = pose[2] + np.linspace(-math.pi, math.pi, beams, endpoint=False)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (B, 2)
    p0, p1 = WALLS[:, :2], WALLS[:, 2:]
    e = p1 - p0  # (W, 2)
    o = pose[:2]
    # Solve o + t d = p0 + u e for every beam/wall pair.
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    w = p0[None, :, :] - o[None, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / den
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / den
    valid = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    t = np.where(valid, t, np.inf)
    wall = np.argmin(t, axis=1)
    r = t[np.arange(beams), wall]
    keep = r < max_range
    r = r[keep] + rng.normal(0.0, noise, keep.sum())
    local = angles[keep] - pose[2]
    pts = np.stack([r * np.cos(local), r * np.sin(local)], axis=1)
    return pts, wall[keep]


def corridor_loop(
    *,
    seed: int = 0,
    step: float = 0.2,
    laps: float = 1.25,
    beams: int = 120,
    max_range: float = 6.0,
    range_noise: float = 0.01,
    odom_xy: float = 0.005,
    odom_theta: float = 0.002,
    fault_at: int | None = 150,
    fault: float = math.radians(4.0),
) -> World:
    """The corridor loop with a heading fault at pose ``fault_at`` (radians ``fault``)."""
    rng = np.random.default_rng(seed)
    truth = _path(step, laps)
    n = truth.shape[0]
    scans, walls = [], []
    for k in range(n):
        pts, wall = _scan(truth[k], beams, max_range, rng, range_noise)
        scans.append(pts)
        walls.append(wall)
    # Odometry: true increments plus noise and the fault, composed from the true start.
    est = np.empty_like(truth)
    est[0] = truth[0]
    for k in range(1, n):
        z = between(truth[k - 1], truth[k])
        z += rng.normal(0.0, [odom_xy, odom_xy, odom_theta])
        if fault_at is not None and k == fault_at:
            z[2] += fault
        est[k] = compose(est[k - 1], z)
    the_map = Map.from_poses_and_scans(est, scans, name="corridor-loop")
    return World(map=the_map, truth=truth, wall_of_point=np.concatenate(walls).astype(np.int64))


def drawn_segment(
    world: World,
    poses: FloatArray,
    wall: int,
    pose_range: tuple[int, int],
    rng: np.random.Generator,
    *,
    noise: float = 0.05,
    along: tuple[float, float] = (0.25, 0.75),
) -> list[list[float]]:
    """What a person would draw over ``wall`` as seen by poses in ``pose_range`` on the map
    as displayed (``poses``): the observed wall's extent, trimmed to ``along``, plus endpoint
    noise."""
    m = world.map
    owner = m.pose_of_point()
    sel = (world.wall_of_point == wall) & (owner >= pose_range[0]) & (owner < pose_range[1])
    pts = m.world_points(poses)[sel]
    if len(pts) < 10:
        raise ValueError(f"wall {wall} is barely seen by poses {pose_range}")
    centre, _, direction = principal_axes(pts)
    proj = (pts - centre) @ direction
    lo, hi = np.quantile(proj, along)
    ends = [centre + lo * direction, centre + hi * direction]
    return [list(map(float, e + rng.normal(0.0, noise, 2))) for e in ends]
