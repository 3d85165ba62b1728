"""The careful person of the full evaluation (issue 11): they draw only true statements, on the
copies of walls they can see on the current map, one correction at a time, and commit each drawing
as drawn (no looking at what it selects, no zooming in to redraw).

Against :class:`~hitl_slam.sim.human.SimulatedHuman` (the person the paper's experiments assume,
who zooms in where copies lie close and redraws until the interface highlights the passes they
meant), this person is harder on the interpreter: every endpoint is off by Gaussian
``endpoint_noise`` (5 or 15 cm) whatever the gap to the next copy, every segment is drawn in a
random direction, the drawing's accuracy is the default ``sigma_h``, and where both passes saw the
same stretch of a wall (the same two ends) they say so with a colocation instead of a collinear
pair.

Other drawing styles (:class:`DrawingStyle`; off by default): a hand that runs each stroke on
past the ends of what it saw by up to ``overshoot`` metres (uniform, each end on its own), and
one that draws the whole stroke beside the wall, both ends shifted by one offset of up to
``side`` metres to either side (docs/ALGORITHM.md §I.16).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Correction, Mode
from hitl_slam.errors import InputError
from hitl_slam.sim.human import Inconsistency, SimulatedHuman, Visit
from hitl_slam.sim.scenario import Scenario, fit_points

__all__ = ["CarefulPerson", "DrawingStyle"]

FloatArray = NDArray[np.float64]

_MIN_STROKE = 8.0
"""A careful person's strokes are at least this many times their endpoint noise long (and at
least 0.3 m): with a hand that wanders 15 cm, a 20 cm stroke has no direction, and a careful
person draws a longer stretch of the wall or none."""

_SAME_ENDS_M = 0.3
"""Two passes saw the same stretch of a wall when both ends of what each saw (the 2nd and 98th
percentiles along the true wall) agree to this [m]: a person sees the same corners in both."""


@dataclass(frozen=True)
class DrawingStyle:
    """How a careful person's strokes depart from the copy they see, beyond endpoint noise [m]:
    each end run on past the copy's end by up to ``overshoot`` (uniform, each end on its own),
    and the whole stroke shifted to one side by up to ``side`` (uniform, either side)."""

    overshoot: float = 0.0
    side: float = 0.0

    def __post_init__(self) -> None:
        if not (self.overshoot >= 0 and self.side >= 0):
            raise InputError(
                f"a drawing style's overshoot and side are >= 0 m, got {self.overshoot}, "
                f"{self.side}"
            )


class CarefulPerson(SimulatedHuman):
    """A person who draws true statements with fixed endpoint noise and random direction (see the
    module's docstring). ``colocations``: say "the same stretch" where both passes saw it."""

    def __init__(
        self,
        scenario: Scenario,
        rng: np.random.Generator | int | None = 0,
        *,
        endpoint_noise: float = 0.05,
        colocations: bool = True,
        style: DrawingStyle = DrawingStyle(),
        config: Config = DEFAULT,
    ) -> None:
        if not endpoint_noise >= 0:
            raise InputError(f"endpoint_noise must be >= 0, got {endpoint_noise}")
        super().__init__(
            scenario,
            rng,
            endpoint_noise=endpoint_noise,
            check_selection=False,
            max_redraws=0,
            max_attempts=1,
            min_sigma_h=config.sigma_h,
            config=config,
        )
        self.colocations = colocations
        self.style = style
        self._true_extent: dict[Visit, tuple[float, float]] = {}

    def _extent(self, visit: Visit) -> tuple[float, float]:
        """Where ``visit``'s points lie along its true wall [m from the wall's first end]."""
        got = self._true_extent.get(visit)
        if got is None:
            pts = self._points(self.scenario.truth, visit)
            x0, y0, x1, y1 = self.scenario.walls[visit.wall]
            d = np.array([x1 - x0, y1 - y0])
            d /= float(np.hypot(*d))
            t = (pts - np.array([x0, y0])) @ d
            lo, hi = (float(q) for q in np.quantile(t, (0.02, 0.98)))
            got = self._true_extent[visit] = (lo, hi)
        return got

    def _same_stretch(self, issue: Inconsistency) -> bool:
        if not self.colocations or issue.a.wall != issue.b.wall or issue.mode is Mode.PARALLEL:
            return False
        if (issue.a, issue.b) in self.splits:
            return False  # two thirds of one pass never saw the same stretch
        (a0, a1), (b0, b1) = self._extent(issue.a), self._extent(issue.b)
        return abs(a0 - b0) <= _SAME_ENDS_M and abs(a1 - b1) <= _SAME_ENDS_M

    def _draw_pair(self, poses: FloatArray, issue: Inconsistency) -> Correction | None:
        same = self._same_stretch(issue)
        segments = []
        for visit in (issue.a, issue.b):
            seg = self._segment(poses, visit, whole=same)
            if seg is None:
                return None
            segments.append(seg)
        mode = Mode.COLOCATION if same else issue.mode
        return Correction.make(segments[0], segments[1], mode)

    def _segment(self, poses: FloatArray, visit: Visit, *, whole: bool) -> list[list[float]] | None:
        if whole:
            pts = self._points(poses, visit)
            fit = fit_points(pts)
            direction = np.array([-fit.normal[1], fit.normal[0]])
            centre = np.asarray(fit.centre)
            lo, hi = np.quantile((pts - centre) @ direction, (0.02, 0.98))
            if hi - lo < 0.3:
                return None
            ends = np.stack([centre + lo * direction, centre + hi * direction])
        else:
            drawn = self._draw_visit(poses, visit, 1.0)
            if drawn is None:
                return None
            ends = np.asarray(drawn[0], dtype=np.float64)
        if float(np.hypot(*(ends[1] - ends[0]))) < max(0.3, _MIN_STROKE * self.endpoint_noise):
            return None
        ends = ends + self.rng.normal(0.0, self.endpoint_noise, (2, 2))
        if self.style != DrawingStyle():
            ends = self._styled(ends)
        if self.rng.random() < 0.5:
            ends = ends[::-1]
        return [[float(v) for v in e] for e in ends]

    def _styled(self, ends: FloatArray) -> FloatArray:
        """``ends`` in this person's :class:`DrawingStyle`."""
        d = ends[1] - ends[0]
        d = d / float(np.hypot(*d))
        normal = np.array([-d[1], d[0]])
        out = ends.copy()
        out[0] -= d * self.rng.uniform(0.0, self.style.overshoot)
        out[1] += d * self.rng.uniform(0.0, self.style.overshoot)
        return out + normal * self.rng.uniform(-self.style.side, self.style.side)

    def _draw_visit(
        self, poses: FloatArray, visit: Visit, zoom: float
    ) -> tuple[list[list[float]], float] | None:
        # The parent's stretch away from other copies, without its zoom-scaled noise: _segment
        # adds this person's fixed noise.
        saved, self.endpoint_noise = self.endpoint_noise, 0.0
        try:
            out = super()._draw_visit(poses, visit, zoom)
        finally:
            self.endpoint_noise = saved
        return out
