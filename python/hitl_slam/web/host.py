"""SessionHost: the one editing :class:`~hitl_slam.session.Session` every browser tab shares, with a
version counter that long-polling clients wait on, the binary arrays they draw, relation residuals,
the inconsistency metric computed off the request path, and save/export paths kept inside the
session's folder. No HTTP here: :mod:`hitl_slam.web.app` is a thin layer over these methods.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import hashlib
import logging
import math
import os
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.corrections import DrawnCorrection, Interpretation, Mode
from hitl_slam.corrections_file import Apply, Step, Undo
from hitl_slam.errors import CorrectionRejected, HitlSlamError, InputError, SolverError
from hitl_slam.geometry import fit_line, to_world
from hitl_slam.session import HistoryEntry, Session

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

SAVE_FORMATS = (".txt", ".g2o", ".pgm")
"""What ``POST /api/save`` writes (the ``.pgm`` brings its ``.yaml``)."""

_SAVE_NAME = re.compile(r"[A-Za-z0-9._-]{1,100}")
_METRIC_CACHE = 64  # inconsistency values remembered by pose hash, so undo/redo show one at once


class NothingToDo(InputError):
    """An undo, redo or journal step with nothing left to do (HTTP 409)."""


class OutsideFolder(InputError):
    """A save or export path that would leave the session's folder (HTTP 403)."""


@dataclass(frozen=True, eq=False)
class Snapshot:
    """Everything a client sees at one version, published atomically after each change."""

    version: int
    map_version: int  # the version at which the poses last changed
    poses: NDArray[np.float64]  # (N, 3) read-only, the session's own checkpoint array
    points_f32: bytes  # (P, 2) world points, float32 little-endian
    poses_f32: bytes  # (N, 3) float32 little-endian
    bounds: tuple[float, float, float, float]
    history: tuple[HistoryEntry, ...]
    active: tuple[Interpretation, ...]
    can_undo: bool
    can_redo: bool
    last: dict[str, Any] | None
    inconsistency_m2: float | None
    journal_next: int


def _segment_json(segment: Any) -> list[list[float]]:
    return [
        [float(segment[0][0]), float(segment[0][1])],
        [float(segment[1][0]), float(segment[1][1])],
    ]


def _indices_json(values: NDArray[np.int64]) -> list[int]:
    out: list[int] = values.astype(np.int64).tolist()
    return out


def _pose_key(poses: NDArray[np.float64]) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(poses).tobytes(), digest_size=16).digest()


class SessionHost:
    """Serves one session to any number of clients.

    Changes (apply, undo, redo, journal step) run one at a time; each publishes a new
    :class:`Snapshot` with a higher version and wakes every waiter (threading and listener
    callbacks). Reads never wait for a running solve: they see the last published snapshot.
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
        if self._map.num_points >= 2**31:
            raise InputError("the map has over 2^31 points; the web UI cannot index them")
        self._owner = self._map.pose_of_point()
        self._offsets_i32 = self._map.offsets.astype("<i4").tobytes()
        self._steps = tuple(journal)
        self._journal_source = journal_source
        self.poll_timeout = float(poll_timeout)
        self._operation = threading.Lock()  # one change at a time, held through the solve
        self._lock = threading.Lock()  # guards the snapshot; held briefly
        self._changed = threading.Condition(self._lock)
        self._listeners: list[Callable[[], None]] = []
        self._closing = False
        self._metric_values: OrderedDict[bytes, float] = OrderedDict()
        self._metric_job: tuple[int, NDArray[np.float64]] | None = None
        self._metric_wake = threading.Condition()
        self._metric_thread: threading.Thread | None = None
        self._snapshot = self._build(None, None, 0)
        if metrics:
            self._metric_thread = threading.Thread(
                target=self._metric_loop, name="hitl-slam-metric", daemon=True
            )
            self._metric_thread.start()
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
            "history": [self._history_json(e) for e in snap.history],
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
        """(version, float32 LE (P, 2) world points of the current poses, pose by pose)."""
        snap = self.snapshot
        return snap.version, snap.points_f32

    def poses(self) -> tuple[int, bytes]:
        """(version, float32 LE (N, 3) current poses)."""
        snap = self.snapshot
        return snap.version, snap.poses_f32

    def offsets(self) -> bytes:
        """int32 LE (N + 1,): pose i's points are points[offsets[i]:offsets[i + 1]]."""
        return self._offsets_i32

    def relations(self) -> list[dict[str, Any]]:
        """For each correction in effect: its relation residual on the current poses, from lines
        refit (total least squares) to S_a and S_b as the current poses place them."""
        snap = self.snapshot
        out = []
        for index, h in self._active_with_index(snap):
            a = self._map.observed_points(h.s_a, snap.poses)
            b = self._map.observed_points(h.s_b, snap.poses)
            phi_a, rho_a = fit_line(a)
            phi_b, _ = fit_line(b)
            # Lines have no direction: fold the angle between normals into [0, 90] degrees.
            diff = abs((phi_b - phi_a + math.pi / 2) % math.pi - math.pi / 2)
            angle = math.degrees(diff)
            if h.mode is Mode.PERPENDICULAR:
                angle = abs(90.0 - angle)
            centre_a, centre_b = a.mean(axis=0), b.mean(axis=0)
            offset: float | None = None
            if h.mode is Mode.COLLINEAR:
                normal = np.array([math.cos(phi_a), math.sin(phi_a)])
                offset = abs(float(normal @ centre_b) - rho_a)
            elif h.mode is Mode.COLOCATION:
                offset = float(np.hypot(*(centre_b - centre_a)))
            out.append(
                {"index": index, "mode": h.mode.value, "angle_deg": angle, "offset_m": offset}
            )
        return out

    def interpret(self, drawn: DrawnCorrection) -> dict[str, Any]:
        """The Preview of ``drawn`` on the current poses: EM only, nothing changes or is
        journaled."""
        from hitl_slam.interpret import interpret

        snap = self.snapshot
        try:
            h = interpret(self._map, snap.poses, drawn, self._session.config)
        except CorrectionRejected as exc:
            return {"accepted": False, "reason": str(exc)}
        return self._preview(h)

    # -- changing ---------------------------------------------------------------------------

    def apply(self, drawn: DrawnCorrection) -> dict[str, Any]:
        """Apply one correction (serialized with every other change); the Applied document.
        A drawing that cannot be interpreted, or a failed solve, answers ``accepted: false``
        with the reason and leaves the map unchanged."""
        with self._operation:
            self._check_open()
            return self._apply(drawn, "")

    def undo(self) -> dict[str, Any]:
        """Undo the last applied correction; the new State.

        Raises:
            NothingToDo: nothing to undo.
        """
        return self._step(undo=True)

    def redo(self) -> dict[str, Any]:
        """Redo the last undone correction; the new State.

        Raises:
            NothingToDo: nothing to redo.
        """
        return self._step(undo=False)

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
            if isinstance(step, Apply):
                return self._apply(step.drawn, where, index + 1)
            undo = isinstance(step, Undo)
            name = "undo" if undo else "redo"
            possible = self._session.can_undo if undo else self._session.can_redo
            if not possible:
                reason = f"{where}nothing to {name}"
                snap = self._publish(
                    self._last("reject", 0.0, reason=reason), journal_next=index + 1
                )
                return {"accepted": False, "reason": reason, "state": self.state(snap)}
            snap = self._do_step(undo, index + 1)
            return {"accepted": True, "state": self.state(snap), "solve_ms": 0.0, "preview": None}

    def save(self, name: str | None = None) -> list[str]:
        """Write the corrected map beside the session as ``name`` + ``.txt`` (TUM), ``.g2o``,
        ``.pgm`` and ``.yaml`` (journaling each save); the file names, relative to the folder.

        Raises:
            InputError: ``name`` is not a plain file stem ([A-Za-z0-9._-], no leading dot,
                no ``..``), or a file cannot be written.
            OutsideFolder: a file of that name is a link leading out of the folder.
        """
        folder = self.folder
        path = self._session.path
        assert path is not None  # folder checked it
        stem = os.path.splitext(os.path.basename(path))[0] + "-corrected" if name is None else name
        if not _SAVE_NAME.fullmatch(stem) or stem.startswith(".") or ".." in stem:
            raise InputError(
                f"cannot save as {stem!r}: give a plain file name of letters, digits, '.', '_' "
                "and '-' (up to 100, not starting with a dot), without a folder or extension"
            )
        targets = [self._inside(folder, stem + ext) for ext in SAVE_FORMATS]
        yaml = self._contained(folder, os.path.splitext(targets[2])[0] + ".yaml")
        with self._operation:
            self._check_open()
            for target in targets:
                self._write(self._session.save, target)
        return [os.path.relpath(t, folder) for t in (*targets, yaml)]

    def export(self, relative: str) -> list[str]:
        """Write one file at ``relative`` (to the session's folder), format from its extension:
        a map format of :func:`hitl_slam.io.export.export` or ``.jsonl`` (the applied
        corrections); the files written, relative to the folder.

        Raises:
            InputError: a NUL byte, an unknown extension, or an unwritable file.
            OutsideFolder: an absolute path, a ``..`` component, or a path that resolves (links
                followed) outside the folder.
        """
        from hitl_slam.io.export import EXPORT_EXTENSIONS

        if "\x00" in relative:
            raise InputError("the path contains a NUL byte; give a plain file name")
        folder = self.folder
        target = self._inside(folder, relative)
        extension = os.path.splitext(target)[1].lower()
        if extension not in (*EXPORT_EXTENSIONS, ".jsonl"):
            raise InputError(
                f"cannot export to {extension or 'a file without extension'!r}; use one of "
                f"{', '.join((*EXPORT_EXTENSIONS, '.jsonl'))}"
            )
        files = [target]
        if extension == ".pgm":
            files.append(self._contained(folder, os.path.splitext(target)[0] + ".yaml"))
        with self._operation:
            self._check_open()
            if extension == ".jsonl":
                self._write(self._session.export_corrections, target)
            else:
                self._write(self._session.save, target)
        return [os.path.relpath(f, folder) for f in files]

    def close(self) -> None:
        """Wake every waiter, stop the metric thread and close the session (waits for a running
        correction to finish; everything acknowledged is already journaled). Idempotent."""
        self.wake_all()
        with self._metric_wake:
            self._metric_wake.notify_all()
        if self._metric_thread is not None:
            self._metric_thread.join(timeout=30.0)
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

    def _apply(
        self, drawn: DrawnCorrection, where: str, journal_next: int | None = None
    ) -> dict[str, Any]:
        t0 = time.perf_counter()
        try:
            outcome = self._session.apply(drawn)
        except CorrectionRejected as exc:
            reason = f"{where}{exc}"
        except SolverError as exc:
            reason = f"{where}the solve failed ({exc}); the map was not changed"
        except HitlSlamError as exc:
            # E.g. the journal cannot be written: the map did not change, but the history may
            # show the request as interrupted; publish that before the error is answered.
            self._publish(
                self._last("reject", 1e3 * (time.perf_counter() - t0), reason=f"{where}{exc}"),
                journal_next=journal_next,
            )
            raise
        else:
            solve_ms = 1e3 * float(outcome.time_s)
            last = self._last(
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
                "preview": self._preview(outcome.interpretation),
            }
        elapsed = 1e3 * (time.perf_counter() - t0)
        snap = self._publish(
            self._last("reject", elapsed, reason=reason), journal_next=journal_next
        )
        return {"accepted": False, "reason": reason, "state": self.state(snap)}

    def _step(self, undo: bool) -> dict[str, Any]:
        with self._operation:
            self._check_open()
            possible = self._session.can_undo if undo else self._session.can_redo
            if not possible:
                raise NothingToDo(f"nothing to {'undo' if undo else 'redo'}")
            return self.state(self._do_step(undo))

    def _do_step(self, undo: bool, journal_next: int | None = None) -> Snapshot:
        t0 = time.perf_counter()
        if undo:
            self._session.undo()
        else:
            self._session.redo()
        elapsed = 1e3 * (time.perf_counter() - t0)
        history = self._session.history
        # The cost shown is that of the map now in effect, as its last solve left it (0 for the
        # input map, which no correction solved).
        top = next((e for e in reversed(history) if e.status.value == "applied"), None)
        stats = None if top is None else top.stats
        cost = 0.0 if stats is None else stats.final_chi2
        return self._publish(
            self._last("undo" if undo else "redo", elapsed, cost=cost, initial_cost=cost),
            journal_next=journal_next,
        )

    @staticmethod
    def _last(
        kind: str,
        time_ms: float,
        *,
        cost: float = 0.0,
        initial_cost: float = 0.0,
        iterations: int = 0,
        reason: str | None = None,
    ) -> dict[str, Any]:
        return {
            "kind": kind,
            "time_ms": time_ms,
            "cost": cost,
            "initial_cost": initial_cost,
            "iterations": iterations,
            "reason": reason,
        }

    def _build(
        self, last: dict[str, Any] | None, previous: Snapshot | None, journal_next: int
    ) -> Snapshot:
        """A snapshot of the session as it is now, its versions still to be set by
        :meth:`_publish` (called with the operation lock held, or before any client exists).
        The arrays are recomputed only when the poses changed."""
        session = self._session
        poses = session.poses
        if previous is not None and previous.poses is poses:
            points_f32, poses_f32, bounds = previous.points_f32, previous.poses_f32, previous.bounds
        else:
            world = to_world(poses, self._owner, self._map.points)
            points_f32 = world.astype("<f4").tobytes()
            poses_f32 = poses.astype("<f4").tobytes()
            # Column by column: a reduction over axis 0 of an (N, 2) array is strided and slow.
            xs, ys = (np.concatenate([world[:, k], poses[:, k]]) for k in (0, 1))
            bounds = (float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max()))
        with self._lock:
            known = self._metric_values.get(_pose_key(poses))
        return Snapshot(
            version=1,
            map_version=1,
            poses=poses,
            points_f32=points_f32,
            poses_f32=poses_f32,
            bounds=bounds,
            history=tuple(session.history),
            active=tuple(session.active),
            can_undo=session.can_undo,
            can_redo=session.can_redo,
            last=last,
            inconsistency_m2=known,
            journal_next=journal_next,
        )

    def _publish(self, last: dict[str, Any] | None, *, journal_next: int | None = None) -> Snapshot:
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
        if self._metric_thread is None:
            return
        with self._metric_wake:
            self._metric_job = (snap.map_version, snap.poses)  # only the newest map matters
            self._metric_wake.notify_all()

    def _metric_loop(self) -> None:
        from hitl_slam.metrics import inconsistency

        while True:
            with self._metric_wake:
                self._metric_wake.wait_for(lambda: self._metric_job is not None or self._closing)
                if self._closing:
                    return
                job = self._metric_job
                self._metric_job = None
            assert job is not None
            map_version, poses = job
            try:
                # One thread: the cores are left to the solver of the next correction.
                total = inconsistency(self._map, poses, self._session.config, threads=1).total_m2
            except HitlSlamError as exc:
                logger.warning("inconsistency not computed: %s", exc)
                continue
            self._publish_metric(map_version, poses, float(total))

    def _publish_metric(self, map_version: int, poses: NDArray[np.float64], total: float) -> None:
        with self._changed:
            self._metric_values[_pose_key(poses)] = total
            while len(self._metric_values) > _METRIC_CACHE:
                self._metric_values.popitem(last=False)
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

    def _global(self, rows: NDArray[np.int64]) -> str:
        index = self._map.point_rows(rows)
        return base64.b64encode(index.astype("<u4").tobytes()).decode("ascii")

    def _preview(self, h: Interpretation) -> dict[str, Any]:
        return {
            "accepted": True,
            "mode": h.mode.value,
            "line_a": _segment_json(h.line_a),
            "line_b": _segment_json(h.line_b),
            "x_a": _indices_json(h.x_a),
            "x_b": _indices_json(h.x_b),
            "notes": list(h.notes),
            "s_a": self._global(h.s_a),
            "s_b": self._global(h.s_b),
        }

    @staticmethod
    def _history_json(entry: HistoryEntry) -> dict[str, Any]:
        h = entry.interpretation
        return {
            "index": entry.index,
            "mode": entry.mode.value,
            "status": entry.status.value,
            "reason": entry.reason,
            "line_a": None if h is None else _segment_json(h.line_a),
            "line_b": None if h is None else _segment_json(h.line_b),
            "drawn": entry.drawn.to_json(),
            "x_a": [] if h is None else _indices_json(h.x_a),
            "x_b": [] if h is None else _indices_json(h.x_b),
        }

    @staticmethod
    def _inside(folder: str, relative: str) -> str:
        """``relative`` resolved (links followed) inside ``folder``, or OutsideFolder."""
        if "\x00" in relative:
            raise InputError("the path contains a NUL byte; give a plain file name")
        parts = relative.replace("\\", "/").split("/")
        if not relative or os.path.isabs(relative) or relative.startswith("~") or ".." in parts:
            raise OutsideFolder(
                f"path outside the session folder: {relative!r}; give a file name relative to "
                "the session's folder, without '..'"
            )
        return SessionHost._contained(folder, os.path.join(folder, relative))

    @staticmethod
    def _contained(folder: str, path: str) -> str:
        """``path`` with every link resolved, if that stays inside ``folder``; else
        OutsideFolder (a link inside the folder may point anywhere)."""
        target = os.path.realpath(path)
        if os.path.commonpath([folder, target]) != folder or target == folder:
            raise OutsideFolder(
                f"path outside the session folder: {os.path.relpath(path, folder)!r} leads to "
                f"{target}; give a file name inside the session's folder"
            )
        return target

    @staticmethod
    def _write(work: Callable[[str], object], target: str) -> None:
        try:
            work(target)
        except OSError as exc:
            raise InputError(
                f"{target}: cannot write the file ({exc.strerror or exc}); check that the folder "
                "exists and is writable"
            ) from None
