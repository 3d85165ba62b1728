"""Robot trajectories through a world: a route of waypoints driven at a constant step, straight
between waypoints and turning on circular arcs at them, heading along the path, optionally around
a closed route several times. Pure geometry; noise belongs to :mod:`hitl_slam.sim.odometry`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.geometry import wrap

__all__ = ["travel_distance", "waypoint_trajectory"]

FloatArray = NDArray[np.float64]


def _route(waypoints: FloatArray, closed: bool, laps: float) -> FloatArray:
    if closed:
        loop = waypoints
        if not np.array_equal(loop[0], loop[-1]):
            loop = np.vstack([loop, loop[:1]])
        reps = max(1, math.ceil(laps - 1e-9))
        return np.vstack([loop[0:1]] + [loop[1:]] * reps)
    return waypoints


def waypoint_trajectory(
    waypoints: FloatArray,
    step: float,
    *,
    turn_radius: float = 0.5,
    closed: bool = False,
    laps: float = 1.0,
) -> FloatArray:
    """Poses ``(N, 3)`` every ``step`` metres of arc length along the route through
    ``waypoints`` (K, 2), starting at the first one.

    At each inner waypoint the route turns on a circular arc of ``turn_radius`` [m] tangent to
    both legs (smaller where a leg is too short for it), so headings change smoothly. With
    ``closed`` the route returns to the first waypoint and is driven ``laps`` times (a fraction
    stops part way round); turns at the start between laps are rounded too.

    Raises:
        InputError: fewer than two distinct waypoints, a non-positive step or radius, a route
            that reverses on itself, or ``laps`` other than 1 on an open route.
    """
    wp = np.asarray(waypoints, dtype=np.float64).reshape(-1, 2)
    if not (math.isfinite(step) and step > 0):
        raise InputError(f"step must be a positive number of metres, got {step!r}")
    if not (math.isfinite(turn_radius) and turn_radius >= 0):
        raise InputError(f"turn_radius must be >= 0 m, got {turn_radius!r}")
    if not (math.isfinite(laps) and laps > 0) or (not closed and laps != 1.0):
        raise InputError("laps must be > 0, and other than 1 only on a closed route")
    route = _route(wp, closed, laps)
    keep = np.concatenate([[True], np.any(np.diff(route, axis=0) != 0, axis=1)])
    route = route[keep]
    if route.shape[0] < 2:
        raise InputError("a trajectory needs at least two distinct waypoints")
    legs = np.diff(route, axis=0)
    lengths = np.hypot(legs[:, 0], legs[:, 1])
    dirs = legs / lengths[:, None]
    headings = np.arctan2(dirs[:, 1], dirs[:, 0])
    # Each primitive: start point, start heading, length, curvature (0 on straight legs).
    starts: list[tuple[float, float]] = []
    h0: list[float] = []
    length: list[float] = []
    kappa: list[float] = []
    cursor = route[0].copy()
    for i in range(legs.shape[0]):
        end = route[i + 1].copy()
        tangent = 0.0
        turn = 0.0
        if i + 1 < legs.shape[0]:
            turn = wrap(float(headings[i + 1] - headings[i]))
            if abs(turn) > math.pi - 1e-6:
                raise InputError(f"the route reverses at waypoint {i + 1}; add a waypoint to turn")
            if abs(turn) > 1e-12 and turn_radius > 0:
                half = math.tan(0.5 * abs(turn))
                radius = min(turn_radius, 0.5 * min(lengths[i], lengths[i + 1]) / half)
                tangent = radius * half
        straight_end = end - tangent * dirs[i]
        run = float(np.hypot(*(straight_end - cursor)))
        if run > 1e-12:
            starts.append((float(cursor[0]), float(cursor[1])))
            h0.append(float(headings[i]))
            length.append(run)
            kappa.append(0.0)
        if tangent > 0:
            radius = tangent / math.tan(0.5 * abs(turn))
            starts.append((float(straight_end[0]), float(straight_end[1])))
            h0.append(float(headings[i]))
            length.append(radius * abs(turn))
            kappa.append(math.copysign(1.0 / radius, turn))
            cursor = end + tangent * dirs[i + 1]
        else:
            cursor = end
    cum = np.concatenate([[0.0], np.cumsum(length)])
    total = float(cum[-1])
    if closed and laps != math.ceil(laps - 1e-9):
        total *= laps / math.ceil(laps - 1e-9)
    s = np.arange(math.floor(total / step + 1e-9) + 1) * step
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(length) - 1)
    u = s - cum[k]
    p0, th0, kap = np.array(starts)[k], np.array(h0)[k], np.array(kappa)[k]
    th = th0 + kap * u
    curved = np.abs(kap) > 0
    safe = np.where(curved, kap, 1.0)
    dx = np.where(curved, (np.sin(th) - np.sin(th0)) / safe, u * np.cos(th0))
    dy = np.where(curved, (np.cos(th0) - np.cos(th)) / safe, u * np.sin(th0))
    return np.column_stack([p0[:, 0] + dx, p0[:, 1] + dy, wrap(th)])


def travel_distance(poses: FloatArray) -> float:
    """The length of the polyline through the positions of ``poses`` (N, 3) [m]."""
    d = np.diff(np.asarray(poses, dtype=np.float64)[:, :2], axis=0)
    return float(np.hypot(d[:, 0], d[:, 1]).sum())
