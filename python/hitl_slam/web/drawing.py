"""What the page draws, as the server hands it over: each scan's points once, in the robot frame
(float32, with the per-pose offsets), and after every change only the poses (float32), the map's
bounds and the solved lines of the corrections in effect as segments. The page places the
points itself (js/view.js, js/splat.js), so a correction costs kilobytes, not a re-sent cloud.

The world-frame points of the earlier API (``GET /api/map/points``) are still available, built
on demand (:meth:`MapDrawing.world_points`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Interpretation
from hitl_slam.errors import InputError
from hitl_slam.geometry import to_world
from hitl_slam.map import Map

__all__ = ["MapDrawing", "line_segment"]

Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class _Hull:
    """The convex hull vertices of every scan with points, scan by scan (robot frame)."""

    scans: NDArray[np.int64]  # (S,) the poses whose scans have points
    starts: NDArray[np.int64]  # (S,) where each scan's vertices start in owner / points
    owner: NDArray[np.int64]  # (H,) each vertex's pose
    points: NDArray[np.float64]  # (H, 2) the vertices
    reach: float  # [m] the farthest point from its robot, of any scan


def line_segment(phi: float, rho: float, points: NDArray[np.float64]) -> list[list[float]]:
    """The stretch of the line ``x cos(phi) + y sin(phi) = rho`` that ``points`` (K, 2, world)
    cover: their projections' extent along it (the line's foot point when K = 0)."""
    normal = np.array([math.cos(phi), math.sin(phi)])
    along = np.array([-normal[1], normal[0]])
    foot = rho * normal
    if points.shape[0] == 0:
        lo = hi = 0.0
    else:
        t = points @ along
        lo, hi = float(t.min()), float(t.max())
    p0, p1 = foot + lo * along, foot + hi * along
    return [[float(p0[0]), float(p0[1])], [float(p1[0]), float(p1[1])]]


class MapDrawing:
    """The drawable arrays of one map (its scans never change; only poses do)."""

    def __init__(self, map: Map) -> None:
        if map.num_points >= 2**31:
            raise InputError("the map has over 2^31 points; the web UI cannot index them")
        self._map = map
        self._owner = map.pose_of_point()
        self.scans_f32 = map.points.astype("<f4").tobytes()
        """(P, 2) robot-frame points, float32 LE, pose by pose."""
        self.offsets_i32 = map.offsets.astype("<i4").tobytes()
        """(N + 1,) int32 LE: pose i's points are points[offsets[i]:offsets[i + 1]]."""
        self._hull: _Hull | None = None  # built on the first call of bounds()

    def poses_f32(self, poses: NDArray[np.float64]) -> bytes:
        """(N, 3) float32 LE."""
        return poses.astype("<f4").tobytes()

    def world_points(self, poses: NDArray[np.float64]) -> bytes:
        """(P, 2) world points under ``poses``, float32 LE (the earlier API's array)."""
        return to_world(poses, self._owner, self._map.points).astype("<f4").tobytes()

    def bounds(self, poses: NDArray[np.float64]) -> Bounds:
        """(x min, y min, x max, y max) of every pose and world point under ``poses``, exactly
        (the very values :meth:`Map.world_points` gives), without placing every point.

        The extreme of a scan in any direction is at a vertex of its convex hull, whatever its
        pose: the hull vertices (a few percent of the points, found once) are placed, and only
        the scans whose hull comes within rounding of the extreme found are then placed whole,
        so the result is bit for bit the extreme of every point (one scan, as a rule)."""
        hull = self._hull_of_scans()
        world = to_world(poses, hull.owner, hull.points)
        # Rounding apart, a point lies within the hull of its scan: a scan whose hull misses
        # the extreme by more than a margin far above the rounding (and qhull's tolerance)
        # holds no point beyond it.
        scale = float(np.abs(poses[:, :2]).max(initial=0.0)) + hull.reach
        margin = 1e-6 + 1e-9 * scale
        out = []
        for axis, sign in ((0, 1.0), (1, 1.0), (0, -1.0), (1, -1.0)):  # min x, min y, max x, max y
            best = float((sign * poses[:, axis]).min())
            if hull.scans.size:
                per_scan = np.minimum.reduceat(sign * world[:, axis], hull.starts)
                best = min(best, float(per_scan.min()))
                near = hull.scans[per_scan <= best + margin]
                if near.size:
                    rows = self._rows(near)
                    placed = to_world(poses, self._owner[rows], self._map.points[rows])
                    best = min(best, float((sign * placed[:, axis]).min()))
            out.append(sign * best)
        return (out[0], out[1], out[2], out[3])

    def _hull_of_scans(self) -> _Hull:
        """Each scan's convex hull vertices (robot frame), found once: every point of a scan of
        fewer than three points or of a degenerate one (qhull refuses a line)."""
        if self._hull is not None:
            return self._hull
        from scipy.spatial import ConvexHull, QhullError

        offsets, points = self._map.offsets, self._map.points
        chosen: list[NDArray[np.int64]] = []
        scans: list[int] = []
        for pose in range(self._map.num_poses):
            lo, hi = int(offsets[pose]), int(offsets[pose + 1])
            if hi == lo:
                continue
            rows = np.arange(lo, hi, dtype=np.int64)
            if hi - lo >= 3:
                try:
                    hull = ConvexHull(points[lo:hi])
                except QhullError:
                    pass
                else:
                    # Vertices and the points qhull found within its tolerance of the hull.
                    keep = np.union1d(hull.vertices, hull.coplanar[:, 0])
                    rows = lo + keep.astype(np.int64)
            chosen.append(rows)
            scans.append(pose)
        rows = np.concatenate(chosen) if chosen else np.empty(0, dtype=np.int64)
        counts = np.array([r.size for r in chosen], dtype=np.int64)
        reach = float(np.hypot(points[:, 0], points[:, 1]).max(initial=0.0))
        self._hull = _Hull(
            scans=np.array(scans, dtype=np.int64),
            starts=np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64),
            owner=self._owner[rows],
            points=points[rows],
            reach=reach,
        )
        return self._hull

    def _rows(self, scans: NDArray[np.int64]) -> NDArray[np.int64]:
        """The point rows of ``scans``, in order."""
        starts = self._map.offsets[scans]
        counts = self._map.offsets[scans + 1] - starts
        shift = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
        rows: NDArray[np.int64] = np.arange(int(counts.sum()), dtype=np.int64) + shift
        return rows

    def line_segments(
        self,
        poses: NDArray[np.float64],
        active: Sequence[tuple[int, Interpretation]],
        lines: NDArray[np.float64],
    ) -> list[dict[str, Any]]:
        """For each correction in effect (history index, interpretation), in order, its solved
        lines a and b (rows 2k and 2k + 1 of ``lines``) as ``{index, mode, a, b}``: each
        ``{phi, rho, segment}``, the segment the stretch S_a (S_b) covers on its line."""
        sets = [rows for _, h in active for rows in (h.s_a, h.s_b)]
        if not sets:
            return []
        # Every S_a and S_b placed at once (the same values as one by one, point by point).
        world = self._map.observed_points(np.concatenate(sets), poses)
        ends = np.cumsum([rows.shape[0] for rows in sets])
        placed = np.split(world, ends[:-1])
        out = []
        for k, (index, h) in enumerate(active):
            sides = {}
            for side, row in (("a", 2 * k), ("b", 2 * k + 1)):
                phi, rho = float(lines[row, 0]), float(lines[row, 1])
                segment = line_segment(phi, rho, placed[row])
                sides[side] = {"phi": phi, "rho": rho, "segment": segment}
            out.append({"index": index, "mode": h.mode.value, **sides})
        return out
