"""Integrity of session files (issue 13, finding 3): a truncated file, bytes changed inside a
stored array or event, a NaN checkpoint, malformed values of every kind: each a clear InputError
naming the file and the last good checkpoint, never silent data and never a traceback; the last
good checkpoint opens with Session.recover; schema 1 files (no checksums) still open and gain
checksums on their next write."""

from __future__ import annotations

import dataclasses
import json
import logging
import random
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hitl_slam.errors import InputError
from hitl_slam.io.maps import load_map
from hitl_slam.journal import decode_array, encode_array, encode_payload
from hitl_slam.session import EntryStatus, Session
from test_session import drawing, fake_applier, reseal, same, tiny_map

DATA = Path(__file__).resolve().parent / "data"


def a_session(path: Path) -> tuple[np.ndarray, list[EntryStatus]]:
    """A session with two corrections, the second undone; its poses and statuses."""
    with Session.new(tiny_map(), path, applier=fake_applier) as session:
        session.apply(drawing(0.6))
        session.apply(drawing(1.6))
        session.undo()
        return session.poses.copy(), [e.status for e in session.history]


def blob(path: Path, sql: str) -> bytes:
    connection = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    try:
        return bytes(connection.execute(sql).fetchone()[0])
    finally:
        connection.close()


def flip_inside(path: Path, stored: bytes, at: float = 0.5) -> int:
    """Flip one bit of ``stored`` (a value in the file) where it is on disk: a 16-byte window of
    its data found exactly once in the file. Returns the file offset changed."""
    data = bytearray(path.read_bytes())
    start = 128 + int((len(stored) - 160) * at)  # past the .npy header
    for shift in range(0, len(stored) - start - 16):
        window = stored[start + shift : start + shift + 16]
        where = data.find(window)
        if where >= 0 and data.find(window, where + 1) < 0:
            data[where + 8] ^= 0x04
            path.write_bytes(bytes(data))
            return where + 8
    raise AssertionError("no unique window of the value in the file")


def opened_state(path: Path) -> tuple[np.ndarray, list[EntryStatus]] | None:
    """The poses and statuses the file opens with, or None when it is refused (InputError)."""
    try:
        with Session.open(path, applier=fake_applier) as session:
            return session.poses.copy(), [e.status for e in session.history]
    except InputError:
        return None


# -- finding 3: truncation, changed bytes, NaN ---------------------------------------------------


def test_a_truncated_file_never_opens_with_other_data(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    poses, _ = a_session(path)
    size = path.stat().st_size
    cuts = sorted({*range(0, size, 509), *range(size - 4096, size, 256), size - 1})
    for cut in cuts:
        copy = tmp_path / "cut.hitl"
        shutil.copyfile(path, copy)
        with copy.open("r+b") as f:
            f.truncate(cut)
        with pytest.raises(InputError) as info:
            Session.open(copy, applier=fake_applier)
        message = str(info.value)
        assert message.startswith(str(copy)), message
        assert "damaged" in message or "not a hitl-slam session" in message, (cut, message)
    assert same(opened_state(path)[0], poses)  # type: ignore[index]


def test_a_changed_byte_in_the_map_arrays_is_found(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    a_session(path)
    flip_inside(path, blob(path, "SELECT npy FROM map_arrays WHERE name = 'points'"))
    with pytest.raises(InputError) as info:
        Session.open(path, applier=fake_applier)
    message = str(info.value)
    assert message.startswith(f"{path}: the session file is damaged (")
    assert "'points' does not match its checksum" in message
    assert "restore it from a copy, or start a new session from the input map" in message
    with pytest.raises(InputError, match="'points' does not match its checksum"):
        load_map(path)


def test_a_changed_byte_in_a_checkpoint_names_the_last_good_one(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    a_session(path)
    with Session.open(path, applier=fake_applier) as session:
        session.redo()
        session.undo()
        session.undo()
        assert same(session.poses, session.input_map.poses)
    # Event 5 holds the second correction's checkpoint; the first (event 3) stays good.
    flip_inside(path, blob(path, "SELECT poses FROM events WHERE seq = 5"), at=0.9)
    with pytest.raises(InputError) as info:
        Session.open(path, applier=fake_applier)
    message = str(info.value)
    assert message.startswith(f"{path}: the session file is damaged (event 5 does not match ")
    assert "events 1 to 4 are intact" in message
    assert "the last good checkpoint is the map after correction 1 of the history" in message
    recovered = tmp_path / "s.recovered.hitl"
    assert f"`hitl-slam recover {path}`" in message
    assert f"hitl_slam.Session.recover('{path}')" in message
    assert str(recovered) in message
    before = path.read_bytes()
    with Session.recover(path, applier=fake_applier) as session:
        assert session.path == str(recovered)
        # Events 1-4: the load, correction 1, and the request of correction 2 without its outcome.
        assert [e.status for e in session.history] == [
            EntryStatus.APPLIED,
            EntryStatus.INTERRUPTED,
        ]
        expected = fake_applier(
            session.input_map, session.input_map.poses, drawing(0.6), [], session.config
        ).poses
        assert same(session.poses, expected)
        session.apply(drawing(2.5))  # a usable session
    assert path.read_bytes() == before  # the damaged file is only read
    assert opened_state(recovered) is not None


def test_a_nan_checkpoint_is_refused_before_redo_can_use_it(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    a_session(path)
    connection = sqlite3.connect(path)
    checkpoint = decode_array(blob(path, "SELECT poses FROM events WHERE seq = 5")).copy()
    checkpoint[3, 0] = np.nan
    connection.execute("UPDATE events SET poses = ? WHERE seq = 5", (encode_array(checkpoint),))
    connection.commit()
    connection.close()
    reseal(path)  # a checksum that agrees: the value itself must be refused
    with pytest.raises(InputError) as info, Session.open(path, applier=fake_applier) as session:
        session.redo()  # before: NaN poses went live here
    message = str(info.value)
    assert "event 5 is unreadable: its pose checkpoint holds NaN or inf" in message
    assert "events 1 to 4 are intact" in message


@pytest.mark.parametrize(
    "sql",
    [
        "UPDATE map_arrays SET npy = ? WHERE name = 'poses'",
        "UPDATE map_arrays SET npy = ? WHERE name = 'measurements'",
    ],
)
def test_a_nan_in_the_stored_map_is_refused(tmp_path: Path, sql: str) -> None:
    path = tmp_path / "s.hitl"
    a_session(path)
    name = sql.split("'")[1]
    array = decode_array(blob(path, f"SELECT npy FROM map_arrays WHERE name = '{name}'")).copy()
    array.flat[4] = np.inf
    connection = sqlite3.connect(path)
    connection.execute(sql, (encode_array(array),))
    connection.commit()
    connection.close()
    reseal(path)
    with pytest.raises(InputError, match=f"the map array '{name}' holds NaN or inf"):
        Session.open(path)


# -- malformed files of every kind: InputError or the very same data -----------------------------

_CELLS = [
    ("map", "name"),
    ("map", "source"),
    ("map", "anchor"),
    ("map", "metadata"),
    ("map_arrays", "name"),
    ("map_arrays", "npy"),
    ("config", "json"),
    ("events", "seq"),
    ("events", "time"),
    ("events", "kind"),
    ("events", "payload"),
    ("events", "poses"),
]


def _odd_value(rng: random.Random, old: Any) -> Any:
    choices: list[Any] = [
        None,
        0,
        -1,
        2**62,
        1.5,
        float("nan"),
        "",
        "x",
        "{}",
        "[]",
        '{"a": 1}',
        "[" * 5000,
        b"",
        b"\x93NUMPY",
        encode_array(np.zeros(3)),
        encode_array(np.array(["a"])),
        encode_array(np.full((24, 3), np.nan)),
        encode_array(np.zeros((24, 3), dtype=np.float32)),
        encode_array(np.zeros((2, 2), dtype=np.int64)),
    ]
    if isinstance(old, bytes | str) and old:
        cut = rng.randrange(len(old))
        choices += [old[:cut], old[:cut] + old[cut + 1 :]]
    if isinstance(old, str):
        choices += [old.replace("1", "2", 1), old.replace('"', "", 1), old.replace(":", ",", 1)]
    return rng.choice(choices)


def test_malformed_values_are_input_errors_or_change_nothing(tmp_path: Path) -> None:
    """Every stored cell replaced by values of the wrong type, shape or content (checksums
    recomputed, so the checks behind them are tested): Session.open and load_map give either an
    InputError naming the file or a session (the value was a valid one), never another
    exception."""
    original = tmp_path / "s.hitl"
    poses, statuses = a_session(original)
    rng = random.Random(13)
    outcomes = {"refused": 0, "opened": 0}
    for trial in range(72):
        table, column = _CELLS[trial % len(_CELLS)]
        path = tmp_path / f"m{trial}.hitl"
        shutil.copyfile(original, path)
        connection = sqlite3.connect(path)
        keys = connection.execute(f"SELECT rowid, {column} FROM {table}").fetchall()
        rowid, old = rng.choice(keys)
        try:
            connection.execute(
                f"UPDATE {table} SET {column} = ? WHERE rowid = ?", (_odd_value(rng, old), rowid)
            )
            connection.commit()
        except sqlite3.IntegrityError:  # NOT NULL, a duplicate key: not a file one can write
            connection.close()
            continue
        connection.close()
        reseal(path)
        for reader in ("session", "load_map"):
            try:
                if reader == "session":
                    state = opened_state(path)
                else:
                    load_map(path)
                    state = (poses, statuses)
            except InputError as exc:  # load_map lets the InputError through
                message = str(exc)
                state = None
            else:
                message = str(path)
            assert message.startswith(str(path)), message
            if state is None:
                outcomes["refused"] += 1
                with pytest.raises(InputError, match=str(path)):
                    Session.open(path)
            else:
                outcomes["opened"] += 1
    assert outcomes["refused"] > 40


def test_flipped_bytes_anywhere_never_open_with_other_data(tmp_path: Path) -> None:
    """Bit flips at random offsets, no reseal: refused, or the very same poses and history."""
    original = tmp_path / "s.hitl"
    poses, statuses = a_session(original)
    data = original.read_bytes()
    rng = random.Random(3)
    refused = 0
    for trial in range(150):
        changed = bytearray(data)
        for _ in range(rng.choice((1, 1, 2, 8))):
            changed[rng.randrange(len(changed))] ^= 1 << rng.randrange(8)
        path = tmp_path / f"f{trial}.hitl"
        path.write_bytes(bytes(changed))
        state = opened_state(path)
        if state is None:
            refused += 1
            continue
        assert same(state[0], poses), trial
        assert state[1] == statuses, trial
    assert refused > 30


# -- schema 1 (no checksums) -----------------------------------------------------------------------


def test_a_schema_1_file_opens_with_a_warning_and_gains_checksums_on_its_next_write(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """tests/data/session_schema1.hitl was written by hitl-slam before checksums (schema 1)."""
    path = tmp_path / "old.hitl"
    shutil.copyfile(DATA / "session_schema1.hitl", path)
    with (
        caplog.at_level(logging.WARNING, logger="hitl_slam"),
        Session.open(path, applier=fake_applier) as session,
    ):
        statuses = [e.status for e in session.history]
        assert statuses == [EntryStatus.APPLIED, EntryStatus.UNDONE]
        assert session.poses[5].tolist() == [
            2.5,
            -0.09589242746631385,
            0.014183109273161312,
        ]
        assert path.read_bytes() == (DATA / "session_schema1.hitl").read_bytes()  # read only
        session.redo()
        poses = session.poses.copy()
    assert "without checksums" in caplog.text
    connection = sqlite3.connect(path)
    assert connection.execute("PRAGMA user_version").fetchone()[0] == 2
    assert connection.execute("SELECT count(*) FROM events WHERE sha256 IS NULL").fetchone()[0] == 0
    connection.close()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hitl_slam"):
        assert same(opened_state(path)[0], poses)  # type: ignore[index]
    assert "without checksums" not in caplog.text
    flip_inside(path, blob(path, "SELECT npy FROM map_arrays WHERE name = 'points'"))
    with pytest.raises(InputError, match="'points' does not match its checksum"):
        Session.open(path)


def test_a_session_file_left_half_created_by_a_killed_run_is_removed(tmp_path: Path) -> None:
    """A run killed while creating a session leaves its temporary copy (``.<name>.<8 hex>.tmp``
    and SQLite's ``-journal``) beside it; the next session created or backed up in that folder
    removes them (they are older than this process), and a fresh temporary file is kept."""
    import os
    import time

    stale = [tmp_path / ".s.hitl.0123abcd.tmp", tmp_path / ".s.hitl.0123abcd.tmp-journal"]
    for p in stale:
        p.write_bytes(b"x" * 100)
        old = time.time() - 3600
        os.utime(p, (old, old))
    unrelated = tmp_path / ".notes.tmp"
    unrelated.write_bytes(b"keep")
    a_session(tmp_path / "other.hitl")
    assert not any(p.exists() for p in stale)
    assert unrelated.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".notes.tmp", "other.hitl"]


@pytest.mark.parametrize("suffix", [".g2o", ".pgm", ".covars"])
def test_a_save_the_journal_cannot_record_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str
) -> None:
    """Issue 13, finding 6: the map was exported, then journaling the save failed, and the
    command failed with the file written anyway. Now the files appear only once the event is
    journaled."""
    import sqlite3 as sq

    with Session.new(tiny_map(), tmp_path / "s.hitl", applier=fake_applier) as session:
        session.apply(drawing(0.6))
        journal = session._journal

        def refuse(*args: Any, **kwargs: Any) -> Any:
            raise sq.OperationalError("disk I/O error")

        monkeypatch.setattr(journal, "append", refuse)
        with pytest.raises((InputError, sq.Error, OSError)):
            session.save(tmp_path / f"map{suffix}")
        monkeypatch.undo()
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.hitl"]
        session.save(tmp_path / f"map{suffix}")
        assert (tmp_path / f"map{suffix}").exists()


def test_the_recover_command_copies_the_last_good_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The damage message names a command, not only a Python call: `hitl-slam recover`."""
    from hitl_slam.cli import main

    path = tmp_path / "s.hitl"
    a_session(path)
    flip_inside(path, blob(path, "SELECT poses FROM events WHERE seq = 5"), at=0.9)
    before = path.read_bytes()
    assert main(["recover", str(path)]) == 0
    recovered = tmp_path / "s.recovered.hitl"
    out = capsys.readouterr().out
    assert f"wrote {recovered}" in out
    assert f"hitl-slam serve {recovered}" in out
    assert path.read_bytes() == before
    assert opened_state(recovered) is not None
    # A second run never overwrites the copy it made: a new name by default, and an existing
    # file given with -o is refused in one line (exit 2), nothing changed.
    copy = recovered.read_bytes()
    assert main(["recover", str(path)]) == 0
    assert (tmp_path / "s.recovered-2.hitl").exists()
    capsys.readouterr()
    assert main(["recover", str(path), "-o", str(recovered)]) == 2
    assert "exists" in capsys.readouterr().err
    assert recovered.read_bytes() == copy


def test_a_damaged_schema_text_is_a_damaged_file_not_a_decode_error(tmp_path: Path) -> None:
    """Found by the session fuzz harness: a byte of the stored schema (its CREATE TABLE text)
    turned into invalid UTF-8 made SQLite's first statement raise UnicodeDecodeError."""
    path = tmp_path / "s.hitl"
    a_session(path)
    data = path.read_bytes()
    at = data.index(b"time REAL NOT NULL") + len(b"time REAL NOT ")
    path.write_bytes(data[:at] + b"\x80" + data[at + 1 :])
    with pytest.raises(InputError, match="damaged"):
        Session.open(path, applier=fake_applier)


# -- the event text: what json.dumps writes, however it is built --------------------------------

_ints = st.integers(min_value=-(2**63), max_value=2**63 - 1)
_small = st.integers(min_value=-(10**6), max_value=10**6)


@st.composite
def integer_arrays(draw: st.DrawFn) -> np.ndarray:
    rows = draw(st.integers(0, 40))
    shape = draw(st.sampled_from([(rows,), (rows, 1), (rows, 2), (rows, 3), (rows, 0)]))
    values = draw(st.lists(draw(st.sampled_from([_ints, _small])), min_size=int(np.prod(shape))))
    array = np.array(values[: int(np.prod(shape))], dtype=np.int64).reshape(shape)
    dtype = draw(st.sampled_from([np.int64, np.int32, np.uint32, np.int8, np.uint64]))
    with np.errstate(over="ignore"):
        return array if dtype is np.int64 else array.astype(dtype)


@settings(max_examples=300, deadline=None)
@given(integer_arrays(), integer_arrays(), st.text(max_size=8), st.floats(allow_nan=True))
def test_a_payload_with_arrays_is_the_text_json_dumps_writes_of_its_lists(
    a: np.ndarray, b: np.ndarray, text: str, number: float
) -> None:
    """The journal writes an interpretation's observation rows from its arrays: the text is
    byte for byte json.dumps of the lists, as every earlier version wrote (and reads)."""
    payload = {"request": 3, "interpretation": {"s_a": a, "n": {"s_b": b}}, "t": [text, number]}
    lists = {"request": 3, "interpretation": {"s_a": a.tolist(), "n": {"s_b": b.tolist()}}}
    lists["t"] = [text, number]
    assert encode_payload(payload) == json.dumps(lists)


@pytest.mark.parametrize(
    "values",
    [
        np.arange(10_000).reshape(-1, 2),  # the digits' table: every number it holds
        np.arange(10_000)[::-1],
        np.array([[0, 7], [9_999, 10_000]]),  # one past the table
        np.arange(-50_000, 2_000_000, 997),
        np.array([-(10**15) + 1, 10**15 - 1, -1, 0, 1]),  # the edges of exact float digits
        np.array([[10**15, 3]]),  # beyond them: written through lists
    ],
)
def test_observation_rows_are_written_as_their_lists_dump(values: np.ndarray) -> None:
    assert encode_payload({"s_a": values}) == json.dumps({"s_a": values.tolist()})


def big_applier(*args: Any) -> Any:
    """The fake applier with observation sets of thousands of rows (as a real map has)."""
    result = fake_applier(*args)
    rng = np.random.default_rng(len(args[3]))
    h = dataclasses.replace(
        result.interpretation,
        s_a=np.stack([rng.integers(0, 24, 5000), rng.integers(0, 3, 5000)], axis=1),
        s_b=np.stack([rng.integers(0, 24, 4000), rng.integers(0, 3, 4000)], axis=1),
    )
    return dataclasses.replace(result, interpretation=h)


def test_a_correction_event_is_written_as_every_earlier_version_wrote_it(tmp_path: Path) -> None:
    """The correction event's payload is json.dumps of the interpretation's JSON object (lists),
    so a file of this version reads the same in an earlier reader and the other way round; the
    reopened session has the very interpretation that was applied."""
    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=big_applier) as session:
        session.apply(drawing(0.6))
        session.apply(drawing(1.6))
        applied = session.active
    connection = sqlite3.connect(path)
    stored = connection.execute(
        "SELECT payload FROM events WHERE kind = 'correction' ORDER BY seq"
    ).fetchall()
    connection.close()
    assert len(stored) == 2
    for (text,), h in zip(stored, applied, strict=True):
        data = json.loads(text)
        assert json.dumps(data) == text
        assert data["interpretation"] == h.to_json()
    with Session.open(path, applier=big_applier) as reopened:
        for h, again in zip(applied, reopened.active, strict=True):
            for name in ("s_a", "s_b", "x_a", "x_b"):
                live, read = getattr(h, name), getattr(again, name)
                assert live.dtype == read.dtype == np.int64
                assert live.shape == read.shape
                assert np.array_equal(live, read)
