"""Atomic file output: write a temporary file next to the target, fsync it, then rename it over
the target, so an interrupted or failed write never leaves a half-written file in its place.

Temporary files are named ``.<name>.<pid>-<8 hex>.hitl-tmp`` (:data:`TEMP_PATTERN`), so one left
behind by a killed process is recognisable: before the first write into a folder, a process
removes the temporary files there that are older than itself and whose writer is no longer
running (:func:`sweep_stale_temps`; files of the previous ``.<name>.<8 hex>.tmp`` naming, older
than the process, too). Each removal is logged (logger ``hitl_slam.io.atomic``, INFO), and a
file that cannot be removed is logged as a WARNING.

Every failure to write (no space, an I/O error, a read-only or missing folder, a directory in
the way) is an :class:`OutputError`: an :class:`~hitl_slam.errors.InputError` (the CLI prints
one line, exit status 2) that is also an :class:`OSError` (``errno`` and ``strerror`` kept).
Its message names the file, what went wrong and what to do; the temporary file is removed, or
the message says it could not be and names it.

Several outputs that belong together (a ``.pgm`` and its ``.yaml``, a map and a session) can be
made all-or-nothing with :func:`atomic_outputs`: inside it, writers only prepare their
temporary files, and the renames happen together when the block ends without an error.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import errno
import logging
import os
import re
import secrets
import time
from collections.abc import Callable, Iterator
from typing import IO, Any, BinaryIO, TextIO

from hitl_slam.errors import InputError, OutputError

__all__ = [
    "TEMP_PATTERN",
    "OutputError",
    "atomic_binary_writer",
    "atomic_outputs",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_writer",
    "discard_temp",
    "fsync_directory",
    "sweep_once",
    "sweep_stale_temps",
    "temp_path",
]

_log = logging.getLogger(__name__)

TEMP_PATTERN = re.compile(r"\A\..+\.(?P<pid>[0-9]+)-[0-9a-f]{8}\.hitl-tmp\Z", re.DOTALL)
"""Names of the temporary files this module creates: ``.<name>.<pid>-<8 hex>.hitl-tmp``."""

# The naming before TEMP_PATTERN (also used for session files under construction, with SQLite's
# own -journal/-wal/-shm companions): no writer pid, so only the age tells it is stale.
_LEGACY_PATTERN = re.compile(r"\A\..+\.[0-9a-f]{8}\.tmp(-journal|-wal|-shm)?\Z", re.DOTALL)

_NAME_BYTES = 180  # of the target's name kept in the temporary name (file names <= 255 bytes)


def _process_start() -> float:
    """When this process started (wall clock, seconds); the module's import time when the
    operating system does not say (later than the true start, so never too early)."""
    now = time.time()
    try:
        with open("/proc/self/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        ticks = int(fields[19])  # field 22 (starttime), counted after "pid (comm)"
        with open("/proc/uptime", "rb") as f:
            uptime = float(f.read().split()[0])
        # The process's age on the boot clock, taken from the wall clock's now: a wall clock
        # stepped since boot (NTP, a resumed virtual machine) does not move it, as adding the
        # age to /proc/stat's btime (the wall clock at boot) would.
        started = now - (uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return now
    # Ticks and the two reads are not one instant: round down a further second so "older"
    # stays conservative.
    return min(now, started - 1.0)


PROCESS_START = _process_start()


@dataclasses.dataclass
class _Prepared:
    temp: str
    target: str


@dataclasses.dataclass
class _Group:
    prepared: list[_Prepared] = dataclasses.field(default_factory=list)


_GROUP: contextvars.ContextVar[_Group | None] = contextvars.ContextVar(
    "hitl_slam_atomic_group", default=None
)
_SWEPT: set[str] = set()


# --------------------------------------------------------------------------------------------
# Temporary files


def temp_path(target: str | os.PathLike[str]) -> str:
    """A new temporary file name next to ``target`` (matching :data:`TEMP_PATTERN`)."""
    directory, name = os.path.split(os.fspath(target))
    encoded = os.fsencode(name)
    if len(encoded) > _NAME_BYTES:
        name = os.fsdecode(encoded[:_NAME_BYTES])
    return os.path.join(directory, f".{name}.{os.getpid()}-{secrets.token_hex(4)}.hitl-tmp")


def discard_temp(temp: str) -> OSError | None:
    """Remove the temporary file ``temp`` if it exists; the error when it cannot be removed (for
    example on a read-only file system), never raised, so the first error stays the one
    reported. Add :func:`_left_behind`'s words to that error's message."""
    try:
        os.unlink(temp)
    except FileNotFoundError:
        return None
    except OSError as exc:
        _log.warning("could not remove the temporary file %s (%s); delete it", temp, _reason(exc))
        return exc
    return None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


def _left_behind(temp: str, exc: OSError | None) -> str:
    if exc is None:
        return ""
    return f"; the temporary file {temp} could not be removed ({_reason(exc)}): delete it"


def _pid_running(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. EPERM: it exists, owned by someone else
        return True
    return True


def sweep_stale_temps(directory: str | os.PathLike[str]) -> list[str]:
    """Remove the temporary files in ``directory`` left by interrupted writes: those matching
    :data:`TEMP_PATTERN` whose writer (the pid in the name) is not running and that were last
    modified before this process started, and those of the older ``.<name>.<8 hex>.tmp`` naming
    last modified before this process started. Each removal is logged (INFO), each file that
    cannot be removed too (WARNING). Returns the paths removed. Never raises."""
    folder = os.fspath(directory) or "."
    removed: list[str] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    me = os.getpid()
    for entry in entries:
        name = entry.name
        if not name.startswith("."):
            continue
        match = TEMP_PATTERN.match(name)
        if match is not None:
            pid = int(match["pid"])
            if pid == me or _pid_running(pid):
                continue
        elif _LEGACY_PATTERN.match(name) is None:
            continue
        try:
            info = entry.stat(follow_symlinks=False)
            if not entry.is_file(follow_symlinks=False) or info.st_mtime >= PROCESS_START:
                continue
            os.unlink(entry.path)
        except FileNotFoundError:
            continue
        except OSError as exc:
            _log.warning(
                "%s: a temporary file left by an interrupted run could not be removed (%s); "
                "delete it",
                entry.path,
                _reason(exc),
            )
            continue
        removed.append(entry.path)
        _log.info(
            "removed %s, a temporary file (%d bytes) left by an interrupted run",
            entry.path,
            info.st_size,
        )
    return removed


def sweep_once(directory: str | os.PathLike[str]) -> None:
    """:func:`sweep_stale_temps` on ``directory``, the first time this process writes there."""
    key = os.path.realpath(os.fspath(directory) or ".")
    if key in _SWEPT:
        return
    sweep_stale_temps(directory)
    _SWEPT.add(key)


# --------------------------------------------------------------------------------------------
# Errors


_ADVICE = {
    errno.ENOSPC: "free some space or write to another folder",
    errno.EDQUOT: "free some space (the disk quota is full) or write to another folder",
    errno.EROFS: "the file system is read-only: write to another folder",
    errno.EACCES: "write to a folder you may write in, or change its permissions",
    errno.EPERM: "write to a folder you may write in, or change its permissions",
    errno.EISDIR: "it is a directory: give a file name",
    errno.ENOTDIR: "a part of the path is not a folder: check the path",
    errno.ENOENT: "the folder does not exist: create it or give another path",
    errno.ENAMETOOLONG: "choose a shorter file name",
    errno.EIO: "the disk reported an I/O error: check it, or write to another disk",
}


def _output_error(target: str, exc: OSError, temp: str | None = None) -> OutputError:
    """The :class:`OutputError` for ``exc`` while writing ``target``; removes ``temp``."""
    left = "" if temp is None else _left_behind(temp, discard_temp(temp))
    code = exc.errno
    advice = _ADVICE.get(code if code is not None else -1, "nothing was written; try again")
    if code == errno.ENOENT:
        folder = os.path.dirname(target) or "."
        advice = f"the folder {folder} does not exist: create it or give another path"
    error = OutputError(
        f"{target}: cannot write the file ({_reason(exc)}); {advice}; "
        f"the file was not changed{left}"
    )
    error.errno = code
    error.strerror = exc.strerror
    error.filename = target
    return error


def _check_target(target: str) -> None:
    if os.path.isdir(target):
        raise _output_error(target, IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR)))


# --------------------------------------------------------------------------------------------
# Writers


def _create_temp(target: str) -> tuple[int, str]:
    while True:
        temp = temp_path(target)
        try:
            # Not tempfile.mkstemp: its 0600 mode would replace the target's permissions; os.open
            # with 0o666 lets the umask decide, as a plain open() would.
            return os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), temp
        except FileExistsError:
            continue


def fsync_directory(directory: str) -> None:
    # Makes the rename itself durable on POSIX; not possible (nor needed) everywhere.
    try:
        fd = os.open(directory or ".", os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


def _keep_mode(temp: str, target: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.chmod(temp, os.stat(target).st_mode & 0o7777)


@contextlib.contextmanager
def _atomic(target: str, opener: Callable[[int], IO[Any]]) -> Iterator[IO[Any]]:
    _check_target(target)
    sweep_once(os.path.dirname(target))
    try:
        fd, temp = _create_temp(target)
    except OSError as exc:
        raise _output_error(target, exc) from None
    try:
        file = opener(fd)
    except BaseException:
        os.close(fd)
        discard_temp(temp)
        raise
    try:
        with file as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        _keep_mode(temp, target)
        group = _GROUP.get()
        if group is not None:
            group.prepared.append(_Prepared(temp, target))
            return
        os.replace(temp, target)
    except OSError as exc:
        if isinstance(exc, InputError):
            discard_temp(temp)
            raise
        raise _output_error(target, exc, temp) from None
    except BaseException as exc:
        left = discard_temp(temp)
        if left is not None:
            exc.add_note(_left_behind(temp, left).lstrip("; "))
        raise
    fsync_directory(os.path.dirname(target))


@contextlib.contextmanager
def atomic_writer(
    path: str | os.PathLike[str], *, encoding: str = "utf-8", newline: str = "\n"
) -> Iterator[TextIO]:
    """Open a text file for writing that replaces ``path`` only if the ``with`` block succeeds.

    On any exception (in the block, the fsync or the rename) the temporary file is removed, the
    old ``path`` (if any) is untouched, and the exception propagates; an :class:`OSError` (no
    space, an I/O error, a read-only folder, ``path`` a directory) becomes an
    :class:`OutputError` naming the file and what to do.
    """
    target = os.fspath(path)
    with _atomic(target, lambda fd: os.fdopen(fd, "w", encoding=encoding, newline=newline)) as f:
        yield f  # type: ignore[misc]


@contextlib.contextmanager
def atomic_binary_writer(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """:func:`atomic_writer` for bytes."""
    target = os.fspath(path)
    with _atomic(target, lambda fd: os.fdopen(fd, "wb")) as f:
        yield f  # type: ignore[misc]


def atomic_write_text(path: str | os.PathLike[str], text: str, *, encoding: str = "utf-8") -> None:
    """Replace ``path`` with ``text`` atomically (see :func:`atomic_writer`)."""
    with atomic_writer(path, encoding=encoding) as f:
        f.write(text)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically (see :func:`atomic_writer`)."""
    with atomic_binary_writer(path) as f:
        f.write(data)


# --------------------------------------------------------------------------------------------
# All-or-nothing groups


@contextlib.contextmanager
def atomic_outputs() -> Iterator[None]:
    """Make every atomic write inside the block (this thread or task) all-or-nothing: writers
    only prepare their fsynced temporary files; when the block ends without an error they are
    renamed into place together, and if one rename fails the ones already done are undone (an
    old file comes back, a new one is removed). On an error nothing is renamed and every
    temporary file is removed. Writes inside the block are not visible under their names
    until it ends. Nested blocks join the outermost one."""
    if _GROUP.get() is not None:
        yield
        return
    group = _Group()
    token = _GROUP.set(group)
    try:
        yield
    except BaseException as exc:
        _GROUP.reset(token)
        notes = [_left_behind(p.temp, discard_temp(p.temp)) for p in group.prepared]
        for note in filter(None, notes):
            exc.add_note(note.lstrip("; "))
        raise
    _GROUP.reset(token)
    _commit(group.prepared)


def _commit(prepared: list[_Prepared]) -> None:
    # A target written twice in one group: the last write wins, the earlier temp goes.
    last: dict[str, _Prepared] = {}
    for p in prepared:
        earlier = last.pop(p.target, None)
        if earlier is not None:
            discard_temp(earlier.temp)
        last[p.target] = p
    pending = list(last.values())
    # (target, whether it existed, a hard-linked backup of the old file if one could be made)
    done: list[tuple[str, bool, str | None]] = []
    for index, p in enumerate(pending):
        backup: str | None = None
        existed = os.path.lexists(p.target)
        try:
            if existed:
                backup = temp_path(p.target)
                try:
                    os.link(p.target, backup, follow_symlinks=False)
                except OSError:
                    backup = None  # no hard links here: the old file cannot be brought back
            os.replace(p.temp, p.target)
        except OSError as exc:
            if backup is not None:
                discard_temp(backup)
            error = _output_error(p.target, exc, p.temp)
            for q in pending[index + 1 :]:
                discard_temp(q.temp)
            undone = _undo(done)
            if done:
                error.add_note(undone)
            raise error from None
        done.append((p.target, existed, backup))
    for _target, _existed, backup in done:
        if backup is not None:
            discard_temp(backup)
    for directory in dict.fromkeys(os.path.dirname(t) for t, _, _ in done):
        fsync_directory(directory)


def _undo(done: list[tuple[str, bool, str | None]]) -> str:
    """Put back what the renames in ``done`` replaced; says what could not be."""
    failed: list[str] = []
    for target, existed, backup in reversed(done):
        try:
            if backup is not None:
                os.replace(backup, target)
            elif not existed:
                os.unlink(target)
            else:
                failed.append(target)
        except OSError:
            failed.append(target)
    if failed:
        return f"these files were already replaced and could not be restored: {', '.join(failed)}"
    return "the files already replaced were restored"
