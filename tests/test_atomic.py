"""Atomic output (issue 13, finding 5): every failure to write is one clear OutputError (an
InputError and an OSError) naming the file, the old file is kept, no temporary file is left,
stale temporary files of killed runs are swept, and groups of outputs are all-or-nothing."""

from __future__ import annotations

import errno
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hitl_slam.errors import InputError
from hitl_slam.io import atomic
from hitl_slam.io.atomic import (
    TEMP_PATTERN,
    OutputError,
    atomic_binary_writer,
    atomic_outputs,
    atomic_write_bytes,
    atomic_write_text,
    sweep_stale_temps,
    temp_path,
)


def failing(code: int, real: object | None = None, *, after: int = 0) -> object:
    """A stand-in for an os function that raises ``code`` (after ``after`` real calls)."""
    calls = [0]

    def fail(*args: object, **kwargs: object) -> object:
        calls[0] += 1
        if calls[0] > after:
            raise OSError(code, os.strerror(code))
        assert callable(real)
        return real(*args, **kwargs)

    return fail


@pytest.mark.parametrize(
    ("function", "code", "words"),
    [
        ("fsync", errno.ENOSPC, "No space left on device"),
        ("fsync", errno.EIO, "I/O error"),
        ("replace", errno.EIO, "I/O error"),
        ("replace", errno.EROFS, "read-only"),
    ],
)
def test_a_failed_write_is_one_clear_error_and_changes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, function: str, code: int, words: str
) -> None:
    path = tmp_path / "out.txt"
    path.write_text("old\n")
    monkeypatch.setattr(os, function, failing(code))
    with pytest.raises(OutputError) as caught:
        atomic_write_text(path, "new\n")
    error = caught.value
    assert isinstance(error, InputError)
    assert isinstance(error, OSError)
    assert error.errno == code
    message = str(error)
    assert message.startswith(f"{path}: cannot write the file")
    assert words in message
    assert "\n" not in message
    monkeypatch.undo()
    assert path.read_text() == "old\n"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_a_temporary_file_that_cannot_be_removed_does_not_mask_the_first_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A read-only file system refuses the clean-up too: the error still says what failed
    first (no space), and names the temporary file to delete."""
    path = tmp_path / "out.txt"
    monkeypatch.setattr(os, "fsync", failing(errno.ENOSPC))
    monkeypatch.setattr(os, "unlink", failing(errno.EROFS))
    with pytest.raises(OutputError) as caught:
        atomic_write_text(path, "new\n")
    monkeypatch.undo()
    message = str(caught.value)
    assert caught.value.errno == errno.ENOSPC
    assert "No space left on device" in message
    (left,) = os.listdir(tmp_path)
    assert TEMP_PATTERN.match(left)
    assert f"the temporary file {tmp_path / left} could not be removed" in message
    assert "Read-only file system" in message


def test_an_exception_in_the_block_keeps_its_type_when_the_clean_up_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(os, "unlink", failing(errno.EROFS))

    def interrupted() -> None:
        with atomic_binary_writer(tmp_path / "a.bin") as f:
            f.write(b"half")
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError, match="interrupted") as caught:
        interrupted()
    assert any("could not be removed" in note for note in caught.value.__notes__)


def test_a_directory_as_the_target_is_refused_before_writing(tmp_path: Path) -> None:
    target = tmp_path / "out.g2o"
    target.mkdir()
    with pytest.raises(OutputError, match=r"out\.g2o: cannot write the file \(Is a directory\)"):
        atomic_write_text(target, "x\n")
    assert os.listdir(tmp_path) == ["out.g2o"]
    assert os.listdir(target) == []


def test_a_missing_folder_is_named(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match=r"the folder .*nowhere does not exist"):
        atomic_write_text(tmp_path / "nowhere" / "a.txt", "x\n")


def test_a_read_only_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_open = os.open

    def refuse(path: str, flags: int, *args: object, **kwargs: object) -> int:
        if flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), path)
        return real_open(path, flags, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(OutputError, match="Permission denied"):
        atomic_write_bytes(tmp_path / "a.png", b"\x89PNG")
    assert os.listdir(tmp_path) == []


def test_temporary_files_have_a_recognisable_name(tmp_path: Path) -> None:
    name = temp_path(tmp_path / "map.covars")
    assert TEMP_PATTERN.match(os.path.basename(name))
    assert os.path.dirname(name) == str(tmp_path)
    assert f".{os.getpid()}-" in name
    long = temp_path(tmp_path / ("x" * 250 + ".covars"))
    assert len(os.fsencode(os.path.basename(long))) <= 255


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_temporary_files_are_swept_and_live_ones_kept(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    old = atomic.PROCESS_START - 3600
    dead = dead_pid()
    stale = tmp_path / f".map.covars.{dead}-0123abcd.hitl-tmp"
    legacy = tmp_path / ".map.covars.0123abcd.tmp"
    legacy_journal = tmp_path / ".s.hitl.89abcdef.tmp-journal"
    alive = tmp_path / f".map.covars.{os.getppid()}-0123abcd.hitl-tmp"  # the writer runs
    fresh = tmp_path / f".map.covars.{dead}-fedcba98.hitl-tmp"  # newer than this process
    mine = tmp_path / f".map.covars.{os.getpid()}-0123abcd.hitl-tmp"
    other = tmp_path / ".map.covars.tmp"  # not ours
    for f in (stale, legacy, legacy_journal, alive, fresh, mine, other):
        f.write_bytes(b"x" * 100)
        if f is not fresh:
            os.utime(f, (old, old))
    with caplog.at_level(logging.INFO, logger="hitl_slam.io.atomic"):
        removed = sweep_stale_temps(tmp_path)
    assert sorted(removed) == sorted(str(f) for f in (stale, legacy, legacy_journal))
    assert sorted(os.listdir(tmp_path)) == sorted(f.name for f in (alive, fresh, mine, other))
    assert sum("left by an interrupted run" in r.getMessage() for r in caplog.records) == 3


def test_the_first_write_into_a_folder_sweeps_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What a kill -9 in the middle of a large write leaves is gone at the next run."""
    monkeypatch.setattr(atomic, "_SWEPT", set())
    stale = tmp_path / f".big.covars.{dead_pid()}-0123abcd.hitl-tmp"
    stale.write_bytes(b"\0" * 100_000)
    # Last modified before this process started (the sweep keeps anything newer: it may be a
    # write this process does not know of), however long the test session has been running.
    past = atomic.PROCESS_START - 60
    os.utime(stale, (past, past))
    atomic_write_text(tmp_path / "other.txt", "x\n")
    assert os.listdir(tmp_path) == ["other.txt"]


def test_a_killed_writer_leaves_only_a_recognisable_temporary_file(tmp_path: Path) -> None:
    """SIGKILL in the middle of a write: the target is untouched, and the file left behind
    matches the pattern the next run sweeps."""
    target = tmp_path / "out.txt"
    target.write_text("old\n")
    script = (
        "import os, signal\n"
        "from hitl_slam.io.atomic import atomic_writer\n"
        f"with atomic_writer({str(target)!r}) as f:\n"
        "    f.write('new' * 100000)\n"
        "    f.flush()\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    subprocess.run([sys.executable, "-c", script], env=env, check=False)
    assert target.read_text() == "old\n"
    left = [n for n in os.listdir(tmp_path) if n != "out.txt"]
    assert len(left) == 1
    assert TEMP_PATTERN.match(left[0])
    past = atomic.PROCESS_START - 60
    os.utime(tmp_path / left[0], (past, past))
    assert sweep_stale_temps(tmp_path) == [str(tmp_path / left[0])]


# --------------------------------------------------------------------------------------------
# Groups


def test_a_group_writes_all_or_nothing(tmp_path: Path) -> None:
    a, b = tmp_path / "a.pgm", tmp_path / "a.yaml"
    a.write_text("old a\n")

    def second_fails() -> None:
        with atomic_outputs():
            atomic_write_text(a, "new a\n")
            assert a.read_text() == "old a\n"  # not renamed before the group ends
            raise RuntimeError("the second output failed")

    with pytest.raises(RuntimeError):
        second_fails()
    assert a.read_text() == "old a\n"
    assert sorted(os.listdir(tmp_path)) == ["a.pgm"]
    with atomic_outputs():
        atomic_write_text(a, "new a\n")
        atomic_write_text(b, "new b\n")
    assert (a.read_text(), b.read_text()) == ("new a\n", "new b\n")
    assert sorted(os.listdir(tmp_path)) == ["a.pgm", "a.yaml"]


def test_a_failed_rename_in_a_group_undoes_the_renames_before_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b, c = tmp_path / "a.txt", tmp_path / "b.txt", tmp_path / "c.txt"
    a.write_text("old a\n")
    real_replace = os.replace

    def replace(src: str, dst: str) -> None:
        if str(dst) == str(c):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)

    def three() -> None:
        with atomic_outputs():
            atomic_write_text(a, "new a\n")
            atomic_write_text(b, "new b\n")
            atomic_write_text(c, "new c\n")

    with pytest.raises(OutputError, match=r"c\.txt: cannot write the file") as caught:
        three()
    assert "restored" in " ".join(caught.value.__notes__)
    assert a.read_text() == "old a\n"
    assert sorted(os.listdir(tmp_path)) == ["a.txt"]
