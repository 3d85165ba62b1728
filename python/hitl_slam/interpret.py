"""Interpreting a drawn correction (docs/ALGORITHM.md §3): EM finds the feature under each drawn
segment and the observations on it, then the pair rules (pose threshold, one visit per segment,
no shared poses, time order) turn them into ``h = <P_a, P_b, S_a, S_b, X_a, X_b, m>``. Both run
in the Rust core (``correction/interpretation.rs``) in one call; this module checks the inputs
and puts a map's scans there (:func:`map_scans`; a session's workspace keeps them).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Correction, Interpretation, Mode, Segment
from hitl_slam.errors import CorrectionRejected, InputError
from hitl_slam.map import Map

__all__ = [
    "MIN_SEGMENT_LENGTH",
    "TOLERANCE_MIXING",
    "VISIT_GAP",
    "checked_drawing",
    "from_core",
    "interpret",
    "map_scans",
]

MIN_SEGMENT_LENGTH = 1e-6
"""[m] A shorter segment is a click, not a drawing: it has no direction."""

VISIT_GAP = DEFAULT.visit_gap
"""[poses] Selected poses farther apart than this in index start a new visit. While the robot
passes a wall, the poses that see it are consecutive except for short holes (a person walking by,
a glance into a doorway, the T_p filter at grazing angles); a return to the same wall comes after
the robot went elsewhere, typically hundreds of poses later. Ten poses is a few seconds of motion
at usual scan rates: longer than those holes and far shorter than a loop."""

TOLERANCE_MIXING = 1e-4
"""[1] EM also waits for the mixing weight to settle (besides the line tolerances of
docs/ALGORITHM.md §3.3): a drawing a few sigma_em beside its wall lets the line settle while pi
still climbs from near zero, and stopping there would leave every weight under 0.5. (The core's
``interpretation::TOLERANCE_MIXING``.)"""


def map_scans(map: Map) -> _core.MapScans:
    """``map``'s scans held in the core (robot-frame points, offsets, and the bounding circles
    of their blocks, so a drawing reads only the scans that reach it). A session keeps them in
    its :class:`~hitl_slam.workspace.Workspace`; this makes them anew."""
    return _core.MapScans(map.points, map.offsets)


def interpret(
    map: Map,
    poses: NDArray[np.float64],
    drawn: Correction,
    config: Config = DEFAULT,
    *,
    visit_gap: int | None = None,
    nearest_visits: bool = False,
    scans: _core.MapScans | None = None,
) -> Interpretation:
    """What the person meant by ``drawn`` on the map shown with ``poses`` (docs/ALGORITHM.md §3).

    For each segment: the points within ``r_c = candidate_band * sigma_h`` of it (from a grid
    index built once per call), EM from the drawn line, ``S`` = points with
    responsibility > 0.5 from poses that own at least ``min_points_per_pose`` of them. Then the
    pair rules: reject an empty set; keep one visit per segment (the one with most points,
    :data:`VISIT_GAP`); drop poses that see both; order the pair in time (``a`` is seen first,
    swapping if needed) or reject interleaved sets. Drawing direction does not matter.
    ``nearest_visits``: choose both segments' visits jointly, each the pass nearest its drawing
    (docs/ALGORITHM.md §I.2), even where the design's rules would keep the biggest.
    ``scans``: the map's scans held in the core (:func:`map_scans`, or a workspace's), if the
    caller has them.

    Raises:
        CorrectionRejected: the drawing cannot be turned into a correction (the reason says
            what to draw instead); nothing was changed.
        InputError: ``poses`` do not fit ``map``, the map has non-finite points, or ``config``
            or ``visit_gap`` is unusable.
    """
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    if poses.shape != map.poses.shape:
        raise InputError(
            f"poses must have shape {map.poses.shape} like the map's, got {poses.shape}"
        )
    if not np.all(np.isfinite(poses)):
        raise InputError("poses contain non-finite values; give finite poses")
    if visit_gap is None:
        visit_gap = config.visit_gap
    if visit_gap < 0:
        raise InputError(f"visit_gap must be a number of poses >= 0, got {visit_gap}")
    seg_a, seg_b, sigma_h = checked_drawing(drawn, config)
    t = (map_scans(map) if scans is None else scans).interpret(
        poses,
        seg_a,
        seg_b,
        drawn.mode.value,
        config,
        sigma_h=sigma_h,
        visit_gap=visit_gap,
        nearest_visits=nearest_visits,
    )
    return from_core(t)


def checked_drawing(
    drawn: Correction, config: Config
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """The two segments as (2, 2) arrays and the drawing's sigma_h, checked: a drawing that
    cannot be read raises CorrectionRejected (what to draw instead), a config that cannot
    interpret anything raises InputError."""
    seg_a, seg_b = _segment("a", drawn.a), _segment("b", drawn.b)
    sigma_h = config.sigma_h if drawn.sigma_h is None else drawn.sigma_h
    if not (math.isfinite(sigma_h) and sigma_h > 0):
        raise CorrectionRejected(f"sigma_h must be a positive number of metres, got {sigma_h!r}")
    if not config.candidate_band * sigma_h > 0:
        raise InputError("config candidate_band must be > 0 (the band r_c would be empty)")
    return seg_a, seg_b, float(sigma_h)


def _pair(v: NDArray[np.float64]) -> Segment:
    return ((float(v[0, 0]), float(v[0, 1])), (float(v[1, 0]), float(v[1, 1])))


def from_core(t: tuple[Any, ...]) -> Interpretation:
    """An :class:`Interpretation` from the core's tuple (``MapScans.interpret``,
    ``CorrectionEngine.apply``)."""
    mode, line_a, line_b, s_a, s_b, x_a, x_b, swapped, iterations, loglik, notes = t
    return Interpretation(
        mode=Mode(mode),
        line_a=_pair(line_a),
        line_b=_pair(line_b),
        s_a=s_a,
        s_b=s_b,
        x_a=x_a,
        x_b=x_b,
        swapped=bool(swapped),
        iterations=(int(iterations[0]), int(iterations[1])),
        log_likelihood=(float(loglik[0]), float(loglik[1])),
        notes=tuple(notes),
    )


def _segment(name: str, value: Segment) -> NDArray[np.float64]:
    try:
        seg = np.asarray(value, dtype=np.float64).reshape(2, 2)
    except (TypeError, ValueError):
        raise CorrectionRejected(
            f"segment {name} must be two [x, y] endpoints, got {value!r}"
        ) from None
    if not np.all(np.isfinite(seg)):
        raise CorrectionRejected(
            f"segment {name} has a non-finite coordinate ({value!r}); draw it again"
        )
    length = float(np.hypot(*(seg[1] - seg[0])))
    if length < MIN_SEGMENT_LENGTH:
        raise CorrectionRejected(
            f"segment {name} has zero length ({length:.1e} m); drag along the feature "
            "instead of clicking"
        )
    return seg


def _span(poses: NDArray[np.int64]) -> str:
    return f"{int(poses[0])}-{int(poses[-1])}" if poses.size else "none"
