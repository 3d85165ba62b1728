"""The odometry checked against the scans (docs/ALGORITHM.md §I.5): every step of the chain,
``z_k = x_k^-1 x_(k+1)``, is compared with a scan-to-scan match of the two scans it joins. Where
their turns disagree far beyond both variances (a gyro fault, a wheel slip: the paper's 30-degree
sensor failure) and the matches across the step confirm it, the step's turn is re-measured: its
heading becomes the scan match's, with the match's variance, so a correction's back-propagation
and joint solve put the error there instead of spreading it over the loop.
Steps the scans cannot check (too little overlap, a featureless view) keep their information.

The map itself is not changed: its poses stay the odometry's until a person corrects it; only
where a correction's error goes is decided by the evidence.

The scans are matched once per map, never per correction:
- a map the front end built (``hitl-slam slam``) needs no matching: its chain edges are the scan
  matches themselves, and the steps it could not match are listed in its metadata
  (``front_end_steps``, one :class:`hitl_slam.slam.StepKind` per scan);
- any other map is matched when a session starts on it (:func:`with_stored_check`), and the
  outcome is kept in the map's metadata, so the session file holds it and a reopen reads it
  (``odometry_check_*``, docs/FORMATS.md). It is used only while the map's scans, chain and
  setting are those it was computed from (a fingerprint is stored with it).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.geometry import chain_steps, compose, wrap
from hitl_slam.map import Map

__all__ = [
    "OdometryCheck",
    "check_odometry",
    "checked_chain",
    "checked_map",
    "stored_check",
    "unchecked_steps",
    "with_stored_check",
]

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


CHUNK = 500
"""Consecutive scan pairs matched per call into the core, between two progress reports."""

FRONT_END_STEPS = "front_end_steps"
"""Metadata of a front-end map: how each scan was placed (``StepKind``, uint8 per scan)."""
FAILED_STEP = 3  # StepKind.FAILED

# The stored outcome of the check (metadata arrays, docs/FORMATS.md).
STORED_SETTING = "odometry_check_setting"  # float64 (1,): Config.odometry_check it used
STORED_MATCHED = "odometry_check_matched"  # bool (N - 1,): the steps the scans could check
STORED_STEPS = "odometry_check_steps"  # int64 (R,): the steps whose turn is the scans'
STORED_TURNS = "odometry_check_turns"  # float64 (R, 2): that turn [rad] and its variance
STORED_FINGERPRINT = "odometry_check_fingerprint"  # int64 (3,): what it was computed from
STORED_KEYS = (STORED_SETTING, STORED_MATCHED, STORED_STEPS, STORED_TURNS, STORED_FINGERPRINT)


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
        r2 = wrap(float(guess[0, 2] - found[0, 2]))
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


def _match_chain(
    map: Map, guesses: FloatArray, progress: Callable[[int, int], object] | None
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray]:
    """Every scan k+1 matched against scan k from ``guesses[k]``, :data:`CHUNK` pairs per call
    into the core (``progress(done, total)`` after each): (matched, found, covariances,
    overlap)."""
    steps = guesses.shape[0]
    points = np.ascontiguousarray(map.points)
    if progress is None or steps <= CHUNK:
        out = _core.match_consecutive(points, map.offsets, guesses, min_overlap=MIN_OVERLAP)
        if progress is not None:
            progress(steps, steps)
        return out
    parts = []
    for lo in range(0, steps, CHUNK):
        hi = min(lo + CHUNK, steps)  # the pairs lo..hi-1: scans lo..hi
        first, last = int(map.offsets[lo]), int(map.offsets[hi + 1])
        parts.append(
            _core.match_consecutive(
                points[first:last],
                np.ascontiguousarray(map.offsets[lo : hi + 2] - first),
                np.ascontiguousarray(guesses[lo:hi]),
                min_overlap=MIN_OVERLAP,
            )
        )
        progress(hi, steps)
    matched, found, cov, overlap = (np.concatenate([p[i] for p in parts]) for i in range(4))
    return matched, found, cov, overlap


def _front_end_steps(map: Map) -> NDArray[np.uint8] | None:
    """The front end's per-scan step kinds of a map it built (None for any other map).

    Raises:
        InputError: the metadata is there but malformed."""
    steps = map.metadata.get(FRONT_END_STEPS)
    if steps is None:
        return None
    a = np.asarray(steps)
    if a.shape != (map.num_poses,) or a.dtype.kind not in "ui" or (a.size and a.max() > 3):
        raise InputError(
            f"{map.name}: metadata {FRONT_END_STEPS} must hold one step kind (0-3) per scan "
            f"({map.num_poses}), got shape {a.shape} and dtype {a.dtype}: the map is damaged; "
            "run the front end again"
        )
    return a.astype(np.uint8)


def check_odometry(
    map: Map,
    config: Config = DEFAULT,
    progress: Callable[[int, int], object] | None = None,
) -> OdometryCheck:
    """Matches every pair of consecutive scans and widens the heading information of the chain
    edges whose turn the scans contradict (squared Mahalanobis distance of the heading
    difference above ``config.odometry_check``, 1 dof): the heading variance grows by the
    squared disagreement. Only the heading: a scan match along a corridor or among repeated
    structure can be off by a metre along it while its turn is right, and heading faults (a
    gyro, a wheel slip while turning) are the ones that bend a whole map. A step is widened only
    when the matches two steps apart across it confirm the fault (:func:`_confirmed`).

    A map the front end built is not matched again: its chain edges are its scan matches, so
    none is contradicted, and the steps it could not match are the unchecked ones.
    ``progress(done, total)`` follows the matching."""
    rows = _chain_rows(map)
    guesses = chain_steps(map.poses)
    has_edge = rows >= 0
    guesses[has_edge] = map.measurements[rows[has_edge]]
    guesses = np.ascontiguousarray(guesses, dtype=np.float64)
    kinds = _front_end_steps(map)
    if kinds is not None:
        return OdometryCheck(
            matched=kinds[1:] != FAILED_STEP,
            scan_match=guesses,
            distance2=np.where(kinds[1:] != FAILED_STEP, 0.0, math.nan),
            relaxed=np.zeros(0, dtype=np.int64),
            measurements=map.measurements,
            information=map.information,
        )
    matched, found, cov, _ = _match_chain(map, guesses, progress)
    info = map.information.copy()
    measurements = map.measurements.copy()
    distance2 = np.full(rows.shape[0], math.nan)
    relaxed = []
    for k in np.flatnonzero(matched & has_edge):
        row = rows[k]
        r = wrap(float(map.measurements[row, 2] - found[k, 2]))
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


def _fingerprint(map: Map) -> NDArray[np.int64]:
    """CRC-32s of what the check reads: the scans (points, offsets) and the chain's edges
    (measurements and information)."""
    rows = _chain_rows(map)
    rows = rows[rows >= 0]
    parts = (
        map.points,
        map.offsets,
        np.concatenate([map.measurements[rows].ravel(), map.information[rows].ravel()]),
    )
    return np.array([zlib.crc32(np.ascontiguousarray(a).data) for a in parts], dtype=np.int64)


def _stored_arrays(map: Map, check: OdometryCheck, config: Config) -> dict[str, object]:
    rows = check.relaxed
    steps = map.edges[rows, 0].astype(np.int64)
    variance = np.linalg.inv(check.information[rows])[:, 2, 2] if rows.size else np.zeros(0)
    return {
        STORED_SETTING: np.array([config.odometry_check], dtype=np.float64),
        STORED_MATCHED: np.asarray(check.matched, dtype=bool),
        STORED_STEPS: steps,
        STORED_TURNS: np.stack([check.measurements[rows, 2], variance], axis=1).reshape(-1, 2),
        STORED_FINGERPRINT: _fingerprint(map),
    }


def _stores(config: Config) -> bool:
    """Whether there is a check's outcome to store under ``config``: the check is on."""
    return config.odometry_check > 0


def with_stored_check(
    map: Map,
    config: Config = DEFAULT,
    progress: Callable[[int, int], object] | None = None,
) -> Map:
    """``map`` with the outcome of :func:`check_odometry` in its metadata (docs/FORMATS.md), so
    that whoever holds the map (a session file, a reopen) does not match its scans again.
    ``map`` itself when nothing needs storing: a map the front end built, one with fewer than
    two scans, the check off, or an outcome already stored for these scans, chain and setting.
    ``progress(done, total)`` follows the matching."""
    if (
        not _stores(config)
        or map.num_poses < 2
        or _front_end_steps(map) is not None
        or stored_check(map, config) is not None
    ):
        return map
    check = check_odometry(map, config, progress)
    metadata = dict(map.metadata)
    metadata.update(_stored_arrays(map, check, config))
    return dataclasses.replace(map, metadata=metadata)


def stored_check(map: Map, config: Config = DEFAULT) -> tuple[Map, NDArray[np.bool_]] | None:
    """The checked map and its unchecked steps from the outcome stored in ``map``'s metadata
    (:func:`with_stored_check`), or None when there is none for this setting, or it was
    computed from other scans or another chain (then the check is made again).

    Raises:
        InputError: the stored arrays are malformed (a damaged map)."""
    md = map.metadata
    present = [k for k in STORED_KEYS if k in md]
    if not present or not _stores(config):
        return None
    n = map.num_poses
    try:
        if len(present) != len(STORED_KEYS):
            raise ValueError(f"only {', '.join(present)} of {', '.join(STORED_KEYS)}")
        setting = np.asarray(md[STORED_SETTING], dtype=np.float64)
        matched = np.asarray(md[STORED_MATCHED])
        steps = np.asarray(md[STORED_STEPS])
        turns = np.asarray(md[STORED_TURNS], dtype=np.float64)
        fingerprint = np.asarray(md[STORED_FINGERPRINT])
        if setting.shape != (1,) or matched.shape != (n - 1,) or matched.dtype != bool:
            raise ValueError("a setting and one flag per chain step expected")
        if steps.ndim != 1 or steps.dtype.kind != "i" or turns.shape != (steps.size, 2):
            raise ValueError("one turn and variance per re-measured step expected")
        if steps.size and not (steps.min() >= 0 and steps.max() < n - 1):
            raise ValueError("a re-measured step outside the chain")
        if not (np.all(np.isfinite(turns)) and np.all(turns[:, 1] > 0)):
            raise ValueError("a turn or variance that is not finite and positive")
        if fingerprint.shape != (3,):
            raise ValueError("a fingerprint of three checksums expected")
    except (ValueError, TypeError) as exc:
        raise InputError(
            f"{map.name}: the stored odometry check is malformed ({exc}): the map is damaged; "
            "load the original map again"
        ) from None
    if float(setting[0]) != config.odometry_check or not np.array_equal(
        fingerprint, _fingerprint(map)
    ):
        return None
    rows = _chain_rows(map)[steps]
    if np.any(rows < 0):
        return None
    information = map.information.copy()
    measurements = map.measurements.copy()
    for row, (turn, variance) in zip(rows, turns, strict=True):
        information[row] = _turn_variance_replaced(np.linalg.inv(map.information[row]), variance)
        measurements[row, 2] = turn
    out = dataclasses.replace(map, measurements=measurements, information=information)
    unchecked = ~matched
    unchecked.flags.writeable = False
    return out, unchecked


def checked_map(map: Map, config: Config = DEFAULT) -> Map:
    """``map`` with its edges' information widened where the scans contradict the odometry
    (:func:`check_odometry`): from the outcome stored with the map, or the front end's own
    matches, or else matched now (a :class:`~hitl_slam.workspace.Workspace` keeps it); ``map``
    itself when the check is off or changes nothing. Same poses, points and edges: only the
    information differs."""
    return checked_chain(map, config)[0]


def unchecked_steps(map: Map, config: Config = DEFAULT) -> NDArray[np.bool_]:
    """``(N - 1,)`` read-only: the chain steps k -> k+1 that the scans could not check (no
    match: too little overlap, a featureless view), where a fault can hide from the check; all
    False when the check is off."""
    return checked_chain(map, config)[1]


def checked_chain(map: Map, config: Config = DEFAULT) -> tuple[Map, NDArray[np.bool_]]:
    """:func:`checked_map` and :func:`unchecked_steps` at once (one check)."""
    if config.odometry_check <= 0 or map.num_poses < 2:
        return map, np.zeros(max(map.num_poses - 1, 0), dtype=bool)
    stored = stored_check(map, config)
    if stored is not None:
        return stored
    check = check_odometry(map, config)
    same = check.measurements is map.measurements and check.information is map.information
    out = (
        map
        if same
        else dataclasses.replace(
            map, measurements=check.measurements, information=check.information
        )
    )
    unchecked = ~check.matched
    unchecked.flags.writeable = False
    return out, unchecked
