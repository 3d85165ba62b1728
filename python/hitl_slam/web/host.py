"""SessionHost: the one editing :class:`~hitl_slam.session.Session` every browser tab shares:
changes run one at a time, each publishes a :class:`Snapshot` under a version counter that
long-polling clients wait on. What it hands out comes from the modules named after each concept:
the arrays and lines the page draws (:mod:`~hitl_slam.web.drawing`), relation residuals
(:mod:`~hitl_slam.web.relations`), the inconsistency off the request path
(:mod:`~hitl_slam.web.metric`), paths kept inside the session's folder
(:mod:`~hitl_slam.web.folder`) and the JSON documents (:mod:`~hitl_slam.web.documents`). No HTTP
here: :mod:`hitl_slam.web.app` is a thin layer over these methods.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.corrections_file import Apply, Step, Undo
from hitl_slam.errors import CorrectionRejected, HitlSlamError, InputError, SolverError
from hitl_slam.session import CorrectionStats, HistoryEntry, Session, StepRefused
from hitl_slam.web import documents, folder
from hitl_slam.web.drawing import MapDrawing
from hitl_slam.web.folder import SAVE_FORMATS, OutsideFolder
from hitl_slam.web.metric import MetricWorker
from hitl_slam.web.relations import relation_residuals

__all__ = [
    "DEFAULT_POLL_TIMEOUT",
    "SAVE_FORMATS",
    "NothingToDo",
    "OutsideFolder",
    "SessionHost",
    "Snapshot",
]

logger = logging.getLogger(__name__)

DEFAULT_POLL_TIMEOUT = 20.0
"""[s] How long ``GET /api/state?after=V`` waits for a change before answering anyway."""


class NothingToDo(InputError):
    """An undo, redo or journal step with nothing left to do (HTTP 409)."""


@dataclass(frozen=True, eq=False)
class Snapshot:
    """Everything a client sees at one version, published atomically after each change."""

    version: int
    map_version: int  # the version at which the poses last changed
    poses: NDArray[np.float64]  # (N, 3) read-only, the session's own checkpoint array
    poses_f32: bytes  # (N, 3) float32 little-endian
    bounds: tuple[float, float, float, float]
    lines: tuple[dict[str, Any], ...]  # the solved lines in effect, as State.lines items
    history: tuple[HistoryEntry, ...]
    active: tuple[Interpretation, ...]
    can_undo: bool
    can_redo: bool
    rejected_loops: tuple[int, ...]  # the loop closures left out of the solve, sorted
    aligned: bool  # an alignment with the scans is in effect (its graph replaced the map's)
    last: dict[str, Any] | None
    inconsistency_m2: float | None
    journal_next: int


class SessionHost:
    """Serves one session to any number of clients.

    Changes (apply, loop closure, alignment, undo, redo, journal step) run one at a time; each
    publishes a new :class:`Snapshot` with a higher version and wakes every waiter (threading
    and listener callbacks). Reads never wait for a running solve: they see the last published
    snapshot.
    The host owns ``session`` and closes it in :meth:`close`.

    Args:
        session: an open session, file-backed for save/export (its folder holds the output).
        journal: corrections-file steps for step-through (:meth:`journal_step`).
        journal_source: where they came from (shown in the state).
        poll_timeout: [s] the long-poll's wait before answering unchanged.
        metrics: compute the inconsistency after each change in a background thread.
    """

    def __init__(
        self,
        session: Session,
        *,
        journal: Sequence[Step] = (),
        journal_source: str | None = None,
        poll_timeout: float = DEFAULT_POLL_TIMEOUT,
        metrics: bool = True,
    ) -> None:
        if not (math.isfinite(poll_timeout) and poll_timeout >= 0):
            raise InputError(f"poll_timeout must be a number of seconds >= 0, got {poll_timeout}")
        self._session = session
        self._map = session.input_map
        self._drawing = MapDrawing(self._map)
        self._loops = documents.loop_closures(session.loop_closures)
        self._info = documents.map_info(self._map)
        self._loop_count = len(self._loops["pairs"])
        self._steps = tuple(journal)
        self._journal_source = journal_source
        self.poll_timeout = float(poll_timeout)
        self._operation = threading.Lock()  # one change at a time, held through the solve
        self._lock = threading.Lock()  # guards the snapshot; held briefly
        self._changed = threading.Condition(self._lock)
        self._listeners: list[Callable[[], None]] = []
        self._closing = False
        self._world: tuple[NDArray[np.float64], bytes] | None = None  # world points, on demand
        self._world_lock = threading.Lock()
        self._metric: MetricWorker | None = None
        self._snapshot = self._build(None, None, 0)
        if metrics:
            self._metric = MetricWorker(self._map, session.config, self._publish_metric)
            self._request_metric(self._snapshot)

    # -- reading ----------------------------------------------------------------------------

    @property
    def session(self) -> Session:
        return self._session

    @property
    def snapshot(self) -> Snapshot:
        with self._lock:
            return self._snapshot

    @property
    def version(self) -> int:
        with self._lock:
            return self._snapshot.version

    @property
    def closing(self) -> bool:
        return self._closing

    @property
    def folder(self) -> str:
        """The session's folder (resolved), where save and export write."""
        path = self._session.path
        if path is None:
            raise InputError(
                "this session lives in memory and has no folder to save into; serve a session "
                "file instead"
            )
        return os.path.realpath(os.path.dirname(os.path.abspath(path)))

    def state(self, snapshot: Snapshot | None = None) -> dict[str, Any]:
        """The State document (see the web contract) of ``snapshot`` (default: the current)."""
        snap = self.snapshot if snapshot is None else snapshot
        path = self._session.path
        return {
            "version": snap.version,
            "map_version": snap.map_version,
            "name": self._map.name,
            "session": "" if path is None else os.path.basename(path),
            "num_poses": self._map.num_poses,
            "num_points": self._map.num_points,
            "bounds": list(snap.bounds),
            "applied": len(snap.active),
            "can_undo": snap.can_undo,
            "can_redo": snap.can_redo,
            "last": None if snap.last is None else dict(snap.last),
            "inconsistency_m2": snap.inconsistency_m2,
            "history": [documents.history_item(e) for e in snap.history],
            "lines": list(snap.lines),
            "loop_closures": {
                "count": self._loop_count,
                "rejected": list(snap.rejected_loops),
            },
            "aligned": snap.aligned,
            "journal": {
                "loaded": len(self._steps),
                "next": snap.journal_next,
                "source": self._journal_source,
            },
        }

    def wait_for_change(self, after: int, timeout: float | None = None) -> dict[str, Any]:
        """The state as soon as its version differs from ``after`` (a client's last version; a
        version from before a server restart also differs), or after ``timeout`` seconds
        (default :attr:`poll_timeout`) unchanged. Returns at once while closing."""
        wait = self.poll_timeout if timeout is None else timeout
        with self._changed:
            self._changed.wait_for(
                lambda: self._snapshot.version != after or self._closing, timeout=wait
            )
            snap = self._snapshot
        return self.state(snap)

    def add_listener(self, callback: Callable[[], None]) -> None:
        """Call ``callback()`` (from whichever thread made the change) after every new version
        and when the host starts closing. Callbacks must be quick and must not raise."""
        with self._lock:
            self._listeners.append(callback)

    def remove_listener(self, callback: Callable[[], None]) -> None:
        with self._lock, contextlib.suppress(ValueError):
            self._listeners.remove(callback)

    def points(self) -> tuple[int, bytes]:
        """(version, float32 LE (P, 2) world points of the current poses, pose by pose), built
        on demand and kept for the current poses (the page itself uses :meth:`scans`)."""
        snap = self.snapshot
        with self._world_lock:
            if self._world is None or self._world[0] is not snap.poses:
                self._world = (snap.poses, self._drawing.world_points(snap.poses))
            return snap.version, self._world[1]

    def scans(self) -> bytes:
        """float32 LE (P, 2): every scan's points in its robot's frame, pose by pose. They never
        change: a page fetches them once and places them with the poses."""
        return self._drawing.scans_f32

    def poses(self) -> tuple[int, bytes]:
        """(version, float32 LE (N, 3) current poses)."""
        snap = self.snapshot
        return snap.version, snap.poses_f32

    def loop_closures(self) -> dict[str, Any]:
        """The map's loop closures, which never change (the page fetches them once): each one's
        pair of poses, the front end's trust in it (weight, 0..1), its score and whether the front
        end rejected it. Which are rejected now is in the state (``loop_closures.rejected``)."""
        return self._loops

    def map_info(self) -> dict[str, Any]:
        """What the served map is, which never changes (the page fetches it once): which poses
        it holds, the front end's verdict and doubtful stretches, and for the front end's map of
        a bag with its own SLAM, the inconsistency of both (see :func:`documents.map_info`)."""
        return self._info

    def offsets(self) -> bytes:
        """int32 LE (N + 1,): pose i's points are points[offsets[i]:offsets[i + 1]]."""
        return self._drawing.offsets_i32

    def relations(self) -> list[dict[str, Any]]:
        """For each correction in effect: its relation residual on the current poses, from lines
        refit (total least squares) to S_a and S_b as the current poses place them."""
        snap = self.snapshot
        return relation_residuals(self._map, snap.poses, self._active_with_index(snap))

    def interpret(self, drawn: Correction) -> dict[str, Any]:
        """The Preview of ``drawn`` on the current poses: EM only, nothing changes or is
        journaled."""
        from hitl_slam.interpret import interpret

        snap = self.snapshot
        try:
            h = interpret(self._map, snap.poses, drawn, self._session.config)
        except CorrectionRejected as exc:
            return {"accepted": False, "reason": str(exc)}
        return documents.preview(self._map, h)

    # -- changing ---------------------------------------------------------------------------

    def apply(self, drawn: Correction) -> dict[str, Any]:
        """Apply one correction (serialized with every other change); the Applied document.
        A drawing that cannot be interpreted, or a failed solve, answers ``accepted: false``
        with the reason and leaves the map unchanged."""
        with self._operation:
            self._check_open()
            return self._run(Apply(drawn), "")

    def set_loop_closure(self, index: int, rejected: bool) -> dict[str, Any]:
        """Reject loop closure ``index`` or reinstate it (serialized with every other change),
        re-solving the map; the new State (its ``last`` says what the re-solve cost).

        Raises:
            NothingToDo: it is already rejected, or already in the solve, or the map is aligned
                with its scans (the alignment's own loop closures replaced the map's).
            InputError: the map has no loop closure ``index``.
            SolverError: the re-solve failed; nothing changed.
        """
        with self._operation:
            self._check_open()
            t0 = time.perf_counter()
            try:
                step = self._session.set_loop_closure(index, rejected)
            except StepRefused as exc:
                raise NothingToDo(str(exc)) from None
            return self._resolved("loop_closure", t0, step.stats)

    def align(self) -> dict[str, Any]:
        """Align the map with its scans (serialized with every other change; seconds to a
        minute on a big map): the scans are matched again from the current poses, their graph
        replaces the map's factors and every correction in effect is solved again over it. The
        new State: its ``last`` (kind ``"align"``) says what the solve cost and carries the
        alignment's figures, and ``aligned`` is true while the step is in effect (until it is
        undone). A step on the undo/redo stack like a correction.

        Raises:
            AlignmentRefused: a guard refused it (too few loop closures, too many odometry
                steps contradicted, or no less inconsistent; an InputError, with the figures);
                nothing changed.
            InputError: the map has no scans to match.
            SolverError: the solve failed; nothing changed.
        """
        with self._operation:
            self._check_open()
            t0 = time.perf_counter()
            step = self._session.align()
            figures = documents.alignment(
                step, self._session.config.relation_dcs, len(self._session.active)
            )
            return self._resolved("align", t0, step.stats, figures)

    def _resolved(
        self,
        kind: str,
        t0: float,
        stats: CorrectionStats,
        alignment: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """The new State after a re-solve (a loop closure step, an alignment) that started at
        ``t0``: its ``last`` says what the solve cost (operation lock held)."""
        last = documents.last_change(
            kind,
            1e3 * (time.perf_counter() - t0),
            cost=stats.final_chi2,
            initial_cost=stats.initial_chi2,
            iterations=stats.iterations,
            alignment=alignment,
        )
        return self.state(self._publish(last))

    def undo(self) -> dict[str, Any]:
        """Undo the last applied step (a correction, a loop closure step or an alignment); the
        new State.

        Raises:
            NothingToDo: nothing to undo.
        """
        return self._step(Undo())

    def redo(self) -> dict[str, Any]:
        """Redo the last undone step; the new State.

        Raises:
            NothingToDo: nothing to redo.
        """
        from hitl_slam.corrections_file import Redo

        return self._step(Redo())

    def journal_step(self) -> dict[str, Any]:
        """Apply the next step of the loaded corrections file, as :meth:`apply` (or an undo or
        redo for such a line, answered with ``preview: null``). A step that cannot be done is
        answered ``accepted: false`` and passed over.

        Raises:
            NothingToDo: no corrections file was loaded, or every step was taken.
        """
        with self._operation:
            self._check_open()
            index = self.snapshot.journal_next
            if not self._steps:
                raise NothingToDo(
                    "no corrections file is loaded; start the server with --journal C.jsonl"
                )
            if index >= len(self._steps):
                raise NothingToDo(f"all {len(self._steps)} steps of the journal were taken")
            step = self._steps[index]
            where = f"journal line {step.line}: " if step.line else ""
            return self._run(step, where, index + 1)

    def save(self, name: str | None = None) -> list[str]:
        """Write the corrected map beside the session as ``name`` + ``.txt`` (TUM), ``.g2o``,
        ``.pgm`` and ``.yaml``, journaling a ``save`` event for each of the four files; the file
        names, relative to the folder.

        Raises:
            InputError: ``name`` is not a plain file stem ([A-Za-z0-9._-], no leading dot,
                no ``..``), or a file cannot be written.
            OutsideFolder: a file of that name is a link leading out of the folder.
        """
        where = self.folder
        path = self._session.path
        assert path is not None  # folder checked it
        stem = os.path.splitext(os.path.basename(path))[0] + "-corrected" if name is None else name
        folder.check_save_name(stem)
        targets = [folder.inside(where, stem + ext) for ext in SAVE_FORMATS]
        yaml = folder.contained(where, os.path.splitext(targets[2])[0] + ".yaml")
        with self._operation:
            self._check_open()
            for target in targets:
                folder.write(self._session.save, target)
            self._journal_output(yaml)
        return [os.path.relpath(t, where) for t in (*targets, yaml)]

    def export(self, relative: str) -> list[str]:
        """Write one file at ``relative`` (to the session's folder), format from its extension:
        a map format of :func:`hitl_slam.io.export.export` or ``.jsonl`` (the applied
        corrections); the files written, relative to the folder. Each file written (the
        ``.pgm``'s ``.yaml`` too) is journaled as a ``save`` event, as :meth:`save` does.

        Raises:
            InputError: a NUL byte, an unknown extension, or an unwritable file.
            OutsideFolder: an absolute path, a ``..`` component, or a path that resolves (links
                followed) outside the folder.
        """
        from hitl_slam.io.export import EXPORT_EXTENSIONS

        if "\x00" in relative:
            raise InputError("the path contains a NUL byte; give a plain file name")
        where = self.folder
        target = folder.inside(where, relative)
        extension = os.path.splitext(target)[1].lower()
        if extension not in (*EXPORT_EXTENSIONS, ".jsonl"):
            raise InputError(
                f"cannot export to {extension or 'a file without extension'!r}; use one of "
                f"{', '.join((*EXPORT_EXTENSIONS, '.jsonl'))}"
            )
        files = [target]
        if extension == ".pgm":
            files.append(folder.contained(where, os.path.splitext(target)[0] + ".yaml"))
        with self._operation:
            self._check_open()
            if extension == ".jsonl":
                folder.write(self._session.export_corrections, target)
                self._journal_output(target)
            else:
                folder.write(self._session.save, target)
                if extension == ".pgm":
                    self._journal_output(files[1])
        return [os.path.relpath(f, where) for f in files]

    def close(self) -> None:
        """Wake every waiter, stop the metric thread and close the session (waits for a running
        correction to finish; everything acknowledged is already journaled). Idempotent."""
        self.wake_all()
        if self._metric is not None:
            self._metric.close()
        with self._operation:
            self._session.close()

    def wake_all(self) -> None:
        """Start closing: every long-poll answers now (e.g. on Ctrl-C)."""
        with self._changed:
            self._closing = True
            self._changed.notify_all()
            listeners = list(self._listeners)
        self._call(listeners)

    # -- plumbing ---------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._session.closed:
            raise InputError("the session is closed; restart `hitl-slam serve`")

    def _journal_output(self, path: str) -> None:
        """Journal a ``save`` event for a file written beside one :meth:`Session.save` journaled
        (a ``.pgm``'s ``.yaml``) or by :meth:`Session.export_corrections` (which journals
        nothing), with the payload :meth:`Session.save` writes, so that every file the server
        writes has its entry. Called after the file was written."""
        self._session.record_output(path)

    def _run(self, step: Step, where: str, journal_next: int | None = None) -> dict[str, Any]:
        """One step through :meth:`Session.run_step` (operation lock held); the Applied
        document (``preview: null`` for an undo or redo)."""
        t0 = time.perf_counter()
        try:
            done = self._session.run_step(step)
        except CorrectionRejected as exc:
            reason = f"{where}{exc}"
        except StepRefused as exc:
            reason = f"{where}{exc}"
        except SolverError as exc:
            reason = f"{where}the solve failed ({exc}); the map was not changed"
        except HitlSlamError as exc:
            # E.g. the journal cannot be written: the map did not change, but the history may
            # show the request as interrupted; publish that before the error is answered.
            self._publish(
                documents.last_change(
                    "reject", 1e3 * (time.perf_counter() - t0), reason=f"{where}{exc}"
                ),
                journal_next=journal_next,
            )
            raise
        else:
            if done.outcome is None:
                snap = self._publish(self._step_change(done.action, done.time_s), journal_next)
                return {
                    "accepted": True,
                    "state": self.state(snap),
                    "solve_ms": 0.0,
                    "preview": None,
                }
            outcome = done.outcome
            solve_ms = 1e3 * float(outcome.time_s)
            last = documents.last_change(
                "apply",
                solve_ms,
                cost=float(outcome.final_chi2),
                initial_cost=float(outcome.initial_chi2),
                iterations=int(outcome.iterations),
            )
            snap = self._publish(last, journal_next=journal_next)
            return {
                "accepted": True,
                "state": self.state(snap),
                "solve_ms": solve_ms,
                "preview": documents.preview(self._map, outcome.interpretation),
            }
        elapsed = 1e3 * (time.perf_counter() - t0)
        snap = self._publish(
            documents.last_change("reject", elapsed, reason=reason), journal_next=journal_next
        )
        return {"accepted": False, "reason": reason, "state": self.state(snap)}

    def _step(self, step: Step) -> dict[str, Any]:
        with self._operation:
            self._check_open()
            try:
                done = self._session.run_step(step)
            except StepRefused as exc:
                raise NothingToDo(str(exc)) from None
            return self.state(self._publish(self._step_change(done.action, done.time_s)))

    def _step_change(self, action: str, time_s: float) -> dict[str, Any]:
        """The ``last`` of an undo or redo: the cost of the map now in effect, as its last solve
        left it (0 for the input map, which no correction solved)."""
        stats = self._session.last_stats
        cost = 0.0 if stats is None else stats.final_chi2
        return documents.last_change(action, 1e3 * time_s, cost=cost, initial_cost=cost)

    def _build(
        self, last: dict[str, Any] | None, previous: Snapshot | None, journal_next: int
    ) -> Snapshot:
        """A snapshot of the session as it is now, its versions still to be set by
        :meth:`_publish` (called with the operation lock held, or before any client exists).
        The arrays and lines are recomputed only when the poses changed."""
        session = self._session
        poses = session.poses
        history = tuple(session.history)
        if previous is not None and previous.poses is poses:
            poses_f32, bounds, lines = previous.poses_f32, previous.bounds, previous.lines
        else:
            poses_f32 = self._drawing.poses_f32(poses)
            bounds = self._drawing.bounds(poses)
            active = [
                (e.index, e.interpretation)
                for e in history
                if e.status.value == "applied" and e.interpretation is not None
            ]
            lines = tuple(self._drawing.line_segments(poses, active, session.lines))
        known = None if self._metric is None else self._metric.known(poses)
        return Snapshot(
            version=1,
            map_version=1,
            poses=poses,
            poses_f32=poses_f32,
            bounds=bounds,
            lines=lines,
            history=history,
            active=tuple(session.active),
            can_undo=session.can_undo,
            can_redo=session.can_redo,
            rejected_loops=tuple(sorted(session.rejected_loop_closures)),
            aligned=session.aligned,
            last=last,
            inconsistency_m2=known,
            journal_next=journal_next,
        )

    def _publish(self, last: dict[str, Any] | None, journal_next: int | None = None) -> Snapshot:
        previous = self.snapshot
        built = self._build(
            last, previous, previous.journal_next if journal_next is None else journal_next
        )
        with self._changed:
            current = self._snapshot  # may carry a metric that arrived meanwhile
            version = current.version + 1
            moved = built.poses is not current.poses
            snap = dataclasses.replace(
                built,
                version=version,
                map_version=version if moved else current.map_version,
                inconsistency_m2=built.inconsistency_m2 if moved else current.inconsistency_m2,
            )
            self._snapshot = snap
            self._changed.notify_all()
            listeners = list(self._listeners)
        self._call(listeners)
        if moved and snap.inconsistency_m2 is None:
            self._request_metric(snap)
        return snap

    def _call(self, listeners: list[Callable[[], None]]) -> None:
        for callback in listeners:
            try:
                callback()
            except Exception:  # a client's event loop may be gone; the others still count
                logger.debug("a change listener failed", exc_info=True)

    # -- the inconsistency metric, off the request path ---------------------------------------

    def _request_metric(self, snap: Snapshot) -> None:
        if self._metric is not None:
            self._metric.request(snap.map_version, snap.poses)

    def _publish_metric(self, map_version: int, poses: NDArray[np.float64], total: float) -> None:
        with self._changed:
            current = self._snapshot
            if current.map_version != map_version or current.inconsistency_m2 is not None:
                return
            # A new version so that clients refresh their status bar.
            self._snapshot = dataclasses.replace(
                current, version=current.version + 1, inconsistency_m2=total
            )
            self._changed.notify_all()
            listeners = list(self._listeners)
        self._call(listeners)

    # -- conversions ------------------------------------------------------------------------

    def _active_with_index(self, snap: Snapshot) -> list[tuple[int, Interpretation]]:
        return [
            (e.index, e.interpretation)
            for e in snap.history
            if e.status.value == "applied" and e.interpretation is not None
        ]
