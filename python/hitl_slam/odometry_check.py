"""The odometry checked against the scans (docs/ALGORITHM.md §I.5): every step of the chain,
``z_k = x_k^-1 x_(k+1)``, is compared with a scan-to-scan match of the two scans it joins. Where
their turns disagree far beyond both variances (a gyro fault, a wheel slip: the paper's 30-degree
sensor failure) and the matches across the step confirm it, the step's turn is re-measured: its
heading becomes the scan match's, with the match's variance, so a correction's back-propagation
and joint solve put the error there instead of spreading it over the loop.
Steps the scans cannot check (too little overlap, a featureless view) keep their information.

The map itself is not changed: its poses stay the odometry's until a person corrects it; only
where a correction's error goes is decided by the evidence.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import weakref
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.geometry import chain_steps, compose
from hitl_slam.map import Map

__all__ = ["OdometryCheck", "check_odometry", "checked_map", "unchecked_steps"]

FloatArray = NDArray[np.float64]
logger = logging.getLogger(__name__)

MIN_OVERLAP = 0.1
"""A scan match counts when this share of the newer scan's points (and at least 25) pair with
lines of the older one. In cluttered rooms (Freiburg 079) a robot turning on the spot matches to a
tenth of a degree with only 13-20% of its points on lines; at the scan matcher's own default
(25%) those steps, a jump among them, went unchecked. A contradiction is still acted on only when
the matches across the step confirm it (:func:`_confirmed`)."""

CONFIRM_OVERLAP = 0.25
"""The confirming matches, two steps apart, count from this overlap: every one that counts must
agree, and a loosely overlapping one that matched wrongly would veto a real fault (Orebro with a
30-degree jump: at 10% the jump went unconfirmed and the first correction left the walls 24
degrees off)."""


FUSE_OVERLAP = 0.5
"""A step is fused with its scan match only when at least half of the scan's points paired: the
fused turn trusts the match, and in clutter (Freiburg 079, where a quarter of the matches pair
under 41% of their points) a loosely overlapping match can agree with the odometry within its
noise and still be biased by what moved."""


@dataclass(frozen=True)
class OdometryCheck:
    """Per chain step k -> k+1 (``N - 1`` rows): whether the scans matched (``matched``), the
    match (``scan_match``, as ``x_k^-1 x_(k+1)``), the squared Mahalanobis distance between it and
    the odometry (``distance2``; NaN where unmatched), and the edge rows of the map whose
    information was widened (``relaxed``)."""

    matched: NDArray[np.bool_]
    scan_match: FloatArray
    distance2: FloatArray
    relaxed: NDArray[np.int64]
    measurements: FloatArray  # (M, 3) the map's edge measurements, turned where contradicted
    information: FloatArray  # (M, 3, 3) the map's edge information, the scans' where contradicted


def _chain_rows(map: Map) -> NDArray[np.int64]:
    """For each step k -> k+1, the row of the map's edge joining them (-1: none)."""
    rows = np.full(max(map.num_poses - 1, 0), -1, dtype=np.int64)
    e = map.edges
    forward = np.flatnonzero(e[:, 1] == e[:, 0] + 1)
    rows[e[forward, 0]] = forward
    return rows


def _confirmed(map: Map, steps: FloatArray, k: int, r: float, config: Config) -> bool:
    """Whether the scans two steps apart across step k (k-1 -> k+1 and k -> k+2) tell the same:
    at least one such match found, and every one found disagrees with the odometry's two-step
    turn by about ``r`` too (beyond the same test). One scan pair can match wrongly with a
    confident covariance (a door frame, a moving person); a real fault shows in every pair
    across it."""
    n = map.num_poses
    votes = []
    for i in (k - 1, k):
        j = i + 2
        if i < 0 or j >= n:
            continue
        pts = [map.points[map.offsets[p] : map.offsets[p + 1]] for p in (i, j)]
        offsets = np.array([0, len(pts[0]), len(pts[0]) + len(pts[1])], dtype=np.int64)
        guess = compose(steps[i], steps[i + 1].reshape(1, 3))
        ok, found, cov, _ = _core.match_consecutive(
            np.ascontiguousarray(np.concatenate(pts)),
            offsets,
            np.ascontiguousarray(guess),
            min_overlap=CONFIRM_OVERLAP,
        )
        if not ok[0]:
            continue
        r2 = math.remainder(float(guess[0, 2] - found[0, 2]), 2 * math.pi)
        votes.append(
            r2 * r > 0
            and r2 * r2 / (4 * float(cov[0, 2, 2])) > config.odometry_check
            and abs(r2 - r) < 0.5 * abs(r)
        )
    return bool(votes) and all(votes)


def _turn_variance_replaced(odo_cov: FloatArray, variance: float) -> FloatArray:
    """The information of a step whose turn gets ``variance``, uncorrelated with its translation,
    which keeps the odometry's covariance ``odo_cov``."""
    out = odo_cov.copy()
    out[2, :] = out[:, 2] = 0.0
    out[2, 2] = variance
    return np.asarray(np.linalg.inv(out), dtype=np.float64)


def check_odometry(map: Map, config: Config = DEFAULT) -> OdometryCheck:
    """Matches every pair of consecutive scans and widens the heading information of the chain
    edges whose turn the scans contradict (squared Mahalanobis distance of the heading
    difference above ``config.odometry_check``, 1 dof): the heading variance grows by the
    squared disagreement. Only the heading: a scan match along a corridor or among repeated
    structure can be off by a metre along it while its turn is right, and heading faults (a
    gyro, a wheel slip while turning) are the ones that bend a whole map. A step is widened only
    when the matches two steps apart across it confirm the fault (:func:`_confirmed`). A step
    whose scans agree with it (distance at most ``config.odometry_fuse``) takes the
    information-weighted mean of both turns, with the fused variance."""
    rows = _chain_rows(map)
    guesses = chain_steps(map.poses)
    has_edge = rows >= 0
    guesses[has_edge] = map.measurements[rows[has_edge]]
    guesses = np.ascontiguousarray(guesses, dtype=np.float64)
    matched, found, cov, overlap = _core.match_consecutive(
        np.ascontiguousarray(map.points), map.offsets, guesses, min_overlap=MIN_OVERLAP
    )
    info = map.information.copy()
    measurements = map.measurements.copy()
    distance2 = np.full(rows.shape[0], math.nan)
    relaxed = []
    for k in np.flatnonzero(matched & has_edge):
        row = rows[k]
        r = float(math.remainder(map.measurements[row, 2] - found[k, 2], 2 * math.pi))
        try:
            odo_cov = np.linalg.inv(info[row])
        except np.linalg.LinAlgError:
            continue
        odo_var = float(odo_cov[2, 2])
        d2 = r * r / (odo_var + float(cov[k, 2, 2]))
        distance2[k] = d2
        if (
            config.odometry_check > 0
            and d2 > config.odometry_check
            and _confirmed(map, guesses, int(k), r, config)
        ):
            # The step's turn is the scans' (with their variance); its translation, in the
            # robot's frame, stays the odometry's (a heading fault leaves it right).
            info[row] = _turn_variance_replaced(odo_cov, float(cov[k, 2, 2]))
            measurements[row, 2] = found[k, 2]
            relaxed.append(int(row))
        elif (
            config.odometry_fuse > 0
            and d2 <= config.odometry_fuse
            and float(overlap[k]) >= FUSE_OVERLAP
        ):
            # The scans agree with the step within their noise: its turn becomes the
            # information-weighted mean of the two (a slow bend or drift biases every step a
            # little; the scans, unbiased, take a share of it out at each step).
            s_var = float(cov[k, 2, 2])
            gain = odo_var / (odo_var + s_var)
            info[row] = _turn_variance_replaced(odo_cov, odo_var * s_var / (odo_var + s_var))
            measurements[row, 2] = map.measurements[row, 2] - gain * r
    if relaxed:
        steps = ", ".join(
            f"{int(map.edges[r, 0])}->{int(map.edges[r, 1])}" for r in relaxed[:8]
        ) + (" ..." if len(relaxed) > 8 else "")
        logger.info(
            "odometry check: %d of %d steps contradicted by their scans (%s)",
            len(relaxed),
            rows.shape[0],
            steps,
        )
    return OdometryCheck(
        matched=np.asarray(matched, dtype=bool),
        scan_match=found,
        distance2=distance2,
        relaxed=np.array(relaxed, dtype=np.int64),
        measurements=measurements,
        information=info,
    )


_CACHE: dict[int, tuple[weakref.ref[Map], tuple[float, float], Map, NDArray[np.bool_]]] = {}


def checked_map(map: Map, config: Config = DEFAULT) -> Map:
    """``map`` with its edges' information widened where the scans contradict the odometry
    (:func:`check_odometry`), computed once per map and threshold; ``map`` itself when the
    check is off. Same poses, points and edges: only the information differs."""
    if (config.odometry_check <= 0 and config.odometry_fuse <= 0) or map.num_poses < 2:
        return map
    key = id(map)
    settings = (config.odometry_check, config.odometry_fuse)
    hit = _CACHE.get(key)
    if hit is not None and hit[0]() is map and hit[1] == settings:
        return hit[2]
    derived = _derived_check(map, config)
    if derived is None:
        check = check_odometry(map, config)
        out = dataclasses.replace(
            map, measurements=check.measurements, information=check.information
        )
        unchecked = ~check.matched
        unchecked.flags.writeable = False
    else:
        out, unchecked = derived
    _CACHE[key] = (weakref.ref(map, partial(_forget, key)), settings, out, unchecked)
    return out


def unchecked_steps(map: Map, config: Config = DEFAULT) -> NDArray[np.bool_]:
    """``(N - 1,)`` read-only: the chain steps k -> k+1 that the scans could not check (no
    match: too little overlap, a featureless view), where a fault can hide from the check; all
    False when the check is off. Computed with :func:`checked_map`, once per map."""
    if (config.odometry_check <= 0 and config.odometry_fuse <= 0) or map.num_poses < 2:
        return np.zeros(max(map.num_poses - 1, 0), dtype=bool)
    checked_map(map, config)
    return _CACHE[id(map)][3]


def _forget(key: int, _ref: object) -> None:
    _CACHE.pop(key, None)


def share_check(full: Map, derived: Map, keep: NDArray[np.bool_]) -> None:
    """Records that ``derived`` is ``full`` with only the edges ``keep`` marks (the chain among
    them), so that checking it does not match its scans again: the check reads and changes the
    chain's edges only, so ``derived``'s checked edges are ``full``'s (computed once, for any
    number of derived maps), less the dropped rows."""
    key = id(derived)
    _DERIVED[key] = (
        weakref.ref(derived, partial(_forget_derived, key)),
        weakref.ref(full),
        np.asarray(keep, dtype=bool),
    )


_DERIVED: dict[int, tuple[weakref.ref[Map], weakref.ref[Map], NDArray[np.bool_]]] = {}


def _forget_derived(key: int, _ref: object) -> None:
    _DERIVED.pop(key, None)


def _derived_check(map: Map, config: Config) -> tuple[Map, NDArray[np.bool_]] | None:
    """:func:`checked_map` of a map registered by :func:`share_check`, from its full map's, and
    the full map's unchecked steps (the same chain)."""
    hit = _DERIVED.get(id(map))
    if hit is None or hit[0]() is not map:
        return None
    full = hit[1]()
    if full is None:
        return None
    checked = checked_map(full, config)
    keep = hit[2]
    out = dataclasses.replace(
        map, measurements=checked.measurements[keep], information=checked.information[keep]
    )
    return out, _CACHE[id(full)][3]
