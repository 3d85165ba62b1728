"""The laser scans of a ROS bag as points in the robot's frame, for
:func:`~hitl_slam.io.rosbag.read_rosbag`: each ``sensor_msgs/LaserScan`` as plain arrays, the
laser's mounting from the frame tree, and every scan's points, counts and intensities at once.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.io.textfile import MAX_ANGLE, MAX_COORDINATE, beam_spacing_problem, sci
from hitl_slam.io.tf_tree import _seconds, _Tree

if TYPE_CHECKING:
    from hitl_slam.io.rosbag import _Contents

_log = logging.getLogger("hitl_slam.io.rosbag")  # the reader's logger, as before the split


@dataclass
class _Scan:
    stamp: int  # [ns]
    frame: str
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: NDArray[np.float64]
    intensities: NDArray[np.float64]  # empty: none


def _mount(
    name: str, tree: _Tree, base_frame: str, laser_frame: str
) -> tuple[NDArray[np.float64], bool]:
    """``T_base_laser`` (4x4) and whether it came from /tf_static alone."""
    if not laser_frame or laser_frame == base_frame:
        return np.eye(4), True
    matrix = tree.rigid(base_frame, laser_frame)
    if matrix is None:
        frames = sorted(tree.frames)
        shown = ", ".join(frames[:12]) + (
            f", ... {len(frames) - 12} more" if len(frames) > 12 else ""
        )
        raise InputError(
            f"{name}: no transform from {base_frame!r} to the laser's frame {laser_frame!r} in "
            f"/tf_static or /tf (frames: {shown or 'none'}); record the robot's static "
            "transforms (robot_state_publisher), or pass --base-frame if the robot's frame has "
            "another name"
        )
    if not np.all(np.isfinite(matrix)) or not np.all(np.abs(matrix[:3, 3]) <= MAX_COORDINATE):
        raise InputError(
            f"{name}: the laser's mounting {base_frame} -> {laser_frame} is beyond "
            f"{sci(MAX_COORDINATE)} m; the transforms are damaged: re-record the bag"
        )
    static = tree.only_static(base_frame, laser_frame)
    if not static:
        _log.info(
            "%s: %s -> %s is not in /tf_static; its first value in /tf is taken as rigid",
            name,
            base_frame,
            laser_frame,
        )
    return matrix, static


def _points(
    name: str,
    contents: _Contents,
    scans: list[_Scan],
    tree: _Tree,
    base_frame: str,
    max_range: float | None,
) -> tuple[
    NDArray[np.float64],
    NDArray[np.int64],
    NDArray[np.float64] | None,
    dict[str, list[float]],
]:
    """Every scan's points in the base frame at once; per-scan counts, per-point intensities
    (None when no scan has any), and each laser frame's mounting ``(x, y, yaw)``."""
    topic = contents.scan_topic
    fields = np.array(
        [[s.angle_min, s.angle_increment, s.range_min, s.range_max] for s in scans]
    ).reshape(-1, 4)
    beams = np.array([len(s.ranges) for s in scans], dtype=np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        limit = fields[:, 3] if max_range is None else np.minimum(fields[:, 3], max_range)
        last_angle = fields[:, 0] + np.maximum(beams - 1, 0) * fields[:, 1]
        bad = (
            ~np.isfinite(fields[:, :3]).all(axis=1)
            | ~(np.abs(fields[:, 0]) <= MAX_ANGLE)
            | ~(np.abs(fields[:, 1]) <= MAX_ANGLE)
            | ~(np.abs(last_angle) <= MAX_ANGLE)
        )
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(
            f"{name}: {topic}: the scan at {_seconds(scans[k].stamp):.9f} s has angle_min "
            f"{float(fields[k, 0])!r}, angle_increment {float(fields[k, 1])!r}, range_min "
            f"{float(fields[k, 2])!r} over {beams[k]} beams: a NaN/inf or angles beyond "
            f"{sci(MAX_ANGLE)} rad; the message is damaged: re-record the bag or drop it"
        )
    for k in np.unique(np.stack([beams, fields[:, 1]], axis=1), axis=0, return_index=True)[1]:
        problem = beam_spacing_problem(int(beams[k]), float(fields[k, 1]))
        if problem:
            raise InputError(
                f"{name}: {topic}: the scan at {_seconds(scans[k].stamp):.9f} s has "
                f"angle_increment {float(fields[k, 1])!r}: "
                f"{problem}; the message is damaged: re-record the bag or drop it"
            )
    with np.errstate(invalid="ignore"):
        inverted = fields[:, 2] > limit
    if inverted.any():
        k = int(np.argmax(inverted))
        _log.warning(
            "%s: %s: %d of %d scans have range_min above range_max%s (first at %.9f s: %g > "
            "%g m); none of their readings can be a point: check the laser driver's range "
            "settings",
            name,
            topic,
            int(inverted.sum()),
            len(scans),
            "" if max_range is None else " (or --max-range)",
            _seconds(scans[k].stamp),
            float(fields[k, 2]),
            float(limit[k]),
        )
    with np.errstate(invalid="ignore"):
        unusable = ~(limit <= MAX_COORDINATE)  # NaN, inf or absurd: no usable maximum
    if unusable.any():
        k = int(np.argmax(unusable))
        raise InputError(
            f"{name}: {topic}: the scan at {_seconds(scans[k].stamp):.9f} s has range_max "
            f"{float(fields[k, 3])!r}, not a usable maximum range; pass --max-range M (the laser's "
            "maximum range in metres)"
        )
    mounts: dict[str, tuple[NDArray[np.float64], bool]] = {}
    for frame in {s.frame for s in scans}:
        mounts[frame] = _mount(name, tree, base_frame, frame)
    total = int(beams.sum())
    if total == 0:
        empty = np.zeros((0, 2))
        return empty, np.zeros(len(scans), dtype=np.int64), None, _mount_table(mounts)
    r = np.concatenate([s.ranges for s in scans])
    index = np.arange(total) - np.repeat(np.cumsum(beams) - beams, beams)
    owner = np.repeat(np.arange(len(scans)), beams)
    angle = fields[owner, 0] + index * fields[owner, 1]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0) & (r >= fields[owner, 2]) & (r <= limit[owner])
    rv, av, ov = r[valid], angle[valid], owner[valid]
    local = np.stack([rv * np.cos(av), rv * np.sin(av)], axis=1)
    points = np.empty_like(local)
    frame_of = np.array([s.frame for s in scans], dtype=object)[ov]
    for frame, (matrix, _) in mounts.items():
        rows = frame_of == frame
        points[rows] = local[rows] @ matrix[:2, :2].T + matrix[:2, 3]
    counts = np.bincount(ov, minlength=len(scans)).astype(np.int64)
    intensities = None
    if any(len(s.intensities) and len(s.intensities) == len(s.ranges) for s in scans):
        per_beam = np.concatenate(
            [
                s.intensities
                if len(s.intensities) == len(s.ranges)
                else np.full(len(s.ranges), np.nan)
                for s in scans
            ]
        )
        intensities = per_beam[valid]
    mismatched = sum(1 for s in scans if len(s.intensities) not in (0, len(s.ranges)))
    if mismatched:
        _log.info(
            "%s: %d scans of %s have intensities, but not one per range; theirs are ignored",
            name,
            mismatched,
            topic,
        )
    return points, counts, intensities, _mount_table(mounts)


def _mount_table(mounts: dict[str, tuple[NDArray[np.float64], bool]]) -> dict[str, list[float]]:
    return {
        frame: [float(m[0, 3]), float(m[1, 3]), math.atan2(float(m[1, 0]), float(m[0, 0]))]
        for frame, (m, _) in mounts.items()
    }
