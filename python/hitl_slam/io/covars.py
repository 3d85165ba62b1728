"""The original HitL-SLAM ``.covars`` format: a map name, a timestamp, then one line per observation
(pose, world point, world normal, pose covariance). Read into a :class:`Map` (points and normals in
the robot frame) and written back exactly, atomically.
"""

from __future__ import annotations

import logging
import math
import os

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.geometry import rotate, to_robot, wrap
from hitl_slam.io.atomic import atomic_writer
from hitl_slam.io.textfile import (
    ANGLE_LIMIT,
    COORDINATE_LIMIT,
    MAX_COORDINATE,
    STRICT_FLOAT,
    Limit,
    PathLike,
    first_beyond,
    input_error,
    limit_error,
    read_lines,
    sci,
)
from hitl_slam.map import Map

__all__ = ["COVARS_FIELDS", "MAX_COVARIANCE", "read_covars", "write_covars"]

_log = logging.getLogger(__name__)

COVARS_FIELDS = (
    "pose_x",
    "pose_y",
    "pose_theta",
    "obs_x",
    "obs_y",
    "normal_x",
    "normal_y",
    "C_xx",
    "C_xy",
    "C_xtheta",
    "C_yx",
    "C_yy",
    "C_ytheta",
    "C_thetax",
    "C_thetay",
    "C_thetatheta",
)
"""The 16 comma-separated numbers of an observation line, in order."""

MAX_COVARIANCE = MAX_COORDINATE**2
"""Largest |entry| of a pose covariance [m^2, m rad, rad^2]: a standard deviation of
:data:`~hitl_slam.io.textfile.MAX_COORDINATE`. Sums and inverses of such matrices stay far
inside float64's range."""

_COVARIANCE_LIMIT = Limit(
    MAX_COVARIANCE,
    f"a covariance entry beyond +/-{sci(MAX_COVARIANCE)} (a standard deviation beyond "
    f"{sci(MAX_COORDINATE)} m): a unit mistake or a damaged file",
    "write the covariance in metres and radians, or all zeros for an unknown one",
)
_NORMAL_LIMIT = Limit(
    MAX_COORDINATE,
    f"a normal component beyond +/-{sci(MAX_COORDINATE)} (normals are directions, about 1)",
    "write a unit normal, or 0, 0 for none",
)
_FIELD_LIMITS = (
    COORDINATE_LIMIT,
    COORDINATE_LIMIT,
    ANGLE_LIMIT,
    COORDINATE_LIMIT,
    COORDINATE_LIMIT,
    _NORMAL_LIMIT,
    _NORMAL_LIMIT,
    *[_COVARIANCE_LIMIT] * 9,
)
_BOUNDS = np.array([limit.bound for limit in _FIELD_LIMITS])
_USAGE = "16 comma-separated numbers: " + ", ".join(COVARS_FIELDS)


def read_covars(path: PathLike, config: Config = DEFAULT) -> Map:
    """Read a ``.covars`` file.

    Layout (FORMATS.md): line 1 the map name, line 2 a timestamp, then one observation per line.
    Consecutive lines with the same pose (bit-for-bit equal ``pose_x, pose_y, pose_theta``) are
    one pose; a pose whose only observation lies exactly at its own position has no scan. Blank
    lines are ignored. Points and normals are converted from the world frame to the robot frame
    of their pose (``s = R(theta)^T (p - t)``); non-zero normals are scaled to unit length and a
    zero normal means none (``map.normals`` is None when no observation has one).

    Covariance: the 3x3 pose covariance, row-major, taken from each pose's first line. As the
    original exporter wrote it, it is assumed to be in the robot frame of its pose, which is the
    frame of the chain edge leaving that pose, so it is used as is: edge (i, i+1) gets the
    information ``(C_i + C_{i+1})^-1`` when that is symmetric positive definite, otherwise the
    motion model of docs/ALGORITHM.md §1.3 (``map.information_source`` says which). An all-zero
    covariance means unknown, and both edges touching that pose use the motion model. The
    covariances as read are kept in ``map.metadata["pose_covariances"]`` (``(N, 3, 3)``, zeros =
    unknown) and the timestamp in ``map.metadata["covars_timestamp"]``, so :func:`write_covars`
    reproduces them.

    Raises:
        InputError: ``{path}:{line}: what; what to do`` for a missing name or timestamp, a line
            without 16 numbers, a bad or non-finite number, or a file without observations.
    """
    name = os.fspath(path)
    lines = read_lines(name)
    while lines and not lines[-1].strip():
        lines.pop()
    todo = "a .covars file starts with a map name line and a timestamp line, then observations"
    if not lines:
        raise input_error(name, None, "empty file", todo)
    map_name = lines[0].strip() or _stem(name)
    if len(lines) < 2 or not lines[1].strip():
        raise input_error(name, 2, "missing the timestamp line", todo)
    stamp_text = lines[1].strip()
    try:
        stamp = float(stamp_text) if STRICT_FLOAT.fullmatch(stamp_text) else math.nan
    except ValueError:  # pragma: no cover - the pattern admits only what float() reads
        stamp = math.nan
    if not math.isfinite(stamp):
        raise input_error(
            name, 2, f"line 2 must be the timestamp (a finite number), got {stamp_text!r}", todo
        )
    numbers = [k for k in range(2, len(lines)) if lines[k].strip()]
    if not numbers:
        raise input_error(name, None, "no observation lines after the name and timestamp", todo)
    rows = _parse_rows(name, lines, numbers)
    return _build(name, rows, map_name, stamp, config, np.asarray(numbers) + 1)


def _stem(name: str) -> str:
    base = os.path.basename(name)
    for suffix in (".gz", ".bz2"):
        base = base.removesuffix(suffix)
    return os.path.splitext(base)[0]


def _parse_rows(name: str, lines: list[str], numbers: list[int]) -> NDArray[np.float64]:
    """``(L, 16)`` values of the observation lines (0-based indices ``numbers`` into ``lines``)."""
    texts = [lines[k] for k in numbers]
    try:
        # numpy's C parser: strict (no empty fields, no "1 2", no "1_000"), one row per line;
        # but it reads non-ASCII digits ("\u0663", fullwidth), so such lines are checked alone.
        if not all(map(str.isascii, texts)):
            raise ValueError("non-ASCII")
        values = np.loadtxt(texts, delimiter=",", comments=None, dtype=np.float64, ndmin=2)
        if values.shape[1] != 16:
            raise ValueError(values.shape)
    except ValueError:
        # Something is wrong: find the first bad line and say what.
        for k, text in zip(numbers, texts, strict=True):
            _check_line(name, k + 1, text)
        raise input_error(name, None, "unreadable observation lines", _fix()) from None
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise input_error(
            name,
            numbers[row] + 1,
            f"{COVARS_FIELDS[col]} is {float(values[row, col])!r} (field {col + 1}): NaN/inf",
            "replace it with a finite number or delete the line",
        )
    beyond = first_beyond(values, _BOUNDS)
    if beyond is not None:
        row, col = beyond
        raise limit_error(
            name,
            numbers[row] + 1,
            f"{COVARS_FIELDS[col]} is {float(values[row, col])!r} (field {col + 1})",
            _FIELD_LIMITS[col],
        )
    return values


def _check_line(name: str, line: int, text: str) -> list[float]:
    tokens = [t.strip() for t in text.split(",")]
    if len(tokens) != 16:
        raise input_error(name, line, f"expected {_USAGE}; got {len(tokens)} fields", _fix())
    for k, token in enumerate(tokens):
        if not STRICT_FLOAT.fullmatch(token):
            raise input_error(
                name,
                line,
                f"bad number {token!r} for {COVARS_FIELDS[k]} (field {k + 1})",
                "write a decimal number such as 1.5 or -2e-3",
            )
    return [float(t) for t in tokens]


def _fix() -> str:
    return "fix the line or delete it"


def _build(
    name: str,
    rows: NDArray[np.float64],
    map_name: str,
    stamp: float,
    config: Config,
    line_numbers: NDArray[np.int64] | None = None,
) -> Map:
    pose_cols = rows[:, :3]
    starts = np.flatnonzero(
        np.concatenate([[True], np.any(pose_cols[1:] != pose_cols[:-1], axis=1)])
    )
    n = len(starts)
    counts = np.diff(np.append(starts, len(rows)))
    poses = pose_cols[starts].copy()
    covariances = rows[starts, 7:16].reshape(n, 3, 3).copy()

    owner = np.repeat(np.arange(n), counts)
    points = to_robot(pose_cols, rows[:, 3:5])
    normals = rotate(-pose_cols[:, 2], rows[:, 5:7])
    length = np.hypot(normals[:, 0], normals[:, 1])
    has_normal = length > 0
    normals[has_normal] /= length[has_normal, None]

    # A pose with one observation exactly at its own position has no scan.
    lone = counts == 1
    at_pose = (rows[starts, 3] == rows[starts, 0]) & (rows[starts, 4] == rows[starts, 1])
    empty = lone & at_pose
    keep = ~empty[owner]
    counts = np.where(empty, 0, counts)
    points, normals = points[keep], normals[keep]
    has_normal = has_normal[keep]

    split_at = np.cumsum(counts)[:-1]
    scans = np.split(points, split_at)
    normal_list = np.split(normals, split_at) if has_normal.any() else None

    poses[:, 2] = wrap(poses[:, 2])
    known = np.any(covariances != 0, axis=(1, 2))
    usable = None
    if known.any():
        usable = covariances.copy()
        usable[~known] = np.nan  # unknown: both neighbouring edges fall back to the motion model
    result = Map.from_poses_and_scans(
        poses,
        scans,
        covariances=usable,
        normals=normal_list,
        config=config,
        name=map_name,
        source=name,
    )
    result.metadata.update(
        {
            "format": "covars",
            "covars_timestamp": stamp,
            "pose_covariances": covariances,
        }
    )
    if usable is not None:
        _warn_bad_covariances(name, covariances, known, starts, line_numbers)
        fallback = int(np.count_nonzero(result.information_source != 0))
        if fallback:
            _log.info(
                "%s: %d of %d edges use the motion model (unknown or non-SPD covariance)",
                name,
                fallback,
                len(result.information_source),
            )
    return result


def _warn_bad_covariances(
    name: str,
    covariances: NDArray[np.float64],
    known: NDArray[np.bool_],
    starts: NDArray[np.intp],
    line_numbers: NDArray[np.int64] | None,
) -> None:
    """A warning (with the first such pose's line) for given covariances that are not
    symmetric positive definite: their edges silently fall back to the motion model otherwise,
    and the file is probably damaged or written in another convention."""
    symmetric = np.all(
        np.abs(covariances - covariances.transpose(0, 2, 1))
        <= 1e-9 * np.maximum(1.0, np.abs(covariances).max(axis=(1, 2), initial=0.0))[:, None, None],
        axis=(1, 2),
    )
    sym = 0.5 * (covariances + covariances.transpose(0, 2, 1))
    positive = np.linalg.eigvalsh(sym).min(axis=1) > 0
    bad = np.flatnonzero(known & ~(symmetric & positive))
    if bad.size == 0:
        return
    first = int(bad[0])
    where = f"{name}:{int(line_numbers[starts[first]])}" if line_numbers is not None else name
    _log.warning(
        "%s: the covariance of %d of %d poses is not symmetric positive definite (first: pose "
        "%d, C_xx = %.6g); the edges next to them use the motion model instead: check how the "
        "file was written (all zeros means unknown)",
        where,
        bad.size,
        len(covariances),
        first + 1,
        float(covariances[first, 0, 0]),
    )


def write_covars(map: Map, poses: ArrayLike, path: PathLike) -> None:
    """Write ``map`` with ``poses`` (``(N, 3)``) as a ``.covars`` file, atomically.

    Line 1 is ``map.name``, line 2 ``map.metadata["covars_timestamp"]`` (else the first pose
    timestamp, else 0). Every point becomes a line with its pose, its world position under
    ``poses`` and its world normal (zeros when it has none); a pose without points becomes one
    line observing its own position. Covariances come from ``map.metadata["pose_covariances"]``
    when it is an ``(N, 3, 3)`` array, else zeros (unknown). Floats are written with Python's
    ``repr`` (the shortest text that reads back to the same double). Since the format has no pose
    ids, a pose exactly equal to the one before it would merge with it on reading; such a pose is
    written with its theta moved by one ulp so the file reads back with the same number of poses.

    Raises:
        InputError: ``poses`` of the wrong shape or not finite, or values :func:`read_covars`
            would refuse (beyond its limits; nothing is written then).
    """
    name = os.fspath(path)
    out_poses = map.checked_poses(poses)
    n = map.num_poses
    covariances = map.metadata.get("pose_covariances")
    cov = np.zeros((n, 9))
    if isinstance(covariances, np.ndarray) and covariances.shape == (n, 3, 3):
        cov = covariances.reshape(n, 9).astype(np.float64)
    stamp = map.metadata.get("covars_timestamp")
    if not isinstance(stamp, float | int) or not math.isfinite(stamp):
        stamp = float(map.timestamps[0]) if map.timestamps is not None else 0.0
    world = map.world_points(out_poses)
    normals = np.zeros_like(world) if map.normals is None else map.normals
    world_normals = rotate(out_poses[map.pose_of_point(), 2], normals)
    written = _distinct_consecutive(out_poses)
    _check_writable(name, written, world, world_normals, cov)
    title = " ".join(map.name.split()) or "map"
    point_rows = np.hstack([world, world_normals]).tolist()
    offsets = map.offsets.tolist()
    with atomic_writer(name) as f:
        f.write(f"{title}\n{float(stamp)!r}\n")
        for i, (pose, cov_row) in enumerate(zip(written.tolist(), cov.tolist(), strict=True)):
            head = ", ".join(_reprs(pose)) + ", "
            tail = ", " + ", ".join(_reprs(cov_row)) + "\n"
            start, stop = offsets[i], offsets[i + 1]
            if start == stop:
                f.write(f"{head}{pose[0]!r}, {pose[1]!r}, 0.0, 0.0{tail}")
                continue
            f.write(
                "".join(
                    f"{head}{x!r}, {y!r}, {nx!r}, {ny!r}{tail}"
                    for x, y, nx, ny in point_rows[start:stop]
                )
            )


def _check_writable(
    name: str,
    poses: NDArray[np.float64],
    world: NDArray[np.float64],
    normals: NDArray[np.float64],
    cov: NDArray[np.float64],
) -> None:
    """Refuse values :func:`read_covars` would refuse, so that what is written reads back."""
    for label, array, columns in (
        ("pose", poses, (0, 1, 2)),
        ("observation", world, (3, 4)),
        ("normal", normals, (5, 6)),
        ("covariance", cov, tuple(range(7, 16))),
    ):
        beyond = first_beyond(array, _BOUNDS[list(columns)])
        if beyond is not None:
            row, col = beyond
            field = columns[col]
            raise InputError(
                f"{name}: cannot write a file hitl-slam could not read back: {label} {row} has "
                f"{COVARS_FIELDS[field]} = {float(array[row, col])!r}, "
                f"{_FIELD_LIMITS[field].what}; bring the values within the limit before saving"
            )


def _reprs(values: list[float]) -> list[str]:
    return [repr(v) for v in values]


def _distinct_consecutive(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    out = poses.copy()
    for i in range(1, len(out)):
        while np.array_equal(out[i], out[i - 1]):
            out[i, 2] = np.nextafter(out[i, 2], np.inf)
    return out
