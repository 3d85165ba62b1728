"""Writing a map as a CARMEN log (``.clf``): the log a SLAM system hands on, its scans with the
corrected poses, which CARMEN tools, the Freiburg benchmark's scoring and :func:`read_carmen`
read back.

Two ways, chosen by what the map knows:

- **The map was read from a CARMEN log that is still there** (its ``metadata["format"]`` is
  ``carmen`` and it records which line each scan came from): the log is copied line by line and
  only the pose fields of its scans change. A FLASER line's ``x y theta`` (the laser pose) and a
  ROBOTLASER1 line's ``laser_pose`` become the map's pose; ROBOTLASER1's ``robot_pose`` becomes
  that pose composed with the inverse of the laser offset (``PARAM robot_frontlaser_*``); the
  odometry fields (FLASER ``odom_*``) and every other line (PARAM, ODOM, ...) are kept. Where the
  scans are ROBOTLASER1, the FLASER lines of the same scans (same ipc timestamp) get the same
  laser pose. Laser lines of scans the map does not hold (dropped by subsampling) are left out:
  they have no corrected pose. Ranges, remissions and timestamps are the log's own, so the
  scans read back exactly.
- **Any other map** (a ROS bag, a generated map, a ``.covars``): one ROBOTLASER1 line per scan,
  synthesized from its points (laser frame: range and bearing). Beams are evenly spaced, so each
  scan gets the spacing of its own bearings (the smallest gap between them, at least
  :data:`MIN_RESOLUTION`) and each point the nearest beam; a scan from a real laser (evenly
  spaced bearings, some dropped) reads back with the same points, others within half a beam.
  Timestamps are the map's (or the scan index in seconds), the laser offset is zero.

Poses and ranges are written with ``repr`` (shortest exact form).
"""

from __future__ import annotations

import math
import os

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam.errors import InputError
from hitl_slam.geometry import compose, invert
from hitl_slam.io.atomic import atomic_write_text
from hitl_slam.io.carmen import _tag
from hitl_slam.io.textfile import PathLike, check_regular_file, input_error, read_lines
from hitl_slam.map import Map

__all__ = ["MIN_RESOLUTION", "write_carmen"]

MIN_RESOLUTION = math.radians(0.05)
"""The finest beam spacing a synthesized scan gets [rad] (7,200 beams per turn)."""

_NO_RETURN_MARGIN = 1.0  # [m] the maximum range written above the farthest point


def write_carmen(map: Map, poses: ArrayLike, path: PathLike) -> None:
    """Write ``map`` with ``poses`` as a CARMEN log at ``path`` (atomically); see the module."""
    out = map.checked_poses(poses)
    source = _source_log(map)
    text = _rewrite(map, out, source) if source is not None else _synthesize(map, out)
    atomic_write_text(path, text)


def _source_log(map: Map) -> str | None:
    """The CARMEN log ``map`` was read from, when it is there and the map says which of its lines
    each scan is."""
    meta = map.metadata
    lines = meta.get("scan_lines")
    if meta.get("format") != "carmen" or map.source is None or lines is None:
        return None
    if meta.get("laser") not in ("FLASER", "ROBOTLASER1") or len(lines) != map.num_poses:
        return None
    try:
        check_regular_file(map.source)
    except InputError:  # moved or deleted since: the scans are written from the map
        return None
    return os.fspath(map.source)


def _fmt(values: NDArray[np.float64] | list[float]) -> list[str]:
    return [repr(float(v)) for v in values]


def _rewrite(map: Map, poses: NDArray[np.float64], source: str) -> str:
    lines = read_lines(source)
    laser = str(map.metadata["laser"])
    scan_lines = np.asarray(map.metadata["scan_lines"], dtype=np.int64)
    offset = np.asarray(map.metadata.get("laser_offset", [0.0, 0.0, 0.0]), dtype=np.float64)
    robots = compose(poses, invert(offset))  # robot = laser o offset^-1
    pose_of_line = {int(line): k for k, line in enumerate(scan_lines)}
    by_stamp: dict[str, int] = {}
    flaser_copies: list[int] = []  # where the FLASER copies of ROBOTLASER1 scans are in `out`
    out: list[str] = []
    written = 0
    for number, line in enumerate(lines, 1):
        tag = _tag(line)
        if tag == laser:
            k = pose_of_line.get(number)
            if k is None:
                continue  # a scan the map does not hold: no corrected pose for it
            tokens = line.split()
            if tag == "FLASER":
                n = int(tokens[1])
                tokens[2 + n : 5 + n] = _fmt(poses[k])
            else:
                n = int(tokens[8])
                m = int(tokens[9 + n])
                first = 10 + n + m
                tokens[first : first + 3] = _fmt(poses[k])
                tokens[first + 3 : first + 6] = _fmt(robots[k])
                by_stamp[tokens[first + 11]] = k
            out.append(" ".join(tokens))
            written += 1
        else:
            if tag == "FLASER":
                flaser_copies.append(len(out))
            out.append(line.rstrip("\r\n"))
    # The FLASER copies of ROBOTLASER1 scans (same ipc timestamp) get the same laser pose.
    for i in flaser_copies:
        tokens = out[i].split()
        n = int(tokens[1]) if len(tokens) > 2 and tokens[1].isdigit() else -1
        if len(tokens) == n + 11 and (k := by_stamp.get(tokens[8 + n])) is not None:
            tokens[2 + n : 5 + n] = _fmt(poses[k])
            out[i] = " ".join(tokens)
    if not written:
        raise input_error(
            source,
            None,
            "none of the map's scans is where the map says in this log (changed since?)",
            "restore the log the map was read from, or move it away to have the scans written "
            "from the map",
        )
    return "\n".join(out) + "\n"


def _beams(points: NDArray[np.float64]) -> tuple[float, float, int, NDArray[np.float64]]:
    """Start angle, spacing, beam count and ranges (no return: NaN) of one scan's points."""
    bearings = np.arctan2(points[:, 1], points[:, 0])
    ranges = np.hypot(points[:, 0], points[:, 1])
    if points.shape[0] == 0:
        return -math.pi / 2, math.pi / 180, 1, np.full(1, np.nan)
    order = np.argsort(bearings, kind="stable")
    bearings, ranges = bearings[order], ranges[order]
    gaps = np.diff(bearings)
    gaps = gaps[gaps > 1e-9]
    resolution = max(float(gaps.min()) if gaps.size else math.pi / 180, MIN_RESOLUTION)
    start = float(bearings[0])
    index = np.rint((bearings - start) / resolution).astype(np.int64)
    count = int(index[-1]) + 1
    beams = np.full(count, np.nan)
    # Where two points share a beam, the nearer one is kept (what a laser would have seen).
    for i, r in zip(index[::-1].tolist(), ranges[::-1].tolist(), strict=True):
        if not (beams[i] <= r):
            beams[i] = r
    return start, resolution, count, beams


def _synthesize(map: Map, poses: NDArray[np.float64]) -> str:
    stamps = (
        map.timestamps if map.timestamps is not None else np.arange(map.num_poses, dtype=np.float64)
    )
    norms = np.hypot(map.points[:, 0], map.points[:, 1]) if map.num_points else np.zeros(1)
    max_range = float(norms.max()) + _NO_RETURN_MARGIN
    out = [
        f"# written by hitl-slam from {map.name!r}: one ROBOTLASER1 line per scan",
        "PARAM robot_frontlaser_offset 0.0",
        "PARAM robot_frontlaser_side_offset 0.0",
        "PARAM robot_frontlaser_angular_offset 0.0",
    ]
    no_return = repr(max_range)
    for k in range(map.num_poses):
        pts = map.points[map.offsets[k] : map.offsets[k + 1]]
        start, resolution, count, beams = _beams(pts)
        ranges = [no_return if math.isnan(r) else repr(r) for r in beams.tolist()]
        pose = _fmt(poses[k])
        stamp = repr(float(stamps[k]))
        out.append(
            " ".join(
                [
                    "ROBOTLASER1",
                    "0",
                    repr(start),
                    repr(resolution * (count - 1)),
                    repr(resolution),
                    no_return,
                    "0.01",
                    "0",
                    str(count),
                    *ranges,
                    "0",
                    *pose,
                    *pose,
                    "0.0 0.0 0.0 0.0 0.0",
                    stamp,
                    "hitl-slam",
                    stamp,
                ]
            )
        )
    return "\n".join(out) + "\n"
