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
from hitl_slam.io.textfile import (
    ANGLE_LIMIT,
    COORDINATE_LIMIT,
    STRICT_FLOAT,
    PathLike,
    input_error,
    limit_error,
    read_lines,
)

__all__ = ["Relations", "match_relations", "read_relations"]

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
    yaw = np.mod(table[:, 7] + math.pi, 2 * math.pi) - math.pi
    yaw = np.where(yaw <= -math.pi, yaw + 2 * math.pi, yaw)
    return Relations(
        t1=table[:, 0].copy(),
        t2=table[:, 1].copy(),
        relative=np.stack([table[:, 2], table[:, 3], yaw], axis=1),
        lines=np.array(numbers, dtype=np.int64),
        source=name,
    )


def match_relations(
    relations: Relations, timestamps: ArrayLike, tolerance: float = 1e-3
) -> NDArray[np.int64]:
    """``(K, 2)`` int64 indices into ``timestamps`` of the scans at ``t1`` and ``t2``.

    Each relation time is matched to the nearest timestamp (the earlier one on a tie).

    Raises:
        InputError: no timestamps, or a relation time farther than ``tolerance`` seconds from
            every timestamp (the first such relation is named, with its line).
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if stamps.size == 0 or not np.all(np.isfinite(stamps)):
        raise InputError(
            "the map has no usable timestamps to match relations to; "
            "load the map from the CARMEN log the relations were made for"
        )
    if not (math.isfinite(tolerance) and tolerance >= 0):
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
    if far.any():
        k = int(np.argmax(far))
        column = int(np.argmax(error[k] > tolerance))
        when, nearest_time = float(wanted[k, column]), float(ordered[nearest[k, column]])
        where = relations.source or "relations"
        raise input_error(
            where,
            int(relations.lines[k]),
            f"relation {k + 1}: no scan within {tolerance:g} s of t{column + 1} = "
            f"{when!r} (nearest scan time {nearest_time!r})",
            "use the relations made for this log, with the map read from that log "
            "without subsampling, or a larger tolerance",
        )
    return order[nearest].astype(np.int64)
