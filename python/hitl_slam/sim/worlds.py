"""Generated worlds as named wall segments with the feature pairs known to hold in them (parallel,
perpendicular, a spacing), for scoring a map the way the paper's Table 1 does: a single room, the
"lost poses" room, a building of parallel corridors (like LGRC) and a multi-building campus.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError

__all__ = [
    "CAMPUS_TOUR",
    "CORRIDOR_TOUR",
    "FeatureKind",
    "FeaturePair",
    "Floorplan",
    "campus",
    "corridor_walls",
    "lost_poses_room",
    "parallel_corridors",
    "rectangle_union_walls",
    "single_room",
]

FloatArray = NDArray[np.float64]
FeatureKind = Literal["parallel", "perpendicular", "spacing"]


@dataclass(frozen=True)
class FeaturePair:
    """A relation known to hold between walls ``i`` and ``j``: ``kind`` "parallel" (``value``
    0 degrees), "perpendicular" (90 degrees) or "spacing" (the distance between the two
    parallel walls, metres)."""

    i: int
    j: int
    kind: FeatureKind
    value: float


@dataclass(frozen=True, eq=False)
class Floorplan:
    """Walls ``(W, 4)`` rows ``(x0, y0, x1, y1)`` [m] with a name each, the feature pairs known
    to hold between them, optional clutter segments (seen by the lidar, labelled -1), and
    ``paths``: named waypoint lists (corridor centre lines) a robot can follow."""

    name: str
    walls: FloatArray
    wall_names: tuple[str, ...]
    feature_pairs: tuple[FeaturePair, ...]
    clutter: FloatArray = field(default_factory=lambda: np.zeros((0, 4)))
    paths: dict[str, FloatArray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.walls.ndim != 2 or self.walls.shape[1] != 4:
            raise InputError(f"walls must have shape (W, 4), got {self.walls.shape}")
        if len(self.wall_names) != self.walls.shape[0]:
            raise InputError("give one name per wall")
        if len(set(self.wall_names)) != len(self.wall_names):
            raise InputError("wall names must be unique")
        w = self.walls.shape[0]
        for p in self.feature_pairs:
            if not (0 <= p.i < w and 0 <= p.j < w and p.i != p.j):
                raise InputError(f"feature pair {p} names a wall that is not in the world")

    @property
    def num_walls(self) -> int:
        return int(self.walls.shape[0])

    def wall(self, name: str) -> int:
        """The index of the wall called ``name``."""
        try:
            return self.wall_names.index(name)
        except ValueError:
            raise InputError(f"no wall called {name!r} in world {self.name!r}") from None

    def wall_at(self, x: float, y: float, tolerance: float = 1e-6) -> int:
        """The index of the wall passing within ``tolerance`` [m] of ``(x, y)``."""
        return _index_at(self.walls, x, y, tolerance)


def _room_walls(width: float, length: float) -> FloatArray:
    return np.array(
        [
            [0.0, 0.0, width, 0.0],
            [width, 0.0, width, length],
            [width, length, 0.0, length],
            [0.0, length, 0.0, 0.0],
        ]
    )


def _room(name: str, width: float, length: float) -> Floorplan:
    if not (width > 0 and length > 0):
        raise InputError(f"a room needs a positive width and length, got {width} x {length}")
    s, e, n, w = 0, 1, 2, 3
    pairs = (
        FeaturePair(w, e, "parallel", 0.0),
        FeaturePair(s, n, "parallel", 0.0),
        FeaturePair(s, e, "perpendicular", 90.0),
        FeaturePair(e, n, "perpendicular", 90.0),
        FeaturePair(n, w, "perpendicular", 90.0),
        FeaturePair(w, s, "perpendicular", 90.0),
        FeaturePair(w, e, "spacing", width),
        FeaturePair(s, n, "spacing", length),
    )
    return Floorplan(name, _room_walls(width, length), ("south", "east", "north", "west"), pairs)


def single_room(width: float = 5.0, length: float = 4.0) -> Floorplan:
    """A rectangular room ``width`` (x) by ``length`` (y) metres, its south-west corner at the
    origin; walls "south", "east", "north", "west"."""
    return _room("single-room", width, length)


def lost_poses_room(width: float = 6.33, length: float = 8.0) -> Floorplan:
    """The paper's "lost poses" room: 6.33 m wide (west to east, the long walls 8 m long), so a
    laser limited to 1.5 m never sees two parallel walls at once."""
    return _room("lost-poses-room", width, length)


def rectangle_union_walls(rects: Sequence[tuple[float, float, float, float]]) -> FloatArray:
    """The walls around the free space that is the union of axis-aligned rectangles
    ``(x0, y0, x1, y1)``: every boundary between inside and outside, merged into maximal
    straight segments. Rows ``(x0, y0, x1, y1)``; horizontal walls first, by y then x."""
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    if r.shape[0] == 0 or np.any(r[:, 2] <= r[:, 0]) or np.any(r[:, 3] <= r[:, 1]):
        raise InputError("rectangles must be (x0, y0, x1, y1) with x0 < x1 and y0 < y1")
    xs = np.unique(np.concatenate([r[:, 0], r[:, 2]]))
    ys = np.unique(np.concatenate([r[:, 1], r[:, 3]]))
    cx, cy = 0.5 * (xs[:-1] + xs[1:]), 0.5 * (ys[:-1] + ys[1:])
    inside = np.zeros((cx.size + 2, cy.size + 2), dtype=bool)  # padded with outside cells
    for x0, y0, x1, y1 in r:
        ix = (cx > x0) & (cx < x1)
        iy = (cy > y0) & (cy < y1)
        inside[1:-1, 1:-1] |= ix[:, None] & iy[None, :]
    walls: list[list[float]] = []
    # Horizontal walls at y = ys[j], between cells row j-1 (below) and row j (above).
    side_h = inside[1:-1, 1:].astype(np.int8) - inside[1:-1, :-1].astype(np.int8)  # (nx, ny + 1)
    for j in range(ys.size):
        for state, run in itertools.groupby(range(cx.size), key=lambda i: int(side_h[i, j])):
            cells = list(run)
            if state:
                walls.append([xs[cells[0]], ys[j], xs[cells[-1] + 1], ys[j]])
    side_v = inside[1:, 1:-1].astype(np.int8) - inside[:-1, 1:-1].astype(np.int8)  # (nx + 1, ny)
    for i in range(xs.size):
        for state, run in itertools.groupby(range(cy.size), key=lambda j: int(side_v[i, j])):
            cells = list(run)
            if state:
                walls.append([xs[i], ys[cells[0]], xs[i], ys[cells[-1] + 1]])
    return np.array(walls, dtype=np.float64)


def corridor_walls(centre_lines: FloatArray, width: float) -> FloatArray:
    """The walls of corridors ``width`` wide along axis-aligned centre-line segments
    ``(x0, y0, x1, y1)``; corridors that meet or cross are joined."""
    c = np.asarray(centre_lines, dtype=np.float64).reshape(-1, 4)
    if np.any((c[:, 0] != c[:, 2]) & (c[:, 1] != c[:, 3])):
        raise InputError("corridor centre lines must be horizontal or vertical")
    h = 0.5 * width
    rects = [
        (min(x0, x1) - h, min(y0, y1) - h, max(x0, x1) + h, max(y0, y1) + h) for x0, y0, x1, y1 in c
    ]
    return rectangle_union_walls(rects)


def _wall_names(walls: FloatArray) -> tuple[str, ...]:
    names = []
    for x0, y0, x1, y1 in walls:
        if y0 == y1:
            names.append(f"h y={y0:g} x={min(x0, x1):g}..{max(x0, x1):g}")
        else:
            names.append(f"v x={x0:g} y={min(y0, y1):g}..{max(y0, y1):g}")
    return tuple(names)


CORRIDOR_TOUR = "tour"
"""The name of the default path in :attr:`Floorplan.paths` of the corridor worlds."""

CAMPUS_TOUR = CORRIDOR_TOUR


def parallel_corridors(
    count: int = 3, length: float = 30.0, width: float = 2.0, spacing: float = 8.0
) -> Floorplan:
    """A building like the paper's LGRC floors: ``count`` long corridors along x, ``length``
    metres between the centres of the end corridors, ``width`` wide, centre lines ``spacing``
    apart, joined at both ends by corridors along y.

    Wall names: "c{k}-south" and "c{k}-north" for corridor k's long walls (the outermost are
    the building's outline and run the whole length); outline walls "west" and "east"; the
    short walls of the end corridors "west-{k}" / "east-{k}" between corridors k and k + 1.
    Feature pairs: the long walls parallel to each other, perpendicular to the end walls, and the
    constant inter-corridor spacing between the south walls of neighbouring corridors.

    ``paths["tour"]`` drives every corridor: east along corridor 0, north, west along corridor 1,
    north, ... and back to the start down the east end.
    """
    if count < 2 or not (length > 2 * width and spacing > width > 0):
        raise InputError("need count >= 2, length > 2 width and spacing > width > 0")
    top = spacing * (count - 1)
    lines = [[0.0, spacing * k, length, spacing * k] for k in range(count)]
    lines += [[0.0, 0.0, 0.0, top], [length, 0.0, length, top]]
    walls = corridor_walls(np.array(lines), width)
    world_names = list(_wall_names(walls))
    h = 0.5 * width

    def at(x: float, y: float) -> int:
        return _index_at(walls, x, y)

    mid = 0.5 * length
    south = [at(mid, spacing * k - h) for k in range(count)]
    north = [at(mid, spacing * k + h) for k in range(count)]
    west, east = at(-h, 0.5 * top), at(length + h, 0.5 * top)
    for k in range(count):
        world_names[south[k]] = f"c{k}-south"
        world_names[north[k]] = f"c{k}-north"
    world_names[west], world_names[east] = "west", "east"
    for k in range(count - 1):
        y = spacing * (k + 0.5)
        world_names[at(h, y)] = f"west-{k}"
        world_names[at(length - h, y)] = f"east-{k}"
    pairs: list[FeaturePair] = []
    longs = [w for k in range(count) for w in (south[k], north[k])]
    pairs += [FeaturePair(a, b, "parallel", 0.0) for a, b in itertools.combinations(longs, 2)]
    pairs.append(FeaturePair(west, east, "parallel", 0.0))
    for w in (south[0], north[-1]):
        pairs += [FeaturePair(w, west, "perpendicular", 90.0)]
        pairs += [FeaturePair(w, east, "perpendicular", 90.0)]
    for k in range(count - 1):
        pairs.append(FeaturePair(south[k], south[k + 1], "spacing", spacing))
        pairs.append(FeaturePair(north[k], north[k + 1], "spacing", spacing))
    tour = [[0.0, 0.0]]
    for k in range(count):
        x = length if k % 2 == 0 else 0.0
        tour += [[x, spacing * k]]
        if k < count - 1:
            tour += [[x, spacing * (k + 1)]]
    # Back to the start: down the east end and west along corridor 0, or down the west end.
    tour += [[length, 0.0], [0.0, 0.0]] if tour[-1][0] == length else [[0.0, 0.0]]
    return Floorplan(
        "parallel-corridors",
        walls,
        tuple(world_names),
        tuple(pairs),
        paths={CORRIDOR_TOUR: np.array(tour, dtype=np.float64)},
    )


def _index_at(walls: FloatArray, x: float, y: float, tolerance: float = 1e-9) -> int:
    p0, e = walls[:, :2], walls[:, 2:] - walls[:, :2]
    t = np.clip(np.einsum("ij,ij->i", [x, y] - p0, e) / np.einsum("ij,ij->i", e, e), 0, 1)
    d = np.hypot(*(p0 + t[:, None] * e - [x, y]).T)
    best = int(np.argmin(d))
    if d[best] > tolerance:
        raise InputError(f"no wall passes through ({x}, {y})")
    return best


def campus(scale: float = 1.2, width: float = 2.4) -> Floorplan:
    """Three buildings joined by corridors, for a tour of about 1 km (``scale`` 1.2).

    Building A is a ring of corridors with a middle corridor, B a ladder of three parallel
    corridors, C a ring; links run A-B, B-C and C-A. All walls are axis aligned, so every pair of
    long walls is parallel or perpendicular; the feature pairs list a sample of them across
    buildings (as a surveyor would measure) and the spacings between the parallel corridors of B.
    ``paths["tour"]`` visits every building and goes around A a second time at the end.
    """
    s = float(scale)
    if not (s > 0 and 0 < width < 10 * s):
        raise InputError("campus needs scale > 0 and 0 < width < 10 scale")
    # Corridor centre lines (unscaled): A ring 60 x 30 with a middle corridor, the A-B link,
    # B ladder 40 x 30, the B-C link, C ring 60 x 30, the C-A link.
    lines = np.array(
        [
            [0, 0, 60, 0],
            [0, 30, 60, 30],
            [0, 0, 0, 30],
            [60, 0, 60, 30],
            [0, 15, 60, 15],
            [60, 15, 100, 15],
            [100, 0, 140, 0],
            [100, 15, 140, 15],
            [100, 30, 140, 30],
            [100, 0, 100, 30],
            [140, 0, 140, 30],
            [120, 30, 120, 70],
            [60, 70, 120, 70],
            [60, 100, 120, 100],
            [60, 70, 60, 100],
            [120, 70, 120, 100],
            [60, 30, 60, 70],
        ],
        dtype=np.float64,
    )
    walls = corridor_walls(lines * s, width)
    names = _wall_names(walls)
    h = 0.5 * width

    def at(x: float, y: float) -> int:
        return _index_at(walls, x * s, y * s)

    hs = h / s
    a_south, a_north = at(30, -hs), at(30, 30 + hs)
    a_west = at(-hs, 7)
    b_south = [at(120, -hs), at(110, 15 - hs), at(110, 30 - hs)]
    b_east = at(140 + hs, 7)
    c_north, c_west = at(90, 100 + hs), at(60 - hs, 85)
    pairs = [
        FeaturePair(a_south, a_north, "parallel", 0.0),
        FeaturePair(a_south, b_south[0], "parallel", 0.0),
        FeaturePair(a_south, c_north, "parallel", 0.0),
        FeaturePair(b_south[0], c_north, "parallel", 0.0),
        FeaturePair(a_west, b_east, "parallel", 0.0),
        FeaturePair(a_west, c_west, "parallel", 0.0),
        FeaturePair(a_south, a_west, "perpendicular", 90.0),
        FeaturePair(b_south[0], b_east, "perpendicular", 90.0),
        FeaturePair(c_north, c_west, "perpendicular", 90.0),
        FeaturePair(a_south, c_west, "perpendicular", 90.0),
        FeaturePair(b_south[2], a_west, "perpendicular", 90.0),
        FeaturePair(b_south[0], b_south[1], "spacing", 15 * s),
        FeaturePair(b_south[1], b_south[2], "spacing", 15 * s),
        FeaturePair(a_south, a_north, "spacing", 30 * s + width),
    ]
    tour = [
        [0, 0],
        [60, 0],
        [60, 15],
        [100, 15],
        [140, 15],
        [140, 0],
        [100, 0],
        [100, 30],
        [120, 30],
        [120, 70],
        [120, 100],
        [60, 100],
        [60, 70],
        [60, 30],
        [0, 30],
        [0, 15],
        [60, 15],
        [60, 0],
        [0, 0],
        [0, 30],
        [60, 30],
        [60, 0],
        [0, 0],
    ]
    return Floorplan(
        "campus",
        walls,
        names,
        tuple(pairs),
        paths={CAMPUS_TOUR: np.array(tour, dtype=np.float64) * s},
    )
