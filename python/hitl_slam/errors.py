"""One exception hierarchy for the whole package, rooted in :class:`HitlSlamError`.

The Rust core raises these same classes (it imports them from here), so a caller catches
one family whatever layer the problem was found in.
"""

from __future__ import annotations

__all__ = ["CorrectionRejected", "HitlSlamError", "InputError", "MissingExtra", "SolverError"]


class HitlSlamError(Exception):
    """Base class of every error hitl-slam raises on purpose."""


class InputError(HitlSlamError, ValueError):
    """Bad input: a file, an array or an argument that cannot be used as given.

    The message names the file and line where there is one, says what is wrong and what to do.
    """


class MissingExtra(InputError, ImportError):
    """An optional dependency is not installed: the message names the extra to install, e.g.
    ``hitl-slam serve needs the web extra: pip install 'hitl-slam[web]'`` (see
    :mod:`hitl_slam.extras`). The CLI reports it as bad input: one line, exit status 2."""


class SolverError(HitlSlamError, RuntimeError):
    """The optimizer could not produce a solution (for example a singular system)."""


class CorrectionRejected(HitlSlamError):
    """A human correction that cannot be interpreted; nothing was changed."""
