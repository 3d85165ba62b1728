"""The wall a drawing meant, found pass by pass (docs/ALGORITHM.md §I.4): where several passes of
the robot by one wall disagree a little each (a half-repaired map), their union near the drawing is
a blur a few decimetres wide in which neither EM nor a Hough search finds one line, although each
pass on its own is a crisp line and the person drew on one of them. So the points near the drawing
are split by pass (runs of poses), each pass's line is fitted robustly, and the pass whose line
is best supported and nearest the drawing (the snapping score: support against sideways offset
and turn) is the selection.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.map import Map

__all__ = ["MAX_TURN", "PassLine", "best_pass"]

MAX_TURN = 0.4
"""[rad] A pass whose line turns more from the drawing is a crossing wall (as snapping's cap)."""


@dataclass(frozen=True)
class PassLine:
    """One pass's line under a drawing: its observations ``rows`` ((pose, point) pairs), the
    score and the runner-up's, how far the drawing is from it and how much it turns."""

    rows: NDArray[np.int64]
    poses: tuple[int, int]
    score: float
    runner_up: float
    offset: float  # [m] mean distance of the drawing's ends from the line
    turn: float  # [rad]

    def note(self, name: str) -> str:
        other = (
            "no other pass near it"
            if not math.isfinite(self.runner_up)
            else f"score {self.score:.2f} against {self.runner_up:.2f} for the next pass"
        )
        return (
            f"segment {name}: no one line under it, so it was matched pass by pass: poses "
            f"{self.poses[0]}-{self.poses[1]} ({self.rows.shape[0]} points), "
            f"{self.offset:.2f} m from the drawing and turned {math.degrees(self.turn):.1f} deg "
            f"({other})"
        )


def best_pass(
    map: Map,
    poses: NDArray[np.float64],
    drawn: NDArray[np.float64],
    *,
    search: float,
    sigma_em: float,
    closeness: float,
    pointing: float,
    gap: int,
    min_points: int,
) -> PassLine | None:
    """The pass whose own line best explains ``drawn`` ((2, 2) endpoints): among the points
    within ``search`` [m] of the drawing (and at most 0.3 m past its ends), split into passes
    (pose runs with no gap over ``gap``), each pass's Cauchy-weighted TLS line; its inliers
    (within ``2 sigma_em``) from poses with ``min_points`` or more of them. Score:
    ``ln(inliers) - o^2 / (2 closeness^2) - t^2 / (2 sigma_t^2)`` with ``o`` the drawing's mean
    distance from the line, ``t`` the turn, ``sigma_t = sqrt(2) pointing / length``. None when
    no pass holds a line."""
    p0, p1 = drawn
    length = float(np.hypot(*(p1 - p0)))
    if length <= 0 or search <= 0:
        return None
    direction = (p1 - p0) / length
    normal = np.array([-direction[1], direction[0]])
    world = map.world_points(poses)
    along = (world - p0) @ direction
    across = (world - p0) @ normal
    near = np.flatnonzero((np.abs(across) <= search) & (along >= -0.3) & (along <= length + 0.3))
    if near.size < min_points:
        return None
    owner_of = map.pose_of_point()
    owner = owner_of[near]
    order = np.argsort(owner, kind="stable")
    near, owner = near[order], owner[order]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(owner) > gap) + 1, [owner.size]])
    sigma_t = math.sqrt(2.0) * pointing / length
    found: list[tuple[float, NDArray[np.int64], tuple[int, int], float, float]] = []
    for lo, hi in itertools.pairwise(starts):
        idx, who = near[lo:hi], owner[lo:hi]
        if idx.size < 3 * min_points:
            continue
        pts = world[idx]
        weights = np.ones(idx.size)
        for _ in range(4):
            phi, rho, _extent = _core.line_fit(pts, weights, drawn, 0.3)
            resid = pts @ np.array([math.cos(phi), math.sin(phi)]) - rho
            weights = 1.0 / (1.0 + (resid / sigma_em) ** 2)
        inlier = np.abs(resid) <= 2.0 * sigma_em
        if inlier.sum() < max(0.5 * idx.size, 3 * min_points):
            continue  # clutter or a corner, not a line
        # T_p: only poses that see enough of it.
        kept_poses, counts = np.unique(who[inlier], return_counts=True)
        kept_poses = kept_poses[counts >= min_points]
        inlier &= np.isin(who, kept_poses)
        n_in = int(inlier.sum())
        if n_in < 3 * min_points:
            continue
        n = np.array([math.cos(phi), math.sin(phi)])
        offset = float(np.mean(np.abs(np.stack([p0, p1]) @ n - rho)))
        line_dir = np.array([-n[1], n[0]])
        turn = math.acos(min(1.0, abs(float(line_dir @ direction))))
        if turn > MAX_TURN:
            continue  # a crossing wall, not the one drawn along
        score = math.log(n_in) - offset**2 / (2 * closeness**2) - turn**2 / (2 * sigma_t**2)
        sel = idx[inlier]
        pose = owner_of[sel]
        rows = np.stack([pose, sel - map.offsets[pose]], axis=1).astype(np.int64)
        found.append((score, rows, (int(who[0]), int(who[-1])), offset, turn))
    if not found:
        return None
    found.sort(key=lambda f: -f[0])
    score, rows, span, offset, turn = found[0]
    runner_up = found[1][0] if len(found) > 1 else -math.inf
    return PassLine(rows, span, score, runner_up, offset, turn)
