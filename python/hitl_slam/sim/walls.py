"""Straight walls found in a point cloud (sequential RANSAC with gap splitting), for real logs
whose ground truth is a corrected trajectory rather than a floor plan: the walls and the label of
every point stand in for the generated worlds' known walls when scoring and simulating a person.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hitl_slam.geometry import principal_axes

__all__ = ["extract_walls"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _split_runs(proj: FloatArray, gap: float) -> list[NDArray[np.intp]]:
    order = np.argsort(proj)
    breaks = np.flatnonzero(np.diff(proj[order]) > gap)
    return list(np.split(order, breaks + 1))


def extract_walls(
    points: FloatArray,
    *,
    tolerance: float = 0.03,
    min_points: int = 200,
    min_length: float = 1.0,
    max_gap: float = 0.3,
    max_walls: int = 80,
    sample: int = 60_000,
    trials: int = 400,
    seed: int = 0,
) -> tuple[FloatArray, IntArray]:
    """Walls ``(W, 4)`` as ``x0, y0, x1, y1`` and each point's wall index ``(P,)`` (-1: none).

    Sequential RANSAC on a deterministic subsample: the line with most points within
    ``tolerance`` is split where its points leave gaps over ``max_gap``; every run at least
    ``min_length`` long with ``min_points`` points (on the subsample, scaled) becomes a wall;
    its points are removed and the search repeats. All points are then labelled with the
    nearest wall within ``tolerance`` whose extent covers them.
    """
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) > sample:
        pts = pts[rng.choice(len(pts), size=sample, replace=False)]
    scale = len(pts) / max(len(points), 1)
    need = max(int(min_points * scale), 10)
    alive = np.ones(len(pts), dtype=bool)
    walls: list[tuple[float, float, float, float]] = []
    misses = 0
    while len(walls) < max_walls and alive.sum() > need and misses < 20:
        cand = np.flatnonzero(alive)
        p = pts[cand]
        i = rng.integers(len(p), size=trials)
        j = rng.integers(len(p), size=trials)
        d = p[j] - p[i]
        length = np.hypot(d[:, 0], d[:, 1])
        ok = length > 0.2
        if not np.any(ok):
            break
        i, d, length = i[ok], d[ok], length[ok]
        normals = np.stack([-d[:, 1], d[:, 0]], axis=1) / length[:, None]
        # Inlier counts of every hypothesis on a chunk, then refine the best on all points.
        probe = p[rng.integers(len(p), size=min(len(p), 4000))]
        dist = np.abs(np.einsum("tk,tqk->tq", normals, probe[None, :, :] - p[i][:, None, :]))
        best = int(np.argmax((dist < tolerance).sum(axis=1)))
        normal, origin = normals[best], p[i[best]]
        inl = np.abs((p - origin) @ normal) < tolerance
        if inl.sum() < need:
            misses += 1
            continue
        # Refit with total least squares, then recompute the inliers.
        q = p[inl]
        centre, normal, direction = principal_axes(q)
        inl = np.abs((p - centre) @ normal) < tolerance
        proj = (p[inl] - centre) @ direction
        found = False
        for run in _split_runs(proj, max_gap):
            lo, hi = proj[run].min(), proj[run].max()
            if len(run) >= need and hi - lo >= min_length:
                a, b = centre + lo * direction, centre + hi * direction
                walls.append((float(a[0]), float(a[1]), float(b[0]), float(b[1])))
                found = True
        alive[cand[np.flatnonzero(inl)]] = False
        misses = 0 if found else misses + 1
    wall_array = np.array(walls, dtype=np.float64).reshape(-1, 4)
    return wall_array, label_points(points, wall_array, tolerance=tolerance)


def label_points(points: FloatArray, walls: FloatArray, *, tolerance: float = 0.03) -> IntArray:
    """Index of the nearest wall segment within ``tolerance`` of each point, or -1."""
    pts = np.asarray(points, dtype=np.float64)
    labels = np.full(len(pts), -1, dtype=np.int64)
    best = np.full(len(pts), math.inf)
    for w, (x0, y0, x1, y1) in enumerate(walls):
        a = np.array([x0, y0])
        d = np.array([x1 - x0, y1 - y0])
        length2 = float(d @ d)
        t = np.clip(((pts - a) @ d) / length2, 0.0, 1.0)
        dist = np.hypot(*(pts - (a + t[:, None] * d)).T)
        better = (dist < tolerance) & (dist < best)
        labels[better] = w
        best[better] = dist[better]
    return labels
