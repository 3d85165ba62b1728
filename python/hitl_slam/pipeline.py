"""One human correction end to end (the paper's Fig. 3, block 2): interpret the drawing,
move the later part of the map rigidly (explicit correction), close the gap along the chain
(back-propagation), then solve poses and line parameters jointly with every active correction.

Inputs are never modified; a drawing that cannot be interpreted raises CorrectionRejected.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.errors import CorrectionRejected, InputError, SolverError
from hitl_slam.geometry import chain_steps
from hitl_slam.map import Map, motion_model_information
from hitl_slam.solve import robust_pairs
from hitl_slam.workspace import Workspace

__all__ = [
    "CorrectionResult",
    "apply_correction",
    "chain_variances",
    "correction_engine",
    "explicit_and_backpropagate",
    "new_engine",
    "solve_all",
]

FloatArray = NDArray[np.float64]

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

    @classmethod
    def solved(
        cls,
        poses: FloatArray,
        interpretation: Interpretation,
        lines: FloatArray,
        transform: FloatArray,
        report: _core.SolveReport,
        times: tuple[float, float, float],
    ) -> CorrectionResult:
        """The result of a joint solve's ``report``; ``times``: (total, interpretation, solve)
        [s]."""
        return cls(
            poses=poses,
            interpretation=interpretation,
            lines=lines,
            transform=transform,
            iterations=report.iterations,
            initial_chi2=report.initial_chi2,
            final_chi2=report.final_chi2,
            termination=report.termination,
            time_s=times[0],
            time_interpret_s=times[1],
            time_solve_s=times[2],
        )


def chain_variances(
    map: Map, poses: FloatArray | None = None, *, workspace: Workspace | None = None
) -> tuple[FloatArray, FloatArray]:
    """Rotational and isotropic translational variance of each chain edge k -> k+1 (N-1,),
    from the map's own edge information, or the motion model where the chain has no edge.

    With ``poses`` (the map as displayed), a step whose turn there differs from its edge's
    measurement (a step the odometry check re-measured from the scans, or one an earlier
    correction already bent) has its rotational variance widened by the squared difference:
    how far the displayed step may be from the truth, which is what back-propagation shares
    the error by (computed by the core, ``correction::Chain::variances``)."""
    if poses is None:
        chain = _chain_of(map)
        return chain.rot.copy(), chain.trans.copy()
    engine, lock = _workspace(map, workspace).engine(map)
    with lock:
        rot, trans = engine.chain_variances(np.ascontiguousarray(poses, dtype=np.float64))
    return rot, trans


@dataclass(frozen=True)
class _Chain:
    """What back-propagation needs of a map's chain (held by its engine)."""

    rot: FloatArray  # (N-1,) rotational variance of each step k -> k+1
    trans: FloatArray  # (N-1,) isotropic translational variance
    steps: NDArray[np.int64]  # the steps that have a chain edge
    turns: FloatArray  # their edges' measured turns, in the k -> k+1 direction


def _chain_of(map: Map) -> _Chain:
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
    return _Chain(
        rot=np.ascontiguousarray(cov[:, 2, 2]),
        trans=np.ascontiguousarray(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
        steps=steps,
        turns=np.ascontiguousarray(turns),
    )


def _observations(map: Map, rows: NDArray[np.int64]) -> tuple[NDArray[np.int64], FloatArray]:
    poses = np.ascontiguousarray(rows[:, 0], dtype=np.int64)
    return poses, np.ascontiguousarray(map.points[map.point_rows(rows)])


def new_engine(map: Map) -> _core.CorrectionEngine:
    """A correction engine of ``map``: its relative-pose factors and chain, with the symbolic
    analyses of the structures it solves (undo, redo and the guards' second solve of one drawing
    return to structures seen a moment ago). Held by a :class:`~hitl_slam.workspace.Workspace`;
    one call at a time (the engine releases the GIL while it solves, and a second thread
    entering it would get "Already borrowed")."""
    chain = _chain_of(map)
    return _core.CorrectionEngine(
        map.num_poses,
        map.edges,
        map.measurements,
        map.information,
        map.anchor,
        chain=(chain.rot, chain.trans, chain.steps, chain.turns),
    )


def correction_engine(
    map: Map, workspace: Workspace | None = None
) -> tuple[_core.CorrectionEngine, threading.Lock]:
    """``map``'s correction engine in ``workspace`` (default: a workspace of ``map`` of its
    own) and the lock to hold around every call into it."""
    return _workspace(map, workspace).engine(map)


def _workspace(map: Map, workspace: Workspace | None) -> Workspace:
    """``workspace``, or one of ``map``'s own for a call that brings none."""
    return workspace if workspace is not None else Workspace(map)


def joint_kernels(config: Config = DEFAULT) -> list[tuple[str, str]]:
    """The robust kernels of the joint solve: ``config.robust``, plus dynamic covariance scaling
    on every correction's relation (``config.relation_dcs``, docs/ALGORITHM.md §I.8) unless
    ``config.robust`` names a kernel for relations itself."""
    pairs = robust_pairs(config.robust)
    if config.relation_dcs > 0 and all(cls != "relation" for cls, _ in pairs):
        pairs.append(("relation", f"dcs:{config.relation_dcs!r}"))
    return pairs


def solve_all(
    map: Map,
    active: Sequence[Interpretation],
    config: Config = DEFAULT,
    start: FloatArray | None = None,
    *,
    workspace: Workspace | None = None,
) -> tuple[FloatArray, FloatArray, _core.SolveReport]:
    """Joint optimization (docs/ALGORITHM.md §4.3) of poses and the lines of every correction in
    ``active``, from ``start`` (default: the map's poses), over the map's ORIGINAL relative-pose
    factors. Each line starts at the total-least-squares fit of its observations at ``start``."""
    x0 = np.ascontiguousarray(map.poses if start is None else start, dtype=np.float64)
    corrections = [
        (h.mode.value, *_observations(map, h.s_a), *_observations(map, h.s_b)) for h in active
    ]
    engine, lock = _workspace(map, workspace).engine(map)
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
            robust=joint_kernels(config),
            # The start is the explicit correction and its back-propagation: a trust region
            # stays in its basin. The watchdog's Gauss-Newton jumps (for starts off by radians)
            # found other, lower-cost basins here that fit the drawings worse (Freiburg 079 in
            # the evaluation: mean angle error 1.75 -> 2.75 deg with it).
            watchdog_steps=0,
        )


def explicit_and_backpropagate(
    map: Map, poses: FloatArray, h: Interpretation, *, workspace: Workspace | None = None
) -> tuple[FloatArray, FloatArray]:
    """docs/ALGORITHM.md §4.1 then §4.2: the rigid move of every pose from ``min(X_b)`` on, and
    the chain from ``max(X_a)`` made to meet it (in the core). Returns (new poses, the
    transform)."""
    engine, lock = _workspace(map, workspace).engine(map)
    with lock:
        moved, transform = engine.explicit_and_backpropagate(
            np.ascontiguousarray(poses, dtype=np.float64),
            h.mode.value,
            np.asarray(h.line_a, dtype=np.float64),
            np.asarray(h.line_b, dtype=np.float64),
            np.ascontiguousarray(h.x_a, dtype=np.int64),
            np.ascontiguousarray(h.x_b, dtype=np.int64),
        )
    return moved, transform


@dataclass(frozen=True)
class _EngineCall:
    """One correction's arguments to ``CorrectionEngine.apply``, to run with a choice of the
    joint solve's robust kernels."""

    engine: _core.CorrectionEngine
    lock: threading.Lock
    scans: Any
    poses: FloatArray
    seg_a: Any
    seg_b: Any
    mode: str
    active_rows: list[tuple[str, NDArray[np.int64], NDArray[np.int64]]]
    config: Config
    sigma_h: float
    consistency_z: float

    def run(self, kernels: list[tuple[str, str]]) -> Any:
        with self.lock:
            return self.engine.apply(
                self.scans,
                self.poses,
                self.seg_a,
                self.seg_b,
                self.mode,
                self.active_rows,
                self.config,
                sigma_h=self.sigma_h,
                robust=kernels,
                consistency_z=self.consistency_z,
            )


def _unchecked_alternative(
    map: Map, unchecked: NDArray[np.bool_], call: _EngineCall, h: Interpretation, poses: FloatArray
) -> tuple[Interpretation, FloatArray, FloatArray, FloatArray, _core.SolveReport] | None:
    """The correction solved again with ``config.unchecked_alternative`` on the odometry when
    the chain between its passes has steps the scans could not check (docs/ALGORITHM.md
    §I.12), if that map is the more consistent (§6); None to keep the first solve."""
    from hitl_slam.interpret import from_core
    from hitl_slam.metrics import inconsistency

    config = call.config
    spec = config.unchecked_alternative
    if not spec or map.num_points == 0:
        return None
    if any(cls == "odometry" for cls, _ in robust_pairs(config.robust)):
        return None  # the person chose the odometry's kernel
    rows = np.concatenate([h.x_a, h.x_b])
    lo, hi = int(rows.min()), int(rows.max())
    gaps = np.flatnonzero(unchecked[lo:hi]) + lo
    if gaps.size == 0:
        return None
    alt_config = config.replace(robust=f"{config.robust},{spec}" if config.robust else spec)
    try:
        t, alt_poses, lines, transform, report, _, _ = call.run(joint_kernels(alt_config))
    except (CorrectionRejected, SolverError) as exc:
        logger.debug("correction: the alternative with %s failed: %s", spec, exc)
        return None
    first = inconsistency(map, poses, config).total_m2
    second = inconsistency(map, alt_poses, config).total_m2
    if not second < first:
        return None
    alt = from_core(t)
    note = (
        f"{gaps.size} chain step{'s' if gaps.size != 1 else ''} between the passes "
        f"(first {int(gaps[0])}) could not be checked by the scans; solved with {spec} on the "
        f"odometry too, which left the map more consistent ({first:.1f} -> {second:.1f} m^2), "
        "and kept that"
    )
    alt = dataclasses.replace(alt, notes=(*alt.notes, note))
    return alt, alt_poses, lines, transform, report


def apply_correction(
    map: Map,
    poses: FloatArray,
    drawn: Correction,
    active: Sequence[Interpretation] = (),
    config: Config = DEFAULT,
    *,
    workspace: Workspace | None = None,
) -> CorrectionResult:
    """Interpret ``drawn`` on the map as displayed (``poses``), correct, and re-solve with every
    correction in ``active`` plus the new one. Raises CorrectionRejected when the drawing
    cannot be interpreted; nothing is modified either way.

    The colocation guard (``config.colocation_guard``, in chi2 units; 0 = off): a colocation
    says more than "same line": that the two observation sets are the same stretch of it (their
    centres coincide). When the two passes saw different stretches of a wall (the usual case on
    a long wall), that along-the-wall part is false, and forcing it bends the map elsewhere. So
    a colocation is also solved as collinear, and if the colocation costs the robot's own
    measurements (the map's relative-pose factors) more than ``colocation_guard`` above the
    collinear solution's chi2, the along-the-wall part contradicts them and the collinear
    solution is applied instead; where the chi2 cannot tell, the scans around the passes decide
    (``config.colocation_consistency``). Either way a note in the interpretation gives the
    figures.

    ``workspace``: what is kept about the map between corrections (its scans in the core, the
    odometry check, the engine); a session passes its own, and a call without one makes one for
    itself."""
    from hitl_slam.interpret import checked_drawing, from_core

    t0 = time.perf_counter()
    current = np.ascontiguousarray(poses, dtype=np.float64)
    if current.shape != map.poses.shape:
        raise InputError(
            f"poses must have shape {map.poses.shape} like the map's, got {current.shape}"
        )
    if not np.all(np.isfinite(current)):
        raise InputError("poses contain non-finite values; give finite poses")
    seg_a, seg_b, sigma_h = checked_drawing(drawn, config)
    held = _workspace(map, workspace)
    scans = held.scans()
    # Where the error goes: the odometry, re-measured where its scans contradict it
    # (docs/ALGORITHM.md §I.5); computed once per graph, and held, by the workspace.
    checked, unchecked = held.checked(map, config)
    engine, lock = held.engine(checked)
    z = NormalDist().inv_cdf(config.consistency_guard) if config.consistency_guard > 0 else 0.0
    active_rows = [
        (
            h.mode.value,
            np.ascontiguousarray(h.s_a, dtype=np.int64),
            np.ascontiguousarray(h.s_b, dtype=np.int64),
        )
        for h in active
    ]
    call = _EngineCall(
        engine,
        lock,
        scans,
        current,
        seg_a,
        seg_b,
        drawn.mode.value,
        active_rows,
        config,
        sigma_h,
        z,
    )
    t, new_poses, lines, transform, report, t_interpret, t_core = call.run(joint_kernels(config))
    h = from_core(t)
    alternative = _unchecked_alternative(map, unchecked, call, h, new_poses)
    if alternative is not None:
        h, new_poses, lines, transform, report = alternative
    for note in h.notes:
        logger.debug("correction: %s", note)
    t2 = time.perf_counter()
    return CorrectionResult.solved(
        new_poses, h, lines, transform, report, (t2 - t0, t_interpret, t_core - t_interpret)
    )
