"""The steps of an editing session (:mod:`hitl_slam.session`) and their records: where a
requested correction stands (:class:`EntryStatus`), the numbers of a step (:class:`CorrectionStats`,
:func:`moved_poses`), and each kind of step as the session shows it (:class:`HistoryEntry`,
:class:`LoopClosureStep`, :class:`AlignStep`) beside the record the session keeps of it.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.geometry import wrap
from hitl_slam.map import Map

__all__ = [
    "MOVED_ANGLE_RAD",
    "MOVED_DISTANCE_M",
    "AlignStep",
    "CorrectionStats",
    "EntryStatus",
    "HistoryEntry",
    "LoopClosureStep",
    "moved_poses",
]


MOVED_DISTANCE_M = 1e-3
"""A pose "moved" in a correction when its position changed by more than this [m] ..."""
MOVED_ANGLE_RAD = 1e-3
"""... or its heading by more than this [rad]."""


class EntryStatus(enum.Enum):
    """Where a requested correction stands."""

    PENDING = "pending"  # being computed right now
    APPLIED = "applied"  # part of the current map
    UNDONE = "undone"  # undone, can be redone
    DISCARDED = "discarded"  # undone, then dropped by a newer correction (as in any editor)
    REJECTED = "rejected"  # could not be interpreted; nothing changed
    INTERRUPTED = "interrupted"  # the computation failed or the program ended during it


@dataclass(frozen=True)
class CorrectionStats:
    """Numbers about one applied correction."""

    iterations: int
    initial_chi2: float
    final_chi2: float
    time_s: float  # [s] the applier's own time
    poses_moved: int  # poses that moved more than MOVED_DISTANCE_M or MOVED_ANGLE_RAD
    max_move_m: float  # [m] the largest change of a pose position

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> CorrectionStats:
        return cls(
            iterations=int(data["iterations"]),
            initial_chi2=float(data["initial_chi2"]),
            final_chi2=float(data["final_chi2"]),
            time_s=float(data["time_s"]),
            poses_moved=int(data["poses_moved"]),
            max_move_m=float(data["max_move_m"]),
        )


@dataclass(frozen=True, eq=False)
class HistoryEntry:
    """One requested correction, as the session's history shows it."""

    index: int  # position in the history, from 0
    seq: int  # journal sequence number of its request event
    time: float  # Unix time of the request
    drawn: Correction  # the raw input
    status: EntryStatus
    interpretation: Interpretation | None = None  # set once applied
    stats: CorrectionStats | None = None  # set once applied
    reason: str | None = None  # why it was rejected or interrupted

    @property
    def mode(self) -> Mode:
        return self.drawn.mode


@dataclass(eq=False)
class _Entry:
    index: int
    seq: int
    time: float
    drawn: Correction
    status: EntryStatus
    interpretation: Interpretation | None = None
    stats: CorrectionStats | None = None
    reason: str | None = None
    poses: NDArray[np.float64] | None = None  # checkpoint, while applied or redoable
    # (2K, 2) solved (phi, rho) of every correction in effect after this one, in order; None in
    # a journal written before lines were journaled (refit on demand, see Session.lines)
    lines: NDArray[np.float64] | None = None

    def snapshot(self) -> HistoryEntry:
        return HistoryEntry(
            self.index,
            self.seq,
            self.time,
            self.drawn,
            self.status,
            self.interpretation,
            self.stats,
            self.reason,
        )


@dataclass(frozen=True, eq=False)
class LoopClosureStep:
    """One loop closure rejected (``rejected``) or reinstated, as a step of the session: on the
    same undo/redo stack as the corrections."""

    seq: int  # journal sequence number of its event
    time: float  # Unix time
    loop: int  # the loop closure's index (:attr:`Session.loop_closures`)
    rejected: bool  # True: left out of the solve by this step; False: reinstated
    status: EntryStatus  # APPLIED, UNDONE or DISCARDED
    stats: CorrectionStats  # the re-solve with every correction in effect


@dataclass(eq=False)
class _Toggle:
    seq: int
    time: float
    loop: int
    rejected: bool
    stats: CorrectionStats
    status: EntryStatus
    poses: NDArray[np.float64] | None  # checkpoint, while applied or redoable
    lines: NDArray[np.float64] | None  # (2K, 2) the re-solved lines of the corrections in effect

    def snapshot(self) -> LoopClosureStep:
        return LoopClosureStep(
            self.seq, self.time, self.loop, self.rejected, self.status, self.stats
        )


@dataclass(frozen=True, eq=False)
class AlignStep:
    """The map aligned with its scans (docs/ALGORITHM.md §I.11), as a step of the session: on the
    same undo/redo stack as the corrections. While it is in effect its graph (the scans' matched
    steps and loop closures) replaces the map's factors in every solve."""

    seq: int  # journal sequence number of its event
    time: float  # Unix time
    status: EntryStatus  # APPLIED, UNDONE or DISCARDED
    stats: CorrectionStats  # the solve of every correction in effect over the aligned graph
    loop_closures: int  # loop closures the front end kept
    loop_closures_rejected: int
    steps: int  # odometry steps of the input map checked by the guard
    contradicted: int  # of them, contradicted by the aligned poses beyond their 99.9% bound
    inconsistency: tuple[float, float]  # [m^2] of the map before and after it
    relation_dcs: float  # the Phi of the corrections' relations in every solve while in effect


@dataclass(eq=False)
class _Align:
    seq: int
    time: float
    stats: CorrectionStats
    status: EntryStatus
    poses: NDArray[np.float64] | None  # checkpoint, while applied or redoable
    lines: NDArray[np.float64] | None  # (2K, 2) the re-solved lines of the corrections in effect
    edges: NDArray[np.int64]
    measurements: NDArray[np.float64]
    information: NDArray[np.float64]
    counts: tuple[int, int, int, int]  # loop closures kept, rejected; steps, contradicted
    inconsistency: tuple[float, float]
    relation_dcs: float | None  # None: an older journal's, config.align_relation_dcs
    graph: Map | None = None  # the aligned map, made on first use

    def snapshot(self, config: Config) -> AlignStep:
        kept, rejected, steps, bad = self.counts
        return AlignStep(
            self.seq,
            self.time,
            self.status,
            self.stats,
            kept,
            rejected,
            steps,
            bad,
            self.inconsistency,
            self.config(config).relation_dcs,
        )

    def config(self, config: Config) -> Config:
        """``config`` as every solve uses it while this alignment is in effect."""
        from hitl_slam.alignment import aligned_config

        return aligned_config(config, self.relation_dcs)

    def map_of(self, map: Map) -> Map:
        if self.graph is None:
            from hitl_slam.alignment import aligned_map

            self.graph = aligned_map(map, self.edges, self.measurements, self.information)
        return self.graph


_Step = _Entry | _Toggle | _Align


def _frozen(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    poses.flags.writeable = False
    return poses


def moved_poses(before: NDArray[np.float64], after: NDArray[np.float64]) -> tuple[int, float]:
    """How many poses moved more than :data:`MOVED_DISTANCE_M` or :data:`MOVED_ANGLE_RAD`
    between two ``(N, 3)`` pose arrays, and the largest change of a position [m]."""
    distance = np.hypot(after[:, 0] - before[:, 0], after[:, 1] - before[:, 1])
    turn = np.abs(wrap(after[:, 2] - before[:, 2]))
    moved = (distance > MOVED_DISTANCE_M) | (turn > MOVED_ANGLE_RAD)
    return int(np.count_nonzero(moved)), float(distance.max(initial=0.0))
