"""One human correction end to end (the paper's Fig. 3, block 2): interpret the drawing,
move the later part of the map rigidly (explicit correction), close the gap along the chain
(back-propagation), then solve poses and line parameters jointly with every active correction.

Inputs are never modified; a drawing that cannot be interpreted raises CorrectionRejected.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from statistics import NormalDist
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import DrawnCorrection, Interpretation, Mode
from hitl_slam.errors import CorrectionRejected
from hitl_slam.geometry import chain_steps, compose, fit_line, wrap
from hitl_slam.map import Map, motion_model_information
from hitl_slam.solve import robust_pairs

__all__ = [
    "CorrectionResult",
    "apply_correction",
    "chain_variances",
    "correction_engine",
    "engine_lock",
    "explicit_and_backpropagate",
    "solve_all",
]

FloatArray = NDArray[np.float64]
_T = TypeVar("_T")

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CorrectionResult:
    """The map after one correction, and how it got there."""

    poses: FloatArray
    interpretation: Interpretation
    lines: FloatArray  # (2K, 2) (phi, rho) of every active correction's two lines, in order
    transform: FloatArray  # the explicit correction's rigid transform (x, y, theta)
    iterations: int
    initial_chi2: float
    final_chi2: float
    termination: str
    time_s: float
    time_interpret_s: float
    time_solve_s: float


def chain_variances(map: Map, poses: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Rotational and isotropic translational variance of each chain edge k -> k+1 (N-1,),
    from the map's own edge information, or the motion model where the chain has no edge.

    With ``poses`` (the map as displayed), a step whose turn there differs from its edge's
    measurement (a step the odometry check re-measured from the scans, or one an earlier
    correction already bent) has its rotational variance widened by the squared difference:
    how far the displayed step may be from the truth, which is what back-propagation shares
    the error by."""
    chain = _chain_of(map)
    rot = chain.rot.copy()
    if poses is not None and chain.steps.size:
        shown = chain_steps(np.asarray(poses, dtype=np.float64))[chain.steps, 2]
        rot[chain.steps] += wrap(shown - chain.turns) ** 2
    return rot, chain.trans.copy()


@dataclass(frozen=True)
class _Chain:
    """What back-propagation needs of a map's chain, computed once per map object."""

    rot: FloatArray  # (N-1,) rotational variance of each step k -> k+1
    trans: FloatArray  # (N-1,) isotropic translational variance
    steps: NDArray[np.int64]  # the steps that have a chain edge
    turns: FloatArray  # their edges' measured turns, in the k -> k+1 direction


_CHAINS: dict[int, tuple[weakref.ref[Map], _Chain]] = {}


def _chain_of(map: Map) -> _Chain:
    key = id(map)
    hit = _CHAINS.get(key)
    if hit is not None and hit[0]() is map:
        return hit[1]
    z = chain_steps(map.poses)
    cov = np.linalg.inv(motion_model_information(z, DEFAULT))
    e = map.edges
    forward = e[:, 1] == e[:, 0] + 1
    backward = e[:, 0] == e[:, 1] + 1
    on_chain = forward | backward
    steps = np.where(forward, e[:, 0], e[:, 1])[on_chain].astype(np.int64)
    turns = np.where(forward, 1.0, -1.0)[on_chain] * map.measurements[on_chain, 2]
    if steps.size:
        cov[steps] = np.linalg.inv(map.information[on_chain])
    chain = _Chain(
        rot=np.ascontiguousarray(cov[:, 2, 2]),
        trans=np.ascontiguousarray(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
        steps=steps,
        turns=np.ascontiguousarray(turns),
    )
    _CHAINS[key] = (weakref.ref(map, partial(_forget, _CHAINS, key)), chain)
    return chain


def _forget(cache: dict[int, _T], key: int, _ref: object) -> None:
    cache.pop(key, None)


def _observations(map: Map, rows: NDArray[np.int64]) -> tuple[NDArray[np.int64], FloatArray]:
    poses = np.ascontiguousarray(rows[:, 0], dtype=np.int64)
    return poses, np.ascontiguousarray(map.points[map.point_rows(rows)])


def correction_engine(map: Map) -> _core.CorrectionEngine:
    """The correction engine of ``map``: its relative-pose factors, held once per map object,
    with the symbolic analyses of the structures it solved recently (undo, redo and the guards'
    second solve of one drawing return to structures seen a moment ago). One call at a time:
    use it under :func:`engine_lock` (the engine releases the GIL while it solves, and a second
    thread entering it would get "Already borrowed")."""
    return _engine_entry(map)[1]


def engine_lock(map: Map) -> threading.Lock:
    """The lock that serializes calls into ``map``'s correction engine."""
    return _engine_entry(map)[2]


_Entry = tuple[weakref.ref[Map], _core.CorrectionEngine, threading.Lock]
_ENGINES: dict[int, _Entry] = {}
_ENGINES_LOCK = threading.Lock()


def _engine_entry(map: Map) -> _Entry:
    key = id(map)
    with _ENGINES_LOCK:
        hit = _ENGINES.get(key)
        if hit is not None and hit[0]() is map:
            return hit
        engine = _core.CorrectionEngine(
            map.num_poses, map.edges, map.measurements, map.information, map.anchor
        )
        entry = (weakref.ref(map, partial(_forget, _ENGINES, key)), engine, threading.Lock())
        _ENGINES[key] = entry
        return entry


def solve_all(
    map: Map,
    active: Sequence[Interpretation],
    config: Config = DEFAULT,
    start: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, _core.SolveReport]:
    """Joint optimization (docs/ALGORITHM.md §4.3) of poses and the lines of every correction in
    ``active``, from ``start`` (default: the map's poses), over the map's ORIGINAL relative-pose
    factors. Each line starts at the total-least-squares fit of its observations at ``start``."""
    x0 = np.ascontiguousarray(map.poses if start is None else start, dtype=np.float64)
    corrections = [
        (h.mode.value, *_observations(map, h.s_a), *_observations(map, h.s_b)) for h in active
    ]
    _, engine, lock = _engine_entry(map)
    with lock:
        return engine.solve(
            x0,
            corrections,
            sigma_f=config.sigma_f,
            k1=config.k1,
            k2=config.k2,
            average_points=config.average_points,
            max_iterations=config.max_iterations,
            relative_tolerance=config.relative_tolerance,
            absolute_tolerance=config.absolute_tolerance,
            robust=robust_pairs(config.robust),
            # The start is the explicit correction and its back-propagation: a trust region
            # stays in its basin. The watchdog's Gauss-Newton jumps (for starts off by radians)
            # found other, lower-cost basins here that fit the drawings worse (Freiburg 079 in
            # the evaluation: mean angle error 1.75 -> 2.75 deg with it).
            watchdog_steps=0,
        )


def explicit_and_backpropagate(
    map: Map, poses: FloatArray, h: Interpretation
) -> tuple[FloatArray, FloatArray]:
    """docs/ALGORITHM.md §4.1 then §4.2: the rigid move of every pose from ``min(X_b)`` on, and
    the chain from ``max(X_a)`` made to meet it. Returns (new poses, the transform)."""
    transform = _core.explicit_transform(
        h.mode.value, np.asarray(h.line_a, dtype=np.float64), np.asarray(h.line_b, dtype=np.float64)
    )
    first = int(h.x_b.min())
    moved = poses.copy()
    moved[first:] = compose(transform, poses[first:])
    last_a = int(h.x_a.max())
    if first > last_a + 1:
        rot, trans = chain_variances(map, poses)
        moved = _core.backpropagate(moved, poses, last_a, first, rot, trans)
    return moved, transform


def _graph_chi2(map: Map, *poses: FloatArray) -> list[float]:
    """chi2 of the map's relative-pose factors alone (the robot's measurements) at each of
    ``poses`` (one graph built for all)."""
    _, engine, lock = _engine_entry(map)
    with lock:
        return [float(engine.base_chi2(np.ascontiguousarray(p, dtype=np.float64))) for p in poses]


def _stretch(map: Map, poses: FloatArray, rows: NDArray[np.int64]) -> float:
    """[m] Length of the stretch of wall the observations ``rows`` cover: the 2nd to 98th
    percentile of their positions along their own line."""
    world = map.observed_points(rows, poses)
    phi, _ = fit_line(world)
    along = world @ np.array([-np.sin(phi), np.cos(phi)])
    lo, hi = np.percentile(along, [2.0, 98.0])
    return float(hi - lo)


def _correct(
    map: Map,
    current: FloatArray,
    h: Interpretation,
    active: Sequence[Interpretation],
    config: Config,
) -> tuple[FloatArray, FloatArray, FloatArray, _core.SolveReport]:
    moved, transform = explicit_and_backpropagate(map, current, h)
    new_poses, lines, report = solve_all(map, [*active, h], config, moved)
    return new_poses, lines, transform, report


def chi2_limit(dof: int, probability: float) -> float:
    """The ``probability`` quantile of chi2 with ``dof`` degrees of freedom (Wilson-Hilferty:
    within 0.1% of the exact value from a few dozen dof on, which pose graphs always have)."""
    z = NormalDist().inv_cdf(probability)
    k = max(dof, 1)
    return float(k * (1.0 - 2.0 / (9.0 * k) + z * math.sqrt(2.0 / (9.0 * k))) ** 3)


def _consistency_guard(
    map: Map,
    current: FloatArray,
    drawn: DrawnCorrection,
    h: Interpretation,
    solved: tuple[FloatArray, FloatArray, FloatArray, _core.SolveReport],
    active: Sequence[Interpretation],
    config: Config,
) -> tuple[Interpretation, FloatArray, FloatArray, FloatArray, _core.SolveReport]:
    """The guard of docs/ALGORITHM.md §I.6: a result whose odometry chi2 is beyond what the
    odometry's own noise allows (``config.consistency_guard`` quantile, 3 dof per edge; once
    the map is past that, a rise of more than that quantile's spread, z sqrt(2 dof)) is not
    applied silently. It is tried again with each segment's pass nearest its drawing (where the
    biggest pass was kept); if that is within the limit it is applied with a note, otherwise the
    correction is refused with the figures."""
    from hitl_slam.interpret import _span, interpret

    new_poses, lines, transform, report = solved
    dof = 3 * map.edges.shape[0]
    limit = chi2_limit(dof, config.consistency_guard)
    # Once earlier corrections have put the map near or past the limit (a drift beyond what
    # the motion model states), one correction may still add what chi2's own spread allows.
    step = NormalDist().inv_cdf(config.consistency_guard) * math.sqrt(2.0 * dof)
    before, cost = _graph_chi2(map, current, new_poses)
    allowed = max(limit, before + step)
    if cost <= allowed:
        return h, new_poses, lines, transform, report
    logger.info("consistency guard: chi2 %.1f > %.1f; trying the nearest passes", cost, limit)
    try:
        alt = interpret(map, current, drawn, config, nearest_visits=True)
    except CorrectionRejected:
        alt = None
    if alt is not None and not (np.array_equal(alt.s_a, h.s_a) and np.array_equal(alt.s_b, h.s_b)):
        if h.mode is Mode.COLLINEAR and alt.mode is Mode.COLOCATION:
            alt = dataclasses.replace(alt, mode=Mode.COLLINEAR)
        alt_solved = _correct(map, current, alt, active, config)
        (alt_cost,) = _graph_chi2(map, alt_solved[0])
        if alt_cost <= allowed:
            note = (
                f"the passes kept first (poses {_span(h.x_a)} and {_span(h.x_b)}) would have "
                f"put the robot's measurements at chi2 {cost:.0f}, beyond the {allowed:.0f} their "
                f"noise allows; the passes nearest the drawings give {alt_cost:.0f}"
            )
            logger.info("correction: %s", note)
            return (dataclasses.replace(alt, notes=(*alt.notes, note)), *alt_solved)
    raise CorrectionRejected(
        f"applying it would contradict the robot's own measurements: their chi2 would go from "
        f"{before:.0f} to {cost:.0f}, beyond the {allowed:.0f} their noise allows (99.9% of chi2 "
        f"with {dof} dof, or that spread above the map before) with the passes it selected (poses "
        f"{_span(h.x_a)} and {_span(h.x_b)}); draw each segment along a longer, clearly "
        "separate stretch of the copy you mean"
    )


def apply_correction(
    map: Map,
    poses: FloatArray,
    drawn: DrawnCorrection,
    active: Sequence[Interpretation] = (),
    config: Config = DEFAULT,
) -> CorrectionResult:
    """Interpret ``drawn`` on the map as displayed (``poses``), correct, and re-solve with every
    correction in ``active`` plus the new one. Raises CorrectionRejected when the drawing
    cannot be interpreted; nothing is modified either way.

    The colocation guard (``config.colocation_guard``, in chi2 units; 0 = off): a colocation
    says more than "same line": that the two observation sets are the same stretch of it (their
    centres coincide). When the two passes saw different stretches of a wall (the usual case on
    a long wall), that along-the-wall part is false, and forcing it bends the map elsewhere. So
    a colocation whose two observation sets differ in length by more than 10% (plus
    ``2 sigma_h``) is applied as collinear; otherwise it is also solved as collinear, and if the
    colocation costs the robot's own measurements (the map's relative-pose factors) more than
    ``colocation_guard`` above the collinear solution's chi2, the along-the-wall part
    contradicts them and the collinear solution is applied instead. Either way a note in the
    interpretation gives the figures."""
    from hitl_slam.interpret import interpret
    from hitl_slam.odometry_check import checked_map

    t0 = time.perf_counter()
    current = np.ascontiguousarray(poses, dtype=np.float64)
    h = interpret(map, current, drawn, config)
    # Where the error goes: the odometry, re-measured where its scans contradict it
    # (docs/ALGORITHM.md §I.5).
    map = checked_map(map, config)
    t1 = time.perf_counter()
    if h.mode is Mode.COLOCATION and config.colocation_guard > 0:
        len_a, len_b = _stretch(map, current, h.s_a), _stretch(map, current, h.s_b)
        tolerance = 0.1 * max(len_a, len_b) + 2.0 * config.sigma_h
        if abs(len_a - len_b) > tolerance:
            note = (
                f"applied as collinear: the two passes saw different stretches of the wall "
                f"({len_a:.2f} m and {len_b:.2f} m long), so their centres are not one place"
            )
            logger.info("correction: %s", note)
            h = dataclasses.replace(h, mode=Mode.COLLINEAR, notes=(*h.notes, note))
    new_poses, lines, transform, report = _correct(map, current, h, active, config)
    if h.mode is Mode.COLOCATION and config.colocation_guard > 0:
        alt = dataclasses.replace(h, mode=Mode.COLLINEAR)
        alt_poses, alt_lines, alt_transform, alt_report = _correct(
            map, current, alt, active, config
        )
        cost, alt_cost = _graph_chi2(map, new_poses, alt_poses)
        logger.debug("colocation guard: chi2 %.2f as colocation, %.2f as collinear", cost, alt_cost)
        if cost - alt_cost > config.colocation_guard:
            note = (
                f"applied as collinear: the two passes' positions along the wall contradict the "
                f"odometry (chi2 of the map's measurements {cost:.1f} as colocation, "
                f"{alt_cost:.1f} as collinear; guard {config.colocation_guard:g})"
            )
            logger.info("correction: %s", note)
            h = dataclasses.replace(alt, notes=(*alt.notes, note))
            new_poses, lines, transform, report = alt_poses, alt_lines, alt_transform, alt_report
    if config.consistency_guard > 0:
        h, new_poses, lines, transform, report = _consistency_guard(
            map, current, drawn, h, (new_poses, lines, transform, report), active, config
        )
    t2 = time.perf_counter()
    return CorrectionResult(
        poses=new_poses,
        interpretation=h,
        lines=lines,
        transform=transform,
        iterations=report.iterations,
        initial_chi2=report.initial_chi2,
        final_chi2=report.final_chi2,
        termination=report.termination,
        time_s=t2 - t0,
        time_interpret_s=t1 - t0,
        time_solve_s=t2 - t1,
    )
