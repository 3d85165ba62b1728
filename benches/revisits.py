"""Drawings a person would make where a robot came back to a place: the same wall seen on two
visits, drawn where the current map shows it (shared by the latency benches)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Correction, Mode
from hitl_slam.geometry import principal_axes
from hitl_slam.map import Map

FloatArray = NDArray[np.float64]


def revisit_pairs(
    truth: FloatArray, *, every: int = 20, gap: int = 800, radius: float = 0.5
) -> list[tuple[int, int]]:
    """Pairs (early i, late j): every ``every``-th pose i and the pose j at least ``gap`` poses
    later (every 5th) whose true position is nearest it, when within ``radius`` [m]."""
    n = truth.shape[0]
    pairs = []
    for i in range(0, n - gap, every):
        late = np.arange(i + gap, n, 5)
        d = np.hypot(*(truth[late, :2] - truth[i, :2]).T)
        if d.min() < radius:
            pairs.append((int(i), int(late[int(np.argmin(d))])))
    return pairs


class WallDrawer:
    """Draws, for a revisit (i, j), the longest straight run scan i sees (in ``truth``) where
    the scans near i and near j show it on the current map, as two segments with 5 cm of hand
    noise at their ends (numpy seed ``seed``)."""

    def __init__(self, m: Map, truth: FloatArray, seed: int) -> None:
        self.map = m
        self.rng = np.random.default_rng(seed)
        self.true_world = m.world_points(truth)
        self.owner = m.pose_of_point()

    def draw(self, poses: FloatArray, i: int, j: int, *, only_if_wrong: bool = True) -> Correction:
        """The colocation of that wall. Raises ValueError when scan i sees no wall, a visit
        barely shows it, or (``only_if_wrong``: a person corrects only what looks wrong) the two
        already meet within 10 cm."""
        pts = self.true_world[self.owner == i]
        best = None
        for _ in range(60):
            p, q = pts[self.rng.integers(len(pts), size=2)]
            d = q - p
            if np.hypot(*d) < 0.5:
                continue
            nrm = np.array([-d[1], d[0]]) / np.hypot(*d)
            inl = np.abs((pts - p) @ nrm) < 0.03
            if best is None or inl.sum() > best[0]:
                best = (int(inl.sum()), p, nrm)
        if best is None or best[0] < 20:
            raise ValueError("no wall in view")
        _, p, nrm = best
        world_now = self.map.world_points(poses)

        def seg(lo: int, hi: int) -> list[list[float]]:
            on = np.abs((self.true_world - p) @ nrm) < 0.03
            sel = (self.owner >= lo) & (self.owner < hi) & on
            sel &= np.hypot(*(self.true_world - p).T) < 2.0
            w = world_now[sel]
            if len(w) < 20:
                raise ValueError("wall barely seen")
            centre, _, dirn = principal_axes(w)
            proj = (w - centre) @ dirn
            lo_q, hi_q = np.quantile(proj, [0.2, 0.8])
            return [
                list(map(float, centre + t * dirn + self.rng.normal(0, 0.05, 2)))
                for t in (lo_q, hi_q)
            ]

        a, b = seg(i - 3, i + 4), seg(j - 3, j + 4)
        if only_if_wrong and np.hypot(*np.subtract(np.mean(a, 0), np.mean(b, 0))) < 0.1:
            raise ValueError("already consistent here")
        return Correction.make(a, b, Mode.COLOCATION)
