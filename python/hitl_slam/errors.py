"""One exception hierarchy for the whole package, rooted in :class:`HitlSlamError`.

The Rust core raises these same classes (it imports them from here), so a caller catches
one family whatever layer the problem was found in.
"""

from __future__ import annotations

__all__ = [
    "AlignmentRefused",
    "CorrectionRejected",
    "DamagedSession",
    "HitlSlamError",
    "InputError",
    "MissingExtra",
    "OutputError",
    "SolverError",
    "StepRefused",
]


class HitlSlamError(Exception):
    """Base class of every error hitl-slam raises on purpose."""


class InputError(HitlSlamError, ValueError):
    """Bad input: a file, an array or an argument that cannot be used as given.

    The message names the file and line where there is one, says what is wrong and what to do.
    """


class MissingExtra(InputError, ImportError):
    """An optional dependency is not installed: the message names the extra to install, e.g.
    ``hitl-slam serve needs the web extra: pip install 'fastapi>=0.110' ...`` (see
    :mod:`hitl_slam.extras`). The CLI reports it as bad input: one line, exit status 2."""


class SolverError(HitlSlamError, RuntimeError):
    """The optimizer could not produce a solution (for example a singular system)."""


class CorrectionRejected(HitlSlamError):
    """A human correction that cannot be interpreted; nothing was changed."""


class StepRefused(InputError):
    """An undo or redo with nothing to undo or redo: refused, nothing changed."""


class AlignmentRefused(InputError):
    """The alignment contradicts the robot's odometry too often to be trusted: nothing changed."""


class OutputError(InputError, OSError):
    """An output file could not be written: the message names the file, says why (the
    operating system's reason) and what to do. Nothing was left under the file's name.
    ``errno``, ``strerror`` and ``filename`` are those of the operating system's error."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class DamagedSession(InputError):
    """A session file whose content is damaged: changed bytes (a checksum mismatch), a torn or
    truncated file, a non-finite or malformed value.

    Attributes:
        path: the file.
        what: what is wrong, in a few words.
        first_bad_seq: the first event that cannot be used; events before it are intact. ``None``
            when the map or the configuration itself is damaged (no event can be used) or the
            damage could not be placed.
    """

    def __init__(
        self,
        path: str,
        what: str,
        first_bad_seq: int | None = None,
        *,
        message: str | None = None,
    ) -> None:
        self.path = path
        self.what = what
        self.first_bad_seq = first_bad_seq
        super().__init__(
            message
            or f"{path}: the session file is damaged ({what}); "
            "restore it from a copy, or start a new session from the input map"
        )
