"""An applier that knows the truth, for measuring what the no-harm target of issue 11 asks
(docs/ALGORITHM.md §I.14): would a correction still make its map worse if the engine knew
exactly which observations the person meant, and where the odometry's error is?

:func:`oracle_applier` replaces :func:`hitl_slam.pipeline.apply_correction` in
:func:`hitl_slam.full_evaluation.evaluate_run`. It does no interpretation: each drawing's
observation sets are the labelled points of the two passes the careful person drew on (their
:attr:`~hitl_slam.sim.human.SimulatedHuman.last` inconsistency), and the correction is the
paper's explicit correction, back-propagation and joint solve (§4) over them, with no guard. With
``error_model=True`` the odometry's information is also the truth's: the noise the simulation drew
its steps with (:data:`~hitl_slam.sim.odometry.DEFAULT_NOISE`), plus each fault's own variance on
the steps it hit.

Not for users: it reads the scenario's labels and faults, which no real map has.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation, Segment
from hitl_slam.errors import CorrectionRejected
from hitl_slam.geometry import to_world
from hitl_slam.map import Map
from hitl_slam.pipeline import CorrectionResult, explicit_and_backpropagate, solve_all
from hitl_slam.session import Applier
from hitl_slam.sim.careful import CarefulPerson
from hitl_slam.sim.human import Visit
from hitl_slam.sim.odometry import DEFAULT_NOISE, HeadingDrift, HeadingJump, ScaleError, Slip
from hitl_slam.sim.scenario import Scenario, fit_points
from hitl_slam.workspace import Workspace

__all__ = ["oracle_applier", "true_information"]

FloatArray = NDArray[np.float64]

_MIN_SIGMA_T = 1e-3
"""[m] a floor under the simulated translational noise, which is 0 on a step that does not move."""
_MIN_VAR_THETA = 1e-8
"""[rad^2] the same for the heading's variance."""


def true_information(scenario: Scenario) -> FloatArray:
    """``(M, 3, 3)``: the information of each edge of ``scenario.map`` under the noise its
    odometry was drawn with (x and y each ``sigma_t``, heading ``sigma_theta``, uncorrelated),
    with each fault's variance added to the steps it hit (a jump's angle squared on its step's
    heading; a drift's rate times the step's length, squared, on each heading of its stretch; a
    slip's length squared on x and y of its step; a scale error's share of each step's length,
    squared, on x and y of each step of its stretch)."""
    m, noise = scenario.map, DEFAULT_NOISE
    e, z = m.edges, m.measurements
    dt = np.hypot(z[:, 0], z[:, 1])
    sigma_t = np.maximum(noise.sigma_t0 + noise.k_t * dt, _MIN_SIGMA_T)
    var_theta = (noise.sigma_theta0 + noise.k_theta * np.abs(z[:, 2]) + noise.k_theta_t * dt) ** 2
    var_t = sigma_t**2
    chain = e[:, 1] == e[:, 0] + 1
    for fault in scenario.faults:
        if isinstance(fault, HeadingJump):
            var_theta[chain & (e[:, 1] == fault.pose)] += fault.angle**2
        elif isinstance(fault, HeadingDrift):
            hit = chain & (e[:, 0] >= fault.start) & (e[:, 0] < fault.stop - 1)
            var_theta[hit] += (fault.rate * dt[hit]) ** 2
        elif isinstance(fault, Slip):
            var_t[chain & (e[:, 1] == fault.pose)] += fault.dx**2 + fault.dy**2
        elif isinstance(fault, ScaleError):
            hit = chain & (e[:, 0] >= fault.start) & (e[:, 0] < fault.stop - 1)
            var_t[hit] += ((fault.factor - 1.0) * dt[hit]) ** 2
    info = np.zeros((e.shape[0], 3, 3))
    info[:, 0, 0] = info[:, 1, 1] = 1.0 / var_t
    info[:, 2, 2] = 1.0 / np.maximum(var_theta, _MIN_VAR_THETA)
    return info


def _rows(scenario: Scenario, visit: Visit) -> NDArray[np.int64]:
    """The (pose, point) rows of the points ``visit`` saw of its wall (the scenario's labels)."""
    m = scenario.map
    lo, hi = int(m.offsets[visit.first]), int(m.offsets[visit.last + 1])
    idx = lo + np.flatnonzero(scenario.wall_of_point[lo:hi] == visit.wall)
    owner = np.searchsorted(m.offsets, idx, side="right") - 1
    return np.stack([owner, idx - m.offsets[owner]], axis=1).astype(np.int64)


def _segment(map: Map, poses: FloatArray, rows: NDArray[np.int64]) -> Segment:
    """The extent of ``rows``' points on their total-least-squares line under ``poses``."""
    pts = to_world(poses, rows[:, 0], map.points[map.offsets[rows[:, 0]] + rows[:, 1]])
    fit = fit_points(pts)
    direction = np.array([-fit.normal[1], fit.normal[0]])
    centre = np.asarray(fit.centre, dtype=np.float64)
    t = (pts - centre) @ direction
    lo, hi = centre + t.min() * direction, centre + t.max() * direction
    return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))


def oracle_applier(
    scenario: Scenario, person: CarefulPerson, *, error_model: bool = False
) -> Applier:
    """An applier (see :data:`hitl_slam.session.Applier`) for ``person``'s drawings on
    ``scenario``, which knows what each drawing meant (see the module's docstring)."""
    info = true_information(scenario) if error_model else None
    held: list[Workspace] = []  # the workspace of the session's map, made on the first call
    modelled: list[tuple[Map, Map]] = []  # (graph, the graph with the true information)

    def workspace(map: Map) -> Workspace:
        if not held or not np.may_share_memory(held[0].map.points, map.points):
            held[:] = [Workspace(map)]
        return held[0]

    def graph(map: Map, config: Config) -> Map:
        if info is None:
            return workspace(map).checked(map, config)[0]
        for seen, out in modelled:
            if seen is map:
                return out
        if map.edges.shape != scenario.map.edges.shape:
            raise CorrectionRejected("the oracle's error model is for the map's own edges")
        out = dataclasses.replace(map, information=np.ascontiguousarray(info))
        modelled[:] = [*modelled[-3:], (map, out)]
        return out

    def apply(
        map: Map,
        poses: FloatArray,
        drawn: Correction,
        active: Sequence[Interpretation],
        config: Config,
    ) -> CorrectionResult:
        t0 = time.perf_counter()
        issue = person.last
        if issue is None:
            raise CorrectionRejected("the oracle knows only the careful person's own drawings")
        a, b = (issue.a, issue.b) if issue.a.first <= issue.b.first else (issue.b, issue.a)
        current = np.ascontiguousarray(poses, dtype=np.float64)
        s_a, s_b = _rows(scenario, a), _rows(scenario, b)
        h = Interpretation(
            mode=drawn.mode,
            line_a=_segment(map, current, s_a),
            line_b=_segment(map, current, s_b),
            s_a=s_a,
            s_b=s_b,
            x_a=np.unique(s_a[:, 0]),
            x_b=np.unique(s_b[:, 0]),
            swapped=a is not issue.a,
            notes=("the oracle: the passes drawn on, every labelled point of the wall",),
        )
        g = graph(map, config)
        t1 = time.perf_counter()
        ws = workspace(map)
        moved, transform = explicit_and_backpropagate(g, current, h, workspace=ws)
        new, lines, report = solve_all(g, [*active, h], config, start=moved, workspace=ws)
        t2 = time.perf_counter()
        return CorrectionResult.solved(
            new, h, lines, transform, report, (t2 - t0, t1 - t0, t2 - t1)
        )

    return apply
