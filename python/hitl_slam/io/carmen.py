"""CARMEN laser logs (``.clf``, ``.log``, optionally ``.gz``/``.bz2``) into a :class:`Map`.

Reads ``FLASER`` or ``ROBOTLASER1`` scans with their poses and ipc timestamps, and the ``PARAM``
lines that describe the laser; turns every valid beam into a point with one numpy pass.
"""

from __future__ import annotations

import enum
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.geometry import compose, wrap
from hitl_slam.io.textfile import (
    ANGLE_LIMIT,
    COORDINATE_LIMIT,
    MAX_COORDINATE,
    STRICT_FLOAT,
    Limit,
    PathLike,
    beam_spacing_problem,
    input_error,
    limit_error,
    parse_int,
    read_lines,
    sci,
)
from hitl_slam.map import Map

__all__ = [
    "DEFAULT_MAX_RANGE",
    "MAX_PLAUSIBLE_RANGE",
    "PoseSource",
    "infer_max_range",
    "read_carmen",
]

_log = logging.getLogger(__name__)

DEFAULT_MAX_RANGE = 80.0
"""[m] FLASER maximum range when no ``PARAM robot_front_laser_max`` says otherwise (CARMEN's own
default for the old laser messages)."""

_MAX_RANGE_MARGIN = 1e-3  # [m] a beam within this of the maximum range is a max-range reading
# Inferring the maximum range of a log that states none: no-return readings pile up at the largest
# value the sensor reports (seen: 32.767 m, a 16-bit millimetre clamp; 51.1 m; 81.9 m), spread
# over a few centimetres by rounding. A pile is the readings within _PILE_WIDTH of the largest
# one, when there are at least _PILE_MIN of them and _PILE_RATIO times as many as in a window of
# the same width just below (the _PILE_BASELINE metres underneath), and they are a minority.
_PILE_WIDTH = 0.15  # [m]
_PILE_BASELINE = 2.0  # [m]
_PILE_MIN = 10
_PILE_RATIO = 10.0
MAX_PLAUSIBLE_RANGE = 1000.0
"""[m] Readings beyond this are not a 2D laser's (the longest-ranged 2D scanners reach a few
hundred metres): garbage such as 1e308 that must not be taken for the sensor's no-return value
when inferring the maximum range. They are never points either (they exceed any maximum)."""
_FIX_LINE = "fix the line or delete it"
_FLASER_TAIL = ("x", "y", "theta", "odom_x", "odom_y", "odom_theta", "ipc_timestamp")
_RANGE_LIMIT = Limit(
    MAX_COORDINATE,
    f"a laser maximum range beyond {sci(MAX_COORDINATE)} m: a unit mistake or a damaged file",
    "write the range in metres, or fix the line",
)
_POSE_LIMITS = (COORDINATE_LIMIT, COORDINATE_LIMIT, ANGLE_LIMIT)
_FLASER_LIMITS = (*_POSE_LIMITS, *_POSE_LIMITS, None)

# PARAM names read (CARMEN robot module): the front laser's mounting on the robot and its range.
_OFFSET_PARAMS = (
    "robot_frontlaser_offset",  # [m] forward
    "robot_frontlaser_side_offset",  # [m] to the left
    "robot_frontlaser_angular_offset",  # [rad]
)
_MAX_RANGE_PARAM = "robot_front_laser_max"
_PARAM_LIMITS = dict(
    zip((*_OFFSET_PARAMS, _MAX_RANGE_PARAM), (*_POSE_LIMITS, _RANGE_LIMIT), strict=True)
)


class PoseSource(enum.Enum):
    """Which pose of a laser line becomes the map's pose."""

    LOGGED = "logged"
    """The laser pose the log carries (``x y theta`` of FLASER, ``laser_pose`` of ROBOTLASER1):
    raw odometry in a raw log, the corrected pose in a corrected one."""
    ODOMETRY = "odometry"
    """The robot's odometry (``odom_*`` of FLASER, ``robot_pose`` of ROBOTLASER1) composed with
    the laser offset from the ``PARAM`` lines."""


@dataclass
class _Scans:
    """What the line loop collects, one entry per laser line."""

    lines: list[int]
    ranges: list[NDArray[np.float64]]
    beam_config: list[tuple[int, float, float]]  # (n, start angle, angular step)
    max_range: list[float]  # nan: the FLASER default (PARAM or 80 m)
    logged: list[NDArray[np.float64]]
    robot: list[NDArray[np.float64]]
    stamps: list[float]


def read_carmen(
    path: PathLike,
    *,
    pose_source: PoseSource = PoseSource.LOGGED,
    max_range: float | None = None,
    config: Config = DEFAULT,
    min_travel: float = 0.0,
    min_rotation: float = 0.0,
) -> Map:
    """Read a CARMEN log into a :class:`Map` with one pose per kept laser scan.

    Frames: a map pose is the pose of the LASER (``t_world_laser``), and the points are in the
    laser frame, so the sensor origin is the pose position (docs/ALGORITHM.md §1.1) and the Map's
    "robot frame" is the laser frame. CARMEN already logs the laser pose in the pose fields of
    FLASER (``x y theta``; ``odom_*`` is the robot's odometry) and ROBOTLASER1 (``laser_pose``),
    i.e. the robot pose composed with ``PARAM robot_frontlaser_offset`` (fr079.clf: ``x y`` =
    ``odom_x odom_y`` + -0.04 m along the heading), so ``PoseSource.LOGGED`` uses those fields
    as they are. ``PoseSource.ODOMETRY`` composes the robot odometry (FLASER ``odom_*``,
    ROBOTLASER1 ``robot_pose``) with the laser offset ``(robot_frontlaser_offset,
    robot_frontlaser_side_offset, robot_frontlaser_angular_offset)`` from the ``PARAM`` lines
    (0 when absent; the last value in the file wins). Relative poses between scans (the
    ``.relations`` ground truth) therefore compare directly with the map's poses.

    Beams: FLASER beams cover 180 degrees from -90 degrees, spaced 180/n degrees, or 180/(n-1)
    for n = 181 or 361; ROBOTLASER1 carries its own start angle and angular resolution. A beam
    is a point unless its range is non-finite, ``<= 0``, or ``>= max_range - 1e-3`` (a max-range
    reading). ``max_range`` (m) overrides every line's; when None, ROBOTLASER1 uses its own field
    and FLASER uses ``PARAM robot_front_laser_max``, else 80 m.

    Lines: if the log has ROBOTLASER1 lines they are the scans and FLASER lines (the same scans in
    the old format) are skipped; otherwise the FLASER lines are. Other tags (ODOM, RLASER,
    RAWLASER*, TRUEPOS, NEFF, ...) are counted in ``map.metadata["skipped_lines"]`` and logged.
    Timestamps are the ipc timestamps. Edges: the consecutive-pose chain with the §1.3 motion model.

    Subsampling: with ``min_travel > 0`` (m) or ``min_rotation > 0`` (rad), a scan is kept only
    when the pose moved at least ``min_travel`` or turned at least ``min_rotation`` since the
    last kept scan (the first scan is always kept); with both 0 every scan is kept.

    Raises:
        InputError: ``{path}:{line}: what; what to do`` for a bad line (field count for the
            declared number of beams, bad or non-finite number), an empty log, or a log
            without laser lines.
    """
    name = os.fspath(path)
    if not isinstance(pose_source, PoseSource):
        raise InputError(f"pose_source must be a PoseSource, got {pose_source!r}")
    for label, value in (("min_travel", min_travel), ("min_rotation", min_rotation)):
        if not math.isfinite(value) or value < 0:
            raise InputError(f"{label} must be a finite number >= 0, got {value!r}")
    if max_range is not None and not (math.isfinite(max_range) and max_range > 0):
        raise InputError(f"max_range must be a finite number > 0 (metres), got {max_range!r}")
    if max_range is not None and max_range > MAX_COORDINATE:
        raise InputError(
            f"max_range {max_range!r} is beyond {sci(MAX_COORDINATE)} m, larger than any laser "
            "reaches; give the laser's maximum range in metres"
        )

    lines = read_lines(name)
    params, has_robotlaser, skipped = _scan_tags(name, lines)
    laser_tag = "ROBOTLASER1" if has_robotlaser else "FLASER"
    scans = _parse_lasers(name, lines, laser_tag)
    if not scans.lines:
        raise _no_lasers(name, lines, skipped)

    offset = np.array([params.get(p, 0.0) for p in _OFFSET_PARAMS])
    if pose_source is PoseSource.LOGGED:
        poses = np.array(scans.logged)
    else:
        poses = compose(np.array(scans.robot), offset)
    poses[:, 2] = wrap(poses[:, 2])
    keep = _subsample(poses, min_travel, min_rotation)

    kept = np.flatnonzero(keep)
    _warn_absurd_ranges(name, scans, kept)
    _warn_backwards(name, scans)
    if max_range is not None:
        flaser_max, max_range_source = max_range, "given (--max-range)"
    elif _MAX_RANGE_PARAM in params:
        flaser_max = params[_MAX_RANGE_PARAM]
        max_range_source = f"PARAM {_MAX_RANGE_PARAM}"
    elif laser_tag == "FLASER" and (
        inferred := infer_max_range(np.concatenate([scans.ranges[k] for k in kept]))
    ):
        flaser_max = inferred[0]
        max_range_source = (
            # At most MAX_PLAUSIBLE_RANGE (infer_max_range ignores beyond), so never 309 digits.
            f"inferred: {inferred[1]} readings piled at {flaser_max:.3f} m and above "
            "(no-returns, dropped); the log states no robot_front_laser_max"
        )
        _log.info("%s: maximum laser range %s", name, max_range_source)
    else:
        flaser_max = DEFAULT_MAX_RANGE
        max_range_source = (
            f"default {DEFAULT_MAX_RANGE:g} m (the log states none, and its largest readings do "
            "not pile up at one value)"
        )
    per_scan_max = np.array(scans.max_range)[kept]
    per_scan_max = np.where(np.isnan(per_scan_max), flaser_max, per_scan_max)
    if max_range is not None:
        per_scan_max[:] = max_range
    points, counts = _beams_to_points(
        [scans.ranges[k] for k in kept], [scans.beam_config[k] for k in kept], per_scan_max
    )
    if skipped:
        shown = ", ".join(f"{tag} x{count}" for tag, count in sorted(skipped.items()))
        _log.info("%s: lines skipped by tag: %s", name, shown)
    split = np.split(points, np.cumsum(counts)[:-1]) if len(kept) else []
    result = Map.from_poses_and_scans(
        poses[kept],
        split,
        timestamps=np.array(scans.stamps)[kept],
        config=config,
        name=_stem(name),
        source=name,
    )
    result.metadata.update(
        {
            "format": "carmen",
            "laser": laser_tag,
            "pose_source": pose_source.value,
            "pose_frame": "laser",
            "laser_offset": offset.tolist(),
            "max_range": max_range,
            "flaser_max_range": flaser_max,
            "max_range_source": max_range_source,
            "scans_in_log": len(scans.lines),
            "scan_lines": np.array(scans.lines, dtype=np.int64)[kept],
            "skipped_lines": dict(skipped),
        }
    )
    return result


def infer_max_range(ranges: NDArray[np.float64]) -> tuple[float, int] | None:
    """``(maximum range, readings at it)`` when the largest readings pile up at one value (the
    sensor's no-return readings), else None (the largest readings look like real returns).
    Readings that are NaN/inf, not positive, or beyond :data:`MAX_PLAUSIBLE_RANGE` are ignored."""
    with np.errstate(invalid="ignore"):
        r = ranges[np.isfinite(ranges) & (ranges > 0) & (ranges <= MAX_PLAUSIBLE_RANGE)]
    if r.size == 0:
        return None
    top = float(r.max())
    pile = r >= top - _PILE_WIDTH
    count = int(pile.sum())
    below = int(np.count_nonzero((r >= top - _PILE_WIDTH - _PILE_BASELINE) & ~pile))
    per_window = below * _PILE_WIDTH / _PILE_BASELINE
    # A third or more of all readings at the largest value is a scene (a robot facing one wall),
    # not a sensor limit.
    if count < _PILE_MIN or count < _PILE_RATIO * max(per_window, 1.0) or 3 * count >= r.size:
        return None
    return float(r[pile].min()), count


def _warn_absurd_ranges(name: str, scans: _Scans, kept: NDArray[np.intp]) -> None:
    """A warning for readings that are NaN/inf or beyond :data:`MAX_PLAUSIBLE_RANGE` (never
    points, and ignored when inferring the maximum range), with the first such line."""
    if kept.size == 0:
        return
    r = np.concatenate([scans.ranges[k] for k in kept])
    with np.errstate(invalid="ignore"):
        nonfinite = ~np.isfinite(r)
        absurd = np.isfinite(r) & (r > MAX_PLAUSIBLE_RANGE)
    bad = nonfinite | absurd
    if not bad.any():
        return
    owner = np.repeat(kept, [len(scans.ranges[k]) for k in kept])
    first = scans.lines[int(owner[int(np.argmax(bad))])]
    _log.warning(
        "%s:%d: %d readings are NaN/inf and %d beyond %g m (not a 2D laser's; the first is on "
        "this line); they are not points and are ignored when inferring the maximum range",
        name,
        first,
        int(nonfinite.sum()),
        int(absurd.sum()),
        MAX_PLAUSIBLE_RANGE,
    )


def _warn_backwards(name: str, scans: _Scans) -> None:
    """A warning, with the first line, when the laser timestamps go backwards (equal ones are
    fine: the Radish corrected logs write 0 everywhere)."""
    stamps = np.array(scans.stamps, dtype=np.float64)
    back = np.flatnonzero(np.diff(stamps) < 0)
    if back.size == 0:
        return
    k = int(back[0]) + 1
    _log.warning(
        "%s:%d: the timestamp goes backwards (%.6f s after %.6f s on line %d), at %d of %d "
        "scans; durations and speeds from it are wrong: check how the log was recorded or merged",
        name,
        scans.lines[k],
        stamps[k],
        stamps[k - 1],
        scans.lines[k - 1],
        back.size,
        len(stamps),
    )


def _stem(name: str) -> str:
    base = os.path.basename(name)
    for suffix in (".gz", ".bz2"):
        base = base.removesuffix(suffix)
    root, extension = os.path.splitext(base)
    return root if extension.lower() in (".clf", ".log") else base


def _subsample(
    poses: NDArray[np.float64], min_travel: float, min_rotation: float
) -> NDArray[np.bool_]:
    keep = np.ones(len(poses), dtype=bool)
    if min_travel <= 0 and min_rotation <= 0:
        return keep
    last = poses[0]
    for k in range(1, len(poses)):
        pose = poses[k]
        moved = math.hypot(pose[0] - last[0], pose[1] - last[1])
        turned = abs(wrap(float(pose[2] - last[2])))
        if (min_travel > 0 and moved >= min_travel) or (
            min_rotation > 0 and turned >= min_rotation
        ):
            last = pose
        else:
            keep[k] = False
    return keep


def _tag(line: str) -> str:
    head = line.split(None, 1)
    return head[0] if head else ""


def _scan_tags(name: str, lines: Sequence[str]) -> tuple[dict[str, float], bool, dict[str, int]]:
    """The laser PARAMs, whether any ROBOTLASER1 line exists, and counts of skipped tags."""
    params: dict[str, float] = {}
    tags: dict[str, int] = {}
    for number, line in enumerate(lines, 1):
        tag = _tag(line)
        if not tag or tag.startswith("#"):
            continue
        tags[tag] = tags.get(tag, 0) + 1
        if tag != "PARAM":
            continue
        tokens = line.split()
        if len(tokens) >= 3 and tokens[1] in _PARAM_LIMITS:
            value = _floats(
                name,
                number,
                tokens[2:3],
                (tokens[1],),
                "PARAM",
                limits=(_PARAM_LIMITS[tokens[1]],),
                strict=_needs_strict(line),
            )[0]
            if tokens[1] == _MAX_RANGE_PARAM and value <= 0:
                raise input_error(
                    name,
                    number,
                    f"{_MAX_RANGE_PARAM} is {tokens[2]}, not a positive range",
                    _FIX_LINE,
                )
            params[tokens[1]] = value
    has_robotlaser = "ROBOTLASER1" in tags
    laser = "ROBOTLASER1" if has_robotlaser else "FLASER"
    skipped = {t: c for t, c in tags.items() if t not in (laser, "PARAM")}
    return params, has_robotlaser, skipped


def _no_lasers(name: str, lines: Sequence[str], skipped: dict[str, int]) -> InputError:
    if not skipped:
        return input_error(
            name,
            None,
            "empty log (no CARMEN message lines)",
            "give a CARMEN log with FLASER or ROBOTLASER1 lines",
        )
    found = ", ".join(f"{tag} x{count}" for tag, count in sorted(skipped.items())[:10])
    return input_error(
        name,
        None,
        f"no laser lines (FLASER or ROBOTLASER1) in the log; found {found}",
        "a map needs laser scans: give a log recorded with the laser on",
    )


def _needs_strict(line: str) -> bool:
    """Whether a line's numbers must be checked one by one: numpy (like float()) reads non-ASCII
    digits and ``_`` separators, which a log holds only when damaged."""
    return not line.isascii() or "_" in line


def _bad_number(
    name: str, line: int, tokens: Sequence[str], names: Sequence[str], tag: str, first: int
) -> InputError:
    for k, token in enumerate(tokens):
        if not STRICT_FLOAT.fullmatch(token):
            return input_error(
                name,
                line,
                f"bad number {token!r} for {names[k]} (field {first + k} of {tag})",
                "write a decimal number such as 1.5 or -2e-3",
            )
    return input_error(name, line, f"unreadable numbers in {tag}", _FIX_LINE)  # pragma: no cover


def _floats(
    name: str,
    line: int,
    tokens: Sequence[str],
    names: Sequence[str],
    tag: str,
    first: int = 2,
    *,
    limits: Sequence[Limit | None] = (),
    strict: bool = False,
) -> NDArray[np.float64]:
    """Finite float64 values of ``tokens`` (fields ``first..`` of the line, tag = field 0), each
    within its entry of ``limits`` (None: any finite value); ``strict``: check each token's
    syntax (see :func:`_needs_strict`)."""
    try:
        if strict and not all(STRICT_FLOAT.fullmatch(t) for t in tokens):
            raise ValueError(tokens)
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        raise _bad_number(name, line, tokens, names, tag, first) from None
    bad = ~np.isfinite(values)
    if bad.any():
        k = int(np.argmax(bad))
        raise input_error(
            name,
            line,
            f"{names[k]} is {tokens[k]!r} (field {first + k} of {tag}): NaN/inf",
            "replace it with a finite number or delete the line",
        )
    for k, limit in enumerate(limits):
        if limit is not None and not abs(values[k]) <= limit.bound:
            raise limit_error(
                name, line, f"{names[k]} is {tokens[k]!r} (field {first + k} of {tag})", limit
            )
    return values


def _ranges(
    name: str, line: int, tokens: Sequence[str], tag: str, first: int, strict: bool
) -> NDArray[np.float64]:
    """Beam ranges; non-finite ones are allowed here (invalid beams, not points)."""
    try:
        if strict and not all(STRICT_FLOAT.fullmatch(t) for t in tokens):
            raise ValueError(tokens)
        return np.array(tokens, dtype=np.float64)
    except ValueError:
        names = [f"range {k + 1}" for k in range(len(tokens))]
        raise _bad_number(name, line, tokens, names, tag, first) from None


def _count(name: str, line: int, token: str, what: str, tag: str) -> int:
    value = parse_int(name, line, token, f"{what} of {tag}")
    if value < 0 or (what == "number of beams" and value == 0):
        raise input_error(name, line, f"{what} of {tag} is {value}", "it must be positive")
    return value


def _flaser_geometry(n: int) -> tuple[float, float]:
    """Start angle and spacing [rad] of an n-beam FLASER scan (FORMATS.md)."""
    spacing = math.pi / (n - 1) if n in (181, 361) else math.pi / n
    return -0.5 * math.pi, spacing


def _parse_lasers(name: str, lines: Sequence[str], laser_tag: str) -> _Scans:
    scans = _Scans([], [], [], [], [], [], [])
    for number, line in enumerate(lines, 1):
        if _tag(line) != laser_tag:
            continue
        tokens = line.split()
        strict = _needs_strict(line)
        if laser_tag == "FLASER":
            _parse_flaser(name, number, tokens, scans, strict)
        else:
            _parse_robotlaser(name, number, tokens, scans, strict)
    return scans


def _parse_flaser(name: str, number: int, tokens: list[str], scans: _Scans, strict: bool) -> None:
    # FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname
    # logger_timestamp (CARMEN logger header; x y theta is the laser pose, odom_* the robot's).
    if len(tokens) < 2:
        raise input_error(name, number, "FLASER without a number of beams", _FIX_LINE)
    n = _count(name, number, tokens[1], "number of beams", "FLASER")
    if len(tokens) != n + 11:
        raise input_error(
            name,
            number,
            f"FLASER with {n} beams needs {n + 10} fields after the tag (n, {n} ranges, x y theta "
            f"odom_x odom_y odom_theta, ipc_timestamp, ipc_hostname, logger_timestamp), "
            f"got {len(tokens) - 1}",
            "check the number of beams against the ranges, or delete the line",
        )
    ranges = _ranges(name, number, tokens[2 : 2 + n], "FLASER", 2, strict)
    tail = _floats(
        name,
        number,
        tokens[2 + n : 9 + n],
        _FLASER_TAIL,
        "FLASER",
        2 + n,
        limits=_FLASER_LIMITS,
        strict=strict,
    )
    start, step = _flaser_geometry(n)
    scans.lines.append(number)
    scans.ranges.append(ranges)
    scans.beam_config.append((n, start, step))
    scans.max_range.append(math.nan)
    scans.logged.append(tail[0:3])
    scans.robot.append(tail[3:6])
    scans.stamps.append(float(tail[6]))


_RL_HEADER = (
    "laser_type",
    "start_angle",
    "field_of_view",
    "angular_resolution",
    "maximum_range",
    "accuracy",
    "remission_mode",
)
_RL_TAIL = (
    "laser_pose_x",
    "laser_pose_y",
    "laser_pose_theta",
    "robot_pose_x",
    "robot_pose_y",
    "robot_pose_theta",
    "tv",
    "rv",
    "forward_safety_dist",
    "side_safety_dist",
    "turn_axis",
    "ipc_timestamp",
)


_RL_HEADER_LIMITS = (None, ANGLE_LIMIT, ANGLE_LIMIT, ANGLE_LIMIT, _RANGE_LIMIT, None, None)
_RL_TAIL_LIMITS = (*_POSE_LIMITS, *_POSE_LIMITS)


def _parse_robotlaser(
    name: str, number: int, tokens: list[str], scans: _Scans, strict: bool
) -> None:
    # Layout, as CARMEN's logger writes it (carmen_logwrite_write_robot_laser in
    # logtools/writelog.c) and reads it (carmen_string_to_robot_laser_message in readlog.c):
    # ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range accuracy
    # remission_mode num_readings [range_readings] num_remissions [remission_values]
    # laser_pose_x laser_pose_y laser_pose_theta robot_pose_x robot_pose_y robot_pose_theta
    # tv rv forward_safety_dist side_safety_dist turn_axis ipc_timestamp ipc_hostname
    # logger_timestamp
    usage = "check the line against the ROBOTLASER1 layout, or delete the line"
    if len(tokens) < 9:
        raise input_error(
            name, number, f"ROBOTLASER1 too short ({len(tokens) - 1} fields after the tag)", usage
        )
    header = _floats(
        name,
        number,
        tokens[1:8],
        _RL_HEADER,
        "ROBOTLASER1",
        1,
        limits=_RL_HEADER_LIMITS,
        strict=strict,
    )
    n = _count(name, number, tokens[8], "number of beams", "ROBOTLASER1")
    if len(tokens) < 10 + n:
        raise input_error(
            name, number, f"ROBOTLASER1 declares {n} beams but the line ends before them", usage
        )
    m = _count(name, number, tokens[9 + n], "num_remissions", "ROBOTLASER1")
    want = 10 + n + m + len(_RL_TAIL) + 2
    if len(tokens) != want:
        raise input_error(
            name,
            number,
            f"ROBOTLASER1 with {n} beams and {m} remissions needs {want - 1} fields after the tag, "
            f"got {len(tokens) - 1}",
            usage,
        )
    ranges = _ranges(name, number, tokens[9 : 9 + n], "ROBOTLASER1", 9, strict)
    first_tail = 10 + n + m
    tail = _floats(
        name,
        number,
        tokens[first_tail : first_tail + 12],
        _RL_TAIL,
        "ROBOTLASER1",
        first_tail,
        limits=_RL_TAIL_LIMITS,
        strict=strict,
    )
    if header[4] <= 0:
        raise input_error(
            name, number, f"ROBOTLASER1 maximum_range is {tokens[5]}", "it must be positive"
        )
    problem = beam_spacing_problem(n, float(header[3]), float(header[2]))
    if problem:
        raise input_error(
            name,
            number,
            f"ROBOTLASER1 angular_resolution {tokens[4]}, field_of_view {tokens[3]}: {problem}",
            "fix the header fields (angles in radians) or delete the line",
        )
    scans.lines.append(number)
    scans.ranges.append(ranges)
    scans.beam_config.append((n, float(header[1]), float(header[3])))
    scans.max_range.append(float(header[4]))
    scans.logged.append(tail[0:3])
    scans.robot.append(tail[3:6])
    scans.stamps.append(float(tail[11]))


def _beams_to_points(
    ranges: list[NDArray[np.float64]],
    configs: list[tuple[int, float, float]],
    max_ranges: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """All scans at once: ``(P, 2)`` laser-frame points and the number of points per scan."""
    if not ranges:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    cache: dict[tuple[int, float, float], NDArray[np.float64]] = {}
    angles: list[NDArray[np.float64]] = []
    for key in configs:
        if key not in cache:
            n, start, step = key
            cache[key] = start + step * np.arange(n, dtype=np.float64)
        angles.append(cache[key])
    r = np.concatenate(ranges)
    a = np.concatenate(angles)
    beams = np.array([len(x) for x in ranges], dtype=np.int64)
    limit = np.repeat(max_ranges, beams) - _MAX_RANGE_MARGIN
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0) & (r < limit)
    owner = np.repeat(np.arange(len(ranges)), beams)
    counts = np.bincount(owner[valid], minlength=len(ranges)).astype(np.int64)
    rv, av = r[valid], a[valid]
    return np.stack([rv * np.cos(av), rv * np.sin(av)], axis=1), counts
