"""A corridor driven in several laps, each lap's poses carrying its own error, so every wall shows
up once per lap ("copies"), and a careful simulated person who draws true statements on them:
segments fitted to the copy they mean, a systematic offset of 10-20 cm to either side, endpoint
noise, either direction. Shared by the interpretation and correction tests of issue 11."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Segment
from hitl_slam.map import Map

FloatArray = NDArray[np.float64]

WALL_A = ((0.0, 0.0), (14.0, 0.0))
WALL_B = ((0.0, 3.0), (14.0, 3.0))
WALL_FAR = ((40.0, 30.0), (52.0, 30.0))  # seen on the excursions between laps
PIVOT = np.array([7.0, 1.5])
SENSOR_RANGE = 4.0
SPACING = 0.05
NOISE = 0.015
CLUTTER = 10  # points per pose and visible wall, uniform in +-0.4 m around it


def apply_error(error: tuple[float, float, float], pts: FloatArray) -> FloatArray:
    """A lap's map error: rotation by error[2] about PIVOT, then the shift error[:2]."""
    dx, dy, dth = error
    c, s = math.cos(dth), math.sin(dth)
    q = pts - PIVOT
    rot = np.stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]], axis=1)
    return rot + PIVOT + np.array([dx, dy])


@dataclass
class CopiesWorld:
    map: Map
    laps: list[NDArray[np.int64]]  # pose indices of each lap's corridor pass
    errors: list[tuple[float, float, float]]
    parts: list[NDArray[np.int64]]  # each lap's poses with the excursion after it

    def copy_of(
        self, wall: tuple[tuple[float, float], tuple[float, float]], lap: int
    ) -> FloatArray:
        """(2, 2) the wall as lap `lap` shows it on the map."""
        return apply_error(self.errors[lap], np.array(wall, dtype=float))

    def lap_of(self, poses: NDArray[np.int64]) -> NDArray[np.int64]:
        out = np.full(len(poses), -1)
        for k, part in enumerate(self.parts):
            out[np.isin(poses, part)] = k
        return out


def _observe(pose: FloatArray, rng: np.random.Generator) -> FloatArray:
    pts = []
    for p0, p1 in (WALL_A, WALL_B, WALL_FAR):
        a, b = np.array(p0), np.array(p1)
        length = float(np.hypot(*(b - a)))
        d = (b - a) / length
        n = np.array([-d[1], d[0]])
        t = np.arange(0.0, length, SPACING) + rng.uniform(0.0, SPACING)
        q = a + t[:, None] * d
        seen = np.hypot(*(q - pose[:2]).T) < SENSOR_RANGE
        if not seen.any():
            continue
        pts.append(q[seen] + rng.normal(0.0, NOISE, (int(seen.sum()), 1)) * n)
        ts = t[seen]
        tc = rng.uniform(ts.min(), ts.max(), CLUTTER)
        pts.append(a + tc[:, None] * d + rng.uniform(-0.4, 0.4, CLUTTER)[:, None] * n)
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def copies_world(
    errors: list[tuple[float, float, float]], seed: int = 0, n: int | list[int] = 50
) -> CopiesWorld:
    """One corridor pass of `n` poses per lap (or `n[k]` on lap k: a lap driven faster is a
    sparser copy; alternating directions), then 20 poses out to
    WALL_FAR and back, in 2-3 m steps (odometry as weak as a long drive, not a teleport). Lap
    k's error applies from the far point before its pass to the far point after it, so each
    copy changes where no wall is seen."""
    rng = np.random.default_rng(seed)
    true_parts, est_parts, laps, parts = [], [], [], []
    count = 0
    far = np.array([46.0, 31.5])
    t_out, t_back = np.linspace(0.0, 1.0, 11)[1:], np.linspace(1.0, 0.0, 11)[1:]
    sizes = [n] * len(errors) if isinstance(n, int) else list(n)
    for k, err in enumerate(errors):
        size = sizes[k]
        xs = np.linspace(1.0, 13.0, size)
        heading = 0.0 if k % 2 == 0 else math.pi
        if k % 2:
            xs = xs[::-1]
        lap = np.stack([xs, np.full(size, 1.5), np.full(size, heading)], axis=1)
        pieces = []
        if k > 0:  # back from the far point to where this pass starts
            back = lap[0, :2] + t_back[:, None] * (far - lap[0, :2])
            pieces.append(np.concatenate([back, np.full((10, 1), heading)], axis=1))
        first = count + sum(len(p) for p in pieces)
        pieces.append(lap)
        if k < len(errors) - 1:  # out to the far point
            out = lap[-1, :2] + t_out[:, None] * (far - lap[-1, :2])
            pieces.append(np.concatenate([out, np.full((10, 1), heading)], axis=1))
        part = np.concatenate(pieces)
        est = part.copy()
        est[:, :2] = apply_error(err, part[:, :2])
        est[:, 2] += err[2]
        true_parts.append(part)
        est_parts.append(est)
        laps.append(np.arange(first, first + size))
        parts.append(np.arange(count, count + len(part)))
        count += len(part)
    true = np.concatenate(true_parts)
    scans = []
    for pose in true:
        world = _observe(pose, rng)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        q = world - pose[:2]
        scans.append(np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1]], axis=1))
    m = Map.from_poses_and_scans(np.concatenate(est_parts), scans)
    return CopiesWorld(m, laps, list(errors), parts)


def _line_distance(copy: FloatArray, p: FloatArray) -> float:
    p0, p1 = copy
    d = (p1 - p0) / float(np.hypot(*(p1 - p0)))
    return abs(float((p - p0) @ np.array([-d[1], d[0]])))


def careful_drawing(
    copy: FloatArray,
    rng: np.random.Generator,
    *,
    offset: tuple[float, float] = (0.10, 0.20),
    endpoint_noise: float = 0.05,
    span: tuple[float, float] = (0.2, 0.75),
    others: tuple[FloatArray, ...] = (),
) -> Segment:
    """A segment on `copy` ((2, 2) wall ends): a part of it, shifted sideways by a random
    offset in `offset` to a random side, each end moved by `endpoint_noise` in a random
    direction, drawn in a random direction. Careful: each end lies nearer `copy` than any of
    `others` (other copies on screen), at most 0.6 times as far; drawings that are not are
    drawn again."""
    for _ in range(1000):
        p0, p1 = copy
        t0 = rng.uniform(span[0], span[0] + 0.1)
        t1 = rng.uniform(span[1] - 0.1, span[1])
        a, b = p0 + t0 * (p1 - p0), p0 + t1 * (p1 - p0)
        d = (b - a) / float(np.hypot(*(b - a)))
        normal = np.array([-d[1], d[0]])
        shift = rng.uniform(*offset) * rng.choice([-1.0, 1.0])
        ends = np.stack([a, b]) + shift * normal
        ang = rng.uniform(0.0, 2.0 * math.pi, 2)
        ends += endpoint_noise * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        if all(_line_distance(copy, e) <= 0.6 * _line_distance(o, e) for e in ends for o in others):
            break
    else:
        raise ValueError("no careful drawing found; the copies are too close for this offset")
    if rng.random() < 0.5:
        ends = ends[::-1]
    return ((float(ends[0, 0]), float(ends[0, 1])), (float(ends[1, 0]), float(ends[1, 1])))
