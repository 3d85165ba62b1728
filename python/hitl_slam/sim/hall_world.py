"""A large hall (an exhibition floor, a warehouse): four outer walls far apart, and inside rows of
booths or shelves along aisles, pillars and round stands (issue 42).

Long straight walls are few and far: the four outer walls are the only ones, seen from 20-40 m
across the aisles in the gaps between booths. The booths (jagged outlines: counters, furniture,
displays), the pillars and the round stands are clutter, seen by the lidar and labelled -1. The
layout (which booths stand where, how wide, where the gaps, pillars and stands are) comes from
``layout_seed``; the scoring pairs are the outer walls', as a room's
(:func:`hitl_slam.sim.worlds.single_room`: parallel, perpendicular, the hall's length and width).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.sim.worlds import CORRIDOR_TOUR, Floorplan, single_room

__all__ = ["hall"]

FloatArray = NDArray[np.float64]

AISLE = 3.0
"""[m] Width kept free along each aisle's centre line (booths stand beside it)."""
END_AISLE = 6.0
"""[m] Distance of the cross aisles at both ends from the end walls."""


def _box(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0, x1, y0], [x1, y0, x1, y1], [x1, y1, x0, y1], [x0, y1, x0, y0]]


def _jagged_box(
    x0: float, y0: float, x1: float, y1: float, rng: np.random.Generator
) -> list[list[float]]:
    """A booth's outline: its box with every side broken into 0.4-1.0 m pieces, each corner
    between pieces set off the side by up to 0.2 m (counters, furniture, displays): no long
    straight surface."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    points: list[tuple[float, float]] = []
    for k in range(4):
        (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 4]
        side = math.hypot(bx - ax, by - ay)
        nx, ny = (by - ay) / side, -(bx - ax) / side
        t = 0.0
        while t < side:
            off = 0.0 if t == 0.0 else float(rng.uniform(-0.2, 0.2))
            f = t / side
            points.append((ax + f * (bx - ax) + off * nx, ay + f * (by - ay) + off * ny))
            t += float(rng.uniform(0.4, 1.0))
    return [[*points[k], *points[(k + 1) % len(points)]] for k in range(len(points))]


def _polygon(cx: float, cy: float, r: float, sides: int) -> list[list[float]]:
    a = np.linspace(0.0, 2.0 * math.pi, sides + 1)
    x, y = cx + r * np.cos(a), cy + r * np.sin(a)
    return [[x[k], y[k], x[k + 1], y[k + 1]] for k in range(sides)]


def hall(layout_seed: int = 0, length: float = 100.0, width: float = 50.0) -> Floorplan:
    """A hall ``length`` x ``width`` [m] (60-120 m long) with horizontal aisles about 12 m apart,
    cross aisles near both ends and in the middle, and between the aisles two rows of booths
    (3-6 m along the aisle, 2-3 m deep, 1-3 m gaps, about one slot in five empty or holding a
    round stand), pillars on a 12 m grid between the rows' backs. ``paths["tour"]`` drives every
    aisle in a serpentine, back along the west cross aisle, and the first aisle again (so the
    start is seen twice)."""
    if not (60.0 <= length <= 120.0 and 30.0 <= width <= length):
        raise InputError(
            f"a hall is 60-120 m long and 30 m to its length wide, got {length} x {width}"
        )
    rng = np.random.default_rng(layout_seed)
    n_aisles = max(2, round(width / 12.0))
    aisles = [width * (k + 0.5) / n_aisles for k in range(n_aisles)]
    band = width / n_aisles  # between aisle centres
    depth_room = 0.5 * (band - AISLE)  # per row, from the aisle's edge to the band's middle
    middle = 0.5 * length
    clutter: list[list[float]] = []
    for y in aisles:
        for side in (-1.0, 1.0):
            edge = y + side * 0.5 * AISLE  # the booths' front, on the aisle
            x = END_AISLE + 0.5 * AISLE + float(rng.uniform(0.0, 2.0))
            while True:
                w = float(rng.uniform(3.0, 6.0))
                if x + w > length - END_AISLE - 0.5 * AISLE:
                    break
                if x < middle + 0.5 * AISLE + 1.0 and x + w > middle - 0.5 * AISLE - 1.0:
                    x = middle + 0.5 * AISLE + 1.0
                    continue
                d = min(float(rng.uniform(2.0, 3.0)), depth_room - 0.3)
                back = edge + side * d
                y0, y1 = sorted((edge, back))
                if y0 < 0.5 or y1 > width - 0.5:
                    break
                slot = float(rng.uniform())
                if slot < 0.08:
                    r = min(0.5 * w, d) * 0.45
                    clutter += _polygon(x + 0.5 * w, 0.5 * (y0 + y1), r, 12)
                elif slot >= 0.2:
                    clutter += _jagged_box(x, y0, x + w, y1, rng)
                x += w + float(rng.uniform(1.0, 3.0))
    # Pillars on a 12 m grid, on the bands' middle lines (between the booth rows' backs).
    for k in range(n_aisles - 1):
        yb = 0.5 * (aisles[k] + aisles[k + 1])
        for xp in np.arange(12.0, length - 6.0, 12.0):
            clutter += _box(xp - 0.3, yb - 0.3, xp + 0.3, yb + 0.3)
    west_x, east_x = END_AISLE, length - END_AISLE
    tour: list[list[float]] = []
    for k, y in enumerate(aisles):
        start, end = (west_x, east_x) if k % 2 == 0 else (east_x, west_x)
        tour += [[start, y], [middle, y], [end, y]]
    # Back to the first aisle along the cross aisle where the serpentine ended, and along it.
    start, end = (west_x, east_x) if len(aisles) % 2 == 0 else (east_x, west_x)
    tour += [[start, aisles[0]], [middle, aisles[0]], [end, aisles[0]]]
    # The outer walls and their pairs are a room's: parallel, perpendicular, length and width.
    return dataclasses.replace(
        single_room(length, width),
        name=f"hall (layout {layout_seed})",
        clutter=np.array(clutter, dtype=np.float64).reshape(-1, 4),
        paths={CORRIDOR_TOUR: np.array(tour, dtype=np.float64)},
    )
