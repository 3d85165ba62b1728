"""An editing session on a map: corrections one at a time, loop closures rejected or reinstated
(on a map the front end built), the map aligned with its scans, undo and redo of any depth across
all of them, save; every event
journaled (:mod:`hitl_slam.journal`) before the map in memory changes, so reopening the file
rebuilds the same state bit for bit from the journal's pose checkpoints (docs/ALGORITHM.md §5).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.corrections_file import Apply, Step, Undo
from hitl_slam.errors import (
    CorrectionRejected,
    DamagedSession,
    InputError,
    SolverError,
    StepRefused,
)
from hitl_slam.geometry import fit_line, wrap
from hitl_slam.io.atomic import atomic_outputs
from hitl_slam.journal import Event, EventKind, Journal
from hitl_slam.loop_closures import (
    AUTO_REJECTED,
    EDGES,
    LoopClosure,
    LoopClosureTable,
)
from hitl_slam.map import Map
from hitl_slam.workspace import Workspace

__all__ = [
    "MOVED_ANGLE_RAD",
    "MOVED_DISTANCE_M",
    "AlignStep",
    "Applier",
    "CorrectionOutcome",
    "CorrectionStats",
    "EntryStatus",
    "HistoryEntry",
    "LoopClosureStep",
    "Session",
    "StepRefused",
    "StepResult",
    "apply_in_order",
    "moved_poses",
    "refit_lines",
]

MOVED_DISTANCE_M = 1e-3
"""A pose "moved" in a correction when its position changed by more than this [m] ..."""
MOVED_ANGLE_RAD = 1e-3
"""... or its heading by more than this [rad]."""

_DIED = "the program ended before the correction finished"


class CorrectionOutcome(Protocol):
    """What an applier returns (``hitl_slam.pipeline.CorrectionResult`` is one).

    An outcome may also carry ``lines``: ``(2K, 2)`` the solved ``(phi, rho)`` of every active
    correction's two lines, in order (the new one last); the session keeps and journals them.
    An outcome without them (a stand-in applier) has its lines refit to S_a / S_b instead.
    """

    @property
    def poses(self) -> NDArray[np.float64]: ...
    @property
    def interpretation(self) -> Interpretation: ...
    @property
    def iterations(self) -> int: ...
    @property
    def initial_chi2(self) -> float: ...
    @property
    def final_chi2(self) -> float: ...
    @property
    def time_s(self) -> float: ...


Applier = Callable[
    [Map, NDArray[np.float64], Correction, Sequence[Interpretation], Config],
    CorrectionOutcome,
]
"""``(map, poses, drawn, active, config) -> outcome``: interpret ``drawn`` on ``poses`` and solve
with the ``active`` corrections plus the new one, without mutating any input; raise
:class:`CorrectionRejected` when the drawing cannot be interpreted."""


def _default_applier(workspace: Workspace) -> Applier:
    """:func:`hitl_slam.pipeline.apply_correction` with ``workspace`` (what is kept about the map
    between corrections)."""
    from hitl_slam.pipeline import apply_correction

    return partial(apply_correction, workspace=workspace)


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


def _lines_from_json(data: Any, count: int) -> NDArray[np.float64]:
    """A journal's ``lines``: ``count`` finite ``[phi, rho]`` pairs (ValueError otherwise)."""
    lines = np.array(data, dtype=np.float64)
    if count == 0 and lines.size == 0:
        lines = lines.reshape(0, 2)
    if lines.shape != (count, 2) or not np.isfinite(lines).all():
        raise ValueError(f"lines must be {count} finite [phi, rho] pairs, got shape {lines.shape}")
    return _frozen(lines)


def _loop_state(rejected: bool) -> str:
    return "rejected" if rejected else "in the solve"


def _graph_from_json(
    data: Any, num_poses: int
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """An ``align`` event's ``graph``: edges, measurements and information (ValueError when
    malformed: missing, not finite, an edge outside the map or from a pose to itself)."""
    if not isinstance(data, dict):
        raise ValueError("its graph is not a JSON object")
    edges = np.array(data["edges"], dtype=np.int64)
    z = np.array(data["measurements"], dtype=np.float64)
    info = np.array(data["information"], dtype=np.float64)
    m = edges.shape[0] if edges.ndim == 2 else -1
    if m < 1 or edges.shape != (m, 2) or z.shape != (m, 3) or info.shape != (m, 9):
        raise ValueError(
            f"its graph must hold M edges, measurements and information rows of 2, 3 and 9 "
            f"numbers; got shapes {edges.shape}, {z.shape}, {info.shape}"
        )
    if not (np.isfinite(z).all() and np.isfinite(info).all()):
        raise ValueError("its graph holds a value that is not finite")
    if edges.min() < 0 or edges.max() >= num_poses or (edges[:, 0] == edges[:, 1]).any():
        raise ValueError(f"its graph has an edge outside the map's {num_poses} poses")
    return edges, z, info.reshape(m, 3, 3)


def _drawn_from_json(data: Any) -> Correction:
    if not isinstance(data, dict):
        raise TypeError("the correction is not a JSON object")
    return Correction.make(data["a"], data["b"], data["mode"], data.get("sigma_h"))


class _State:
    """The undo/redo state machine; fed the same events live and when a journal is replayed."""

    def __init__(self, initial: NDArray[np.float64], loops: LoopClosureTable | None = None) -> None:
        self.initial = _frozen(np.array(initial, dtype=np.float64, order="C"))
        self.loops = loops
        self.entries: list[_Entry] = []
        self.by_seq: dict[int, _Entry] = {}
        self.applied: list[_Step] = []
        self.redo: list[_Step] = []
        self.toggles: list[_Toggle] = []
        self.aligns: list[_Align] = []
        self.pending: _Entry | None = None

    @classmethod
    def for_map(cls, map: Map) -> _State:
        """The state of a new session on ``map`` (its loop closures, if any, from its metadata)."""
        return cls(map.poses, LoopClosureTable.of(map))

    def rejected(self) -> frozenset[int]:
        """The loop closures left out of the solve: the front end's rejections, then every
        applied toggle in order."""
        out = set() if self.loops is None else set(self.loops.auto_rejected_set)
        for step in self.applied:
            if isinstance(step, _Toggle):
                if step.rejected:
                    out.add(step.loop)
                else:
                    out.discard(step.loop)
        return frozenset(out)

    def alignment(self) -> _Align | None:
        """The alignment in effect: the last applied one (each replaces the previous one's
        graph), or None."""
        for step in reversed(self.applied):
            if isinstance(step, _Align):
                return step
        return None

    def graph(self, held: Workspace) -> Map:
        """The map every solve runs over now: the aligned map while an alignment is in effect,
        otherwise the workspace's map without the rejected loop closures."""
        aligned = self.alignment()
        if aligned is not None:
            return aligned.map_of(held.map)
        return held.graph(self.rejected())

    @property
    def poses(self) -> NDArray[np.float64]:
        if not self.applied:
            return self.initial
        top = self.applied[-1].poses
        assert top is not None
        return top

    def active(self) -> list[Interpretation]:
        return [
            e.interpretation
            for e in self.applied
            if isinstance(e, _Entry) and e.interpretation is not None
        ]

    def _discard_redo(self) -> None:
        for dropped in self.redo:
            dropped.status = EntryStatus.DISCARDED
            dropped.poses = None
        self.redo.clear()

    def _toggle(self, event: Event) -> None:
        """A ``loop_closure`` event: checked against the map's loop closures and the state."""
        payload = event.payload
        loop, rejected = payload.get("loop"), payload.get("rejected")
        count = 0 if self.loops is None else self.loops.count
        if not isinstance(loop, int) or isinstance(loop, bool) or not 0 <= loop < count:
            raise ValueError(f"loop closure {loop!r} is not one of the map's {count}")
        if not isinstance(rejected, bool):
            raise ValueError("its 'rejected' is not true or false")
        assert self.loops is not None
        if "edge" in payload and payload["edge"] != int(self.loops.edges[loop]):
            raise ValueError(f"loop closure {loop} is not edge {payload['edge']!r} of the map")
        if (loop in self.rejected()) == rejected:
            raise ValueError(f"loop closure {loop} is already {_loop_state(rejected)}")
        if self.alignment() is not None:
            raise ValueError("a loop closure step while an alignment with the scans is in effect")
        poses = event.poses
        if poses is None or poses.dtype != np.float64 or poses.shape != self.initial.shape:
            raise ValueError("a loop closure step without a valid pose checkpoint")
        toggle = _Toggle(
            seq=event.seq,
            time=event.time,
            loop=loop,
            rejected=rejected,
            stats=CorrectionStats.from_json(payload["stats"]),
            status=EntryStatus.APPLIED,
            poses=_frozen(np.ascontiguousarray(poses)),
            lines=_lines_from_json(payload["lines"], 2 * len(self.active())),
        )
        self._discard_redo()
        self.applied.append(toggle)
        self.toggles.append(toggle)

    def _align(self, event: Event) -> None:
        """An ``align`` event: its graph and checkpoint checked against the map."""
        payload = event.payload
        poses = event.poses
        if poses is None or poses.dtype != np.float64 or poses.shape != self.initial.shape:
            raise ValueError("an alignment without a valid pose checkpoint")
        edges, z, info = _graph_from_json(payload.get("graph"), self.initial.shape[0])
        counts = tuple(
            payload.get(k)
            for k in ("loop_closures", "loop_closures_rejected", "steps", "contradicted")
        )
        if not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in counts):
            raise ValueError(f"its counts are not whole numbers: {counts!r}")
        inc = payload.get("inconsistency", [math.nan, math.nan])
        if not (isinstance(inc, list) and len(inc) == 2):
            raise ValueError(f"its inconsistency is not [before, after]: {inc!r}")
        inc_pair = (float(inc[0]), float(inc[1]))
        phi = payload.get("relation_dcs")
        if phi is not None and not (
            isinstance(phi, (int, float)) and not isinstance(phi, bool) and phi >= 0
        ):
            raise ValueError(f"its relation_dcs is not a Phi >= 0: {phi!r}")
        step = _Align(
            seq=event.seq,
            time=event.time,
            stats=CorrectionStats.from_json(payload["stats"]),
            status=EntryStatus.APPLIED,
            poses=_frozen(np.ascontiguousarray(poses)),
            lines=_lines_from_json(payload["lines"], 2 * len(self.active())),
            edges=edges,
            measurements=z,
            information=info,
            counts=counts,  # type: ignore[arg-type]
            inconsistency=inc_pair,
            relation_dcs=None if phi is None else float(phi),
        )
        self._discard_redo()
        self.applied.append(step)
        self.aligns.append(step)

    def close_pending(self, reason: str) -> None:
        if self.pending is not None:
            self.pending.status = EntryStatus.INTERRUPTED
            self.pending.reason = reason
            self.pending = None

    def _outcome_of(self, event: Event) -> _Entry:
        entry = self.pending
        if entry is None or event.payload.get("request") != entry.seq:
            raise ValueError(f"{event.kind.value} without its request")
        self.pending = None
        return entry

    def _stacked(self, event: Event, stack: list[_Step]) -> _Step:
        if not stack or stack[-1].seq != event.payload.get("request"):
            raise ValueError(f"{event.kind.value} of a step that is not the next one")
        return stack.pop()

    def apply(self, event: Event) -> None:
        kind = event.kind
        if kind in (EventKind.LOAD, EventKind.SAVE):
            return
        if kind is EventKind.REQUEST:
            self.close_pending(_DIED)
            drawn = _drawn_from_json(event.payload["correction"])
            entry = _Entry(len(self.entries), event.seq, event.time, drawn, EntryStatus.PENDING)
            self.entries.append(entry)
            self.by_seq[entry.seq] = entry
            self.pending = entry
        elif kind is EventKind.CORRECTION:
            entry = self._outcome_of(event)
            poses = event.poses
            if poses is None or poses.dtype != np.float64 or poses.shape != self.initial.shape:
                raise ValueError("a correction without a valid pose checkpoint")
            entry.interpretation = Interpretation.from_json(event.payload["interpretation"])
            entry.stats = CorrectionStats.from_json(event.payload["stats"])
            if "lines" in event.payload:  # absent in journals written before lines were kept
                count = 2 * (len(self.active()) + 1)
                entry.lines = _lines_from_json(event.payload["lines"], count)
            entry.poses = _frozen(np.ascontiguousarray(poses))
            entry.status = EntryStatus.APPLIED
            self._discard_redo()
            self.applied.append(entry)
        elif kind in (EventKind.REJECTION, EventKind.INTERRUPTED):
            entry = self._outcome_of(event)
            rejected = kind is EventKind.REJECTION
            entry.status = EntryStatus.REJECTED if rejected else EntryStatus.INTERRUPTED
            entry.reason = str(event.payload.get("reason", ""))
        elif kind is EventKind.LOOP_CLOSURE:
            self.close_pending(_DIED)
            self._toggle(event)
        elif kind is EventKind.ALIGN:
            self.close_pending(_DIED)
            self._align(event)
        elif kind is EventKind.UNDO:
            self.close_pending(_DIED)
            step = self._stacked(event, self.applied)
            step.status = EntryStatus.UNDONE
            self.redo.append(step)
        elif kind is EventKind.REDO:
            self.close_pending(_DIED)
            step = self._stacked(event, self.redo)
            step.status = EntryStatus.APPLIED
            self.applied.append(step)
        else:  # pragma: no cover - EventKind is closed
            raise ValueError(f"unknown event kind {kind}")

    def feed(self, event: Event) -> str | None:
        """Apply a journaled ``event``; return what is wrong with it (None: it applied). A failed
        event may have changed the state half-way: the caller stops there and does not use this
        state afterwards."""
        try:
            self.apply(event)
        except Exception as exc:  # any malformed stored value is damage
            return f"event {event.seq}, {event.kind.value}: {exc}"
        return None

    @classmethod
    def replay(cls, map: Map, events: Sequence[Event], where: str) -> _State:
        state = cls.for_map(map)
        for event in events:
            problem = state.feed(event)
            if problem is not None:
                raise DamagedSession(where, problem, event.seq)
        state.close_pending(_DIED)
        return state


def _recovery_path(path: str) -> str:
    """A new file beside ``path`` for what is intact in it: ``<stem>.recovered.hitl`` (or
    ``.recovered-2.hitl``, ... when taken)."""
    stem = os.path.splitext(path)[0]
    candidate, k = f"{stem}.recovered.hitl", 1
    while os.path.exists(candidate):
        k += 1
        candidate = f"{stem}.recovered-{k}.hitl"
    return candidate


def _intact(journal: Journal, map: Map) -> tuple[_State, int, str | None]:
    """Replay the journal's events up to the first that cannot be used (damaged on disk, or
    not a valid step): the state they give, how many there are, and what is wrong with the next
    one (None: every event is intact). Never raises for damaged events."""
    state = _State.for_map(map)
    good: list[Event] = []
    for item in journal.intact_events():
        if isinstance(item, DamagedSession):
            return state, len(good), item.what
        problem = state.feed(item)
        if problem is not None:
            # The failed event may have changed the state half-way: replay the good ones again.
            state = _State.for_map(map)
            for event in good:
                state.feed(event)
            return state, len(good), problem
        good.append(item)
    return state, len(good), None


def _describe(state: _State) -> str:
    applied = len(state.applied)
    if not applied:
        return "the input map (no correction applied)"
    top = state.applied[-1]
    if isinstance(top, _Toggle):
        verb = "rejecting" if top.rejected else "reinstating"
        return f"the map after {verb} loop closure {top.loop} ({applied} steps applied)"
    if isinstance(top, _Align):
        return f"the map after aligning it with its scans ({applied} steps applied)"
    return f"the map after correction {top.index + 1} of the history ({applied} applied)"


def _damage_report(path: str, what: str, journal: Journal, map: Map | None) -> DamagedSession:
    """The error a user gets for a damaged file: what is wrong and the last good checkpoint,
    with the call that opens it (the intact events copied to a new file; the damaged one kept).
    ``map``: the stored input map, None when it is damaged too."""
    if map is None:
        return DamagedSession(
            path,
            what,
            message=f"{path}: the session file is damaged ({what}); the stored input map is "
            "damaged too, so no checkpoint in it can be trusted; restore the file from a copy, "
            "or start a new session from the input map",
        )
    state, count, _ = _intact(journal, map)
    if count == 0:
        return DamagedSession(
            path,
            what,
            1,
            message=f"{path}: the session file is damaged ({what}); no event in it is intact; "
            "restore the file from a copy, or start a new session from the input map",
        )
    return DamagedSession(
        path,
        what,
        count + 1,
        message=f"{path}: the session file is damaged ({what}); events 1 to {count} are "
        f"intact; the last good checkpoint is {_describe(state)}: `hitl-slam recover {path}` "
        f"(or hitl_slam.Session.recover({path!r})) copies those events to "
        f"{_recovery_path(path)} and leaves this file as it is; or restore the file from a copy",
    )


def _structural_report(path: str, damage: DamagedSession, journal: Journal) -> DamagedSession:
    """:func:`_damage_report` for a file whose SQLite structure is damaged: what can still be
    read (rows whose checksums hold) decides the last good checkpoint."""
    try:
        stored = journal.read_map()
        journal.read_config()
    except InputError:
        return _damage_report(path, damage.what, journal, None)
    return _damage_report(path, damage.what, journal, stored)


def moved_poses(before: NDArray[np.float64], after: NDArray[np.float64]) -> tuple[int, float]:
    """How many poses moved more than :data:`MOVED_DISTANCE_M` or :data:`MOVED_ANGLE_RAD`
    between two ``(N, 3)`` pose arrays, and the largest change of a position [m]."""
    distance = np.hypot(after[:, 0] - before[:, 0], after[:, 1] - before[:, 1])
    turn = np.abs(wrap(after[:, 2] - before[:, 2]))
    moved = (distance > MOVED_DISTANCE_M) | (turn > MOVED_ANGLE_RAD)
    return int(np.count_nonzero(moved)), float(distance.max(initial=0.0))


def _stats(
    before: NDArray[np.float64], after: NDArray[np.float64], outcome: CorrectionOutcome
) -> CorrectionStats:
    count, largest = moved_poses(before, after)
    return CorrectionStats(
        iterations=int(outcome.iterations),
        initial_chi2=float(outcome.initial_chi2),
        final_chi2=float(outcome.final_chi2),
        time_s=float(outcome.time_s),
        poses_moved=count,
        max_move_m=largest,
    )


def _solve_stats(
    before: NDArray[np.float64], after: NDArray[np.float64], solve: Any, elapsed: float
) -> CorrectionStats:
    """The stats of a re-solve (a loop closure step's, an alignment's): ``solve`` has its
    ``iterations``, ``initial_chi2`` and ``final_chi2``."""
    moved, largest = moved_poses(before, after)
    return CorrectionStats(
        iterations=int(solve.iterations),
        initial_chi2=float(solve.initial_chi2),
        final_chi2=float(solve.final_chi2),
        time_s=elapsed,
        poses_moved=moved,
        max_move_m=largest,
    )


def _checked_poses(poses: Any, shape: tuple[int, ...]) -> NDArray[np.float64]:
    out = np.array(poses, dtype=np.float64, order="C")
    if out.shape != shape:
        raise SolverError(f"the correction returned poses of shape {out.shape}, expected {shape}")
    if not np.isfinite(out).all():
        raise SolverError("the correction returned non-finite poses; the map was not changed")
    return out


def _checked_lines(outcome: Any, count: int) -> NDArray[np.float64] | None:
    """The outcome's solved lines as a ``(count, 2)`` float64 array; None when it has none."""
    lines = getattr(outcome, "lines", None)
    if lines is None:
        return None
    out = np.array(lines, dtype=np.float64, order="C")
    if out.shape != (count, 2):
        raise SolverError(f"the correction returned lines of shape {out.shape}, expected {count}")
    if not np.isfinite(out).all():
        raise SolverError("the correction returned non-finite lines; the map was not changed")
    return out


def refit_lines(
    map: Map, poses: NDArray[np.float64], active: Sequence[Interpretation]
) -> NDArray[np.float64]:
    """``(2K, 2)`` total-least-squares ``(phi, rho)`` of each correction's S_a and S_b under
    ``poses``: the lines of a step whose solved lines were not journaled."""
    out = np.empty((2 * len(active), 2), dtype=np.float64)
    for k, h in enumerate(active):
        out[2 * k] = fit_line(map.observed_points(h.s_a, poses))
        out[2 * k + 1] = fit_line(map.observed_points(h.s_b, poses))
    return _frozen(out)


@dataclass(frozen=True)
class StepResult:
    """What :meth:`Session.run_step` did: ``action`` "apply", "undo" or "redo"; the applier's
    ``outcome`` (apply only); the history entry the step concerned; its wall time [s]."""

    action: str
    outcome: CorrectionOutcome | None
    entry: HistoryEntry | LoopClosureStep | AlignStep
    time_s: float


def apply_in_order(
    map: Map,
    corrections: Sequence[Correction],
    config: Config = DEFAULT,
    applier: Applier | None = None,
    *,
    start: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], list[CorrectionOutcome]]:
    """Apply ``corrections`` one after another from ``start`` (default: the map's poses), each on
    the map as it stands, with no session or journal. Returns the final poses and every outcome.

    Raises:
        CorrectionRejected: a correction cannot be interpreted (its index is in the message).
    """
    apply = applier if applier is not None else _default_applier(Workspace(map))
    poses = np.array(map.poses if start is None else start, dtype=np.float64, order="C")
    active: list[Interpretation] = []
    outcomes: list[CorrectionOutcome] = []
    for k, drawn in enumerate(corrections):
        poses = _apply_next(
            apply, map, poses, drawn, active, outcomes, config, f"correction {k + 1}"
        )
    return poses, outcomes


def _apply_next(
    apply: Applier,
    map: Map,
    poses: NDArray[np.float64],
    drawn: Correction,
    active: list[Interpretation],
    outcomes: list[Any],
    config: Config,
    where: str,
) -> NDArray[np.float64]:
    """Applies ``drawn`` on top of ``active`` at ``poses``, appends its interpretation and
    outcome, and returns the new poses; a refusal names ``where``."""
    try:
        outcome = apply(map, poses, drawn, list(active), config)
    except CorrectionRejected as exc:
        raise CorrectionRejected(f"{where}: {exc}") from exc
    active.append(outcome.interpretation)
    outcomes.append(outcome)
    return _checked_poses(outcome.poses, poses.shape)


class Session:
    """A map being corrected, with its journal. Create with :meth:`new`, reopen with :meth:`open`.

    Operations are serialized (one correction at a time); reading :attr:`poses` and
    :attr:`history` from another thread while a correction computes is safe.
    """

    def __init__(
        self, journal: Journal, map: Map, config: Config, state: _State, applier: Applier | None
    ) -> None:
        self._journal = journal
        self._map = map
        self._config = config
        self._state = state
        self._applier = applier
        # What is computed once about the map and kept: its scans in the core, the graphs the
        # corrections solve over, their odometry check and their engines.
        self._workspace = Workspace(map)
        self._operation = threading.Lock()  # held for a whole operation, including the solve
        self._guard = threading.Lock()  # held briefly around every state change and read
        self._closed = False

    # -- opening ----------------------------------------------------------------------------

    @classmethod
    def new(
        cls,
        map: Map,
        path: str | os.PathLike[str] | None = None,
        config: Config = DEFAULT,
        applier: Applier | None = None,
        progress: Callable[[int, int], object] | None = None,
    ) -> Session:
        """Start a session on ``map`` journaled at ``path`` (a new file; ``None``: in memory).

        ``applier`` computes a correction (default :func:`hitl_slam.pipeline.apply_correction`).
        A map the front end built lists its loop closures in its metadata; the ones it rejected
        start rejected (:attr:`loop_closures`).

        The map's odometry is checked against its scans here, once, and the outcome stored with
        the map (:func:`hitl_slam.odometry_check.with_stored_check`; a map the front end built
        needs no check): no correction, and no reopen, matches scans again.
        ``progress(done, total)`` follows that matching.

        Raises:
            InputError: ``path`` exists or cannot be written, or the map's loop closures are
                malformed (nothing is written then).
        """
        LoopClosureTable.of(map)  # malformed loop closures are refused before anything is written
        from hitl_slam.odometry_check import with_stored_check

        map = with_stored_check(map, config, progress)
        journal = Journal.create(path, map, config)
        try:
            stored = journal.read_map()
            state = _State.for_map(stored)
            from hitl_slam import __version__

            journal.append(
                EventKind.LOAD,
                {
                    "name": stored.name,
                    "source": stored.source,
                    "poses": stored.num_poses,
                    "points": stored.num_points,
                    "tool": f"hitl-slam {__version__}",
                },
            )
            return cls(journal, stored, journal.read_config(), state, applier)
        except BaseException:
            journal.close()
            raise

    @classmethod
    def open(cls, path: str | os.PathLike[str], applier: Applier | None = None) -> Session:
        """Reopen a session file: the same map, history and undo/redo stacks as when it was left,
        from the journal's checkpoints (nothing is recomputed). A correction that was being
        computed when the program ended shows as :attr:`EntryStatus.INTERRUPTED`.

        Raises:
            InputError: not a session file, or one of a newer schema.
            DamagedSession: the file is damaged (an InputError): truncated, bytes changed (a
                checksum mismatch), a NaN or malformed value; the message names the last good
                checkpoint, which :meth:`recover` opens.
        """
        where = os.fspath(path)
        try:
            journal = Journal.open(path)
        except DamagedSession as damage:
            # The file's structure is damaged: look at what can still be read, to name it.
            try:
                salvage = Journal.open(path, check=False)
            except InputError:
                raise damage from None
            with salvage:
                raise _structural_report(where, damage, salvage) from None
        try:
            stored = journal.read_map()
            config = journal.read_config()
            try:
                state = _State.replay(stored, journal.events(), where)
            except DamagedSession as damage:
                raise _damage_report(where, damage.what, journal, stored) from None
            return cls(journal, stored, config, state, applier)
        except BaseException:
            journal.close()
            raise

    @classmethod
    def recover(
        cls,
        path: str | os.PathLike[str],
        target: str | os.PathLike[str] | None = None,
        applier: Applier | None = None,
    ) -> Session:
        """Open the last good checkpoint of a damaged session file: copy its map, configuration
        and the events before the first damaged one (checksums verified, each a valid step) to a
        NEW session file ``target`` (default ``<stem>.recovered.hitl`` beside it) and open that.
        ``path`` is only read; an intact file is copied whole.

        Raises:
            InputError: ``target`` exists or cannot be written, or the map or configuration in
                ``path`` is damaged (nothing in it can be trusted then).
        """
        where = os.fspath(path)
        destination = _recovery_path(where) if target is None else os.fspath(target)
        with Journal.open(where, check=False) as damaged:
            stored = damaged.read_map()
            damaged.read_config()
            _, count, _ = _intact(damaged, stored)
        Journal.salvage(where, destination, limit=count)
        return cls.open(destination, applier)

    # -- reading ----------------------------------------------------------------------------

    @property
    def path(self) -> str | None:
        """The session file, or ``None`` for an in-memory session."""
        return self._journal.path

    @property
    def config(self) -> Config:
        return self._config

    @property
    def input_map(self) -> Map:
        """The map the session started from (its poses are the input poses)."""
        return self._map

    @property
    def poses(self) -> NDArray[np.float64]:
        """``(N, 3)`` the current poses (a read-only array; copy it to modify)."""
        with self._guard:
            return self._state.poses

    def current_map(self) -> Map:
        """The input map with the current poses (observation arrays shared with the input),
        without the rejected loop closures: the map as it stands. Its remaining loop closures
        (if any) are listed in its metadata, none marked as rejected by the front end, so a
        session started from it starts where this one is."""
        with self._guard:
            poses = self._state.poses.copy()
            target = self._state.graph(self._workspace)
        metadata = target.metadata
        if EDGES in metadata:
            metadata = dict(metadata)
            metadata[AUTO_REJECTED] = np.zeros(np.shape(metadata[EDGES]), dtype=bool)
        return dataclasses.replace(target, poses=poses, metadata=metadata)

    def solved_map(self) -> Map:
        """The map the session's corrections solve over now: the input map without the rejected
        loop closures (the input map itself when none is rejected), or while an alignment with
        the scans is in effect the aligned map (its graph instead of the map's factors); with
        the input poses."""
        with self._guard:
            return self._state.graph(self._workspace)

    def _solve_config(self) -> Config:
        """The configuration corrections solve with now (called with the guard held): the
        session's, or while an alignment is in effect its :func:`aligned_config`."""
        aligned = self._state.alignment()
        return self._config if aligned is None else aligned.config(self._config)

    @property
    def alignment(self) -> AlignStep | None:
        """The alignment with the scans in effect (:meth:`align`), None when there is none."""
        with self._guard:
            step = self._state.alignment()
            return None if step is None else step.snapshot(self._config)

    @property
    def aligned(self) -> bool:
        """Whether an alignment with the scans is in effect (:meth:`align`): every solve then
        runs over its graph, and the map's own loop closures cannot be rejected or reinstated."""
        with self._guard:
            return self._state.alignment() is not None

    @property
    def loop_closures(self) -> list[LoopClosure]:
        """Every loop closure of the map (a map built by the front end; empty for any other),
        each with its pair of poses, the front end's trust in it (weight, 0..1), its score, and
        whether it is rejected now (left out of every solve)."""
        with self._guard:
            loops = self._state.loops
            return [] if loops is None else loops.items(self._state.rejected())

    @property
    def rejected_loop_closures(self) -> frozenset[int]:
        """The indices of the loop closures left out of the solve now."""
        with self._guard:
            return self._state.rejected()

    @property
    def loop_closure_steps(self) -> list[LoopClosureStep]:
        """Every loop closure rejected or reinstated in this session, in order, with its
        status (applied, undone, or discarded by a later step)."""
        with self._guard:
            return [t.snapshot() for t in self._state.toggles]

    @property
    def last_stats(self) -> CorrectionStats | None:
        """The numbers of the step in effect (the top of the undo stack: a correction or a loop
        closure step); None for the input map."""
        with self._guard:
            top = self._state.applied[-1] if self._state.applied else None
            return None if top is None else top.stats

    @property
    def history(self) -> list[HistoryEntry]:
        """Every requested correction in order, with its status."""
        with self._guard:
            return [e.snapshot() for e in self._state.entries]

    @property
    def active(self) -> list[Interpretation]:
        """The interpretations of the applied corrections, in the order they were applied."""
        with self._guard:
            return self._state.active()

    @property
    def lines(self) -> NDArray[np.float64]:
        """``(2K, 2)`` read-only: the solved ``(phi, rho)`` of each applied correction's lines a
        and b, in the order of :attr:`active`, as the solve of the map in effect left them
        (undo and redo restore them with the poses). For a step of a journal written before
        lines were journaled, or of an applier that returns none, they are refit (total least
        squares) to S_a and S_b under that step's poses, once."""
        with self._guard:
            top = self._state.applied[-1] if self._state.applied else None
            if top is None:
                return _frozen(np.empty((0, 2), dtype=np.float64))
            if top.lines is None:
                assert top.poses is not None
                top.lines = refit_lines(self._map, top.poses, self._state.active())
            return top.lines

    @property
    def corrections(self) -> list[Correction]:
        """The raw input of the applied corrections, in order."""
        with self._guard:
            return [e.drawn for e in self._state.applied if isinstance(e, _Entry)]

    @property
    def can_undo(self) -> bool:
        with self._guard:
            return bool(self._state.applied)

    @property
    def can_redo(self) -> bool:
        with self._guard:
            return bool(self._state.redo)

    # -- editing ----------------------------------------------------------------------------

    def correct(
        self, a: Any, b: Any, mode: Mode | str, *, sigma_h: float | None = None
    ) -> CorrectionOutcome:
        """Apply the correction drawn as segments ``a`` and ``b`` (two ``[x, y]`` endpoints each,
        world frame, metres) with ``mode``; see :meth:`apply`."""
        return self.apply(Correction.make(a, b, mode, sigma_h))

    def prepare(self) -> threading.Thread | None:
        """Starts making, in a background thread, what the first correction would wait for
        (the scans in the core, the odometry check of the graph solved now, its engine:
        :meth:`hitl_slam.workspace.Workspace.prepare`), so that it costs what a later one
        does; ``serve`` calls it as the page opens. Returns the thread (None with a custom
        applier, which does not use them). A failure there is left to the first correction,
        which meets it again and reports it."""
        if self._applier is not None:
            return None
        with self._guard:
            graph = self._state.graph(self._workspace)
            config = self._solve_config()
        held = self._workspace

        def run() -> None:
            with contextlib.suppress(Exception):
                held.prepare(graph, config)

        thread = threading.Thread(target=run, name="hitl-slam prepare", daemon=True)
        thread.start()
        return thread

    def _correct_with(self, applier: Applier | None) -> Applier:
        """``applier``, or the default one (:func:`hitl_slam.pipeline.apply_correction`) with
        this session's workspace."""
        return applier if applier is not None else _default_applier(self._workspace)

    def apply(self, drawn: Correction) -> CorrectionOutcome:
        """Apply one correction on the map as it stands, dropping anything undone.

        Order: the request is journaled, then computed, then the outcome journaled (with the new
        poses as a checkpoint), and only then does the session's map change.

        Raises:
            CorrectionRejected: the drawing cannot be interpreted; only the rejection is journaled.
            SolverError: the solve failed; the request is journaled as interrupted.
        """
        with self._operation:
            self._check_open()
            apply = self._correct_with(self._applier)
            self._record(EventKind.REQUEST, {"correction": drawn.to_json()})
            with self._guard:
                pending = self._state.pending
                assert pending is not None
                before = self._state.poses
                active = self._state.active()
                target = self._state.graph(self._workspace)
                config = self._solve_config()
            seq = pending.seq
            try:
                outcome = apply(target, before, drawn, active, config)
                after = _checked_poses(outcome.poses, before.shape)
                lines = _checked_lines(outcome, 2 * (len(active) + 1))
                interpretation = outcome.interpretation.to_json(arrays=True)
                stats = _stats(before, after, outcome)
            except CorrectionRejected as exc:
                self._record(
                    EventKind.REJECTION,
                    {"request": seq, "reason": str(exc), "correction": drawn.to_json()},
                )
                raise
            except BaseException as exc:
                self._interrupt(seq, f"{type(exc).__name__}: {exc}")
                raise
            payload: dict[str, Any] = {
                "request": seq,
                "interpretation": interpretation,
                "stats": stats.to_json(),
            }
            if lines is not None:
                # JSON floats round-trip exactly: the reopened session has these very values.
                payload["lines"] = lines.tolist()
            try:
                self._record(EventKind.CORRECTION, payload, after)
            except BaseException:
                with self._guard:
                    self._state.close_pending("the result could not be journaled")
                raise
            return outcome

    def set_loop_closure(self, loop: int, rejected: bool) -> LoopClosureStep:
        """Reject loop closure ``loop`` (``rejected=True``: it leaves the solve) or reinstate it,
        and re-solve the map: every correction in effect jointly, from the current poses, over
        the map without the loop closures rejected then (docs/ALGORITHM.md §F.6). The result is
        journaled (with the new poses as a checkpoint) and only then does the map change. A step
        on the undo/redo stack like a correction: undo returns to the poses before it exactly.

        Raises:
            InputError: the map has no loop closures, or no loop closure ``loop``.
            StepRefused: it is already rejected (or already in the solve); nothing changed.
            SolverError: the solve failed; nothing changed and nothing was journaled.
        """
        from hitl_slam.pipeline import solve_all

        with self._operation:
            self._check_open()
            with self._guard:
                loops = self._state.loops
                current = self._state.rejected()
                before = self._state.poses
                active = self._state.active()
                aligned = self._state.alignment() is not None
            if loops is None or loops.count == 0:
                raise InputError(
                    "this map has no loop closures to reject or reinstate; only maps the front "
                    "end built (`hitl-slam slam`, or `hitl-slam serve` on a raw log) have them"
                )
            if isinstance(loop, bool) or not isinstance(loop, int | np.integer):
                raise InputError(f"a loop closure is given by its index, got {loop!r}")
            loop = int(loop)
            if not 0 <= loop < loops.count:
                raise InputError(
                    f"no loop closure {loop}: the map has {loops.count} (0 to {loops.count - 1})"
                )
            rejected = bool(rejected)
            if (loop in current) == rejected:
                raise StepRefused(f"loop closure {loop} is already {_loop_state(rejected)}")
            if aligned:
                raise StepRefused(
                    "the map is aligned with its scans: the alignment's own loop closures "
                    "replaced the map's; undo the alignment to reject or reinstate the map's"
                )
            wanted = current | {loop} if rejected else current - {loop}
            target = self._workspace.graph(wanted)
            t0 = time.perf_counter()
            poses, lines, report = solve_all(
                target, active, self._config, start=before, workspace=self._workspace
            )
            elapsed = time.perf_counter() - t0
            after = _checked_poses(poses, before.shape)
            count = 2 * len(active)
            solved = np.array(lines, dtype=np.float64).reshape(-1, 2)
            if solved.shape != (count, 2) or not np.isfinite(solved).all():
                raise SolverError("the re-solve returned malformed lines; the map was not changed")
            stats = _solve_stats(before, after, report, elapsed)
            payload = {
                "loop": loop,
                "edge": int(loops.edges[loop]),
                "rejected": rejected,
                "stats": stats.to_json(),
                "lines": solved.tolist(),
            }
            self._record(EventKind.LOOP_CLOSURE, payload, after)
            with self._guard:
                top = self._state.applied[-1]
                assert isinstance(top, _Toggle)
                return top.snapshot()

    def align(self, progress: Callable[[int, int], object] | None = None) -> AlignStep:
        """Align the map with its scans (docs/ALGORITHM.md §I.11): the front end matches the
        scans again from the current poses, its graph replaces the map's factors, and every
        correction in effect is solved again over it. Journaled (with the new poses as a
        checkpoint) before the map changes; a step on the undo/redo stack like a correction.
        ``progress(done, total)`` is called as the scans are matched.

        Raises:
            InputError: the map has no scans to match.
            AlignmentRefused: a guard refused it (an InputError, with the figures): the front
                end kept too few loop closures, the aligned map contradicts the robot's odometry
                at too many steps, or it is no more consistent; nothing changed.
            SolverError: the solve failed; nothing changed and nothing was journaled.
        """
        from hitl_slam.alignment import align

        with self._operation:
            self._check_open()
            with self._guard:
                before = self._state.poses
                active = self._state.active()
            t0 = time.perf_counter()
            done = align(self._map, before, active, self._config, progress=progress)
            elapsed = time.perf_counter() - t0
            after = _checked_poses(done.poses, before.shape)
            solved = np.array(done.lines, dtype=np.float64).reshape(-1, 2)
            if solved.shape != (2 * len(active), 2) or not np.isfinite(solved).all():
                raise SolverError("the aligned solve returned malformed lines; nothing changed")
            stats = _solve_stats(before, after, done, elapsed)
            m = done.edges.shape[0]
            payload = {
                "graph": {
                    "edges": done.edges,
                    "measurements": done.measurements.tolist(),
                    "information": done.information.reshape(m, 9).tolist(),
                },
                "stats": stats.to_json(),
                "lines": solved.tolist(),
                "loop_closures": done.loop_closures,
                "loop_closures_rejected": done.loop_closures_rejected,
                "steps": done.steps,
                "contradicted": done.contradicted,
                "inconsistency": list(done.inconsistency),
                "relation_dcs": done.relation_dcs,
            }
            self._record(EventKind.ALIGN, payload, after)
            with self._guard:
                top = self._state.applied[-1]
                assert isinstance(top, _Align)
                return top.snapshot(self._config)

    def undo(self) -> HistoryEntry | LoopClosureStep | AlignStep:
        """Undo the last applied step (a correction, a loop closure rejected or reinstated, or an
        alignment): the map returns exactly to what it was before it.

        Raises:
            StepRefused: nothing to undo (an InputError).
        """
        return self._step(EventKind.UNDO)

    def redo(self) -> HistoryEntry | LoopClosureStep | AlignStep:
        """Redo the last undone step (its stored result; nothing is recomputed).

        Raises:
            StepRefused: nothing to redo (an InputError).
        """
        return self._step(EventKind.REDO)

    def run_step(self, step: Step) -> StepResult:
        """Do one step of a corrections file or journal (:mod:`hitl_slam.corrections_file`):
        apply its correction, or undo, or redo. The one place the CLI, the web host and tests
        replay steps through.

        Raises:
            CorrectionRejected: the correction cannot be interpreted (nothing changed).
            StepRefused: an undo or redo with nothing to undo or redo (nothing changed).
            SolverError: the solve failed (the request is journaled as interrupted).
        """
        t0 = time.perf_counter()
        if isinstance(step, Apply):
            outcome: CorrectionOutcome | None = self.apply(step.drawn)
            entry: HistoryEntry | LoopClosureStep | AlignStep = self.history[-1]
            action = "apply"
        else:
            outcome = None
            action = "undo" if isinstance(step, Undo) else "redo"
            entry = self.undo() if action == "undo" else self.redo()
        return StepResult(action, outcome, entry, time.perf_counter() - t0)

    def _step(self, kind: EventKind) -> HistoryEntry | LoopClosureStep | AlignStep:
        with self._operation:
            self._check_open()
            with self._guard:
                stack = self._state.applied if kind is EventKind.UNDO else self._state.redo
                if not stack:
                    raise StepRefused(f"nothing to {kind.value}")
                entry = stack[-1]
            self._record(kind, {"request": entry.seq})
            if isinstance(entry, _Align):
                return entry.snapshot(self._config)
            return entry.snapshot()

    def record_output(self, path: str | os.PathLike[str]) -> None:
        """Journals a ``save`` event for a file written for this session by its caller (the
        ``.yaml`` beside an exported ``.pgm``, an export of the corrections), with the payload
        :meth:`save` journals for its own files, so that every written file has its entry."""
        target = os.path.abspath(path)
        with self._operation:
            self._check_open()
            self._record(
                EventKind.SAVE, {"path": target, "format": os.path.splitext(target)[1].lower()}
            )

    def save(self, path: str | os.PathLike[str]) -> None:
        """Export the current map to ``path`` (format from its extension, see
        :func:`hitl_slam.io.export.export`) and journal a ``save`` event: all or nothing."""
        from hitl_slam.io.export import export

        with self._operation:
            self._check_open()
            target = os.path.abspath(os.fspath(path))
            # The files are prepared, the event journaled, and only then are they renamed into
            # place: a save the journal cannot record writes nothing (issue 13, finding 6).
            with atomic_outputs():
                export(self.solved_map(), self.poses.copy(), path)
                self._record(
                    EventKind.SAVE, {"path": target, "format": os.path.splitext(target)[1].lower()}
                )

    def export_corrections(self, path: str | os.PathLike[str]) -> int:
        """Write the applied corrections, in order, as a JSON Lines corrections file (atomic),
        replayable by ``hitl-slam correct``. Returns how many were written."""
        from hitl_slam.corrections_file import write_corrections

        corrections = self.corrections
        write_corrections(path, corrections)
        return len(corrections)

    def write_journal(self, path: str | os.PathLike[str]) -> None:
        """Copy the whole session (map, configuration, journal) to a NEW file ``path``, e.g. to
        keep an in-memory session. Atomic; an existing file is never overwritten."""
        with self._operation:
            self._check_open()
            self._journal.backup_to(path)

    def replay(self, applier: Applier | None = None) -> tuple[NDArray[np.float64], list[Any]]:
        """Recompute the applied steps from the input poses, from scratch, to verify the stored
        result: each correction on the map as it stood, each loop closure step as its re-solve,
        each alignment as its alignment. Changes nothing. Returns the final poses and each step's
        outcome (a loop closure step's: its SolveReport; an alignment's: its Alignment); with
        the same build the poses equal :attr:`poses` bit for bit.

        Raises:
            CorrectionRejected: a correction cannot be interpreted (its index is in the message).
        """
        from hitl_slam.pipeline import solve_all

        apply = self._correct_with(applier or self._applier)
        with self._guard:
            steps = list(self._state.applied)
            loops = self._state.loops
        rejected = set() if loops is None else set(loops.auto_rejected_set)
        poses = np.array(self._map.poses, dtype=np.float64, order="C")
        active: list[Interpretation] = []
        outcomes: list[Any] = []
        aligned: Map | None = None
        aligned_phi = 0.0
        for k, step in enumerate(steps):
            if isinstance(step, _Align):
                from hitl_slam.alignment import align, aligned_map

                done = align(self._map, poses, active, self._config)
                poses = _checked_poses(done.poses, poses.shape)
                aligned = aligned_map(self._map, done.edges, done.measurements, done.information)
                aligned_phi = done.relation_dcs
                outcomes.append(done)
                continue
            if isinstance(step, _Toggle):
                if step.rejected:
                    rejected.add(step.loop)
                else:
                    rejected.discard(step.loop)
            target = aligned if aligned is not None else self._workspace.graph(frozenset(rejected))
            if isinstance(step, _Toggle):
                solved, _, report = solve_all(
                    target, active, self._config, start=poses, workspace=self._workspace
                )
                poses = _checked_poses(solved, poses.shape)
                outcomes.append(report)
                continue
            config = self._config
            if aligned is not None:
                from hitl_slam.alignment import aligned_config

                config = aligned_config(config, aligned_phi)
            poses = _apply_next(
                apply, target, poses, step.drawn, active, outcomes, config, f"step {k + 1}"
            )
        return poses, outcomes

    # -- plumbing ---------------------------------------------------------------------------

    def _record(
        self,
        kind: EventKind,
        payload: dict[str, Any],
        poses: NDArray[np.float64] | None = None,
    ) -> None:
        """Journal first (committed), then change the state in memory."""
        event = self._journal.append(kind, payload, poses)
        if poses is not None:
            # The checkpoint in memory is the very array that was written, not a recomputation.
            event = dataclasses.replace(event, poses=poses)
        with self._guard:
            self._state.apply(event)

    def _interrupt(self, seq: int, reason: str) -> None:
        try:
            self._record(EventKind.INTERRUPTED, {"request": seq, "reason": reason})
        except Exception:
            # The journal is unwritable too; the request stays unanswered there, which reads back
            # as interrupted, and memory says the same.
            with self._guard:
                self._state.close_pending(reason)

    def _check_open(self) -> None:
        if self._closed:
            raise InputError("the session is closed; open the session file again")

    def close(self) -> None:
        """Close the journal (idempotent); waits for a correction being computed to finish.
        Everything was already committed."""
        with self._operation:
            with contextlib.suppress(Exception):
                self._journal.close()
            self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
