"""Writers for a map with given poses: TUM trajectories, g2o pose graphs, ROS map_server occupancy
grids (``.pgm`` + ``.yaml``), figures (``.png``, ``.svg``), and :func:`export`, which picks one
from the file extension. All of them write atomically.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.extras import require
from hitl_slam.geometry import to_world
from hitl_slam.io import save_graph
from hitl_slam.io.atomic import atomic_binary_writer, atomic_outputs, atomic_write_text
from hitl_slam.io.carmen_writer import write_carmen
from hitl_slam.io.covars import write_covars
from hitl_slam.io.textfile import PathLike, input_error
from hitl_slam.map import Map

__all__ = [
    "EXPORT_EXTENSIONS",
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "OccupancyGrid",
    "export",
    "occupancy_grid",
    "write_figure",
    "write_g2o_map",
    "write_occupancy",
    "write_tum",
]

FREE, OCCUPIED, UNKNOWN = 254, 0, 205
"""Pixel values of the trinary PGM (what ROS map_saver writes)."""

_MAX_CELLS = 100_000_000  # ~1 GB of counters; beyond this the resolution is surely a mistake
_CHUNK = 10_000_000  # scanline crossings per vectorized batch (bounds temporary memory)
# Neighbouring points at most this many median angular spacings apart are joined by free space
# (up to four missing beams); not an integer, so that whole numbers of beams never tie.
_JOIN_GAP = 5.5


def write_tum(map: Map, poses: ArrayLike, path: PathLike) -> None:
    """Write the trajectory in TUM format, one ``t x y z qx qy qz qw`` line per pose.

    ``z = 0``; the quaternion is the rotation by theta about z, ``(0, 0, sin(theta/2),
    cos(theta/2))``. ``t`` is the pose's timestamp, or its index when the map has none. Floats
    are written with ``repr`` (exact).
    """
    out = map.checked_poses(poses)
    stamps = map.timestamps if map.timestamps is not None else np.arange(map.num_poses, dtype=float)
    half = 0.5 * out[:, 2]
    table = np.stack(
        [stamps, out[:, 0], out[:, 1], np.zeros(len(out)), np.sin(half), np.cos(half)], axis=1
    )
    text = "".join(
        f"{t!r} {x!r} {y!r} {z!r} 0.0 0.0 {qz!r} {qw!r}\n" for t, x, y, z, qz, qw in table.tolist()
    )
    atomic_write_text(path, text)


def write_g2o_map(map: Map, poses: ArrayLike, path: PathLike) -> None:
    """Write the map's pose graph (its ORIGINAL factors) with ``poses`` as ``VERTEX_SE2`` /
    ``EDGE_SE2`` lines (see :func:`hitl_slam.io.save_graph`; ``.graph`` gives TORO).

    What is written reads back with :func:`hitl_slam.io.load_graph`: values its reader would
    refuse (e.g. a step between consecutive poses beyond 1e9 m) are an InputError instead, and
    nothing is written."""
    out = map.checked_poses(poses)
    save_graph(map.pose_graph(out), out, path)


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A trinary occupancy grid as ROS map_server reads it.

    Attributes:
        image: ``(H, W)`` uint8, :data:`FREE` / :data:`OCCUPIED` / :data:`UNKNOWN`; row 0 is the
            TOP of the map (largest y), as in the PGM file.
        free_counts, hit_counts: ``(H, W)`` int64, same orientation: how many scans saw each cell
            free, and how many hit it.
        origin: world ``(x, y)`` of the lower-left corner of the bottom-left cell.
        resolution: cell size [m].
    """

    image: NDArray[np.uint8]
    free_counts: NDArray[np.int64]
    hit_counts: NDArray[np.int64]
    origin: tuple[float, float]
    resolution: float

    def cell(self, x: float, y: float) -> tuple[int, int]:
        """``(row, column)`` in :attr:`image` of the cell holding world point ``(x, y)``."""
        column = math.floor((x - self.origin[0]) / self.resolution)
        row_from_bottom = math.floor((y - self.origin[1]) / self.resolution)
        return self.image.shape[0] - 1 - row_from_bottom, column

    def value_at(self, x: float, y: float) -> int:
        """The pixel value at world point ``(x, y)`` (:data:`UNKNOWN` outside the grid)."""
        row, column = self.cell(x, y)
        height, width = self.image.shape
        if not (0 <= row < height and 0 <= column < width):
            return UNKNOWN
        return int(self.image[row, column])


def occupancy_grid(
    map: Map,
    poses: ArrayLike,
    *,
    resolution: float | None = None,
    surface_margin: float | None = None,
    config: Config = DEFAULT,
) -> OccupancyGrid:
    """The occupancy grid of ``map`` under ``poses``.

    Each scan is counted once per cell. Hit: the cell holds at least one point of the scan.
    Free: the cell's centre lies in the scan's free space, the fan of its beams: the triangles
    between the sensor (the pose position) and consecutive points in angle order, each cut back
    by ``surface_margin`` (default one cell) measured across the surface the two points lie on,
    so a beam that grazes a wall does not clear the wall's cells, and a cell holding a point
    (centre within 0.71 cell of it) is not cleared by the triangles ending at that point; on a
    real map, whose scans do not align perfectly, this also keeps walls whole. Neighbouring
    points more than 5.5 times the scan's median angular spacing apart (missing beams, max-range
    gaps) are not joined; a scan that covers the full circle closes around the sensor. The free
    space is rasterized exactly (scanline crossings of the fan's boundary into a difference
    grid), not sampled along rays.

    Rule: a cell is OCCUPIED when it was hit in at least one scan and hit in more scans than saw
    it free; otherwise FREE when any scan saw it (free or hit); UNKNOWN when none did.

    The grid covers every pose and point with two cells to spare; ``origin`` is a multiple of
    the resolution.

    Raises:
        InputError: bad poses, a non-positive resolution, or a grid over 1e8 cells.
    """
    out = map.checked_poses(poses)
    res = config.grid_resolution if resolution is None else float(resolution)
    if not (math.isfinite(res) and res > 0):
        raise InputError(f"resolution must be a finite number > 0 (metres), got {resolution!r}")
    margin = res if surface_margin is None else float(surface_margin)
    if not (math.isfinite(margin) and margin >= 0):
        raise InputError(f"surface_margin must be a finite number >= 0, got {surface_margin!r}")

    world = map.world_points(out)
    everything = np.vstack([world, out[:, :2]])
    low = np.floor(everything.min(axis=0) / res).astype(np.int64) - 2
    high = np.floor(everything.max(axis=0) / res).astype(np.int64) + 2
    width, height = (int(v) for v in high - low + 1)
    if width * height > _MAX_CELLS:
        raise InputError(
            f"an occupancy grid of {width} x {height} cells at {res:g} m is too large; "
            "use a coarser resolution"
        )
    origin = low.astype(np.float64) * res
    owner = map.pose_of_point()

    # Hits, once per scan per cell.
    hx = np.floor((world[:, 0] - origin[0]) / res).astype(np.int64)
    hy = np.floor((world[:, 1] - origin[1]) / res).astype(np.int64)
    cells = width * height
    keys = owner * cells + (hy * width + hx)
    # Neighbouring points of a scan often share a cell: drop those repeats before the unique.
    keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])]
    pairs = np.unique(keys)
    hits = np.bincount(pairs % cells, minlength=cells).reshape(height, width)

    diff = np.zeros(height * (width + 1))
    for start, stop in _free_space_edges(map, out, margin):
        diff += _crossings(start, stop, origin, res, width, height)
    free = np.rint(np.cumsum(diff.reshape(height, width + 1), axis=1)[:, :width]).astype(np.int64)

    image = np.full((height, width), UNKNOWN, dtype=np.uint8)
    image[(free > 0) | (hits > 0)] = FREE
    image[(hits > 0) & (hits > free)] = OCCUPIED
    return OccupancyGrid(
        image=np.ascontiguousarray(image[::-1]),
        free_counts=np.ascontiguousarray(free[::-1]),
        hit_counts=np.ascontiguousarray(hits[::-1]),
        origin=(float(origin[0]), float(origin[1])),
        resolution=res,
    )


def _free_space_edges(
    map: Map, poses: NDArray[np.float64], margin: float
) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Directed boundary edges (start ``(E, 2)``, end ``(E, 2)``) of every scan's free space,
    each scan's boundary counter-clockwise, in batches."""
    owner = map.pose_of_point()
    if len(owner) < 2:
        return []
    angle = np.arctan2(map.points[:, 1], map.points[:, 0])
    # One float key orders by scan, then angle (angles span less than 7); laser scans usually
    # come in beam order already, and then the sort is skipped.
    key = owner * 7.0 + angle
    if np.any(key[1:] < key[:-1]):
        order = np.argsort(key, kind="stable")
        owner, angle, local = owner[order], angle[order], map.points[order]
    else:
        local = map.points
    counts = np.bincount(owner, minlength=map.num_poses)
    first = np.concatenate([[0], np.cumsum(counts)])[:-1][owner]  # first point of own scan
    last = first + counts[owner] - 1

    # Candidate pair starting at every point: to the next point, or from the scan's last point
    # around to its first (the wrap, which matters only for full-circle scans).
    is_last = np.arange(len(owner)) == last
    nxt = np.where(is_last, first, np.arange(len(owner)) + 1)
    gap = np.where(is_last, angle[first] + 2 * math.pi - angle, angle[nxt] - angle)
    n_scans = map.num_poses
    spacing = _median_per_scan(gap, owner, ~is_last, n_scans)
    has_pair = (gap <= _JOIN_GAP * spacing[owner]) & (counts[owner] >= 2)
    has_pair &= ~is_last | (counts[owner] >= 3)

    # Cut each triangle back by `margin` across its chord: scale it about the sensor by lambda.
    a, b = local, local[nxt]
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    chord = np.hypot(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(chord > 0, cross / chord, 0.0)  # distance sensor -> chord line
        scale = np.where(depth > margin, 1.0 - margin / depth, 0.0)

    # where the cut-back chord meets the beam of point a (of b)
    corner_a = to_world(poses, owner, scale[:, None] * a)
    corner_b = to_world(poses, owner, scale[:, None] * b)
    sensor = poses[owner, :2]
    prev = np.where(np.arange(len(owner)) == first, last, np.arange(len(owner)) - 1)
    follow = has_pair[nxt]
    lead = has_pair[prev]

    p = np.flatnonzero(has_pair)
    linked = p[follow[p]]
    ends = p[~follow[p]]
    starts = p[~lead[p]]
    batches = [
        (corner_a[p], corner_b[p]),  # the cut-back chords
        (corner_b[linked], corner_a[nxt[linked]]),  # along a beam to the next chord
        (corner_b[ends], sensor[ends]),  # back to the sensor where the fan breaks
        (sensor[starts], corner_a[starts]),  # out from the sensor where it resumes
    ]
    return batches


def _median_per_scan(
    gap: NDArray[np.float64], owner: NDArray[np.int64], use: NDArray[np.bool_], n_scans: int
) -> NDArray[np.float64]:
    """Lower median of ``gap[use]`` per scan (inf for scans with none)."""
    o = owner[use]
    key = np.sort(o * 8.0 + gap[use])  # gaps lie in [0, 2 pi]: sorts by scan, then gap
    counts = np.bincount(o, minlength=n_scans)
    starts = np.concatenate([[0], np.cumsum(counts)])[:-1]
    median = np.full(n_scans, np.inf)
    present = np.flatnonzero(counts > 0)
    pick = starts[present] + (counts[present] - 1) // 2
    median[present] = key[pick] - present * 8.0
    return median


def _crossings(
    start: NDArray[np.float64],
    stop: NDArray[np.float64],
    origin: NDArray[np.float64],
    res: float,
    width: int,
    height: int,
) -> NDArray[np.float64]:
    """Difference grid ``(H * (W + 1),)`` of directed edges: where an edge crosses the centre
    line of a row, -1 (upward) or +1 (downward) at the first cell centre right of it. Summed
    along a row this is the winding number of counter-clockwise boundaries at each cell centre.
    Rows use half-open spans so that a vertex on a centre line is counted once."""
    total = np.zeros(height * (width + 1))
    ay, by = (start[:, 1] - origin[1]) / res - 0.5, (stop[:, 1] - origin[1]) / res - 0.5
    ax, bx = (start[:, 0] - origin[0]) / res - 0.5, (stop[:, 0] - origin[0]) / res - 0.5
    moving = ay != by
    ax, ay, bx, by = ax[moving], ay[moving], bx[moving], by[moving]
    sign = np.where(by > ay, -1.0, 1.0)
    lo = np.ceil(np.minimum(ay, by)).astype(np.int64)
    hi = np.ceil(np.maximum(ay, by)).astype(np.int64)
    rows = np.maximum(hi - lo, 0)
    slope = (bx - ax) / (by - ay)
    ends = np.cumsum(rows)
    chunk_starts = np.searchsorted(ends, np.arange(0, ends[-1] if len(ends) else 0, _CHUNK))
    bounds = [*chunk_starts.tolist(), len(rows)]
    for e0, e1 in itertools.pairwise(bounds):
        if e0 >= e1:
            continue
        n = rows[e0:e1]
        edge = np.repeat(np.arange(e0, e1), n)
        step = np.arange(len(edge)) - np.repeat(np.cumsum(n) - n, n)
        row = lo[edge] + step
        x = ax[edge] + (row - ay[edge]) * slope[edge]
        column = np.clip(np.ceil(x), 0, width).astype(np.int64)
        row = np.clip(row, 0, height - 1)
        total += np.bincount(
            row * (width + 1) + column, weights=sign[edge], minlength=height * (width + 1)
        )
    return total


def write_occupancy(
    map: Map,
    poses: ArrayLike,
    path_pgm: PathLike,
    *,
    resolution: float | None = None,
    config: Config = DEFAULT,
) -> OccupancyGrid:
    """Write the occupancy grid (see :func:`occupancy_grid`) as a ROS map_server map: a binary
    P5 ``.pgm`` (row 0 = largest y) and, last, a ``.yaml`` next to it with the same stem
    (``image`` relative to the yaml, ``resolution``, ``origin: [x, y, 0.0]``, ``negate: 0``,
    ``occupied_thresh: 0.65``, ``free_thresh: 0.196``, ``mode: trinary``). ``resolution``
    defaults to ``config.grid_resolution``. Returns the grid."""
    grid = occupancy_grid(map, poses, resolution=resolution, config=config)
    name = os.fspath(path_pgm)
    height, width = grid.image.shape
    header = f"P5\n# hitl-slam occupancy grid, {grid.resolution!r} m/cell\n{width} {height}\n255\n"
    ox, oy = grid.origin
    image = os.path.basename(name)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", image):
        image = json.dumps(image)  # a JSON string is a valid double-quoted YAML scalar
    yaml = (
        f"image: {image}\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{ox!r}, {oy!r}, 0.0]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
        "mode: trinary\n"
    )
    # Both files or neither: a .pgm without its .yaml is no map for map_server.
    with atomic_outputs():
        with atomic_binary_writer(name) as f:
            f.write(header.encode("ascii"))
            f.write(grid.image.tobytes())
        atomic_write_text(os.path.splitext(name)[0] + ".yaml", yaml)
    return grid


def _write_occupancy(map: Map, poses: ArrayLike, path: PathLike) -> None:
    write_occupancy(map, poses, path)


def write_figure(map: Map, poses: ArrayLike, path: PathLike) -> None:
    """Write the picture of the map under ``poses`` (``.png`` or ``.svg``, see
    :func:`hitl_slam.plot.write_map`); needs the ``plot`` extra (matplotlib).

    Raises:
        MissingExtra: matplotlib is not installed (the message names the extra).
    """
    out = map.checked_poses(poses)
    require("plot", f"exporting {os.path.basename(os.fspath(path))} (a figure)")
    from hitl_slam.plot import write_map

    write_map(map, out, path)


_WRITERS: dict[str, Callable[[Map, ArrayLike, PathLike], None]] = {
    ".covars": write_covars,
    ".clf": write_carmen,
    ".g2o": write_g2o_map,
    ".txt": write_tum,
    ".pgm": _write_occupancy,
    ".png": write_figure,
    ".svg": write_figure,
}
EXPORT_EXTENSIONS = tuple(_WRITERS)
"""Extensions :func:`export` writes: ``.covars``, ``.clf`` (a CARMEN log), ``.g2o``, ``.txt``
(TUM), ``.pgm`` (+ yaml), ``.png`` and ``.svg`` (a figure of the map; the ``plot`` extra)."""


def export(map: Map, poses: ArrayLike, path: PathLike) -> None:
    """Write ``map`` with ``poses`` in the format named by the extension of ``path``:
    ``.covars`` (HitL-SLAM), ``.clf`` (a CARMEN log: :mod:`hitl_slam.io.carmen_writer`),
    ``.g2o`` (pose graph), ``.txt`` (TUM trajectory), ``.pgm``
    (occupancy grid, with its ``.yaml``), ``.png`` / ``.svg`` (a picture of the map, as
    :func:`hitl_slam.plot.plot_map` draws it; needs matplotlib, the ``plot`` extra).

    Raises:
        InputError: any other extension (the message lists the supported ones), bad poses, or
            an output that cannot be written (:class:`~hitl_slam.io.atomic.OutputError`).
        MissingExtra: ``.png`` / ``.svg`` without matplotlib.
    """
    name = os.fspath(path)
    extension = os.path.splitext(name)[1].lower()
    writer = _WRITERS.get(extension)
    if writer is None:
        raise input_error(
            name,
            None,
            f"cannot export to {extension or 'a file without extension'!r}",
            f"use one of the supported extensions: {', '.join(EXPORT_EXTENSIONS)}",
        )
    writer(map, poses, name)
