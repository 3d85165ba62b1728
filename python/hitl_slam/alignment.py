"""Aligning a corrected map with its scans (docs/ALGORITHM.md §I.11).

A person's statements bring the copies of a wall together to within the drawing's accuracy; what
is left (centimetres between dense passes, the odometry's own noise along every pass) is what the
scans themselves resolve. Alignment runs the scan-matching front end (§F) again, with the current
poses as its odometry: every scan matched to its local map, loop closures searched between the
passes the corrections brought together. Its graph (the matched steps and the loop closures it
kept) then replaces the map's factors, and every correction in effect is solved again over it.

Scan matching can be wrong where the scans say little (a featureless corridor, a sparse or
simulated scanner), and then it contradicts the robot's own odometry at many steps at once. Three
guards judge the result without the truth, each refusing with its figures (nothing changes):

- loop closures: the front end must have kept at least ``Config.align_min_loop_closures``
  between the passes; without one the scans only re-measure the chain, which drifts;
- odometry: the share of the input map's odometry steps the aligned poses contradict beyond the
  99.9% chi2 bound under the odometry's own information must be at most
  ``Config.align_max_contradicted`` over the whole path;
- consistency (``Config.align_consistency_guard``): the aligned map's inconsistency (§6) must be
  lower than the map's before it (the point of aligning with the scans; the odometry guard keeps
  a map that flew apart, whose overlaps and so inconsistency shrink, from passing this one).

Before those, the solve itself is chosen among candidates (how far the person's statements may
yield to the scans, :func:`relation_candidates`): a candidate that overrules more than
``Config.align_max_overruled`` of the statements (holds them off by more than
:data:`OVERRULED_DEG` or :data:`OVERRULED_M`) is not the scans refining the map but a wrong
match folding it, and is set aside; where every candidate is, the alignment is refused
(docs/ALGORITHM.md §I.16).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam._core import SolveReport
from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Interpretation, Mode
from hitl_slam.errors import AlignmentRefused, InputError, SolverError
from hitl_slam.geometry import between, wrap
from hitl_slam.map import InformationSource, Map

__all__ = [
    "CHI2_3_999",
    "OVERRULED_DEG",
    "OVERRULED_M",
    "Alignment",
    "AlignmentRefused",
    "align",
    "aligned_map",
    "contradicted",
    "contradicted_steps",
    "overruled",
]

FloatArray = NDArray[np.float64]

logger = logging.getLogger(__name__)

CHI2_3_999 = 16.266
"""The 99.9% quantile of chi2 with 3 degrees of freedom: a step beyond it contradicts the
odometry."""

OVERRULED_DEG = 5.0
"""[deg] A statement whose two lines the aligned solve leaves further apart in angle than this is
overruled by the scans: a statement on a neighbouring pass yields by centimetres and a fraction
of a degree, a fold of the map by degrees (docs/ALGORITHM.md §I.16)."""

OVERRULED_M = 0.5
"""[m] Likewise for the offset between the two observation sets' centres (across the line for a
collinear statement, anywhere for a colocation)."""

_MIN_POINTS_PER_SCAN = 20
"""Fewer laser points per scan on average than this and there is nothing to match."""


@dataclass(frozen=True, eq=False)
class Alignment:
    """The result of :func:`align`: the aligned graph's factors (``edges`` ``(M, 2)``,
    ``measurements`` ``(M, 3)``, ``information`` ``(M, 3, 3)``; the matched steps first, then
    the loop closures kept), the solved poses and lines, and what the guard measured."""

    edges: NDArray[np.int64]
    measurements: FloatArray
    information: FloatArray
    poses: FloatArray
    lines: FloatArray
    loop_closures: int  # kept by the front end
    loop_closures_rejected: int
    steps: int  # odometry steps of the input map checked
    contradicted: int  # of them, contradicted by the aligned poses
    inconsistency: tuple[float, float]  # [m^2] before and after
    relation_dcs: float  # the Phi of the relations in the solve kept (see align_relation_dcs)
    iterations: int
    initial_chi2: float
    final_chi2: float
    time_s: float


def aligned_config(config: Config, relation_dcs: float | None = None) -> Config:
    """The configuration of every solve over an aligned graph: each correction's relation
    carries dynamic covariance scaling with ``relation_dcs`` (the Phi the alignment kept,
    :attr:`Alignment.relation_dcs`; default ``config.align_relation_dcs``)."""
    phi = config.align_relation_dcs if relation_dcs is None else relation_dcs
    return config.replace(relation_dcs=phi)


def relation_candidates(config: Config) -> tuple[float, ...]:
    """The Phis an alignment solves with, in order of preference on a tie: the scans as a
    second witness (``config.align_relation_dcs``: a statement they contradict yields to
    them), then the relations as firm as in every other solve (``config.relation_dcs``)."""
    return tuple(dict.fromkeys((config.align_relation_dcs, config.relation_dcs)))


def overruled(
    map: Map, poses: FloatArray, lines: FloatArray, active: Sequence[Interpretation]
) -> int:
    """How many of the statements in ``active`` the solve (``poses`` and its ``lines``,
    ``(2K, 2)`` ``(phi, rho)``, a then b per correction) holds off by more than
    :data:`OVERRULED_DEG` between their lines or :data:`OVERRULED_M` between their observation
    sets' centres (collinear: across line a; colocation: anywhere; the residual of the
    relation, docs/ALGORITHM.md §4.3)."""
    phis = np.asarray(lines, dtype=np.float64).reshape(-1, 2)[:, 0]
    count = 0
    for k, h in enumerate(active):
        pa, pb = float(phis[2 * k]), float(phis[2 * k + 1])
        e = pb - pa - (np.pi / 2 if h.mode is Mode.PERPENDICULAR else 0.0)
        e = (e + np.pi / 2) % np.pi - np.pi / 2  # lines are undirected
        off = 0.0
        if h.mode in (Mode.COLLINEAR, Mode.COLOCATION):
            ca, cb = (map.observed_points(s, poses).mean(axis=0) for s in (h.s_a, h.s_b))
            d = cb - ca
            if h.mode is Mode.COLLINEAR:
                off = abs(float(np.cos(pa) * d[0] + np.sin(pa) * d[1]))
            else:
                off = float(np.hypot(d[0], d[1]))
        count += abs(np.degrees(e)) > OVERRULED_DEG or off > OVERRULED_M
    return count


def contradicted_steps(map: Map, poses: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """``(first, beyond)``: ``map``'s odometry steps (edges between consecutive poses) by the
    pose they start from, and whether ``poses`` contradict each beyond :data:`CHI2_3_999`
    (squared Mahalanobis distance of the relative pose, under the step's own information)."""
    e = map.edges
    chain = np.flatnonzero(np.abs(e[:, 1] - e[:, 0]) == 1)
    first = np.minimum(e[chain, 0], e[chain, 1])
    order = np.argsort(first, kind="stable")
    chain, first = chain[order], first[order]
    i, j = e[chain, 0], e[chain, 1]
    r = between(poses[i], poses[j]) - map.measurements[chain]
    r[:, 2] = wrap(r[:, 2])
    d2 = np.einsum("ki,kij,kj->k", r, map.information[chain], r)
    return first.astype(np.int64), ~(d2 <= CHI2_3_999)


def contradicted(map: Map, poses: FloatArray) -> tuple[int, int]:
    """``(k, n)``: of ``map``'s ``n`` odometry steps (edges between consecutive poses), the
    ``k`` that ``poses`` contradict beyond :data:`CHI2_3_999` (:func:`contradicted_steps`)."""
    _, beyond = contradicted_steps(map, poses)
    return int(np.count_nonzero(beyond)), int(beyond.size)


def aligned_map(
    map: Map,
    edges: NDArray[np.int64],
    measurements: FloatArray,
    information: FloatArray,
) -> Map:
    """``map`` (its poses, scans and metadata) with its factors replaced by an alignment's. The
    map's loop closures (if it lists any) are not among them: an alignment's are its own."""
    from hitl_slam.loop_closures import KEYS

    return dataclasses.replace(
        map,
        edges=np.ascontiguousarray(edges, dtype=np.int64),
        measurements=np.ascontiguousarray(measurements, dtype=np.float64),
        information=np.ascontiguousarray(information, dtype=np.float64),
        information_source=np.full(edges.shape[0], InformationSource.INPUT, dtype=np.int8),
        metadata={k: v for k, v in map.metadata.items() if k not in KEYS},
    )


def _contradicts_odometry(k: int, steps: int, config: Config) -> AlignmentRefused:
    return AlignmentRefused(
        f"the scans disagree with the odometry: the aligned map contradicts {k} of the "
        f"{steps} odometry steps ({100 * k / steps:.1f}%) beyond their 99.9% bound, more "
        f"than the {100 * config.align_max_contradicted:.1f}% allowed "
        "(config align_max_contradicted); the map was not changed. Scan matching is "
        "unreliable on these scans here (few features, or a fault not yet corrected): "
        "correct what is left by drawing"
    )


def align(
    map: Map,
    poses: FloatArray,
    active: Sequence[Interpretation],
    config: Config = DEFAULT,
    *,
    progress: Callable[[int, int], object] | None = None,
) -> Alignment:
    """Aligns ``map`` (the input map: its scans and odometry) at ``poses`` (the corrected poses)
    with its scans, keeping every correction in ``active`` (see the module's notes).

    Raises:
        InputError: the map has too few laser points to match.
        AlignmentRefused: the aligned poses contradict more than
            ``config.align_max_contradicted`` of the odometry steps.
        SolverError: the joint solve failed.
    """
    from hitl_slam.pipeline import solve_all
    from hitl_slam.slam import slam
    from hitl_slam.workspace import Workspace

    n = map.num_poses
    if n < 2 or map.num_points < _MIN_POINTS_PER_SCAN * n:
        raise InputError(
            f"{map.name}: {map.num_points} laser points over {n} poses; aligning with the scans "
            f"needs scans of at least {_MIN_POINTS_PER_SCAN} points on average (a pose graph "
            "without scans cannot be aligned)"
        )
    from hitl_slam.metrics import inconsistency

    t0 = time.perf_counter()
    seeded = dataclasses.replace(map, poses=np.ascontiguousarray(poses, dtype=np.float64))
    front = slam(seeded, progress=progress)
    kept = int(front.loop_closures.accepted.sum())
    rejected = int(front.loop_closures.pairs.shape[0]) - kept
    if kept < config.align_min_loop_closures:
        raise AlignmentRefused(
            f"the scans found {kept} loop closure{'' if kept == 1 else 's'} between the passes "
            f"({rejected} rejected), fewer than the {config.align_min_loop_closures} needed "
            "(config align_min_loop_closures); without them aligning only re-measures the "
            "chain, which drifts. The map was not changed. Bring the copies of the walls "
            "closer by drawing first, or there is no place the robot saw twice"
        )
    graph = front.accepted_map()
    before = inconsistency(map, poses, config).total_m2
    # How far a statement yields to the scans is decided by the scans too: each candidate Phi
    # is solved and the more consistent map kept. Yielding lets passes the statements held a
    # few centimetres apart meet, but where the front end kept few loop closures it can also
    # let part of the map turn about them (docs/ALGORITHM.md §I.11); and where one of its
    # matches is wrong by degrees, the map folds there and overrules many statements at once,
    # while its inconsistency falls (a folded map overlaps less): such a candidate is set
    # aside, and if every one is, the alignment is refused (§I.16).
    best: tuple[float, float, FloatArray, FloatArray, SolveReport] | None = None
    limit = config.align_max_overruled * len(active)
    setaside: list[tuple[float, int]] = []  # (Phi, statements overruled)
    held = Workspace(graph)  # one engine for every candidate's solve
    for phi in relation_candidates(config) if active else (config.align_relation_dcs,):
        x, lines_x, report_x = solve_all(
            graph, active, aligned_config(config, phi), start=graph.poses, workspace=held
        )
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (n, 3) or not np.isfinite(x).all():
            raise SolverError("the aligned solve returned malformed poses; the map was not changed")
        lines_x = np.asarray(lines_x, dtype=np.float64)
        held_off = overruled(map, x, lines_x, active) if active else 0
        if held_off > limit:
            setaside.append((phi, held_off))
            continue
        inc = inconsistency(map, x, config).total_m2
        if best is None or inc < best[0]:
            best = (inc, phi, x, lines_x, report_x)
    each = ", ".join(f"Phi {phi:g}: {k}" for phi, k in setaside)
    if best is None:
        raise AlignmentRefused(
            f"the scans contradict what you said: the aligned map would hold at least "
            f"{min(k for _, k in setaside)} of your {len(active)} statements off by more than "
            f"{OVERRULED_DEG:g} degrees or {OVERRULED_M:g} m ({each}; at most "
            f"{100 * config.align_max_overruled:.0f}% may be, config align_max_overruled); the "
            "map was not changed. A scan match folded the map somewhere (a wrong match where "
            "the robot turned, or too few loop closures to hold the map): correct what is left "
            "by drawing"
        )
    after, phi, solved, lines, report = best
    if setaside:
        logger.info(
            "alignment: set aside the solves that would hold too many of the %d statements off "
            "by more than %g deg or %g m (%s); kept Phi %g",
            len(active),
            OVERRULED_DEG,
            OVERRULED_M,
            each,
            phi,
        )
    k, steps = contradicted(map, solved)
    if steps and k > config.align_max_contradicted * steps:
        raise _contradicts_odometry(k, steps, config)
    if config.align_consistency_guard and not after < before:
        raise AlignmentRefused(
            f"the aligned map is no more consistent with its scans than the map is: its "
            f"inconsistency would go from {before:.1f} to {after:.1f} m^2; the map was not "
            "changed. The scans disagree with the corrections here (a statement on the wrong "
            "copy?): look at the last corrections, or correct what is left by drawing"
        )
    return Alignment(
        edges=graph.edges,
        measurements=graph.measurements,
        information=graph.information,
        poses=solved,
        lines=lines.reshape(-1, 2),
        loop_closures=kept,
        loop_closures_rejected=rejected,
        steps=steps,
        contradicted=k,
        inconsistency=(float(before), float(after)),
        relation_dcs=float(phi),
        iterations=int(report.iterations),
        initial_chi2=float(report.initial_chi2),
        final_chi2=float(report.final_chi2),
        time_s=time.perf_counter() - t0,
    )
