"""The session file (``.hitl``): an SQLite database holding the input map, the configuration and an
append-only journal of events, each committed (and fsynced) in its own transaction before the
session's map in memory changes. Plain storage: what the events mean is :mod:`hitl_slam.session`'s.

Durability choice: SQLite's rollback journal (``journal_mode=DELETE``) with ``synchronous=FULL``,
not WAL: a committed event is on disk when :meth:`Journal.append` returns, and between events the
``.hitl`` file alone holds everything (no ``-wal`` side file to lose when copying it). Events come
at human pace, so the extra fsyncs cost nothing that matters.

Schema (``PRAGMA user_version`` = :data:`SCHEMA_VERSION`, ``PRAGMA application_id`` =
:data:`APPLICATION_ID`)::

    meta(key TEXT PRIMARY KEY, value TEXT)          -- created_by, created (unix time)
    map(id = 1, name, source, anchor, metadata, sha256)   -- metadata: JSON object
    map_arrays(name TEXT PRIMARY KEY, npy BLOB, sha256)   -- Map arrays as .npy (np.save) blobs,
                                                    -- and array metadata as "metadata/<key>"
    config(id = 1, json TEXT, sha256)               -- Config.to_dict() as JSON
    events(seq INTEGER PRIMARY KEY, time REAL, kind TEXT, payload TEXT, poses BLOB NULL, sha256)

``seq`` counts from 1 without gaps; ``time`` is Unix time in seconds; ``payload`` is a JSON object;
``poses`` is an optional ``(N, 3)`` float64 .npy checkpoint.

A ``correction`` event's payload holds ``request``, ``interpretation`` and ``stats`` and, since the
solved lines became part of the state, ``lines``: ``[[phi, rho], ...]``, the solved lines a and b
of every correction in effect after it, in order (2K pairs of JSON numbers, which round-trip
exactly). An addition within schema 1: a journal without ``lines`` still opens, its lines refit
to S_a / S_b at the checkpoint poses (:attr:`hitl_slam.session.Session.lines`).

A ``loop_closure`` event (an addition within schema 2; maps built by the front end list their loop
closures, :mod:`hitl_slam.loop_closures`) rejects or reinstates one: its payload holds ``loop``
(the loop closure's index), ``edge`` (its row among the map's edges), ``rejected`` (true: left out
of the solve from now on; false: reinstated), ``stats`` (as a correction's) and ``lines`` (as a
correction's: every correction in effect, re-solved), and its ``poses`` are the re-solved
checkpoint. It is computed first and journaled as one event, then the state changes; ``undo`` and
``redo`` name it by its ``seq`` as ``request``, as they name a correction by its request's.

An ``align`` event (an addition within schema 2; docs/ALGORITHM.md §I.11) records the map aligned
with its scans: its payload holds ``graph`` (``edges`` ``[[i, j], ...]``, ``measurements``
``[[x, y, theta], ...]`` and ``information`` ``[[9 numbers, row-major], ...]``: the factors that
replace the map's from then on), ``stats`` and ``lines`` (as a loop closure step's),
``loop_closures`` and ``loop_closures_rejected`` (the front end's counts), ``steps`` and
``contradicted`` (the guard's figures); its ``poses`` are the aligned checkpoint. Journaled as one
event once computed, undone and redone like a loop closure step.

Integrity (schema 2): every stored row carries ``sha256 TEXT``, the SHA-256 of its values with
their SQLite types (:func:`row_digest`): ``map``, ``config``, each ``map_arrays`` blob and each
event, so a byte changed on disk (which SQLite's own checks do not see) is found when the row is
read. Opening runs ``PRAGMA quick_check`` (the file's structure: truncation, torn pages) and checks
every float array of the map and every pose checkpoint is finite. Any failure is a
:class:`DamagedSession` naming the file, what is wrong and the first damaged event (the events
before it are intact; :meth:`Journal.salvage` copies them to a new session file). A schema 1 file
still opens (its rows are unchecked; a warning says so) and is upgraded to schema 2 (checksums
added, in the same transaction) by its next write.

Failure path of :meth:`Journal.append`: when a write fails (disk full, I/O error, read-only file)
the first error is the one reported; the transaction is rolled back and the journal reconnects to
the file to learn what it holds (a hot rollback journal left by a failed commit is rolled back
then), so the caller's state follows the file: an event that reached the file counts as written,
one that did not is reported as not written, and the next append works once the disk does. If the
file cannot even be reopened the journal turns read-only and every later write says why.
"""

from __future__ import annotations

import contextlib
import enum
import json
import logging
import os
import secrets
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import DamagedSession, InputError
from hitl_slam.io.atomic import sweep_once
from hitl_slam.journal_encoding import decode_array, encode_array, encode_payload
from hitl_slam.journal_schema import (
    _UPGRADE,
    APPLICATION_ID,
    MEMORY,
    SCHEMA_VERSION,
    _configure,
    _connect,
    _corrupt,
    _event_digest,
    _label,
    _link_no_clobber,
    _map_from_rows,
    _non_finite,
    _unlink_quietly,
    _write_header,
    row_digest,
)
from hitl_slam.map import Map

__all__ = [
    "APPLICATION_ID",
    "SCHEMA_VERSION",
    "DamagedSession",
    "Event",
    "EventKind",
    "Journal",
    "decode_array",
    "encode_array",
    "encode_payload",
    "read_journal",
    "row_digest",
]

_log = logging.getLogger(__name__)


class EventKind(enum.Enum):
    """What a journal event records (its payload's meaning is the session's)."""

    LOAD = "load"  # the session started from the stored map
    REQUEST = "request"  # a drawn correction, before any computing
    CORRECTION = "correction"  # the request's outcome: applied (interpretation, stats, poses)
    REJECTION = "rejection"  # the request's outcome: could not be interpreted, nothing changed
    INTERRUPTED = "interrupted"  # the request's outcome: the computation failed or was stopped
    LOOP_CLOSURE = "loop_closure"  # a loop closure rejected or reinstated (result and poses)
    ALIGN = "align"  # the map aligned with its scans (the aligned graph, result and poses)
    UNDO = "undo"
    REDO = "redo"
    SAVE = "save"  # the current map was exported to a file


@dataclass(frozen=True, eq=False)
class Event:
    """One journal row."""

    seq: int
    time: float
    kind: EventKind
    payload: dict[str, Any]
    poses: NDArray[np.float64] | None = None


class Journal:
    """An open session file. Create with :meth:`create`, open with :meth:`open`.

    Appends are serialized by a lock, so one journal may be shared by threads (a web server).
    """

    def __init__(
        self, connection: sqlite3.Connection, path: str | None, version: int = SCHEMA_VERSION
    ) -> None:
        self._connection = connection
        self._path = path
        self._version = version
        self._lock = threading.Lock()
        self._read_only: str | None = None  # why writing stopped, once it did
        last = connection.execute("SELECT max(seq) FROM events").fetchone()[0]
        if last is not None and not isinstance(last, int):
            raise sqlite3.DatabaseError(f"event number {last!r} is not an integer")
        self._last_seq: int = 0 if last is None else int(last)

    # -- opening ----------------------------------------------------------------------------

    @classmethod
    def create(
        cls, path: str | os.PathLike[str] | None, map: Map, config: Config = DEFAULT
    ) -> Journal:
        """A new session file at ``path`` (``None``: in memory) holding ``map`` and ``config``.

        The file appears complete or not at all (built under a temporary name, then linked into
        place). It is never overwritten: an existing ``path`` is an :class:`InputError`, and so
        is a map holding NaN or inf (the file could not be opened again).
        """
        problem = _non_finite(map)
        if problem is not None:
            raise InputError(
                f"{_label(path)}: cannot start a session on this map: {problem}; "
                "fix the map's file first"
            )
        return cls._build(path, lambda connection: _write_header(connection, map, config))

    @classmethod
    def _build(
        cls,
        path: str | os.PathLike[str] | None,
        fill: Callable[[sqlite3.Connection], None],
    ) -> Journal:
        """A new session file written by ``fill`` in one transaction, linked into place."""
        if path is None:
            connection = sqlite3.connect(MEMORY, isolation_level=None, check_same_thread=False)
            connection.execute("BEGIN")
            fill(connection)
            connection.execute("COMMIT")
            return cls(connection, None)
        target = os.fspath(path)
        if os.path.exists(target):
            raise InputError(
                f"{target}: already exists; a new session needs a new file "
                "(open the existing one to continue it, or choose another name)"
            )
        directory, name = os.path.split(target)
        # Session files of a run killed while creating one are left under this naming.
        sweep_once(directory)
        temp = os.path.join(directory, f".{name}.{secrets.token_hex(4)}.tmp")
        try:
            connection = sqlite3.connect(temp, isolation_level=None)
            try:
                _configure(connection)
                connection.execute("BEGIN")
                fill(connection)
                connection.execute("COMMIT")
            finally:
                connection.close()
            _link_no_clobber(temp, target)
        except FileExistsError:
            raise InputError(f"{target}: already exists; a new session needs a new file") from None
        except (OSError, sqlite3.Error) as exc:
            raise InputError(
                f"{target}: cannot create the session file ({exc}); "
                "check that the directory exists and is writable"
            ) from None
        finally:
            _unlink_quietly(temp)
            _unlink_quietly(temp + "-journal")
        return cls.open(target)

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, check: bool = True) -> Journal:
        """Open an existing session file (never creates one).

        With ``check`` (the default), SQLite's ``quick_check`` must pass (the file's structure:
        truncation, torn pages); :meth:`salvage` opens without it to copy what is still intact.

        Raises:
            InputError: missing file, not a session file, a newer schema.
            DamagedSession: a damaged file (an InputError).
        """
        where = os.fspath(path)
        if not os.path.isfile(where):
            raise InputError(f"{where}: no such file; give the path of a .hitl session file")
        try:
            connection = _connect(where)
        except sqlite3.Error as exc:
            raise InputError(f"{where}: cannot open the session file ({exc})") from None
        try:
            application_id = connection.execute("PRAGMA application_id").fetchone()[0]
            version = connection.execute("PRAGMA user_version").fetchone()[0]
            if application_id != APPLICATION_ID:
                raise InputError(
                    f"{where}: not a hitl-slam session file (an SQLite database of another "
                    "kind); give a .hitl file written by hitl-slam"
                )
            if version > SCHEMA_VERSION:
                raise InputError(
                    f"{where}: this session was written by a newer hitl-slam (schema {version}); "
                    f"upgrade hitl-slam to open it (this one reads schema {SCHEMA_VERSION} "
                    "and older)"
                )
            if version < 1:
                raise _corrupt(where, f"schema version {version}")
            # A hitl-slam file from here on: what fails now is damage, not another kind of file.
            try:
                _configure(connection)
                problems = ["ok"]
                if check:
                    problems = [r[0] for r in connection.execute("PRAGMA quick_check(5)")]
            except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
                problems = [str(exc)]
            if problems != ["ok"]:
                raise _corrupt(where, "SQLite integrity check: " + "; ".join(map(str, problems)))
            try:
                journal = cls(connection, where, version)
            except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
                raise _corrupt(where, str(exc)) from None
            if version < SCHEMA_VERSION:
                _log.warning(
                    "%s: a session file of schema %d, without checksums: changed bytes in it "
                    "cannot be detected; its next write adds them (schema %d)",
                    where,
                    version,
                    SCHEMA_VERSION,
                )
        except DamagedSession:
            connection.close()
            raise
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
            connection.close()
            raise InputError(
                f"{where}: not a hitl-slam session file ({exc}); give a .hitl file written by "
                "hitl-slam"
            ) from None
        except BaseException:
            connection.close()
            raise
        return journal

    # -- reading ----------------------------------------------------------------------------

    @property
    def path(self) -> str | None:
        """The file, or ``None`` for an in-memory journal."""
        return self._path

    @property
    def last_seq(self) -> int:
        """The ``seq`` of the last event (0: none)."""
        return self._last_seq

    @property
    def version(self) -> int:
        """The file's schema version (1: without checksums; upgraded by the next write)."""
        return self._version

    @property
    def read_only(self) -> str | None:
        """Why the journal stopped writing (the file could not be reopened after a failed
        write), or ``None`` while it writes."""
        return self._read_only

    def _checked(self) -> bool:
        return self._version >= 2

    def read_map(self) -> Map:
        """The input map, exactly as stored (checksums verified, every float finite).

        Raises:
            DamagedSession: anything missing, changed or malformed.
        """
        where = _label(self._path)
        checked = self._checked()
        sha = ", sha256" if checked else ""
        try:
            with self._lock:
                row = self._connection.execute(
                    f"SELECT name, source, anchor, metadata{sha} FROM map WHERE id = 1"
                ).fetchone()
                stored = self._connection.execute(
                    f"SELECT name, npy{sha} FROM map_arrays"
                ).fetchall()
        except (sqlite3.Error, UnicodeDecodeError) as exc:
            raise _corrupt(where, str(exc)) from None
        return _map_from_rows(where, row, stored, checked)

    def read_config(self) -> Config:
        """The session's configuration (checksum verified)."""
        where = _label(self._path)
        checked = self._checked()
        try:
            with self._lock:
                row = self._connection.execute(
                    "SELECT json" + (", sha256" if checked else "") + " FROM config WHERE id = 1"
                ).fetchone()
        except (sqlite3.Error, UnicodeDecodeError) as exc:
            raise _corrupt(where, str(exc)) from None
        if row is None:
            raise _corrupt(where, "no configuration")
        if checked and row[1] != row_digest("config", row[0]):
            raise _corrupt(where, "the configuration does not match its checksum")
        try:
            data = json.loads(row[0])
        except (ValueError, TypeError, RecursionError) as exc:
            raise _corrupt(where, f"unreadable configuration: {exc}") from None
        if not isinstance(data, dict):
            raise _corrupt(where, "the configuration is not a JSON object")
        data, dropped = Config.known(data)
        if dropped:
            # Only an older version wrote them (a newer schema is refused at open, and a checksum
            # guards the row): options since deleted. The history opens as it was left (its
            # checkpoints hold every result); later corrections use this version's method.
            _log.warning(
                "%s: the stored configuration names option(s) this version does not have (%s); "
                "they are ignored: the history opens as it was, later corrections use this "
                "version's method",
                where,
                ", ".join(f"{k}={v!r}" for k, v in sorted(dropped.items())),
            )
        try:
            return Config.from_dict(data)
        except InputError as exc:
            raise _corrupt(where, f"the configuration is invalid: {exc}") from None
        except Exception as exc:  # a malformed stored value is a damaged file
            raise _corrupt(where, f"the configuration is invalid: {exc}") from None

    def events(self) -> list[Event]:
        """Every event, in order (checksums verified).

        Raises:
            DamagedSession: with ``first_bad_seq``, the first event that cannot be used.
        """
        out: list[Event] = []
        for item in self.intact_events():
            if isinstance(item, DamagedSession):
                raise item
            out.append(item)
        return out

    def intact_events(self) -> Iterable[Event | DamagedSession]:
        """The events in order, ending at the first that cannot be used, which is yielded as the
        :class:`DamagedSession` describing it (nothing after it is read)."""
        where = _label(self._path)
        checked = self._checked()
        kinds = {k.value: k for k in EventKind}
        sql = "SELECT seq, time, kind, payload, poses" + (", sha256" if checked else "")
        expected = 1
        while True:
            try:
                with self._lock:
                    row = self._connection.execute(
                        f"{sql} FROM events WHERE seq >= ? ORDER BY seq LIMIT 1", (expected,)
                    ).fetchone()
                    if row is None:
                        # An event numbered below 1 or not an integer is damage too.
                        odd = self._connection.execute(
                            "SELECT count(*) FROM events WHERE NOT (typeof(seq) = 'integer' "
                            "AND seq >= 1)"
                        ).fetchone()[0]
                        if odd:
                            yield _corrupt(where, f"event {expected} is missing", expected)
                        return
            except (sqlite3.Error, UnicodeDecodeError) as exc:
                yield _corrupt(where, f"event {expected} is unreadable: {exc}", expected)
                return
            seq, stamp, kind, payload, poses = row[:5]
            if seq != expected:
                yield _corrupt(where, f"event {expected} is missing", expected)
                return
            if checked and row[5] != _event_digest(seq, stamp, kind, payload, poses):
                yield _corrupt(where, f"event {seq} does not match its checksum", seq)
                return
            try:
                if kind not in kinds:
                    raise ValueError(f"unknown kind {kind!r}")
                if not isinstance(stamp, float | int) or not isinstance(payload, str):
                    raise ValueError("its time or payload has the wrong type")
                data = json.loads(payload)
                if not isinstance(data, dict):
                    raise ValueError("its payload is not a JSON object")
                checkpoint = None if poses is None else decode_array(poses)
                if checkpoint is not None and (
                    checkpoint.dtype != np.float64 or not np.isfinite(checkpoint).all()
                ):
                    raise ValueError("its pose checkpoint holds NaN or inf, or is not float64")
            except (ValueError, TypeError, RecursionError) as exc:
                yield _corrupt(where, f"event {seq} is unreadable: {exc}", seq)
                return
            yield Event(int(seq), float(stamp), kinds[kind], data, checkpoint)
            expected += 1

    # -- writing ----------------------------------------------------------------------------

    def append(
        self,
        kind: EventKind,
        payload: dict[str, Any],
        poses: NDArray[np.float64] | None = None,
    ) -> Event:
        """Commit one event in its own transaction; durable on disk when this returns.

        The payload is written by :func:`encode_payload` (its dicts may hold integer arrays, as
        the JSON lists they are); the event returned carries it as given.

        When the write fails, the first error is the one raised; the journal then agrees with the
        file again (see the module's notes), and the event was not written. When the commit
        reported an error but the event did reach the file, this returns normally (the error is
        logged): the caller's state must follow the file.

        Raises:
            InputError: the file was changed by another program since it was opened (two
                sessions on one file), or it cannot be written (disk full, I/O error, read-only).
        """
        where = _label(self._path)
        text = encode_payload(payload)
        blob = None if poses is None else encode_array(np.asarray(poses, dtype=np.float64))
        stamp = time.time()
        with self._lock:
            if self._read_only is not None:
                raise InputError(
                    f"{where}: the session is read-only: {self._read_only}; the map shown is the "
                    "last one written to the file; fix the disk, then open the file again"
                )
            seq = self._last_seq + 1
            digest = _event_digest(seq, stamp, kind.value, text, blob)
            try:
                if self._stale:
                    # After a failed write: a new connection, as the one kept may have been
                    # opened read-only while the disk was (SQLite falls back to that silently).
                    self._reconnect()
                    self._stale = False
                self._connection.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as exc:
                self._stale = True
                raise self._write_error(where, exc) from None
            try:
                last = self._connection.execute("SELECT max(seq) FROM events").fetchone()[0]
                if (0 if last is None else last) != self._last_seq:
                    raise InputError(
                        f"{where}: the session file was changed by another program since it "
                        "was opened; close the other session and open the file again"
                    )
                if self._version < SCHEMA_VERSION:
                    self._upgrade()
                columns = "seq, time, kind, payload, poses"
                values: tuple[Any, ...] = (seq, stamp, kind.value, text, blob)
                if self._version >= 2 or self._upgrading:
                    columns += ", sha256"
                    values += (digest,)
                self._connection.execute(
                    f"INSERT INTO events({columns}) VALUES ({', '.join('?' * len(values))})",
                    values,
                )
                self._connection.execute("COMMIT")
            except InputError:  # another program's event: nothing of ours was written
                with contextlib.suppress(sqlite3.Error):
                    self._connection.execute("ROLLBACK")
                raise
            except BaseException as first:
                self._stale = True
                written = self._settle(where, seq, digest, first)
                if not written:
                    if isinstance(first, sqlite3.Error | OSError):
                        raise self._write_error(where, first) from None
                    raise
                _log.warning(
                    "%s: the commit of event %d reported %r, but the event is in the file; "
                    "carrying on",
                    where,
                    seq,
                    str(first),
                )
            else:
                if self._upgrading:
                    self._version = SCHEMA_VERSION
            finally:
                self._upgrading = False
            self._last_seq = seq
        return Event(seq, stamp, kind, payload, None if poses is None else np.array(poses))

    _upgrading = False
    _stale = False

    def _reconnect(self) -> None:
        """Replace the connection by a new one to the file (no-op in memory)."""
        if self._path is None:
            return
        with contextlib.suppress(sqlite3.Error):
            self._connection.close()
        connection = _connect(self._path)
        try:
            _configure(connection)
        except BaseException:
            connection.close()
            raise
        self._connection = connection

    def _upgrade(self) -> None:
        """Schema 1 -> 2 inside the caller's transaction: checksum columns, filled from the
        rows as they stand."""
        connection = self._connection
        for statement in _UPGRADE:
            connection.execute(statement)
        for row in connection.execute("SELECT name, source, anchor, metadata FROM map").fetchall():
            connection.execute("UPDATE map SET sha256 = ? WHERE id = 1", (row_digest("map", *row),))
        for name, blob in connection.execute("SELECT name, npy FROM map_arrays").fetchall():
            connection.execute(
                "UPDATE map_arrays SET sha256 = ? WHERE name = ?",
                (row_digest("map_arrays", name, blob), name),
            )
        for (text,) in connection.execute("SELECT json FROM config").fetchall():
            connection.execute("UPDATE config SET sha256 = ?", (row_digest("config", text),))
        rows = connection.execute("SELECT seq, time, kind, payload, poses FROM events").fetchall()
        connection.executemany(
            "UPDATE events SET sha256 = ? WHERE seq = ?",
            [(_event_digest(*row), row[0]) for row in rows],
        )
        connection.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        self._upgrading = True

    def _write_error(self, where: str, exc: BaseException) -> InputError:
        return InputError(
            f"{where}: cannot write to the session file ({exc}); nothing was changed; check the "
            "disk (space, errors) and the file's permissions, then try again"
        )

    def _settle(self, where: str, seq: int, digest: str, first: BaseException) -> bool:
        """After a failed write: roll back (its own error never replaces ``first``), then learn
        from the file whether event ``seq`` is in it. Reconnects to a file (a failed commit can
        leave a hot rollback journal that only a new connection rolls back); a file that cannot
        be reopened turns the journal read-only. Returns whether the event is in the file."""
        with contextlib.suppress(sqlite3.Error):
            if self._connection.in_transaction:
                self._connection.execute("ROLLBACK")
        try:
            self._reconnect()
        except sqlite3.Error as exc:
            self._read_only = (
                f"a write failed ({first}) and the file could not be opened again ({exc})"
            )
            _log.error("%s: %s", where, self._read_only)
            return False
        connection = self._connection
        try:
            version = connection.execute("PRAGMA user_version").fetchone()[0]
            column = "sha256" if version >= 2 else "NULL"
            row = connection.execute(
                f"SELECT {column} FROM events WHERE seq = ?", (seq,)
            ).fetchone()
            last = connection.execute("SELECT max(seq) FROM events").fetchone()[0]
        except (sqlite3.Error, UnicodeDecodeError) as exc:
            self._read_only = f"a write failed ({first}) and the file cannot be read ({exc})"
            _log.error("%s: %s", where, self._read_only)
            return False
        self._version = int(version)
        if row is None:
            return False
        if last != seq or (version >= 2 and row[0] != digest):
            self._read_only = (
                f"a write failed ({first}) and the file now holds an event this session did "
                "not write"
            )
            return False
        return True

    def backup_to(self, path: str | os.PathLike[str]) -> None:
        """Write a copy of the whole journal to a NEW file ``path`` (atomic, never overwrites)."""
        target = os.fspath(path)
        if os.path.exists(target):
            raise InputError(
                f"{target}: already exists; choose a new file name for the session, or delete "
                "the old one"
            )
        directory, name = os.path.split(target)
        sweep_once(directory)
        temp = os.path.join(directory, f".{name}.{secrets.token_hex(4)}.tmp")
        try:
            copy = sqlite3.connect(temp, isolation_level=None)
            try:
                with self._lock:
                    self._connection.backup(copy)
                _configure(copy)
            finally:
                copy.close()
            with open(temp, "rb+") as f:
                os.fsync(f.fileno())
            _link_no_clobber(temp, target)
        except FileExistsError:
            raise InputError(f"{target}: already exists; choose a new file name") from None
        except (OSError, sqlite3.Error) as exc:
            raise InputError(
                f"{target}: cannot write the session file ({exc}); check that the directory "
                "exists and is writable"
            ) from None
        finally:
            _unlink_quietly(temp)

    @classmethod
    def salvage(
        cls,
        path: str | os.PathLike[str],
        target: str | os.PathLike[str],
        limit: int | None = None,
    ) -> int:
        """Copy what is intact in the damaged session file ``path`` to a NEW session file
        ``target``: the map, the configuration and the events before the first damaged one
        (their checksums verified; at most ``limit`` of them), then a ``load`` event saying where
        they came from. Returns how many events were copied. ``path`` is only read.

        Raises:
            InputError: ``target`` exists or cannot be written, or the map or configuration of
                ``path`` is itself damaged (then nothing can be saved from it).
        """
        source = os.fspath(path)
        with cls.open(source, check=False) as damaged:
            map = damaged.read_map()
            config = damaged.read_config()
            events: list[Event] = []
            damage: DamagedSession | None = None
            for item in damaged.intact_events():
                if isinstance(item, DamagedSession):
                    damage = item
                    break
                if limit is not None and len(events) == limit:
                    break
                events.append(item)

        def fill(connection: sqlite3.Connection) -> None:
            _write_header(connection, map, config)
            rows = []
            for e in events:
                text = json.dumps(e.payload)
                blob = None if e.poses is None else encode_array(e.poses)
                digest = _event_digest(e.seq, e.time, e.kind.value, text, blob)
                rows.append((e.seq, e.time, e.kind.value, text, blob, digest))
            note = {
                "recovered_from": os.path.abspath(source),
                "events": len(events),
                "damage": None if damage is None else damage.what,
            }
            seq, stamp, text = len(events) + 1, time.time(), json.dumps(note)
            rows.append(
                (seq, stamp, "load", text, None, _event_digest(seq, stamp, "load", text, None))
            )
            connection.executemany(
                "INSERT INTO events(seq, time, kind, payload, poses, sha256) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                rows,
            )

        cls._build(target, fill).close()
        return len(events)

    def close(self) -> None:
        """Close the database (idempotent)."""
        with self._lock:
            self._connection.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_journal(path: str | os.PathLike[str]) -> tuple[Map, Config, list[Event]]:
    """The input map, the configuration and every event of the session file ``path``."""
    with Journal.open(path) as journal:
        return journal.read_map(), journal.read_config(), journal.events()
