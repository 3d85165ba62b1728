"""The transforms of a ROS bag (``/tf``, ``/tf_static``, a ``nav_msgs/Odometry`` topic) as a
tf2-like frame tree, for :func:`~hitl_slam.io.rosbag.read_rosbag`: the records as checked arrays,
their 3D-to-2D projection (a unit quaternion's yaw, SE(3) -> SE(2)), interpolation in time at the
scans' stamps, and lookups along the tree.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.geometry import between, compose_rows, invert, wrap
from hitl_slam.io.textfile import MAX_COORDINATE, sci

_STAMP_LIMIT = 2**62  # [ns] about 146 years: differences of two stamps stay within int64
_MIN_QUATERNION_NORM = 1e-6


@dataclass
class _Transforms:
    """TransformStamped-like records of one source: ``parent -> child`` at ``stamp``."""

    where: str  # e.g. "/tf" or "topic /odom", for messages
    stamps: list[int] = field(default_factory=list)
    parents: list[str] = field(default_factory=list)
    children: list[str] = field(default_factory=list)
    values: list[tuple[float, ...]] = field(default_factory=list)  # x y z qx qy qz qw

    def add(self, stamp: int, parent: str, child: str, values: tuple[float, ...]) -> None:
        self.stamps.append(stamp)
        self.parents.append(_frame_name(parent))
        self.children.append(_frame_name(child))
        self.values.append(values)


def _frame_name(name: str) -> str:
    """tf2 ignores a leading slash (ROS 1's ``/odom`` is ``odom``)."""
    return name.lstrip("/")


# ---------------------------------------------------------------------------------------------
# Transforms: checked arrays, the frame tree, lookups at the scans' stamps


@dataclass
class _Series:
    """One edge ``parent -> child``: its samples sorted by stamp (one per stamp, the last)."""

    parent: str
    stamps: NDArray[np.int64]
    se2: NDArray[np.float64]  # (S, 3)
    matrix: NDArray[np.float64]  # (4, 4): the first sample in 3D, for rigid mounts
    static: bool

    def at(self, when: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """SE(2) at ``when`` (linear in x, y; shorter arc in heading), and which stamps lie
        within the samples' span (a static edge holds at every time)."""
        if self.static:
            return np.repeat(self.se2[:1], len(when), axis=0), np.ones(len(when), dtype=bool)
        return _interpolate(self.stamps, self.se2, when)


def _interpolate(
    stamps: NDArray[np.int64], poses: NDArray[np.float64], when: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    last = len(stamps) - 1
    left = np.clip(np.searchsorted(stamps, when, side="right") - 1, 0, last)
    right = np.minimum(left + 1, last)
    valid = (when >= stamps[0]) & (when <= stamps[last])
    span = (stamps[right] - stamps[left]).astype(np.float64)
    offset = (when - stamps[left]).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(span > 0, offset / np.where(span > 0, span, 1.0), 0.0)
    fraction = np.where(valid, np.clip(fraction, 0.0, 1.0), 0.0)
    a, b = poses[left], poses[right]
    turn = wrap(b[:, 2] - a[:, 2])
    out = np.stack(
        [
            a[:, 0] + fraction * (b[:, 0] - a[:, 0]),
            a[:, 1] + fraction * (b[:, 1] - a[:, 1]),
            wrap(a[:, 2] + fraction * turn),
        ],
        axis=1,
    )
    return out, valid


def _checked(name: str, records: _Transforms) -> NDArray[np.float64]:
    """``(K, 7)`` ``x y z qx qy qz qw`` with unit quaternions, or an InputError for a value
    that is not finite, a translation beyond the readers' limit, or a zero quaternion."""
    values = np.array(records.values, dtype=np.float64).reshape(-1, 7)
    finite = np.asarray(np.isfinite(values).all(axis=1), dtype=bool)
    safe = np.where(finite[:, None], values, 0.0)
    norm = np.sqrt(np.sum(np.clip(safe[:, 3:], -1e6, 1e6) ** 2, axis=1))
    within = np.asarray(
        (np.abs(safe[:, :3]) <= MAX_COORDINATE).all(axis=1)
        & (np.abs(safe[:, 3:]) <= 1e6).all(axis=1),
        dtype=bool,
    )
    bad = ~finite | ~within | (norm < _MIN_QUATERNION_NORM)
    if bad.any():
        k = int(np.argmax(bad))
        shown = ", ".join(f"{v!r}" for v in records.values[k])
        raise InputError(
            f"{name}: {records.where}: the transform {records.parents[k] or '?'} -> "
            f"{records.children[k] or '?'} at {_seconds(records.stamps[k]):.9f} s is "
            f"({shown}): a NaN/inf, a translation beyond {sci(MAX_COORDINATE)} m or a quaternion "
            "of norm 0 or beyond 1e6; the bag is damaged: re-record it or drop that message"
        )
    values[:, 3:] /= norm[:, None]  # tf2 wants unit quaternions; a rounded one is normalized
    return values


def _yaw(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Heading of unit quaternions ``(K, 4)`` ``x y z w`` (the rotation's z-y-x yaw)."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _matrix(row: NDArray[np.float64]) -> NDArray[np.float64]:
    """4x4 homogeneous transform of ``x y z qx qy qz qw`` (unit quaternion)."""
    x, y, z, w = row[3:7]
    out = np.eye(4)
    out[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    out[:3, 3] = row[:3]
    return out


def _se2(rows: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.stack([rows[:, 0], rows[:, 1], _yaw(rows[:, 3:7])], axis=1)


def _series(name: str, records: _Transforms, static: bool) -> dict[tuple[str, str], _Series]:
    """The records grouped by edge ``(parent, child)``."""
    if not records.stamps:
        return {}
    values = _checked(name, records)
    stamps = np.array(records.stamps, dtype=object)
    out: dict[tuple[str, str], _Series] = {}
    edges: dict[tuple[str, str], list[int]] = {}
    for k, edge in enumerate(zip(records.parents, records.children, strict=True)):
        edges.setdefault(edge, []).append(k)
    for (parent, child), rows in edges.items():
        if static:
            rows = rows[-1:]  # a later static transform replaces an earlier one
        picked = np.array(rows, dtype=np.int64)
        times = _stamps_array(name, records.where, stamps[picked])
        order = np.argsort(times, kind="stable")
        times, chosen = times[order], values[picked[order]]
        last = np.append(times[1:] != times[:-1], True)  # one sample per stamp: the last
        out[(parent, child)] = _Series(
            parent=parent,
            stamps=times[last],
            se2=_se2(chosen[last]),
            matrix=_matrix(chosen[0]),
            static=static,
        )
    return out


def _stamps_array(name: str, where: str, stamps: NDArray[Any]) -> NDArray[np.int64]:
    for stamp in stamps:
        if not -_STAMP_LIMIT < int(stamp) < _STAMP_LIMIT:
            raise InputError(
                f"{name}: {where}: a stamp of {int(stamp)} ns, beyond the year 2116; the bag is "
                "damaged: re-record it"
            )
    return np.array([int(s) for s in stamps], dtype=np.int64)


def _seconds(ns: int) -> float:
    return ns // 1_000_000_000 + (ns % 1_000_000_000) / 1e9


class _Tree:
    """The frames of ``/tf`` and ``/tf_static``: each child's edge to its parent."""

    def __init__(
        self,
        name: str,
        dynamic: dict[tuple[str, str], _Series],
        static: dict[tuple[str, str], _Series],
    ) -> None:
        self.edges: dict[str, _Series] = {}
        for (parent, child), series in [*dynamic.items(), *static.items()]:
            known = self.edges.get(child)
            if known is not None and known.parent != parent:
                raise InputError(
                    f"{name}: frame {child!r} has two parents in the transforms, "
                    f"{known.parent!r} and {parent!r}; a tf tree gives each frame one parent: "
                    "drop one of the publishers"
                )
            self.edges[child] = series  # static after dynamic: /tf_static wins

    @property
    def frames(self) -> set[str]:
        return set(self.edges) | {s.parent for s in self.edges.values()}

    def ancestry(self, frame: str) -> list[str]:
        """``frame``, its parent, ... up to the root (a cycle stops the walk)."""
        out = [frame]
        seen = {frame}
        while (edge := self.edges.get(out[-1])) is not None and edge.parent not in seen:
            out.append(edge.parent)
            seen.add(edge.parent)
        return out

    def path(self, target: str, source: str) -> tuple[list[str], list[str]] | None:
        """The frames from ``source`` and from ``target`` up to their first common ancestor
        (excluded), or None when they are not connected."""
        up_source = self.ancestry(source)
        up_target = self.ancestry(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            return None
        return up_source[: up_source.index(common)], up_target[: up_target.index(common)]

    def connects(self, target: str, source: str) -> bool:
        return self.path(target, source) is not None

    def se2(
        self, target: str, source: str, when: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """``T_target_source`` in SE(2) at ``when``, and where every edge on the way is defined."""
        found = self.path(target, source)
        assert found is not None  # callers check connects() first
        valid = np.ones(len(when), dtype=bool)

        def up(frames: list[str]) -> NDArray[np.float64] | None:
            nonlocal valid
            total: NDArray[np.float64] | None = None
            for frame in frames:
                step, ok = self.edges[frame].at(when)
                valid &= ok
                total = step if total is None else compose_rows(step, total)
            return total

        from_source, from_target = up(found[0]), up(found[1])
        if from_target is None:
            result = from_source
        elif from_source is None:
            result = invert(from_target)
        else:
            result = between(from_target, from_source)
        if result is None:
            result = np.zeros((len(when), 3))
        return result, valid

    def rigid(self, target: str, source: str) -> NDArray[np.float64] | None:
        """``T_target_source`` in 3D from each edge's first sample (a rigid mount), or None."""
        found = self.path(target, source)
        if found is None:
            return None

        def up(frames: list[str]) -> NDArray[np.float64]:
            total = np.eye(4)
            for frame in frames:
                total = self.edges[frame].matrix @ total
            return total

        return np.linalg.inv(up(found[1])) @ up(found[0])

    def only_static(self, target: str, source: str) -> bool:
        found = self.path(target, source)
        return found is not None and all(self.edges[f].static for f in found[0] + found[1])
