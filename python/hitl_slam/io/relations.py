"""Ground-truth relations (Kuemmerle et al. 2009, "On measuring the accuracy of SLAM algorithms"):
``t1 t2 dx dy dz roll pitch yaw`` per line, the pose of the scan at ipc time t2 in the frame of the
scan at t1. Read them, and match their timestamps to the scans of a map.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam.errors import InputError
from hitl_slam.geometry import wrap
from hitl_slam.io.textfile import (
    ANGLE_LIMIT,
    COORDINATE_LIMIT,
    STRICT_FLOAT,
    PathLike,
    input_error,
    limit_error,
    read_lines,
)

__all__ = ["RelationMatch", "Relations", "match_relations", "nearest_scans", "read_relations"]

_FIELDS = ("t1", "t2", "dx", "dy", "dz", "roll", "pitch", "yaw")
# dx, dy, dz in metres, the angles in radians; the timestamps only need to be finite.
_LIMITS = (None, None, *[COORDINATE_LIMIT] * 3, *[ANGLE_LIMIT] * 3)


@dataclass(frozen=True, eq=False)
class Relations:
    """Relative poses between scans named by their timestamps.

    Attributes:
        t1, t2: ``(K,)`` ipc timestamps [s] of the two scans.
        relative: ``(K, 3)`` pose ``(dx, dy, yaw)`` of the scan at t2 in the frame of the scan at
            t1 (yaw wrapped to (-pi, pi]; dz, roll and pitch of the 3D form are dropped).
        lines: ``(K,)`` int64 line of each relation in ``source``.
        source: the file read, if any.
    """

    t1: NDArray[np.float64]
    t2: NDArray[np.float64]
    relative: NDArray[np.float64]
    lines: NDArray[np.int64]
    source: str | None = None

    def __len__(self) -> int:
        return int(self.t1.shape[0])


def read_relations(path: PathLike) -> Relations:
    """Read a ``.relations`` file (``.gz``/``.bz2`` too); blank and ``#`` lines are ignored.

    Raises:
        InputError: ``{path}:{line}: what; what to do`` for a line without 8 numbers, a bad or
            non-finite number, a displacement beyond +/-1e9 m or an angle beyond +/-1e6 rad (the
            readers' limits), or a file without relations.
    """
    name = os.fspath(path)
    rows: list[list[float]] = []
    numbers: list[int] = []
    for number, line in enumerate(read_lines(name), 1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) != len(_FIELDS):
            raise input_error(
                name,
                number,
                f"expected 8 numbers ({' '.join(_FIELDS)}), got {len(tokens)}",
                "fix the line or delete it",
            )
        values: list[float] = []
        for k, token in enumerate(tokens):
            try:
                value = float(token) if STRICT_FLOAT.fullmatch(token) else math.nan
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise input_error(
                    name,
                    number,
                    f"bad number {token!r} for {_FIELDS[k]} (field {k + 1})",
                    "write a finite decimal number such as 1.5 or -2e-3",
                )
            limit = _LIMITS[k]
            if limit is not None and not abs(value) <= limit.bound:
                raise limit_error(name, number, f"{_FIELDS[k]} is {token!r} (field {k + 1})", limit)
            values.append(value)
        rows.append(values)
        numbers.append(number)
    if not rows:
        raise input_error(
            name, None, "no relations in the file", "give a file of 't1 t2 dx dy dz roll pitch yaw'"
        )
    table = np.array(rows)
    yaw = wrap(table[:, 7])
    return Relations(
        t1=table[:, 0].copy(),
        t2=table[:, 1].copy(),
        relative=np.stack([table[:, 2], table[:, 3], yaw], axis=1),
        lines=np.array(numbers, dtype=np.int64),
        source=name,
    )


@dataclass(frozen=True, eq=False)
class RelationMatch:
    """Relations matched to the scans nearest their timestamps.

    Attributes:
        pairs: ``(M, 2)`` int64 indices into the timestamps of the scans at ``t1`` and ``t2`` of
            each matched relation.
        rows: ``(M,)`` int64 indices into the relations of the matched ones, in order.
        skipped: ``(K - M,)`` int64 indices of the relations with a timestamp farther than
            ``tolerance`` from every scan.
        tolerance: [s] the tolerance used.
    """

    pairs: NDArray[np.int64]
    rows: NDArray[np.int64]
    skipped: NDArray[np.int64]
    tolerance: float


def nearest_scans(
    relations: Relations, timestamps: ArrayLike, tolerance: float = 1e-3
) -> RelationMatch:
    """Match each relation's two times to the nearest timestamp (the earlier one on a tie); a
    relation with a time farther than ``tolerance`` seconds from every timestamp is skipped (a
    log cut short, or scans dropped). The timestamps need not be sorted.

    Raises:
        InputError: no usable timestamps, a bad tolerance, or no relation matched (the first one
            is named, with its line and the nearest scan time).
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if stamps.size == 0 or not np.all(np.isfinite(stamps)):
        raise InputError(
            "the map has no usable timestamps to match relations to; "
            "load the map from the CARMEN log the relations were made for"
        )
    if not (isinstance(tolerance, int | float) and math.isfinite(tolerance) and tolerance >= 0):
        raise InputError(f"tolerance must be a finite number >= 0 (seconds), got {tolerance!r}")
    order = np.argsort(stamps, kind="stable")
    ordered = stamps[order]
    wanted = np.stack([relations.t1, relations.t2], axis=1)
    right = np.clip(np.searchsorted(ordered, wanted), 1, len(ordered) - 1)
    left = right - 1
    if len(ordered) == 1:
        right = left = np.zeros_like(right)
    pick_left = np.abs(wanted - ordered[left]) <= np.abs(ordered[right] - wanted)
    nearest = np.where(pick_left, left, right)
    error = np.abs(ordered[nearest] - wanted)
    far = np.any(error > tolerance, axis=1)
    if far.all():
        k = 0
        column = int(np.argmax(error[k] > tolerance))
        when, nearest_time = float(wanted[k, column]), float(ordered[nearest[k, column]])
        others = "" if len(relations) == 1 else f": none of the {len(relations)} relations fits"
        raise input_error(
            relations.source or "relations",
            int(relations.lines[k]),
            f"relation 1: no scan within {tolerance:g} s of t{column + 1} = {when!r} (nearest "
            f"scan time {nearest_time!r}){others}",
            "use the relations made for this log, with the map read from that log "
            "without subsampling, or a larger tolerance (--tolerance) for a re-stamped log",
        )
    return RelationMatch(
        pairs=order[nearest[~far]].astype(np.int64),
        rows=np.flatnonzero(~far).astype(np.int64),
        skipped=np.flatnonzero(far).astype(np.int64),
        tolerance=float(tolerance),
    )


def match_relations(
    relations: Relations, timestamps: ArrayLike, tolerance: float = 1e-3
) -> NDArray[np.int64]:
    """``(K, 2)`` int64 indices into ``timestamps`` of the scans at ``t1`` and ``t2``: every
    relation must match (:func:`nearest_scans` skips those that do not).

    Each relation time is matched to the nearest timestamp (the earlier one on a tie).

    Raises:
        InputError: no timestamps, or a relation time farther than ``tolerance`` seconds from
            every timestamp (the first such relation is named, with its line).
    """
    match = nearest_scans(relations, timestamps, tolerance)
    if match.skipped.size:
        stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        k = int(match.skipped[0])
        wanted = (float(relations.t1[k]), float(relations.t2[k]))
        gaps = [float(np.min(np.abs(stamps - t))) for t in wanted]
        column = 0 if gaps[0] > tolerance else 1
        nearest_time = float(stamps[np.argmin(np.abs(stamps - wanted[column]))])
        raise input_error(
            relations.source or "relations",
            int(relations.lines[k]),
            f"relation {k + 1}: no scan within {tolerance:g} s of t{column + 1} = "
            f"{wanted[column]!r} (nearest scan time {nearest_time!r})",
            "use the relations made for this log, with the map read from that log "
            "without subsampling, or a larger tolerance",
        )
    return match.pairs
