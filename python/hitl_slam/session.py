"""An editing session on a map: corrections one at a time, loop closures rejected or reinstated
(on a map the front end built), the map aligned with its scans, undo and redo of any depth across
all of them, save; every event
journaled (:mod:`hitl_slam.journal`) before the map in memory changes, so reopening the file
rebuilds the same state bit for bit from the journal's pose checkpoints (docs/ALGORITHM.md §5).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

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
from hitl_slam.io.atomic import atomic_outputs
from hitl_slam.journal import EventKind, Journal
from hitl_slam.loop_closures import LoopClosureTable
from hitl_slam.map import Map
from hitl_slam.session_outcomes import (
    Applier,
    CorrectionOutcome,
    StepResult,
    _apply_next,
    _checked_lines,
    _checked_poses,
    _solve_stats,
    _stats,
    refit_lines,
)
from hitl_slam.session_recovery import (
    _damage_report,
    _intact,
    _recovery_path,
    _structural_report,
)
from hitl_slam.session_state import _loop_state, _State
from hitl_slam.session_steps import (
    MOVED_ANGLE_RAD,
    MOVED_DISTANCE_M,
    AlignStep,
    CorrectionStats,
    EntryStatus,
    HistoryEntry,
    LoopClosureStep,
    _Align,
    _Toggle,
    moved_poses,
)
from hitl_slam.session_view import _SessionView
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


def _default_applier(workspace: Workspace) -> Applier:
    """:func:`hitl_slam.pipeline.apply_correction` with ``workspace`` (what is kept about the map
    between corrections)."""
    from hitl_slam.pipeline import apply_correction

    return partial(apply_correction, workspace=workspace)


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


class Session(_SessionView):
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
