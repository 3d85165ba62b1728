"""What is intact in a damaged session file: the events before the first damaged one, the last
good checkpoint they give, the message that names it, and the new file
:meth:`hitl_slam.session.Session.recover` copies them to.
"""

from __future__ import annotations

import os

from hitl_slam.errors import DamagedSession, InputError
from hitl_slam.journal import Event, Journal
from hitl_slam.map import Map
from hitl_slam.session_state import _State
from hitl_slam.session_steps import _Align, _Toggle


def _recovery_path(path: str) -> str:
    """A new file beside ``path`` for what is intact in it: ``<stem>.recovered.hitl`` (or
    ``.recovered-2.hitl``, ... when taken)."""
    stem = os.path.splitext(path)[0]
    candidate, k = f"{stem}.recovered.hitl", 1
    while os.path.exists(candidate):
        k += 1
        candidate = f"{stem}.recovered-{k}.hitl"
    return candidate


def _intact(journal: Journal, map: Map) -> tuple[_State, int, str | None]:
    """Replay the journal's events up to the first that cannot be used (damaged on disk, or
    not a valid step): the state they give, how many there are, and what is wrong with the next
    one (None: every event is intact). Never raises for damaged events."""
    state = _State.for_map(map)
    good: list[Event] = []
    for item in journal.intact_events():
        if isinstance(item, DamagedSession):
            return state, len(good), item.what
        problem = state.feed(item)
        if problem is not None:
            # The failed event may have changed the state half-way: replay the good ones again.
            state = _State.for_map(map)
            for event in good:
                state.feed(event)
            return state, len(good), problem
        good.append(item)
    return state, len(good), None


def _describe(state: _State) -> str:
    applied = len(state.applied)
    if not applied:
        return "the input map (no correction applied)"
    top = state.applied[-1]
    if isinstance(top, _Toggle):
        verb = "rejecting" if top.rejected else "reinstating"
        return f"the map after {verb} loop closure {top.loop} ({applied} steps applied)"
    if isinstance(top, _Align):
        return f"the map after aligning it with its scans ({applied} steps applied)"
    return f"the map after correction {top.index + 1} of the history ({applied} applied)"


def _damage_report(path: str, what: str, journal: Journal, map: Map | None) -> DamagedSession:
    """The error a user gets for a damaged file: what is wrong and the last good checkpoint,
    with the call that opens it (the intact events copied to a new file; the damaged one kept).
    ``map``: the stored input map, None when it is damaged too."""
    if map is None:
        return DamagedSession(
            path,
            what,
            message=f"{path}: the session file is damaged ({what}); the stored input map is "
            "damaged too, so no checkpoint in it can be trusted; restore the file from a copy, "
            "or start a new session from the input map",
        )
    state, count, _ = _intact(journal, map)
    if count == 0:
        return DamagedSession(
            path,
            what,
            1,
            message=f"{path}: the session file is damaged ({what}); no event in it is intact; "
            "restore the file from a copy, or start a new session from the input map",
        )
    return DamagedSession(
        path,
        what,
        count + 1,
        message=f"{path}: the session file is damaged ({what}); events 1 to {count} are "
        f"intact; the last good checkpoint is {_describe(state)}: `hitl-slam recover {path}` "
        f"(or hitl_slam.Session.recover({path!r})) copies those events to "
        f"{_recovery_path(path)} and leaves this file as it is; or restore the file from a copy",
    )


def _structural_report(path: str, damage: DamagedSession, journal: Journal) -> DamagedSession:
    """:func:`_damage_report` for a file whose SQLite structure is damaged: what can still be
    read (rows whose checksums hold) decides the last good checkpoint."""
    try:
        stored = journal.read_map()
        journal.read_config()
    except InputError:
        return _damage_report(path, damage.what, journal, None)
    return _damage_report(path, damage.what, journal, stored)
