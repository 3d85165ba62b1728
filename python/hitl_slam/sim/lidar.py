"""A simulated 2D lidar over wall segments: field of view, angular resolution, maximum range,
Gaussian range noise and random dropouts, every beam against every nearby wall at once (numpy).
Each point carries the index of the wall it hit: the ground-truth label used for scoring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError

__all__ = ["Lidar", "Scans", "cast_rays"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# Beam x wall pairs evaluated at once; poses are processed in chunks that stay under this.
_PAIR_BUDGET = 2_000_000


def cast_rays(
    segments: FloatArray, origins: FloatArray, angles: FloatArray
) -> tuple[FloatArray, IntArray]:
    """Exact ranges from ``origins`` (K, 2) along world-frame beam ``angles`` (K, B) to the
    nearest of ``segments`` (S, 4) rows ``(x0, y0, x1, y1)``.

    Returns ``(ranges, hit)``, both (K, B): the distance to the first segment crossed (``inf``
    when none is) and that segment's row (-1 when none is). Only segments that can be reached
    are tested per chunk of origins, so a large world costs little more than a small one.
    """
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 2)
    angles = np.asarray(angles, dtype=np.float64)
    k, b = angles.shape
    ranges = np.full((k, b), np.inf)
    hit = np.full((k, b), -1, dtype=np.int64)
    if k == 0 or segments.shape[0] == 0:
        return ranges, hit
    chunk = max(1, _PAIR_BUDGET // max(1, b * segments.shape[0]))
    for lo in range(0, k, chunk):
        hi = min(k, lo + chunk)
        r, h = _cast_chunk(segments, origins[lo:hi], angles[lo:hi])
        ranges[lo:hi], hit[lo:hi] = r, h
    return ranges, hit


def _cast_chunk(
    segments: FloatArray, origins: FloatArray, angles: FloatArray
) -> tuple[FloatArray, IntArray]:
    p0, e = segments[:, :2], segments[:, 2:] - segments[:, :2]  # (S, 2)
    dx, dy = np.cos(angles)[..., None], np.sin(angles)[..., None]  # (K, B, 1)
    # Solve o + t d = p0 + u e for every (origin, beam, segment).
    wx = (p0[None, :, 0] - origins[:, None, 0])[:, None, :]  # (K, 1, S)
    wy = (p0[None, :, 1] - origins[:, None, 1])[:, None, :]
    den = dx * e[:, 1] - dy * e[:, 0]  # (K, B, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * e[:, 1] - wy * e[:, 0]) / den
        u = (wx * dy - wy * dx) / den
    valid = (np.abs(den) > 1e-12) & (t > 0.0) & (u >= 0.0) & (u <= 1.0)
    t = np.where(valid, t, np.inf)
    nearest = np.argmin(t, axis=2)
    r = np.take_along_axis(t, nearest[..., None], axis=2)[..., 0]
    return r, np.where(np.isfinite(r), nearest, -1).astype(np.int64)


@dataclass(frozen=True)
class Scans:
    """Every pose's scan, flattened: pose i's points are ``points[offsets[i]:offsets[i + 1]]``.

    Attributes:
        points: (P, 2) robot-frame points [m].
        offsets: (N + 1,) int64.
        wall: (P,) int64 index of the wall each point lies on (-1: clutter).
        beam: (P,) int64 index of the beam that produced each point.
    """

    points: FloatArray
    offsets: IntArray
    wall: IntArray
    beam: IntArray

    @property
    def num_poses(self) -> int:
        return int(self.offsets.shape[0] - 1)

    def per_pose(self) -> list[FloatArray]:
        """The points as one (K_i, 2) array per pose (views), as ``Map.from_poses_and_scans``
        takes them."""
        return [self.points[a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:], strict=True)]


@dataclass(frozen=True)
class Lidar:
    """A planar laser scanner. Units in brackets.

    Attributes:
        fov: total field of view, centred on the heading [rad]; 2 pi is a full circle.
        resolution: angle between neighbouring beams [rad].
        max_range: beams whose true range is this or more return nothing [m].
        min_range: beams whose true range is under this return nothing [m].
        range_noise: standard deviation of the Gaussian range noise [m].
        dropout: probability that a beam returns nothing at all [1].
    """

    fov: float = math.radians(270.0)
    resolution: float = math.radians(1.0)
    max_range: float = 10.0
    min_range: float = 0.05
    range_noise: float = 0.01
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 < self.fov <= 2.0 * math.pi:
            raise InputError(f"lidar fov must be in (0, 2 pi] radians, got {self.fov!r}")
        if not 0.0 < self.resolution <= self.fov:
            raise InputError(f"lidar resolution must be in (0, fov] radians, got {self.resolution}")
        if not (math.isfinite(self.max_range) and self.max_range > self.min_range >= 0.0):
            raise InputError("lidar ranges must satisfy 0 <= min_range < max_range < inf")
        if not (math.isfinite(self.range_noise) and self.range_noise >= 0.0):
            raise InputError(f"lidar range_noise must be >= 0 m, got {self.range_noise!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise InputError(f"lidar dropout must be a probability in [0, 1), got {self.dropout}")

    @property
    def num_beams(self) -> int:
        if self.fov >= 2.0 * math.pi - 1e-12:
            return max(1, round(2.0 * math.pi / self.resolution))
        return math.floor(self.fov / self.resolution + 1e-9) + 1

    def beam_angles(self) -> FloatArray:
        """(B,) beam directions in the robot frame [rad], symmetric about the heading."""
        n = self.num_beams
        if self.fov >= 2.0 * math.pi - 1e-12:
            return np.linspace(-math.pi, math.pi, n, endpoint=False)
        half = 0.5 * (n - 1) * self.resolution
        return np.linspace(-half, half, n)

    def scan(
        self,
        walls: FloatArray,
        poses: FloatArray,
        rng: np.random.Generator,
        *,
        clutter: FloatArray | None = None,
    ) -> Scans:
        """Scan ``walls`` (W, 4) and ``clutter`` segments (C, 4) from every pose (N, 3).

        Points on wall k are labelled k, points on clutter -1. The random draws (noise and
        dropouts for every pose and beam) are made up front, so the result depends only on
        the inputs and the generator's state.
        """
        walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        extra = np.zeros((0, 4)) if clutter is None else np.asarray(clutter, dtype=np.float64)
        segments = np.concatenate([walls, extra.reshape(-1, 4)])
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        n, local = poses.shape[0], self.beam_angles()
        noise = rng.normal(0.0, 1.0, (n, local.size)) * self.range_noise
        dropped = rng.random((n, local.size)) < self.dropout
        ranges = np.full((n, local.size), np.inf)
        hit = np.full((n, local.size), -1, dtype=np.int64)
        # Chunks of consecutive poses are close together: test only the segments in reach.
        chunk = max(1, _PAIR_BUDGET // (local.size * 16))
        for lo in range(0, n, chunk):
            hi = min(n, lo + chunk)
            near = self._reachable(segments, poses[lo:hi, :2])
            if near.size == 0:
                continue
            r, h = cast_rays(segments[near], poses[lo:hi, :2], poses[lo:hi, 2:3] + local)
            ranges[lo:hi] = r
            hit[lo:hi] = np.where(h >= 0, near[np.maximum(h, 0)], -1)
        keep = (ranges >= self.min_range) & (ranges < self.max_range) & ~dropped
        r = ranges + noise
        keep &= r > 0.0
        counts = keep.sum(axis=1)
        pose_idx, beam_idx = np.nonzero(keep)
        rr, aa = r[pose_idx, beam_idx], local[beam_idx]
        points = np.stack([rr * np.cos(aa), rr * np.sin(aa)], axis=1)
        label = hit[pose_idx, beam_idx]
        label = np.where(label < walls.shape[0], label, -1).astype(np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return Scans(
            points=np.ascontiguousarray(points),
            offsets=offsets,
            wall=label,
            beam=beam_idx.astype(np.int64),
        )

    def _reachable(self, segments: FloatArray, xy: FloatArray) -> IntArray:
        """Rows of ``segments`` whose bounding box comes within max_range of the box of ``xy``."""
        lo, hi = xy.min(axis=0) - self.max_range, xy.max(axis=0) + self.max_range
        s_lo = np.minimum(segments[:, :2], segments[:, 2:])
        s_hi = np.maximum(segments[:, :2], segments[:, 2:])
        inside = np.all((s_hi >= lo) & (s_lo <= hi), axis=1)
        return np.flatnonzero(inside).astype(np.int64)
