"""A simulated person correcting a map: knowing the true walls, they look for two observations of
walls far apart in time that disagree on the map as shown, draw a noisy segment over each and pick
a mode; :func:`repair` repeats that through a :class:`~hitl_slam.session.Session` until they stop.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.errors import CorrectionRejected, InputError
from hitl_slam.geometry import to_world
from hitl_slam.interpret import interpret
from hitl_slam.session import Session
from hitl_slam.sim.odometry import HeadingJump, Slip
from hitl_slam.sim.scenario import Scenario, WallFit, angle_between, fit_points, spacing_between

__all__ = ["Inconsistency", "RepairResult", "RepairStep", "SimulatedHuman", "Visit", "repair"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_WINDOWS = ((0.0, 1.0), (0.0, 0.6), (0.4, 1.0), (0.0, 0.4), (0.6, 1.0), (0.3, 0.7))
"""Stretches of a visit (fractions of its drawn extent) a person considers drawing over, in order
of preference: the whole, then parts away from where another copy of the wall crosses it."""


@dataclass(frozen=True)
class Visit:
    """One pass of the robot by a wall: poses ``first``..``last`` (inclusive) each saw at least
    ``min_points_per_pose`` points of ``wall``; ``points`` in all."""

    wall: int
    first: int
    last: int
    points: int


@dataclass(frozen=True)
class Inconsistency:
    """Two visits that disagree on the current map, and how: ``angle_deg`` off the known
    relation, ``offset_m`` between the two copies of one wall (0 for two different walls), and
    ``score`` (how many times the visibility threshold)."""

    a: Visit
    b: Visit
    mode: Mode
    angle_deg: float
    offset_m: float
    score: float

    @property
    def key(self) -> tuple[int, int, int, int, str]:
        return (self.a.wall, self.a.first, self.b.wall, self.b.first, self.mode.value)


class SimulatedHuman:
    """A person who knows the building (the scenario's walls and feature pairs) and corrects the
    map one drawing at a time.

    A visit is one pass by a wall, broken where a heading jump or a slip of the scenario's faults
    fell within it: before and after the fault the wall is two copies on the damaged map. Passes
    that coincide on the map as shown (within the thresholds below) are one line to them: they
    draw on it, not on a stretch clear of the other pass (docs/ALGORITHM.md §I.19).

    What they see as wrong (:meth:`inconsistencies`): two visits at least ``min_separation``
    poses apart in time, either of the same wall and displaced by more than ``offset_threshold``
    [m] or turned by more than ``angle_threshold_deg``, or of a known parallel / perpendicular
    pair of walls and off that relation by more than ``angle_threshold_deg``. They fix the worst
    first, in mode ``same_wall_mode`` (collinear by default: two passes rarely see the same
    stretch of a wall, so their centroids need not coincide) or the pair's relation.

    How they draw: over each visit as the map shows it (its labelled points on the current
    poses), from quantile ``along[0]`` to ``along[1]`` of the points along the wall, each endpoint
    off by Gaussian ``endpoint_noise`` [m]. Where another copy of the wall lies close, they zoom
    in first, so their accuracy ``sigma_h`` (passed with the drawing) is a sixth of the gap and
    the endpoint noise shrinks alike (down to ``min_sigma_h``). With ``check_selection`` they
    look at what the drawing selects (the interface highlights it) before committing, and
    redraw zoomed in twice as far, up to ``max_redraws`` times, if it is not the two passes they
    meant. A pair drawn ``max_attempts`` times, or rejected once, is not drawn again.

    With ``split_visits`` they also look along each long pass (at least ``3 * min_separation``
    poses): a wall whose first and last thirds, as the map shows them, are not one straight line
    is a bent corridor (heading drift within the pass), fixed by a collinear drawing over the
    two ends, as the paper's users do.
    """

    def __init__(
        self,
        scenario: Scenario,
        rng: np.random.Generator | int | None = 0,
        *,
        endpoint_noise: float = 0.05,
        angle_threshold_deg: float = 0.5,
        offset_threshold: float = 0.03,
        min_separation: int = 20,
        along: tuple[float, float] = (0.1, 0.9),
        same_wall_mode: Mode = Mode.COLLINEAR,
        min_visit_points: int = 100,
        min_sigma_h: float = 0.02,
        check_selection: bool = True,
        max_redraws: int = 2,
        max_attempts: int = 2,
        split_visits: bool = True,
        config: Config = DEFAULT,
    ) -> None:
        if not (endpoint_noise >= 0 and angle_threshold_deg > 0 and offset_threshold > 0):
            raise InputError("endpoint_noise must be >= 0 and the thresholds > 0")
        if not 0.0 <= along[0] < along[1] <= 1.0:
            raise InputError(f"along must be two quantiles 0 <= lo < hi <= 1, got {along}")
        if same_wall_mode not in (Mode.COLLINEAR, Mode.COLOCATION):
            raise InputError("same_wall_mode must be collinear or colocation")
        self.scenario = scenario
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.endpoint_noise = endpoint_noise
        self.angle_threshold_deg = angle_threshold_deg
        self.offset_threshold = offset_threshold
        self.min_separation = min_separation
        self.along = along
        self.same_wall_mode = same_wall_mode
        self.min_sigma_h = min_sigma_h
        self.check_selection = check_selection
        self.max_redraws = max_redraws
        self.max_attempts = max_attempts
        self.config = config
        self._owner = scenario.map.pose_of_point()
        self._index: dict[Visit, IntArray] = {}
        self.visits = self._find_visits(min_visit_points)
        self.splits = self._split_visits(min_visit_points) if split_visits else ()
        self.redraws = 0  # drawings thrown away after looking at their selection
        self.last: Inconsistency | None = None  # what the latest drawing was meant to fix
        self._attempts: dict[tuple[int, int, int, int, str], int] = {}
        self._skipped: set[tuple[int, int, int, int, str]] = set()  # until the map changes
        self._seen: FloatArray | None = None

    # -- looking at the map -----------------------------------------------------------------

    def _find_visits(self, min_points: int) -> tuple[Visit, ...]:
        s, m = self.scenario, self.scenario.map
        owner = m.pose_of_point()
        labelled = s.wall_of_point >= 0
        w, p = s.wall_of_point[labelled], owner[labelled]
        counts = np.zeros((len(s.wall_names), m.num_poses), dtype=np.int64)
        np.add.at(counts, (w, p), 1)
        visits = []
        gap = self.config.visit_gap
        breaks = np.array(
            sorted(f.pose for f in s.faults if isinstance(f, HeadingJump | Slip)), dtype=np.int64
        )
        for wall in range(counts.shape[0]):
            seen = np.flatnonzero(counts[wall] >= self.config.min_points_per_pose)
            if seen.size == 0:
                continue
            # A pass is broken where the robot lost sight of the wall for more than the visit
            # gap, and where a jump or slip fell within it: the wall before and after such a
            # fault is two copies on the damaged map, which a person sees and draws apart.
            broken = np.diff(seen) > gap
            # Fault at pose q: between poses q - 1 and q. seen[i] < q <= seen[i + 1] breaks i.
            at = np.searchsorted(seen, breaks, side="left") - 1
            broken[at[(at >= 0) & (at < seen.size - 1)]] = True
            starts = np.concatenate([[0], np.flatnonzero(broken) + 1])
            for run in np.split(seen, starts[1:]):
                total = int(counts[wall, run[0] : run[-1] + 1].sum())
                if total >= min_points and run.size >= 5:
                    visits.append(Visit(wall, int(run[0]), int(run[-1]), total))
        return tuple(sorted(visits, key=lambda v: (v.first, v.wall)))

    def _split_visits(self, min_points: int) -> tuple[tuple[Visit, Visit], ...]:
        """The first and last thirds of every pass long enough to hold two visits
        ``min_separation`` apart, as (earlier, later) pairs."""
        s = self.scenario
        out = []
        for v in self.visits:
            n = v.last - v.first + 1
            if n < 3 * self.min_separation:
                continue
            third = n // 3
            parts = []
            for first, last in ((v.first, v.first + third - 1), (v.last - third + 1, v.last)):
                lo, hi = s.map.offsets[first], s.map.offsets[last + 1]
                count = int(np.count_nonzero(s.wall_of_point[lo:hi] == v.wall))
                parts.append(Visit(v.wall, first, last, count))
            if all(p.points >= min_points for p in parts):
                out.append((parts[0], parts[1]))
        return tuple(out)

    def _points(self, poses: FloatArray, visit: Visit) -> FloatArray:
        """The visit's labelled points in the world frame under ``poses``."""
        idx = self._index.get(visit)
        if idx is None:
            m = self.scenario.map
            lo, hi = m.offsets[visit.first], m.offsets[visit.last + 1]
            idx = lo + np.flatnonzero(self.scenario.wall_of_point[lo:hi] == visit.wall)
            self._index[visit] = idx
        return to_world(poses, self._owner[idx], self.scenario.map.points[idx])

    def inconsistencies(self, poses: FloatArray) -> list[Inconsistency]:
        """Every visibly wrong pair of visits on the map shown with ``poses``, worst first."""
        poses = np.asarray(poses, dtype=np.float64)
        fits = {v: fit_points(self._points(poses, v)) for v in self.visits}
        by_wall: dict[int, list[Visit]] = {}
        for v in self.visits:
            by_wall.setdefault(v.wall, []).append(v)
        found: list[Inconsistency] = []
        for visits in by_wall.values():
            for a, b in itertools.combinations(visits, 2):
                if self._apart(a, b):
                    found.append(self._same_wall(a, b, fits[a], fits[b]))
        for a, b in self.splits:
            fa, fb = fit_points(self._points(poses, a)), fit_points(self._points(poses, b))
            found.append(self._same_wall(a, b, fa, fb))
        for pair in self.scenario.feature_pairs:
            if pair.kind == "spacing":
                continue
            mode = Mode.PARALLEL if pair.kind == "parallel" else Mode.PERPENDICULAR
            for a, b in itertools.product(by_wall.get(pair.i, []), by_wall.get(pair.j, [])):
                if self._apart(a, b):
                    first, second = (a, b) if a.first < b.first else (b, a)
                    angle = angle_between(fits[first], fits[second])
                    error = angle if mode is Mode.PARALLEL else 90.0 - angle
                    score = error / self.angle_threshold_deg
                    found.append(Inconsistency(first, second, mode, error, 0.0, score))
        visible = [f for f in found if f.score > 1.0]
        return sorted(visible, key=lambda f: (-f.score, f.a.first, f.b.first))

    def _apart(self, a: Visit, b: Visit) -> bool:
        first, second = (a, b) if a.first < b.first else (b, a)
        return second.first - first.last >= self.min_separation

    def _same_wall(self, a: Visit, b: Visit, fa: WallFit, fb: WallFit) -> Inconsistency:
        angle = angle_between(fa, fb)
        offset = spacing_between(fa, fb)
        score = max(angle / self.angle_threshold_deg, offset / self.offset_threshold)
        return Inconsistency(a, b, self.same_wall_mode, angle, offset, score)

    # -- drawing ----------------------------------------------------------------------------

    def next_correction(self, poses: FloatArray) -> Correction | None:
        """The next drawing on the map shown with ``poses``, or None when nothing visibly wrong
        is left (or every wrong pair was tried). :attr:`last` says what it is meant to fix."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        if self._seen is None or not np.array_equal(self._seen, poses):
            self._skipped.clear()
            self._seen = poses.copy()
        for issue in self.inconsistencies(poses):
            key = issue.key
            if key in self._skipped or self._attempts.get(key, 0) >= self.max_attempts:
                continue
            drawn = self._draw_pair(poses, issue)
            if drawn is None:
                self._skipped.add(key)
                continue
            self._attempts[key] = self._attempts.get(key, 0) + 1
            self.last = issue
            return drawn
        self.last = None
        return None

    def rejected(self, drawn: Correction) -> None:
        """Told that ``drawn`` (the latest drawing) was rejected: that pair is not tried again."""
        if self.last is not None:
            self._attempts[self.last.key] = self.max_attempts

    def _draw_pair(self, poses: FloatArray, issue: Inconsistency) -> Correction | None:
        zoom = 1.0
        for _ in range(self.max_redraws + 1):
            a = self._draw_visit(poses, issue.a, zoom)
            b = self._draw_visit(poses, issue.b, zoom)
            if a is None or b is None:
                return None
            (seg_a, sigma_a), (seg_b, sigma_b) = a, b
            sigma = min(sigma_a, sigma_b)
            drawn = Correction.make(
                seg_a, seg_b, issue.mode, sigma if sigma < self.config.sigma_h else None
            )
            if not self.check_selection or self._selects(poses, drawn, issue):
                return drawn
            self.redraws += 1
            zoom *= 2.0
        return None

    def _draw_visit(
        self, poses: FloatArray, visit: Visit, zoom: float
    ) -> tuple[list[list[float]], float] | None:
        """Endpoints drawn over ``visit`` and the accuracy they were drawn with [m]: over the
        stretch of it farthest from any other copy of the same wall."""
        pts = self._points(poses, visit)
        fit = fit_points(pts)
        normal = fit.normal
        direction = np.array([-normal[1], normal[0]])
        centre = np.asarray(fit.centre)
        proj = (pts - centre) @ direction
        lo, hi = (float(q) for q in np.quantile(proj, self.along))
        if hi - lo < 0.3:
            return None
        # Other copies of the wall: other passes (not the pass a third of a visit belongs to),
        # except those that coincide with this one on the map as shown (within the thresholds
        # below which the person sees no disagreement): to the eye they are the same line, and
        # a stroke on it means both.
        others = []
        for v in self.visits:
            if v.wall != visit.wall or not (v.last < visit.first or v.first > visit.last):
                continue
            q = self._points(poses, v)
            if self._same_wall(visit, v, fit, fit_points(q)).score <= 1.0:
                continue  # not visibly apart (the test of :meth:`inconsistencies`)
            others.append(q)
        clear = 6.0 * self.config.sigma_h  # twice the default candidate band
        best, best_gap = (lo, hi), -1.0
        for f0, f1 in _WINDOWS:
            w0, w1 = lo + f0 * (hi - lo), lo + f1 * (hi - lo)
            if w1 - w0 < 0.3:
                continue
            gap = self._gap(others, centre, direction, normal, w0, w1)
            if gap > best_gap + 1e-9:
                best, best_gap = (w0, w1), gap
            if gap >= clear:
                break
        sigma_h = min(self.config.sigma_h, best_gap / 6.0) / zoom
        sigma_h = max(sigma_h, self.min_sigma_h)
        noise = self.endpoint_noise * sigma_h / self.config.sigma_h
        ends = [centre + best[0] * direction, centre + best[1] * direction]
        return [[float(v) for v in e + self.rng.normal(0.0, noise, 2)] for e in ends], sigma_h

    def _gap(
        self,
        others: list[FloatArray],
        centre: FloatArray,
        direction: FloatArray,
        normal: FloatArray,
        w0: float,
        w1: float,
    ) -> float:
        """How close other copies come to the line beside the stretch w0..w1 [m]."""
        gap = math.inf
        for q in others:
            t = (q - centre) @ direction
            beside = (t > w0 - 0.3) & (t < w1 + 0.3)
            if np.count_nonzero(beside) >= self.config.min_points_per_pose:
                d = np.abs((q[beside] - centre) @ normal)
                gap = min(gap, float(np.quantile(d, 0.05)))
        return gap

    def _selects(self, poses: FloatArray, drawn: Correction, issue: Inconsistency) -> bool:
        """Whether ``drawn`` selects two passes by the walls meant that visibly disagree: the
        passes meant, or, where copies of a wall coincide on the map, others just like them."""
        try:
            h = interpret(self.scenario.map, poses, drawn, self.config)
        except CorrectionRejected:
            return False
        if (issue.a, issue.b) in self.splits:
            return self._selects_split(poses, h, issue)
        a, b = self._visit_of(h.s_a), self._visit_of(h.s_b)
        if a is None or b is None or a == b:
            return False
        if {a.wall, b.wall} != {issue.a.wall, issue.b.wall}:
            return False
        if issue.a.wall != issue.b.wall and (a.wall, b.wall) != (issue.a.wall, issue.b.wall):
            a, b = b, a
            if (a.wall, b.wall) != (issue.a.wall, issue.b.wall):
                return False
        first, second = (a, b) if a.first < b.first else (b, a)
        fa, fb = fit_points(self._points(poses, first)), fit_points(self._points(poses, second))
        if issue.a.wall == issue.b.wall:
            return self._same_wall(first, second, fa, fb).score > 1.0
        angle = angle_between(fa, fb)
        error = angle if issue.mode is Mode.PARALLEL else 90.0 - angle
        return error > self.angle_threshold_deg

    def _selects_split(self, poses: FloatArray, h: Interpretation, issue: Inconsistency) -> bool:
        """For a bent pass: both selections on the wall meant, within that pass, and still
        visibly not one straight line."""
        m, wall = self.scenario.map, issue.a.wall
        first, last = issue.a.first, issue.b.last
        fits = []
        for rows in (h.s_a, h.s_b):
            if rows.shape[0] < self.config.min_points_per_pose:
                return False
            labels = self.scenario.wall_of_point[m.point_rows(rows)]
            inside = (labels == wall) & (rows[:, 0] >= first) & (rows[:, 0] <= last)
            if np.mean(inside) < 0.9:
                return False
            fits.append(fit_points(m.observed_points(rows, poses)))
        return self._same_wall(issue.a, issue.b, fits[0], fits[1]).score > 1.0

    def _visit_of(self, rows: IntArray, share: float = 0.9) -> Visit | None:
        """The visit that (nearly) all of the selected (pose, point) ``rows`` belong to."""
        if rows.shape[0] < self.config.min_points_per_pose:
            return None
        m = self.scenario.map
        labels = self.scenario.wall_of_point[m.point_rows(rows)]
        for v in self.visits:
            inside = (labels == v.wall) & (rows[:, 0] >= v.first) & (rows[:, 0] <= v.last)
            if np.mean(inside) >= share:
                return v
        return None


@dataclass(frozen=True)
class RepairStep:
    """One applied correction: what was drawn, what it was meant to fix, how it was understood."""

    drawn: Correction
    intent: Inconsistency | None
    interpretation: Interpretation
    time_s: float


@dataclass(frozen=True)
class RepairResult:
    """The end of a simulated repair.

    ``used`` corrections were applied (``corrections``), ``rejections`` drawings were rejected by
    the interpreter, ``redraws`` thrown away by the human before committing; ``finished`` says the
    human saw nothing more to fix (rather than running out of corrections).
    """

    poses: FloatArray
    corrections: tuple[RepairStep, ...]
    used: int
    rejections: int
    redraws: int
    finished: bool
    time_s: float


def repair(
    scenario: Scenario,
    human: SimulatedHuman,
    *,
    max_corrections: int = 50,
    session: Session | None = None,
) -> RepairResult:
    """Let ``human`` correct ``scenario``'s map until they see nothing wrong or ``max_corrections``
    were applied: draw on the current map, apply through ``session`` (default: a new in-memory
    session on the scenario's map, closed at the end), repeat. A rejected drawing is counted and
    the human tries another pair."""
    if max_corrections < 0:
        raise InputError(f"max_corrections must be >= 0, got {max_corrections}")
    if session is not None and (
        session.input_map.num_poses != scenario.map.num_poses
        or session.input_map.num_points != scenario.map.num_points
    ):
        raise InputError("the session is not on this scenario's map; start it with scenario.map")
    start = time.perf_counter()
    own = session is None
    active = Session.new(scenario.map) if session is None else session
    steps: list[RepairStep] = []
    rejections, redraws0, finished = 0, human.redraws, False
    try:
        while len(steps) < max_corrections:
            drawn = human.next_correction(active.poses)
            if drawn is None:
                finished = True
                break
            intent = human.last
            try:
                outcome = active.apply(drawn)
            except CorrectionRejected:
                rejections += 1
                human.rejected(drawn)
                continue
            steps.append(RepairStep(drawn, intent, outcome.interpretation, outcome.time_s))
        poses = np.array(active.poses, dtype=np.float64)
    finally:
        if own:
            active.close()
    return RepairResult(
        poses=poses,
        corrections=tuple(steps),
        used=len(steps),
        rejections=rejections,
        redraws=human.redraws - redraws0,
        finished=finished,
        time_s=time.perf_counter() - start,
    )
