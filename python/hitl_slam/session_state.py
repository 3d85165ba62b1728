"""The undo/redo state machine of a session (:class:`_State`): the events of its journal, fed
one at a time as they are written or replayed, rebuild its history, its undo and redo stacks and
its current poses; a malformed event is reported as damage.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.errors import DamagedSession
from hitl_slam.journal import Event, EventKind
from hitl_slam.loop_closures import LoopClosureTable
from hitl_slam.map import Map
from hitl_slam.session_steps import (
    CorrectionStats,
    EntryStatus,
    _Align,
    _Entry,
    _frozen,
    _Step,
    _Toggle,
)
from hitl_slam.workspace import Workspace

_DIED = "the program ended before the correction finished"


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
