"""From a raw laser log to a consistent map: the scan-matching front end of the Rust core
(``rust/src/frontend/slam.rs``; docs/ALGORITHM.md §F) run over a :class:`~hitl_slam.map.Map`
whose poses are the log's odometry, giving a map whose poses are the front end's and whose
factors are what it measured: each step between consecutive scans (from their matches) and every
loop closure it found. The map's metadata lists the loop closures (:mod:`hitl_slam.loop_closures`)
with the trust the final solve gave each; the ones it rejected (weight below 0.5) are left out of
every solve of a session until a person reinstates them. A person can then repair what the front
end got wrong, reject a loop closure it trusted, or reinstate one it rejected.
"""

from __future__ import annotations

import enum
import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.errors import InputError
from hitl_slam.geometry import chain_steps
from hitl_slam.loop_closures import effective_map, loop_closure_metadata
from hitl_slam.map import InformationSource, Map

__all__ = ["Doubtful", "LoopClosures", "SlamResult", "StepKind", "slam"]

FloatArray = NDArray[np.float64]

REJECTED_WEIGHT = 0.5
"""A loop closure the final solve's dynamic covariance scaling weighs below this is rejected."""


_MIN_SCAN_PERIOD_S = 1e-3
"""Timestamps spanning less than this per scan are not the robot's clock (see
:attr:`SlamResult.real_time_factor`)."""


class StepKind(enum.IntEnum):
    """How the front end placed a scan (:attr:`SlamResult.steps`)."""

    DIRECT = 0
    """ICP against the local map from the odometry's prediction (and the first scan)."""
    SEARCHED = 1
    """The correlative search over the local window, refined by ICP."""
    AMBIGUOUS = 2
    """Two distinct poses explain the scan about as well (a corridor, along its axis): counted,
    and the best match is kept (keeping the odometry was measured worse, docs §F.1)."""
    FAILED = 3
    """No match (too few points, too low a score, a failed refinement): the odometry's step."""


_DOUBTS = {
    0: "match failed",
    1: "contradicts the loop closures",
    2: "weak match",
    3: "odometry jump",
}


@dataclass(frozen=True)
class Doubtful:
    """A stretch of the map the front end does not vouch for: scans ``first..last`` (0-based,
    inclusive) and why: ``"match failed"`` (its scans could not be matched over at least a
    keyframe's worth of motion: their poses are the odometry's), ``"weak match"`` (three or more
    matches in a row paired under half the share of points the recent ones paired: scans that
    fit the local map only in part, as scans from elsewhere do), ``"odometry jump"`` (a scan
    placed far outside what the odometry predicts, by a match that is ambiguous or pairs under
    half the usual share: a glitch of the odometry, or scans from elsewhere) or ``"contradicts
    the loop closures"`` (the final solve bends steps there far from what the scans matched)."""

    first: int
    last: int
    reason: str

    def as_dict(self) -> dict[str, object]:
        return {"first": self.first, "last": self.last, "reason": self.reason}


@dataclass(frozen=True)
class LoopClosures:
    """Every loop closure the front end found: scan pairs ``(L, 2)``, the matched relative pose
    of the second scan in the first's frame ``(L, 3)``, its information ``(L, 3, 3)``, the
    correlative score (mean likelihood, 0..1), the final solve's robust weight (1: fully
    trusted; below :data:`REJECTED_WEIGHT`: rejected) and whether the group test set it aside
    before any solve (inconsistent with the other closures found with it; weight 0)."""

    pairs: NDArray[np.int64]
    measurements: FloatArray
    information: FloatArray
    scores: FloatArray
    weights: FloatArray
    set_aside: NDArray[np.bool_]

    @property
    def accepted(self) -> NDArray[np.bool_]:
        return (self.weights >= REJECTED_WEIGHT) & ~self.set_aside


@dataclass(frozen=True)
class SlamResult:
    """The map the front end built (poses per scan; factors: the matched steps and every loop
    closure, listed in its metadata, see :mod:`hitl_slam.loop_closures`), its keyframes (scan
    indices), every loop closure, and the timing. :meth:`accepted_map` is the map without the
    rejected loop closures: the graph the front end's poses solve."""

    map: Map
    keyframes: NDArray[np.int64]
    loop_closures: LoopClosures
    submaps: int
    time_s: float
    duration_s: float | None  # [s] of data in the log (timestamps), if known
    steps: NDArray[np.uint8]  # per scan, a StepKind
    overlap: FloatArray  # per scan, the share of its points its match paired (NaN: none)
    doubtful: tuple[Doubtful, ...]

    @property
    def verdict(self) -> str:
        """``"good"``, or ``"doubtful"`` when a stretch is (:attr:`doubtful`)."""
        return "doubtful" if self.doubtful else "good"

    def accepted_map(self) -> Map:
        """:attr:`map` without the loop closures the front end rejected (its edges: the matched
        steps and the accepted loop closures), e.g. to export as a pose graph."""
        rejected = np.flatnonzero(~self.loop_closures.accepted)
        return effective_map(self.map, frozenset(int(k) for k in rejected))

    @property
    def real_time_factor(self) -> float | None:
        """Seconds of data per second of work; None when the log's timestamps cannot say (none,
        or spanning under a millisecond per scan: no laser scans at a kilohertz, so the log's
        clock was not the robot's, as in logs whose timestamps were all written at once)."""
        d = self.duration_s
        if d is None or not math.isfinite(d) or self.time_s <= 0:
            return None
        if d < _MIN_SCAN_PERIOD_S * max(self.map.num_poses - 1, 1):
            return None
        return d / self.time_s

    def summary(self) -> str:
        loops = self.loop_closures
        accepted = int(loops.accepted.sum())
        rtf = self.real_time_factor
        if rtf is not None:
            speed = f", {rtf:.1f}x real time"
        elif self.duration_s is not None and math.isfinite(self.duration_s):
            speed = f"; the log's timestamps span {self.duration_s:.3g} s, too little to time it by"
        else:
            speed = ""
        set_aside = int(loops.set_aside.sum())
        failed = int(np.count_nonzero(self.steps == StepKind.FAILED))
        ambiguous = int(np.count_nonzero(self.steps == StepKind.AMBIGUOUS))
        if self.doubtful:
            shown = ", ".join(
                f"scans {d.first}-{d.last} ({d.reason})" for d in self.doubtful[:_SHOWN]
            )
            more = len(self.doubtful) - _SHOWN
            verdict = (
                f"DOUBTFUL map, {len(self.doubtful)} stretch"
                f"{'es' if len(self.doubtful) > 1 else ''}: {shown}"
                + (f" and {more} more" if more > 0 else "")
                + "; look there first"
            )
        else:
            verdict = "good map"
        return (
            f"{verdict}; {self.map.num_poses} scans ({failed} unmatched, {ambiguous} ambiguous), "
            f"{self.keyframes.size} keyframes, {self.submaps} submaps; loop closures: "
            f"{accepted} accepted, {loops.pairs.shape[0] - accepted - set_aside} rejected, "
            f"{set_aside} set aside as inconsistent; {self.time_s:.1f} s "
            f"({self.map.num_poses / max(self.time_s, 1e-9):.0f} scans/s{speed})"
        )


_SHOWN = 3
"""Doubtful stretches named in the summary line (all are in :attr:`SlamResult.doubtful`)."""


def _scan_place(raw: Map, message: str) -> str:
    """``FILE`` or ``FILE:LINE`` for a core message that starts ``scan K of N`` (1-based), when
    the map knows its scans' lines."""
    where = raw.source or raw.name
    lines = raw.metadata.get("scan_lines")
    found = re.match(r"scan (\d+) of ", message)
    if found and isinstance(lines, np.ndarray) and 1 <= int(found[1]) <= lines.size:
        return f"{where}:{int(lines[int(found[1]) - 1])}"
    return where


def slam(
    source: Map | str | os.PathLike[str],
    *,
    progress: Callable[[int, int], object] | None = None,
    keyframe_distance: float = 0.2,
    keyframe_angle_deg: float = 10.0,
    max_range: float = 20.0,
    loop_min_score: float = 0.55,
    dcs: float = 10.0,
) -> SlamResult:
    """Runs the front end over ``source`` (a Map whose poses are odometry, or a log's path,
    read by :func:`hitl_slam.io.maps.load_map`). ``progress(done, total)`` is called every few
    hundred scans. Matching uses points within ``max_range`` [m]; a scan that moved
    ``keyframe_distance`` [m] or turned ``keyframe_angle_deg`` since the last keyframe becomes
    one; loop closures need a correlative score of ``loop_min_score`` and are weighed by dynamic
    covariance scaling with Phi = ``dcs``.

    Raises:
        InputError: the log cannot be read, has no scans, or a setting is out of range.
    """
    if isinstance(source, Map):
        raw = source
    else:
        from hitl_slam.io.maps import load_map

        raw = load_map(source)
    n = raw.num_poses
    total = n
    where = raw.source or raw.name
    if n > 1 and raw.num_points == 0:
        raise InputError(
            f"{where}: none of the {n} scans has a usable point (every reading is a no-return, "
            "invalid or out of the laser's range); the front end matches scans by their points: "
            "check the laser's range fields (or --max-range) and the log"
        )

    def report(done: int) -> None:
        if progress is not None:
            progress(done, total)

    t0 = time.perf_counter()
    try:
        out = _core.run_slam(
            raw.points,
            raw.offsets,
            raw.poses,
            progress=report,
            keyframe_distance=keyframe_distance,
            keyframe_angle_deg=keyframe_angle_deg,
            max_range=max_range,
            loop_min_score=loop_min_score,
            dcs=dcs,
        )
    except InputError as exc:
        # The core names scans by their place in the log; the file (and for a CARMEN log the
        # line of the scan named first) is said here.
        raise InputError(f"{_scan_place(raw, str(exc))}: {exc}") from None
    elapsed = time.perf_counter() - t0
    poses, step_info = out["poses"], out["step_information"]
    pairs, z, info = out["loop_pairs"], out["loop_measurements"], out["loop_information"]
    scores, weights = out["loop_scores"], out["loop_weights"]
    loops = LoopClosures(pairs, z, info, scores, weights, out["loop_set_aside"])
    doubtful = tuple(
        Doubtful(int(a), int(b), _DOUBTS[int(why)])
        for (a, b), why in zip(out["doubtful"], out["doubt"], strict=True)
    )
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(np.int64)
    edges = np.concatenate([chain, pairs]).astype(np.int64)
    measurements = np.concatenate([chain_steps(poses), z])
    information = np.concatenate([step_info[1:], info])
    if edges.shape[0] == 0:
        raise InputError(
            f"{raw.source or raw.name}: one laser scan; the front end needs at least two to "
            "build a map: give a longer log"
        )
    metadata = dict(raw.metadata)
    metadata["front_end"] = "hitl-slam"
    metadata["front_end_verdict"] = "doubtful" if doubtful else "good"
    metadata["front_end_doubtful"] = [d.as_dict() for d in doubtful]
    # How each scan was placed: the odometry check reads its unmatched steps from here instead
    # of matching the scans again (hitl_slam.odometry_check).
    metadata["front_end_steps"] = np.ascontiguousarray(out["steps"], dtype=np.uint8)
    metadata.update(
        loop_closure_metadata(
            np.arange(n - 1, n - 1 + pairs.shape[0], dtype=np.int64),
            np.clip(weights, 0.0, 1.0),
            scores,
            ~loops.accepted,
        )
    )
    built = Map(
        poses=poses,
        points=raw.points,
        offsets=raw.offsets,
        edges=edges,
        measurements=measurements,
        information=information,
        information_source=np.full(edges.shape[0], InformationSource.INPUT, dtype=np.int8),
        normals=raw.normals,
        timestamps=raw.timestamps,
        anchor=0,
        name=f"{raw.name} (hitl-slam front end)",
        source=raw.source,
        metadata=metadata,
    )
    duration = None
    if raw.timestamps is not None and n > 1:
        duration = float(raw.timestamps[-1] - raw.timestamps[0])
    return SlamResult(
        built,
        out["keyframes"],
        loops,
        int(out["submaps"]),
        elapsed,
        duration,
        out["steps"],
        out["overlap"],
        doubtful,
    )
