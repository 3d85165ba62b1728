"""The session file's layout (:mod:`hitl_slam.journal` describes it): the schema and its
version, the checksum of a row (:func:`row_digest`), how a new file's map and configuration are
written and the map read back and checked, and the file operations that put a new file in place.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

from hitl_slam.config import Config
from hitl_slam.errors import DamagedSession
from hitl_slam.io.atomic import fsync_directory
from hitl_slam.journal_encoding import decode_array, encode_array
from hitl_slam.map import Map

__all__ = ["APPLICATION_ID", "SCHEMA_VERSION", "row_digest"]

SCHEMA_VERSION = 2
"""The schema this module writes; it reads this one and older ones (1: without checksums)."""

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
    metadata TEXT NOT NULL,
    sha256 TEXT
);
CREATE TABLE map_arrays (name TEXT PRIMARY KEY, npy BLOB NOT NULL, sha256 TEXT);
CREATE TABLE config (id INTEGER PRIMARY KEY CHECK (id = 1), json TEXT NOT NULL, sha256 TEXT);
CREATE TABLE events (
    seq INTEGER PRIMARY KEY,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    payload TEXT NOT NULL,
    poses BLOB,
    sha256 TEXT
);
"""

# Schema 1 -> 2: the checksum columns (filled in the same transaction, see Journal._upgrade).
_UPGRADE = (
    "ALTER TABLE map ADD COLUMN sha256 TEXT",
    "ALTER TABLE map_arrays ADD COLUMN sha256 TEXT",
    "ALTER TABLE config ADD COLUMN sha256 TEXT",
    "ALTER TABLE events ADD COLUMN sha256 TEXT",
)

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
_FLOAT_ARRAYS = ("poses", "points", "measurements", "information", "normals", "timestamps")
_METADATA_PREFIX = "metadata/"


def row_digest(table: str, *values: Any) -> str:
    """SHA-256 (hex) of one row's values with their SQLite types (None, int, float, str, bytes),
    each length-prefixed, so a changed byte or type anywhere in the row changes it."""
    h = hashlib.sha256(table.encode())
    for value in values:
        if value is None:
            token = b"N"
        elif isinstance(value, bytes):
            token = b"B" + value
        elif isinstance(value, str):
            token = b"S" + value.encode("utf-8", "surrogatepass")
        elif isinstance(value, int):
            token = b"I" + str(value).encode()
        elif isinstance(value, float):
            token = b"F" + value.hex().encode()
        else:
            raise TypeError(f"not an SQLite value: {type(value).__name__}")
        h.update(len(token).to_bytes(8, "little"))
        h.update(token)
    return h.hexdigest()


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


def _non_finite(map: Map) -> str | None:
    """The first map array holding NaN or inf, or an edge naming no pose (None: all good)."""
    for name in _FLOAT_ARRAYS:
        array = getattr(map, name)
        if array is not None and not np.isfinite(array).all():
            return f"the map array {name!r} holds NaN or inf"
    if map.edges.size and (map.edges.min() < 0 or map.edges.max() >= map.num_poses):
        return "an edge of the map names a pose that does not exist"
    return None


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
    source = None if map.source is None else str(map.source)
    connection.execute(
        "INSERT INTO map(id, name, source, anchor, metadata, sha256) VALUES (1, ?, ?, ?, ?, ?)",
        (
            str(map.name),
            source,
            int(map.anchor),
            metadata,
            row_digest("map", str(map.name), source, int(map.anchor), metadata),
        ),
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
    connection.executemany(
        "INSERT INTO map_arrays(name, npy, sha256) VALUES (?, ?, ?)",
        [(name, blob, row_digest("map_arrays", name, blob)) for name, blob in arrays],
    )
    text = json.dumps(config.to_dict())
    connection.execute(
        "INSERT INTO config(id, json, sha256) VALUES (1, ?, ?)",
        (text, row_digest("config", text)),
    )


def _event_digest(
    seq: Any, stamp: Any, kind: Any, payload: Any, poses: Any
) -> str:  # the event row's checksum
    return row_digest("events", seq, stamp, kind, payload, poses)


def _unlink_quietly(path: str) -> None:
    # A cleanup must never replace the error being reported (e.g. EROFS on a read-only disk).
    with contextlib.suppress(OSError):
        os.unlink(path)


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
        _unlink_quietly(temp)
    fsync_directory(os.path.dirname(target))


def _connect(where: str) -> sqlite3.Connection:
    uri = Path(where).resolve().as_uri() + "?mode=rw"
    return sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)


def _label(path: str | os.PathLike[str] | None) -> str:
    return MEMORY if path is None else os.fspath(path)


def _corrupt(where: str, what: str, first_bad_seq: int | None = None) -> DamagedSession:
    return DamagedSession(where, what, first_bad_seq)


def _map_from_rows(where: str, row: Any, stored: list[Any], checked: bool) -> Map:
    """The map stored in the ``map`` row ``row`` and the ``map_arrays`` rows ``stored``, checked
    as :meth:`hitl_slam.journal.Journal.read_map` describes (a :class:`DamagedSession` if not)."""
    if row is None:
        raise _corrupt(where, "no map")
    if checked and row[4] != row_digest("map", *row[:4]):
        raise _corrupt(where, "the map's name or metadata does not match its checksum")
    blobs: dict[str, Any] = {}
    for item in stored:
        if not isinstance(item[0], str):
            raise _corrupt(where, f"a map array has the name {item[0]!r}")
        if checked and item[2] != row_digest("map_arrays", item[0], item[1]):
            raise _corrupt(where, f"the map array {item[0]!r} does not match its checksum")
        blobs[item[0]] = item[1]
    missing = [name for name in _REQUIRED_ARRAYS if name not in blobs]
    if missing:
        raise _corrupt(where, f"map arrays missing: {', '.join(missing)}")
    try:
        arrays = {name: decode_array(blob) for name, blob in blobs.items()}
        metadata = json.loads(row[3])
    except (ValueError, TypeError, RecursionError) as exc:
        raise _corrupt(where, f"unreadable map data: {exc}") from None
    if not isinstance(metadata, dict):
        metadata = {}
    for name, array in arrays.items():
        if name.startswith(_METADATA_PREFIX):
            metadata[name[len(_METADATA_PREFIX) :]] = array
    try:
        if not isinstance(row[2], int) or not isinstance(row[0], str):
            raise ValueError("the map's name or anchor has the wrong type")
        for name, kinds in (
            ("poses", "fiu"),
            ("points", "fiu"),
            ("measurements", "fiu"),
            ("information", "fiu"),
            ("offsets", "iu"),
            ("edges", "iu"),
            ("information_source", "iu"),
            ("normals", "fiu"),
            ("timestamps", "fiu"),
        ):
            if name in arrays and arrays[name].dtype.kind not in kinds:
                raise ValueError(f"the map array {name!r} has the wrong type")
        map = Map(
            poses=arrays["poses"],
            points=arrays["points"],
            offsets=arrays["offsets"],
            edges=arrays["edges"],
            measurements=arrays["measurements"],
            information=arrays["information"],
            information_source=arrays["information_source"],
            normals=arrays.get("normals"),
            timestamps=arrays.get("timestamps"),
            anchor=row[2],
            name=row[0],
            source=None if row[1] is None else str(row[1]),
            metadata=metadata,
        )
    except Exception as exc:  # any malformed array is a damaged file
        raise _corrupt(where, f"the stored map is malformed: {exc}") from None
    problem = _non_finite(map)
    if problem is not None:
        raise _corrupt(where, problem)
    return map
