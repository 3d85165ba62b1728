"""Fault injection on the journal (issue 13, finding 4): a commit that fails with "disk I/O
error" (after or before the durable write), a failing ROLLBACK, an I/O error on the insert, a
full disk (SQLite's page limit, and a real full tmpfs where mounting is allowed), a read-only file
system, a file that cannot be reopened. Each time: the first error is the one reported, the
session in memory is what the file holds (reopening gives the same poses and history), and the
next correction works once the disk does (or a clear read-only error says why not)."""

from __future__ import annotations

import contextlib
import os
import sqlite3
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam import journal as journal_module
from hitl_slam.errors import InputError
from hitl_slam.session import EntryStatus, Session
from test_session import drawing, fake_applier, same, tiny_map

EIO = "disk I/O error"


class Faulty:
    """A sqlite3 connection whose statements matching ``when`` fail with ``error``: "before"
    (not run) or "after" (run, then the error, as a commit whose data reached the disk)."""

    def __init__(
        self,
        real: sqlite3.Connection,
        when: Callable[[str], str | None],
        error: str = EIO,
    ) -> None:
        self.real = real
        self.when = when
        self.error = error
        self.failures = 0

    def execute(self, sql: str, *args: Any) -> Any:
        mode = self.when(sql)
        if mode == "before":
            self.failures += 1
            raise sqlite3.OperationalError(self.error)
        result = self.real.execute(sql, *args)
        if mode == "after":
            self.failures += 1
            raise sqlite3.OperationalError(self.error)
        return result

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


def inject(session: Session, when: Callable[[str], str | None], error: str = EIO) -> Faulty:
    journal = session._journal
    faulty = Faulty(journal._connection, when, error)
    journal._connection = faulty  # type: ignore[assignment]
    return faulty


def once(statement: str, mode: str) -> Callable[[str], str | None]:
    done: list[bool] = []

    def when(sql: str) -> str | None:
        if not done and sql.startswith(statement):
            done.append(True)
            return mode
        return None

    return when


def state(session: Session) -> tuple[np.ndarray, list[EntryStatus]]:
    return session.poses.copy(), [e.status for e in session.history]


def assert_memory_is_the_file(session: Session, path: Path) -> None:
    poses, statuses = state(session)
    with Session.open(path, applier=fake_applier) as reopened:
        assert same(reopened.poses, poses)
        assert [e.status for e in reopened.history] == statuses


def until_refused(session: Session) -> tuple[tuple[np.ndarray, list[EntryStatus]], InputError]:
    """Apply corrections until one is refused: the state before it, and the error."""
    before = state(session)
    for k in range(300):
        try:
            session.apply(drawing(1.0 + k))
        except InputError as exc:
            return before, exc
        before = state(session)
    raise AssertionError("never refused")


@pytest.fixture
def started(tmp_path: Path) -> Iterator[tuple[Session, Path]]:
    path = tmp_path / "s.hitl"
    session = Session.new(tiny_map(), path, applier=fake_applier)
    session.apply(drawing(0.6))
    yield session, path
    session.close()


# -- finding 4: the commit's error, the rollback's error, the state after --------------------------


@pytest.mark.parametrize("event", ["request", "correction"])
def test_a_commit_that_fails_after_the_durable_write_leaves_memory_as_the_file(
    started: tuple[Session, Path], event: str
) -> None:
    """The reported case: COMMIT reaches the disk, then says "disk I/O error"; the ROLLBACK
    that follows fails too ("no transaction is active"). Before: that second error was
    reported, the file had the event but memory did not, and every later write was refused as
    "changed by another program"."""
    session, path = started
    calls: list[str] = []

    def when(sql: str) -> str | None:
        if sql == "COMMIT":
            calls.append(sql)
            if len(calls) == (1 if event == "request" else 2):
                return "after"
        return None

    faulty = inject(session, when)
    try:
        session.apply(drawing(1.6))
        reported = ""
    except InputError as exc:  # reporting it is allowed; then it must be the first error
        reported = str(exc)
    if reported:
        assert EIO in reported, reported
        assert "rollback" not in reported.lower(), reported
    assert faulty.failures == 1
    assert_memory_is_the_file(session, path)
    session.apply(drawing(2.5))  # not wedged
    session.undo()
    session.redo()
    assert_memory_is_the_file(session, path)


def test_a_commit_that_fails_before_the_write_reports_the_first_error(
    started: tuple[Session, Path],
) -> None:
    session, path = started
    before = state(session)

    def when(sql: str) -> str | None:
        if sql == "COMMIT":
            return "before"
        if sql == "ROLLBACK":
            return "before"  # the rollback fails as well: its error must not be the one shown
        return None

    faulty = inject(session, when)
    with pytest.raises(InputError) as info:
        session.apply(drawing(1.6))
    message = str(info.value)
    assert message.startswith(f"{path}: cannot write to the session file ({EIO})"), message
    assert "nothing was changed" in message
    assert faulty.failures >= 1
    assert same(session.poses, before[0])
    assert [e.status for e in session.history] == before[1]
    assert_memory_is_the_file(session, path)
    session.apply(drawing(2.5))  # the journal reconnected: the next correction works
    assert len(session.active) == 2
    assert_memory_is_the_file(session, path)


@pytest.mark.parametrize("event", ["request", "correction", "undo"])
def test_an_io_error_on_the_insert_changes_nothing(
    started: tuple[Session, Path], event: str
) -> None:
    session, path = started
    before = state(session)
    inserts: list[str] = []
    failing = 2 if event == "correction" else 1  # a correction's request goes through

    def when(sql: str) -> str | None:
        if sql.startswith("INSERT"):
            inserts.append(sql)
            return "before" if len(inserts) == failing else None
        return None

    inject(session, when)
    step = session.undo if event == "undo" else lambda: session.apply(drawing(1.6))
    with pytest.raises(InputError, match=EIO):
        step()
    assert same(session.poses, before[0])
    statuses = [e.status for e in session.history]
    if event == "correction":
        assert statuses == [*before[1], EntryStatus.INTERRUPTED]  # its request was journaled
    else:
        assert statuses == before[1]
    assert_memory_is_the_file(session, path)
    session.apply(drawing(2.5))
    assert_memory_is_the_file(session, path)


def test_a_full_database_is_a_clear_error_and_the_next_write_works(
    started: tuple[Session, Path],
) -> None:
    session, path = started
    connection = session._journal._connection
    pages = connection.execute("PRAGMA page_count").fetchone()[0]
    connection.execute(f"PRAGMA max_page_count = {pages}")  # SQLITE_FULL, as a full disk gives
    before, info = until_refused(session)
    assert "database or disk is full" in str(info)
    assert same(session.poses, before[0])
    assert_memory_is_the_file(session, path)
    session.apply(drawing(0.25))  # the limit was this connection's; the new one has none
    assert_memory_is_the_file(session, path)


def test_a_file_that_cannot_be_reopened_turns_the_session_read_only(
    started: tuple[Session, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    session, path = started
    before = state(session)
    inject(session, lambda sql: "before" if sql.startswith("INSERT") else None)

    def cannot(where: str) -> sqlite3.Connection:
        raise sqlite3.OperationalError("unable to open database file")

    monkeypatch.setattr(journal_module, "_connect", cannot)
    with pytest.raises(InputError, match=EIO):
        session.apply(drawing(1.6))
    with pytest.raises(InputError) as info:
        session.apply(drawing(2.6))
    message = str(info.value)
    assert message.startswith(f"{path}: the session is read-only: a write failed ({EIO})")
    assert "could not be opened again (unable to open database file)" in message
    assert same(session.poses, before[0])  # still readable, as it was
    monkeypatch.undo()
    assert_memory_is_the_file(session, path)


def test_a_temporary_file_that_cannot_be_removed_does_not_hide_the_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Removing the temporary file on a read-only file system raised EROFS from journal.py
    instead of the error that mattered."""

    def erofs(path: Any) -> None:
        raise OSError(30, "Read-only file system", str(path))

    def failing_connect(*args: Any, **kwargs: Any) -> sqlite3.Connection:
        raise sqlite3.OperationalError("attempt to write a readonly database")

    monkeypatch.setattr(journal_module.os, "unlink", erofs)
    monkeypatch.setattr(journal_module.sqlite3, "connect", failing_connect)
    with pytest.raises(InputError, match="cannot create the session file"):
        Session.new(tiny_map(), tmp_path / "s.hitl")


# -- a real full disk and a read-only file system (tmpfs; root with CAP_SYS_ADMIN only) -----------


@contextlib.contextmanager
def tmpfs(where: Path, size: str) -> Iterator[Path]:
    where.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def fill(directory: Path) -> Path:
    filler = directory / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:
        with contextlib.suppress(OSError):
            while True:
                os.write(fd, b"\0" * 4096)
    finally:
        os.close(fd)
    return filler


def test_a_full_file_system(tmp_path: Path) -> None:
    with tmpfs(tmp_path / "small", "512k") as disk:
        path = disk / "s.hitl"
        session = Session.new(tiny_map(60), path, applier=fake_applier)
        session.apply(drawing(0.6))
        filler = fill(disk)
        before, info = until_refused(session)
        message = str(info)
        assert message.startswith(f"{path}: cannot write to the session file ("), message
        assert "full" in message or "I/O" in message, message
        assert same(session.poses, before[0])
        filler.unlink()
        assert_memory_is_the_file(session, path)
        session.apply(drawing(0.25))  # space again: the next correction works
        assert_memory_is_the_file(session, path)
        session.close()


def test_a_read_only_file_system(tmp_path: Path) -> None:
    with tmpfs(tmp_path / "ro", "4m") as disk:
        path = disk / "s.hitl"
        with Session.new(tiny_map(), path, applier=fake_applier) as session:
            session.apply(drawing(0.6))
            before = state(session)
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        session = Session.open(path, applier=fake_applier)  # reading still works
        assert same(session.poses, before[0])
        with pytest.raises(InputError) as info:
            session.apply(drawing(1.6))
        message = str(info.value)
        assert message.startswith(f"{path}: cannot write to the session file ("), message
        assert "readonly" in message or "read-only" in message, message
        assert same(session.poses, before[0])
        assert [e.status for e in session.history] == before[1]
        with pytest.raises(InputError, match="cannot write to the session file"):
            session.undo()
        with pytest.raises(InputError, match="cannot create the session file"):
            Session.new(tiny_map(), disk / "new.hitl")
        assert sorted(p.name for p in disk.iterdir()) == ["s.hitl"]
        subprocess.run(["mount", "-o", "remount,rw", str(disk)], check=True)
        session.apply(drawing(2.5))  # writable again: the next correction works
        assert_memory_is_the_file(session, path)
        session.close()
