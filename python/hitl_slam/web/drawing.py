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
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Interpretation
from hitl_slam.errors import InputError
from hitl_slam.geometry import to_world
from hitl_slam.map import Map

__all__ = ["MapDrawing", "line_segment"]

Bounds = tuple[float, float, float, float]
_CHUNK = 16  # scans placed at a time while looking for the map's extremes


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
        # For the bounds: each scan's reach from its pose, and one of its points.
        counts = np.diff(map.offsets)
        self._has_points = counts > 0
        reach = np.hypot(map.points[:, 0], map.points[:, 1])
        self._reach = np.zeros(map.num_poses)
        if map.num_points:
            starts = map.offsets[:-1][self._has_points]
            self._reach[self._has_points] = np.maximum.reduceat(reach, starts)
        self._first = np.minimum(map.offsets[:-1], max(map.num_points - 1, 0))

    def poses_f32(self, poses: NDArray[np.float64]) -> bytes:
        """(N, 3) float32 LE."""
        return poses.astype("<f4").tobytes()

    def world_points(self, poses: NDArray[np.float64]) -> bytes:
        """(P, 2) world points under ``poses``, float32 LE (the earlier API's array)."""
        return to_world(poses, self._owner, self._map.points).astype("<f4").tobytes()

    def bounds(self, poses: NDArray[np.float64]) -> Bounds:
        """(x min, y min, x max, y max) of every pose and world point under ``poses``, exactly,
        without placing every point: a scan can hold an extreme only if its pose, less the
        scan's reach, passes the extreme found so far; scans are placed in that order, a chunk
        at a time, until none can."""
        out = []
        scans = np.flatnonzero(self._has_points)
        first = to_world(poses, scans, self._map.points[self._first[scans]])
        for axis, sign in ((0, 1.0), (1, 1.0), (0, -1.0), (1, -1.0)):  # min x, min y, max x, max y
            best = float((sign * poses[:, axis]).min())
            if scans.size:
                # An actual point of each scan: the extreme is at most the least of them.
                best = min(best, float((sign * first[:, axis]).min()))
                lower = sign * poses[scans, axis] - self._reach[scans]
                order = scans[np.argsort(lower, kind="stable")]
                lower = np.sort(lower, kind="stable")
                for start in range(0, order.size, _CHUNK):
                    if lower[start] > best:
                        break
                    chunk = order[start : start + _CHUNK][lower[start : start + _CHUNK] <= best]
                    rows = self._rows(chunk)
                    world = to_world(poses, self._owner[rows], self._map.points[rows])
                    best = min(best, float((sign * world[:, axis]).min()))
            out.append(sign * best)
        return (out[0], out[1], out[2], out[3])

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
        out = []
        for k, (index, h) in enumerate(active):
            sides = {}
            for side, rows, row in (("a", h.s_a, 2 * k), ("b", h.s_b, 2 * k + 1)):
                phi, rho = float(lines[row, 0]), float(lines[row, 1])
                world = self._map.observed_points(rows, poses)
                sides[side] = {"phi": phi, "rho": rho, "segment": line_segment(phi, rho, world)}
            out.append({"index": index, "mode": h.mode.value, **sides})
        return out
