"""Interpreting a drawn correction (docs/ALGORITHM.md §3): EM finds the feature under each drawn
segment and the observations on it (in the Rust core), then the pair rules here (pose threshold,
one visit per segment, no shared poses, time order) turn them into
``h = <P_a, P_b, S_a, S_b, X_a, X_b, m>``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import DrawnCorrection, Interpretation, Segment
from hitl_slam.errors import CorrectionRejected, InputError
from hitl_slam.map import Map
from hitl_slam.passes import best_pass

__all__ = ["MIN_SEGMENT_LENGTH", "TOLERANCE_MIXING", "VISIT_GAP", "interpret"]

logger = logging.getLogger(__name__)

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
still climbs from near zero, and stopping there would leave every weight under 0.5."""


@dataclass
class _Selection:
    """What one drawn segment selected, narrowed step by step by the pair rules."""

    name: str
    drawn: NDArray[np.float64]  # (2, 2) as drawn
    fit: _core.EmFit
    rows: NDArray[np.int64]  # (K, 2) (pose, point index within that pose's scan)
    weights: NDArray[np.float64]  # (K,) EM responsibilities of those rows

    @property
    def poses(self) -> NDArray[np.int64]:
        return np.unique(self.rows[:, 0])

    def keep_poses(self, keep: NDArray[np.int64]) -> None:
        mask = np.isin(self.rows[:, 0], keep)
        self.rows, self.weights = self.rows[mask], self.weights[mask]


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


def _select(
    name: str,
    drawn: NDArray[np.float64],
    fit: _core.EmFit,
    offsets: NDArray[np.int64],
    min_points: int,
) -> _Selection:
    """S = candidates with w > 0.5, as (pose, point) rows, restricted to the poses that own at
    least ``min_points`` of them (T_p, the paper's outlier rejection)."""
    inlier = fit.weights > 0.5
    index = fit.candidates[inlier]
    # side="right" skips poses with empty scans (equal consecutive offsets).
    pose = np.searchsorted(offsets, index, side="right").astype(np.int64) - 1
    rows = np.stack([pose, index - offsets[pose]], axis=1).astype(np.int64)
    sel = _Selection(name, drawn, fit, rows, fit.weights[inlier])
    owners, counts = np.unique(pose, return_counts=True)
    sel.keep_poses(owners[counts >= min_points])
    return sel


def _why_empty(sel: _Selection, band: float, min_points: int) -> str:
    fit = sel.fit
    if fit.candidates.size == 0:
        return f"no map points within {band:.2f} m of segment {sel.name}"
    if fit.num_inliers == 0:
        return f"{fit.candidates.size} points near segment {sel.name}, none of them on one line"
    return (
        f"{fit.num_inliers} points on the line under segment {sel.name}, but no pose saw "
        f"{min_points} or more of them"
    )


def _one_visit(sel: _Selection, gap: int, notes: list[str]) -> None:
    """Keep the visit (run of pose indices with no gap over ``gap``) with the most points."""
    owners, counts = np.unique(sel.rows[:, 0], return_counts=True)
    starts = np.concatenate([[0], np.flatnonzero(np.diff(owners) > gap) + 1])
    if starts.size == 1:
        return
    per_visit = np.add.reduceat(counts, starts)
    visits = np.split(owners, starts[1:])
    best = int(np.argmax(per_visit))  # the earliest on a tie, so the rule is deterministic
    dropped = ", ".join(
        f"poses {_span(v)} ({int(c)} points)"
        for k, (v, c) in enumerate(zip(visits, per_visit, strict=True))
        if k != best
    )
    notes.append(
        f"segment {sel.name} covers {len(visits)} visits; kept poses {_span(visits[best])} "
        f"({int(per_visit[best])} points), dropped {dropped}"
    )
    sel.keep_poses(visits[best])


def _snap_note(sel: _Selection) -> str:
    snap = sel.fit.snap
    assert snap is not None
    clear = (
        "no other line near it"
        if not math.isfinite(snap.runner_up)
        else f"score {snap.score:.2f} against {snap.runner_up:.2f} for the next line"
    )
    return (
        f"segment {sel.name}: the nearest dense line has {snap.support} points; the drawing was "
        f"moved {snap.moved[0]:.2f} m and {snap.moved[1]:.2f} m onto it and turned "
        f"{math.degrees(snap.turn):.1f} deg ({clear})"
    )


@dataclass(frozen=True)
class _Visit:
    """One run of a selection's poses (no gap over ``visit_gap``): one pass of the robot."""

    poses: NDArray[np.int64]  # ascending
    points: int
    rms: float  # [m] RMS distance of its points to the drawn line

    def score(self, sigma_c: float) -> float:
        """The snapping score for a visit: support against the drawing's distance."""
        return math.log(self.points) - self.rms**2 / (2.0 * sigma_c**2)

    def before(self, other: _Visit) -> bool:
        return bool(self.poses[-1] < other.poses[0])


def _visits(sel: _Selection, map: Map, poses: NDArray[np.float64], gap: int) -> list[_Visit]:
    owners = np.unique(sel.rows[:, 0])
    starts = np.concatenate([[0], np.flatnonzero(np.diff(owners) > gap) + 1])
    world = map.observed_points(sel.rows, poses)
    p0, p1 = sel.drawn
    d = p1 - p0
    normal = np.array([-d[1], d[0]]) / float(np.hypot(*d))
    dist = (world - p0) @ normal
    out = []
    for run in np.split(owners, starts[1:]):
        mask = np.isin(sel.rows[:, 0], run)
        out.append(_Visit(run, int(mask.sum()), float(np.sqrt(np.mean(dist[mask] ** 2)))))
    return out


def _joint_visits(
    a: _Selection,
    b: _Selection,
    map: Map,
    poses: NDArray[np.float64],
    gap: int,
    sigma_c: float,
    notes: list[str],
) -> bool:
    """Chooses one visit per segment jointly: the pair of visits, one before the other in
    time, with the best summed score (support against distance to each drawing). Two segments
    on near copies of one wall, whose EM lines hold both copies, thus get the copy each was
    drawn on; with three or more copies, each segment keeps the one under it. False (nothing
    changed) when no two visits are apart in time; the caller then applies the single-segment
    rules and their refusals."""
    va, vb = _visits(a, map, poses, gap), _visits(b, map, poses, gap)
    best: tuple[float, _Visit, _Visit] | None = None
    for x in va:
        for y in vb:
            if not (x.before(y) or y.before(x)):
                continue
            total = x.score(sigma_c) + y.score(sigma_c)
            if best is None or total > best[0]:
                best = (total, x, y)
    if best is None:
        return False
    _, x, y = best
    for sel, visits, kept in ((a, va, x), (b, vb, y)):
        if len(visits) > 1:
            dropped = ", ".join(
                f"poses {_span(v.poses)} ({v.points} points, {v.rms:.2f} m)"
                for v in visits
                if v is not kept
            )
            notes.append(
                f"segment {sel.name} covers {len(visits)} visits; kept poses "
                f"{_span(kept.poses)} ({kept.points} points, {kept.rms:.2f} m from the "
                f"drawing), dropped {dropped}"
            )
        sel.keep_poses(kept.poses)
    return True


def _pair_rules(
    a: _Selection, b: _Selection, visit_gap: int, notes: list[str]
) -> tuple[_Selection, _Selection, NDArray[np.int64], NDArray[np.int64], bool]:
    """The design's pair rules (docs/ALGORITHM.md §3.5): refuse one set selected twice; keep one
    visit per segment (the one with most points); drop poses that see both; order the pair in
    time."""
    if np.array_equal(a.rows, b.rows):
        raise CorrectionRejected(
            f"segments a and b select the same observations ({a.rows.shape[0]} points "
            f"from poses {_span(a.poses)}); draw each segment on a different copy of the "
            "feature"
        )
    for s in (a, b):
        _one_visit(s, visit_gap, notes)
    xa, xb = a.poses, b.poses
    common = np.intersect1d(xa, xb)
    if common.size:
        if common.size in (xa.size, xb.size):
            inner = a if common.size == xa.size else b
            other = b if inner is a else a
            raise CorrectionRejected(
                f"segments a and b are seen from the same visit: every pose that sees segment "
                f"{inner.name} (poses {_span(inner.poses)}) also sees segment {other.name} "
                f"(poses {_span(other.poses)}), so one cannot be moved relative to the other; "
                "draw the two segments on copies of the feature seen at different times"
            )
        a.keep_poses(np.setdiff1d(xa, common))
        b.keep_poses(np.setdiff1d(xb, common))
        notes.append(f"removed {common.size} poses seen by both segments ({_span(common)})")
        xa, xb = a.poses, b.poses
    swapped = False
    if xa[-1] < xb[0]:
        pass
    elif xb[-1] < xa[0]:
        a, b, xa, xb, swapped = b, a, xb, xa, True
        notes.append("swapped a and b: the segment drawn second was observed first")
    else:
        raise CorrectionRejected(
            f"the observations interleave in time: segment a is seen from poses {_span(xa)}, "
            f"segment b from poses {_span(xb)}; draw each segment where the map shows one "
            "pass of the robot"
        )
    return a, b, xa, xb, swapped


MIN_EXTENT_M = 0.05
"""[m] Observations spanning less than this along their line give it no direction."""


def _refit(
    sel: _Selection, map: Map, poses: NDArray[np.float64], band: float
) -> tuple[tuple[float, float], tuple[float, float]]:
    """P = the weighted TLS line of the final S and its extent: after the pair rules S may be a
    subset of what EM fitted (one visit of several), and P must describe S."""
    world = map.observed_points(sel.rows, poses)
    _, _, extent = _core.line_fit(world, sel.weights, sel.drawn, band)
    return (
        (float(extent[0, 0]), float(extent[0, 1])),
        (float(extent[1, 0]), float(extent[1, 1])),
    )


def interpret(
    map: Map,
    poses: NDArray[np.float64],
    drawn: DrawnCorrection,
    config: Config = DEFAULT,
    *,
    visit_gap: int | None = None,
    nearest_visits: bool = False,
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
    seg_a, seg_b = _segment("a", drawn.a), _segment("b", drawn.b)
    sigma_h = config.sigma_h if drawn.sigma_h is None else drawn.sigma_h
    if not (math.isfinite(sigma_h) and sigma_h > 0):
        raise CorrectionRejected(f"sigma_h must be a positive number of metres, got {sigma_h!r}")
    band = config.candidate_band * sigma_h
    if not band > 0:
        raise InputError("config candidate_band must be > 0 (the band r_c would be empty)")

    search = config.search_band * sigma_h
    t_p = config.min_points_per_pose
    fit_a, fit_b = _core.em_fit_scans(
        poses,
        map.points,
        map.offsets,
        np.stack([seg_a, seg_b]),
        band=band,
        sigma_em=config.sigma_em,
        pi0=config.clutter_weight,
        tol_m=config.em_tolerance_m,
        tol_rad=config.em_tolerance_rad,
        tol_pi=TOLERANCE_MIXING,
        max_iterations=config.em_max_iterations,
        search_band=search if search > 0 else None,
        closeness=config.drawing_sigma * sigma_h,
        pointing=sigma_h,
        min_support=t_p,
    )
    a = _select("a", seg_a, fit_a, map.offsets, t_p)
    b = _select("b", seg_b, fit_b, map.offsets, t_p)
    notes = [_snap_note(s) for s in (a, b) if s.fit.snap is not None]
    notes += [
        f"segment {s.name}: EM {'converged' if s.fit.converged else 'stopped'} after "
        f"{s.fit.iterations} iterations, {s.fit.num_inliers} of {s.fit.candidates.size} "
        f"candidates on the line, {s.rows.shape[0]} from {s.poses.size} poses with >= {t_p} "
        f"(log-likelihood {s.fit.log_likelihood:.1f})"
        for s in (a, b)
    ]

    for s in (a, b):
        if s.rows.shape[0] == 0 and search > 0 and config.pass_by_pass:
            # A blur of passes that disagree a little each: find the one drawn on by itself.
            found = best_pass(
                map,
                poses,
                s.drawn,
                search=search,
                sigma_em=config.sigma_em,
                closeness=config.drawing_sigma * sigma_h,
                pointing=sigma_h,
                gap=visit_gap,
                min_points=t_p,
            )
            if found is not None:
                s.rows, s.weights = found.rows, np.ones(found.rows.shape[0])
                notes.append(found.note(s.name))
    empty = [s for s in (a, b) if s.rows.shape[0] == 0]
    if empty:
        which = " and ".join(s.name for s in empty)
        plural = "s" if len(empty) > 1 else ""
        details = "; ".join(_why_empty(s, band, t_p) for s in empty)
        raise CorrectionRejected(
            f"no observations under segment{plural} {which}; draw along a wall ({details})"
        )
    sigma_c = config.drawing_sigma * sigma_h
    # One segment drawn twice points at one copy, whatever the visits under it.
    same_drawing = np.allclose(seg_a, seg_b, rtol=0, atol=1e-9) or np.allclose(
        seg_a, seg_b[::-1], rtol=0, atol=1e-9
    )
    # The design's pair rules first (each segment's biggest visit); only where they refuse
    # (near copies in one EM line, a segment over several passes) are the visits chosen
    # jointly, which keeps every drawing the rules accept exactly as before.
    trial = list(notes)
    if nearest_visits and not same_drawing:
        # The passes nearest each drawing, even where the biggest ones would be kept.
        if _joint_visits(a, b, map, poses, visit_gap, sigma_c, notes):
            trial = notes
        a, b, xa, xb, swapped = _pair_rules(a, b, visit_gap, trial)
        notes = trial
    else:
        try:
            a2, b2 = dataclasses.replace(a), dataclasses.replace(b)
            a, b, xa, xb, swapped = _pair_rules(a2, b2, visit_gap, trial)
            notes = trial
        except CorrectionRejected:
            if same_drawing or not _joint_visits(a, b, map, poses, visit_gap, sigma_c, notes):
                raise
            a, b, xa, xb, swapped = _pair_rules(a, b, visit_gap, notes)

    for note in notes:
        logger.debug("interpret: %s", note)
    line_a, line_b = _refit(a, map, poses, band), _refit(b, map, poses, band)
    for name, (p, q) in (("a", line_a), ("b", line_b)):
        length = math.hypot(q[0] - p[0], q[1] - p[1])
        if not length >= MIN_EXTENT_M:
            raise CorrectionRejected(
                f"the observations under segment {name} cover {length:.3f} m of wall, too little "
                "to give it a direction; draw along a longer stretch of wall"
            )
    return Interpretation(
        mode=drawn.mode,
        line_a=line_a,
        line_b=line_b,
        s_a=a.rows,
        s_b=b.rows,
        x_a=xa,
        x_b=xb,
        swapped=swapped,
        iterations=(a.fit.iterations, b.fit.iterations),
        log_likelihood=(a.fit.log_likelihood, b.fit.log_likelihood),
        notes=tuple(notes),
    )
