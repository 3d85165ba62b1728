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
    map(id = 1, name, source, anchor, metadata)    -- metadata: JSON object
    map_arrays(name TEXT PRIMARY KEY, npy BLOB)     -- Map arrays as .npy (np.save) blobs, and
                                                    -- array metadata as "metadata/<key>"
    config(id = 1, json TEXT)                       -- Config.to_dict() as JSON
    events(seq INTEGER PRIMARY KEY, time REAL, kind TEXT, payload TEXT, poses BLOB NULL)

``seq`` counts from 1 without gaps; ``time`` is Unix time in seconds; ``payload`` is a JSON object;
``poses`` is an optional ``(N, 3)`` float64 .npy checkpoint.

A ``correction`` event's payload holds ``request``, ``interpretation`` and ``stats`` and, since the
solved lines became part of the state, ``lines``: ``[[phi, rho], ...]``, the solved lines a and b
of every correction in effect after it, in order (2K pairs of JSON numbers, which round-trip
exactly). An addition within schema 1: a journal without ``lines`` still opens, its lines refit
to S_a / S_b at the checkpoint poses (:attr:`hitl_slam.session.Session.lines`).
"""

from __future__ import annotations

import contextlib
import enum
import io
import json
import os
import secrets
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.io.atomic import fsync_directory
from hitl_slam.map import Map

__all__ = [
    "APPLICATION_ID",
    "SCHEMA_VERSION",
    "Event",
    "EventKind",
    "Journal",
    "decode_array",
    "encode_array",
    "read_journal",
]

SCHEMA_VERSION = 1
"""The schema this module writes; it reads this one and older ones."""

APPLICATION_ID = 0x4849544C
"""``PRAGMA application_id`` of a session file: the bytes "HITL"."""

MEMORY = ":memory:"

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE map (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    name TEXT NOT NULL,
    source TEXT,
    anchor INTEGER NOT NULL,
    metadata TEXT NOT NULL
);
CREATE TABLE map_arrays (name TEXT PRIMARY KEY, npy BLOB NOT NULL);
CREATE TABLE config (id INTEGER PRIMARY KEY CHECK (id = 1), json TEXT NOT NULL);
CREATE TABLE events (
    seq INTEGER PRIMARY KEY,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    payload TEXT NOT NULL,
    poses BLOB
);
"""

_REQUIRED_ARRAYS = (
    "poses",
    "points",
    "offsets",
    "edges",
    "measurements",
    "information",
    "information_source",
)
_OPTIONAL_ARRAYS = ("normals", "timestamps")
_METADATA_PREFIX = "metadata/"


class EventKind(enum.Enum):
    """What a journal event records (its payload's meaning is the session's)."""

    LOAD = "load"  # the session started from the stored map
    REQUEST = "request"  # a drawn correction, before any computing
    CORRECTION = "correction"  # the request's outcome: applied (interpretation, stats, poses)
    REJECTION = "rejection"  # the request's outcome: could not be interpreted, nothing changed
    INTERRUPTED = "interrupted"  # the request's outcome: the computation failed or was stopped
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


def encode_array(array: NDArray[Any]) -> bytes:
    """``array`` as the bytes of a ``.npy`` file (exact: dtype, shape and every bit kept)."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def decode_array(blob: bytes) -> NDArray[Any]:
    """The array stored by :func:`encode_array`."""
    array: NDArray[Any] = np.load(io.BytesIO(blob), allow_pickle=False)
    return array


def _label(path: str | os.PathLike[str] | None) -> str:
    return MEMORY if path is None else os.fspath(path)


def _corrupt(where: str, what: str) -> InputError:
    return InputError(
        f"{where}: the session file is damaged ({what}); "
        "restore it from a copy, or start a new session from the input map"
    )


def _configure(connection: sqlite3.Connection) -> None:
    connection.execute("PRAGMA journal_mode=DELETE")
    connection.execute("PRAGMA synchronous=FULL")
    connection.execute("PRAGMA foreign_keys=ON")


def _json_default(value: Any) -> Any:
    # Map metadata is free-form: numpy values become plain ones, anything else its str().
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


def _split_metadata(metadata: dict[str, Any]) -> tuple[str, list[tuple[str, bytes]]]:
    """Metadata as JSON, except top-level arrays, which are kept exactly as .npy blobs (e.g. the
    pose covariances a .covars file carries)."""
    plain = {k: v for k, v in metadata.items() if not isinstance(v, np.ndarray)}
    arrays = [
        (_METADATA_PREFIX + str(k), encode_array(v))
        for k, v in metadata.items()
        if isinstance(v, np.ndarray) and v.dtype != object
    ]
    plain.update(
        {k: v for k, v in metadata.items() if isinstance(v, np.ndarray) and v.dtype == object}
    )
    return json.dumps(plain, default=_json_default, sort_keys=True), arrays


def _write_header(connection: sqlite3.Connection, map: Map, config: Config) -> None:
    from hitl_slam import __version__

    # One statement at a time: executescript() would commit the caller's open transaction.
    for statement in _SCHEMA.split(";"):
        if statement.strip():
            connection.execute(statement)
    connection.execute(f"PRAGMA application_id={APPLICATION_ID}")
    connection.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
    connection.executemany(
        "INSERT INTO meta(key, value) VALUES (?, ?)",
        [("created_by", f"hitl-slam {__version__}"), ("created", repr(time.time()))],
    )
    metadata, metadata_arrays = _split_metadata(map.metadata)
    connection.execute(
        "INSERT INTO map(id, name, source, anchor, metadata) VALUES (1, ?, ?, ?, ?)",
        (map.name, map.source, int(map.anchor), metadata),
    )
    arrays: list[tuple[str, bytes]] = [
        (name, encode_array(getattr(map, name))) for name in _REQUIRED_ARRAYS
    ]
    arrays += [
        (name, encode_array(getattr(map, name)))
        for name in _OPTIONAL_ARRAYS
        if getattr(map, name) is not None
    ]
    arrays += metadata_arrays
    connection.executemany("INSERT INTO map_arrays(name, npy) VALUES (?, ?)", arrays)
    connection.execute(
        "INSERT INTO config(id, json) VALUES (1, ?)", (json.dumps(config.to_dict()),)
    )


def _link_no_clobber(temp: str, target: str) -> None:
    """Move ``temp`` to ``target`` unless ``target`` exists (atomically where links work)."""
    try:
        os.link(temp, target)
    except FileExistsError:
        raise
    except OSError:
        # A file system without hard links: the existence check and the rename are two steps.
        if os.path.exists(target):
            raise FileExistsError(target) from None
        os.replace(temp, target)
    else:
        os.unlink(temp)
    fsync_directory(os.path.dirname(target))


class Journal:
    """An open session file. Create with :meth:`create`, open with :meth:`open`.

    Appends are serialized by a lock, so one journal may be shared by threads (a web server).
    """

    def __init__(self, connection: sqlite3.Connection, path: str | None) -> None:
        self._connection = connection
        self._path = path
        self._lock = threading.Lock()
        last = connection.execute("SELECT max(seq) FROM events").fetchone()[0]
        self._last_seq: int = 0 if last is None else int(last)

    # -- opening ----------------------------------------------------------------------------

    @classmethod
    def create(
        cls, path: str | os.PathLike[str] | None, map: Map, config: Config = DEFAULT
    ) -> Journal:
        """A new session file at ``path`` (``None``: in memory) holding ``map`` and ``config``.

        The file appears complete or not at all (built under a temporary name, then linked into
        place). It is never overwritten: an existing ``path`` is an :class:`InputError`.
        """
        if path is None:
            connection = sqlite3.connect(MEMORY, isolation_level=None, check_same_thread=False)
            connection.execute("BEGIN")
            _write_header(connection, map, config)
            connection.execute("COMMIT")
            return cls(connection, None)
        target = os.fspath(path)
        if os.path.exists(target):
            raise InputError(
                f"{target}: already exists; a new session needs a new file "
                "(open the existing one to continue it, or choose another name)"
            )
        directory, name = os.path.split(target)
        temp = os.path.join(directory, f".{name}.{secrets.token_hex(4)}.tmp")
        try:
            connection = sqlite3.connect(temp, isolation_level=None)
            try:
                _configure(connection)
                connection.execute("BEGIN")
                _write_header(connection, map, config)
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
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temp)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temp + "-journal")
        return cls.open(target)

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Journal:
        """Open an existing session file (never creates one).

        Raises:
            InputError: missing file, not a session file, a newer schema, or a damaged file.
        """
        where = os.fspath(path)
        if not os.path.isfile(where):
            raise InputError(f"{where}: no such file; give the path of a .hitl session file")
        uri = Path(where).resolve().as_uri() + "?mode=rw"
        try:
            connection = sqlite3.connect(
                uri, uri=True, isolation_level=None, check_same_thread=False
            )
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
            _configure(connection)
            journal = cls(connection, where)
        except sqlite3.DatabaseError as exc:
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

    def read_map(self) -> Map:
        """The input map, exactly as stored."""
        where = _label(self._path)
        try:
            row = self._connection.execute(
                "SELECT name, source, anchor, metadata FROM map WHERE id = 1"
            ).fetchone()
            blobs = dict(self._connection.execute("SELECT name, npy FROM map_arrays").fetchall())
        except sqlite3.Error as exc:
            raise _corrupt(where, str(exc)) from None
        if row is None:
            raise _corrupt(where, "no map")
        missing = [name for name in _REQUIRED_ARRAYS if name not in blobs]
        if missing:
            raise _corrupt(where, f"map arrays missing: {', '.join(missing)}")
        try:
            arrays = {name: decode_array(blob) for name, blob in blobs.items()}
            metadata = json.loads(row[3])
        except (ValueError, OSError) as exc:
            raise _corrupt(where, f"unreadable map data: {exc}") from None
        if not isinstance(metadata, dict):
            metadata = {}
        for name, array in arrays.items():
            if name.startswith(_METADATA_PREFIX):
                metadata[name[len(_METADATA_PREFIX) :]] = array
        return Map(
            poses=arrays["poses"],
            points=arrays["points"],
            offsets=arrays["offsets"],
            edges=arrays["edges"],
            measurements=arrays["measurements"],
            information=arrays["information"],
            information_source=arrays["information_source"],
            normals=arrays.get("normals"),
            timestamps=arrays.get("timestamps"),
            anchor=int(row[2]),
            name=str(row[0]),
            source=None if row[1] is None else str(row[1]),
            metadata=metadata,
        )

    def read_config(self) -> Config:
        """The session's configuration."""
        where = _label(self._path)
        try:
            row = self._connection.execute("SELECT json FROM config WHERE id = 1").fetchone()
        except sqlite3.Error as exc:
            raise _corrupt(where, str(exc)) from None
        if row is None:
            raise _corrupt(where, "no configuration")
        try:
            data = json.loads(row[0])
        except ValueError as exc:
            raise _corrupt(where, f"unreadable configuration: {exc}") from None
        if not isinstance(data, dict):
            raise _corrupt(where, "the configuration is not a JSON object")
        try:
            return Config.from_dict(data)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None

    def events(self) -> list[Event]:
        """Every event, in order."""
        where = _label(self._path)
        try:
            rows = self._connection.execute(
                "SELECT seq, time, kind, payload, poses FROM events ORDER BY seq"
            ).fetchall()
        except sqlite3.Error as exc:
            raise _corrupt(where, str(exc)) from None
        out: list[Event] = []
        kinds = {k.value: k for k in EventKind}
        for expected, (seq, stamp, kind, payload, poses) in enumerate(rows, 1):
            if seq != expected:
                raise _corrupt(where, f"event {expected} is missing")
            if kind not in kinds:
                raise _corrupt(where, f"event {seq} has unknown kind {kind!r}")
            try:
                data = json.loads(payload)
                checkpoint = None if poses is None else decode_array(poses)
            except (ValueError, OSError) as exc:
                raise _corrupt(where, f"event {seq} is unreadable: {exc}") from None
            if not isinstance(data, dict):
                raise _corrupt(where, f"event {seq} payload is not a JSON object")
            out.append(Event(int(seq), float(stamp), kinds[kind], data, checkpoint))
        return out

    # -- writing ----------------------------------------------------------------------------

    def append(
        self,
        kind: EventKind,
        payload: dict[str, Any],
        poses: NDArray[np.float64] | None = None,
    ) -> Event:
        """Commit one event in its own transaction; durable on disk when this returns.

        Raises:
            InputError: the file was changed by another program since it was opened (two
                sessions on one file), or it cannot be written.
        """
        where = _label(self._path)
        text = json.dumps(payload)
        blob = None if poses is None else encode_array(np.asarray(poses, dtype=np.float64))
        stamp = time.time()
        with self._lock:
            connection = self._connection
            try:
                connection.execute("BEGIN IMMEDIATE")
                try:
                    last = connection.execute("SELECT max(seq) FROM events").fetchone()[0]
                    if (0 if last is None else int(last)) != self._last_seq:
                        raise InputError(
                            f"{where}: the session file was changed by another program since it "
                            "was opened; close the other session and open the file again"
                        )
                    seq = self._last_seq + 1
                    connection.execute(
                        "INSERT INTO events(seq, time, kind, payload, poses) "
                        "VALUES (?, ?, ?, ?, ?)",
                        (seq, stamp, kind.value, text, blob),
                    )
                    connection.execute("COMMIT")
                except BaseException:
                    connection.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise InputError(
                    f"{where}: cannot write to the session file ({exc}); check the disk and "
                    "the file's permissions"
                ) from None
            self._last_seq = seq
        return Event(seq, stamp, kind, payload, None if poses is None else np.array(poses))

    def backup_to(self, path: str | os.PathLike[str]) -> None:
        """Write a copy of the whole journal to a NEW file ``path`` (atomic, never overwrites)."""
        target = os.fspath(path)
        if os.path.exists(target):
            raise InputError(
                f"{target}: already exists; choose a new file name for the session, or delete "
                "the old one"
            )
        directory, name = os.path.split(target)
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
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temp)

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
