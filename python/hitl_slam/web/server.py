"""Starting the web UI: open or create the session (a map file, a ``.hitl`` file, a raw log run
through the front end first, or the demo room), bind the socket, build the app and run uvicorn
until Ctrl-C. Everything the user is told goes through the ``announce`` and ``progress``
callbacks (the CLI prints them); this module never prints.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import ipaddress
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from fastapi import FastAPI

from hitl_slam.corrections_file import Step
from hitl_slam.errors import InputError
from hitl_slam.session import Session
from hitl_slam.web.app import DEFAULT_MAX_BODY, create_app
from hitl_slam.web.host import DEFAULT_POLL_TIMEOUT, SessionHost
from hitl_slam.web.security import check_token, is_loopback, new_token

if TYPE_CHECKING:
    from hitl_slam.io.rosbag import BagOptions

__all__ = [
    "DEFAULT_PORT",
    "DEMO_FOLDER",
    "DEMO_WORLDS",
    "FrontEndProgress",
    "is_raw_log",
    "open_session",
    "run_server",
    "session_path_for",
]

logger = logging.getLogger(__name__)

DEFAULT_PORT = 8765
DEMO_FOLDER = "hitl-demo"
"""``--demo`` keeps its session in this folder under the current directory."""
DEMO_WORLDS = ("lost-poses", "campus")
"""The generated worlds ``--demo`` can serve (``hitl_slam.sim.lost_poses_room`` and ``campus``)."""

_COMPRESSED = (".gz", ".bz2")
_RAW_LOGS = (".clf", ".log")
_FRONT_END_MARK = "hitl-slam"  # map.metadata["front_end"] of a map the front end built

FrontEndProgress = Callable[[int, int, float | None], object]
"""``progress(scans done, scans in all, real-time factor so far or None)`` while the front end
runs over a raw log."""


def is_raw_log(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a laser log the front end turns into a map: a CARMEN log (``.clf``,
    ``.log``, optionally ``.gz``/``.bz2``) or a ROS bag (``.bag``, ``.db3``, ``.mcap``, or a ROS 2
    bag directory)."""
    from hitl_slam.io.rosbag import is_rosbag

    name = Path(path).name.lower()
    if name.endswith(_COMPRESSED):
        name = os.path.splitext(name)[0]
    return os.path.splitext(name)[1] in _RAW_LOGS or is_rosbag(path)


def _built_by_front_end(session: Session) -> bool:
    m = session.input_map
    return m.metadata.get("front_end") == _FRONT_END_MARK or m.name.endswith(
        "(hitl-slam front end)"
    )


def _front_end(
    source: Path,
    max_range: float | None,
    progress: FrontEndProgress | None,
    bag: BagOptions | None = None,
) -> tuple[Session, str]:
    """Runs the front end over the raw log ``source`` and starts its session beside it (a bag
    read with ``bag``'s topics and frames)."""
    from hitl_slam.io.maps import load_map
    from hitl_slam.io.rosbag import BagOptions, is_rosbag
    from hitl_slam.slam import slam

    # A bag's own SLAM trajectory is not where the front end starts: its odometry is.
    if is_rosbag(source):
        bag = dataclasses.replace(bag or BagOptions(), map_frame=None)
    raw = load_map(source, max_range=max_range, bag=bag)
    duration = None
    if raw.timestamps is not None and raw.num_poses > 1:
        duration = float(raw.timestamps[-1] - raw.timestamps[0])
    started = time.perf_counter()

    def report(done: int, total: int) -> None:
        if progress is None:
            return
        elapsed = time.perf_counter() - started
        rtf = None
        if duration is not None and duration > 0 and elapsed > 0 and total > 0:
            rtf = duration * done / total / elapsed
        progress(done, total, rtf)

    result = slam(raw, progress=report)
    path = session_path_for(source)
    session = Session.new(result.map, path)
    return session, (
        f"ran the front end over {source} ({result.summary()}) and created the session {path} "
        f"({_describe(session)})"
    )


_HINT = (
    "in the page: p toggles correction mode, then Ctrl-drag (colocation), Shift-drag "
    "(collinear), Shift+Alt-drag (perpendicular) or Shift+Ctrl-drag (parallel) draws; "
    "? lists every key; Ctrl-C here stops the server (everything is saved as you go)"
)


def session_path_for(map_path: str | os.PathLike[str]) -> Path:
    """Where the session of a map file lives: beside it, ``<stem>.hitl`` (``run.clf.gz`` ->
    ``run.hitl``)."""
    path = Path(map_path)
    name = path.name
    if name.lower().endswith(_COMPRESSED):
        name = os.path.splitext(name)[0]
    return path.with_name(os.path.splitext(name)[0] + ".hitl")


def _describe(session: Session) -> str:
    m = session.input_map
    applied = len(session.active)
    loops = session.loop_closures
    closures = ""
    if loops:
        rejected = len(session.rejected_loop_closures)
        closures = f", {len(loops)} loop closures ({rejected} rejected)"
    return (
        f"{m.num_poses} poses, {m.num_points} points{closures}, {applied} correction"
        f"{'' if applied == 1 else 's'} applied"
    )


def open_session(
    target: str | os.PathLike[str] | None = None,
    *,
    demo: str | None = None,
    seed: int = 0,
    cwd: str | os.PathLike[str] | None = None,
    max_range: float | None = None,
    front_end: bool = True,
    progress: FrontEndProgress | None = None,
    bag: BagOptions | None = None,
) -> tuple[Session, str]:
    """The session to serve and a sentence saying where it came from.

    ``target``: a ``.hitl`` file (reopened) or a map file (its session ``<stem>.hitl`` beside it
    is created, or reopened when it exists). A raw log (:func:`is_raw_log`) is first run through
    the front end (``progress`` is told how far it is), unless ``front_end`` is False: then its
    logged poses are the map, as for a log that is already a corrected map. An existing session
    is reopened only when it was made the same way (with or without the front end) from a file
    of this name. ``demo``: one of :data:`DEMO_WORLDS`, kept in ``<cwd>/hitl-demo/<world>.hitl``
    (reopened when present). Exactly one of them. ``bag``: what to read from a ROS bag (topics,
    frames; the front end always starts from the odometry).

    Raises:
        InputError: neither or both given, an unknown demo world, a missing or unreadable file,
            ``front_end=False`` for a target that is not a raw log, an existing session that is
            not this log's (made from another file, or the other way).
    """
    if (target is None) == (demo is None):
        raise InputError(
            "give a map or session file to serve, or --demo (exactly one of them); "
            "e.g. `hitl-slam serve --demo`"
        )
    if demo is not None:
        if demo not in DEMO_WORLDS:
            raise InputError(f"unknown demo world {demo!r}; use one of {', '.join(DEMO_WORLDS)}")
        folder = Path.cwd() if cwd is None else Path(cwd)
        path = folder / DEMO_FOLDER / f"{demo}.hitl"
        if path.exists():
            session = Session.open(path)
            return session, f"reopened the demo session {path} ({_describe(session)})"
        from hitl_slam.sim import campus, lost_poses_room

        scenario = (lost_poses_room if demo == "lost-poses" else campus)(seed)
        path.parent.mkdir(parents=True, exist_ok=True)
        session = Session.new(scenario.map, path)
        return session, (
            f"created the demo session {path}: the generated {demo} world, damaged and not yet "
            f"corrected (seed {seed}; {_describe(session)})"
        )
    assert target is not None  # checked above
    source = Path(target)
    raw = is_raw_log(source)
    if not front_end and not raw:
        raise InputError(
            f"{source}: --no-slam applies to raw logs (.clf, .log, ROS bags), which the front end "
            "would turn into a map; this is not one: drop --no-slam"
        )
    if source.suffix.lower() == ".hitl":
        if not source.is_file():
            raise InputError(f"{source}: no such session file; give an existing .hitl file")
        session = Session.open(source)
        return session, f"reopened the session {source} ({_describe(session)})"
    if not (source.is_file() or (raw and source.is_dir())):
        raise InputError(
            f"{source}: no such file; give a map (.covars), a raw log (.clf, .log, a ROS bag) "
            "or a .hitl"
        )
    path = session_path_for(source)
    if path.exists():
        session = Session.open(path)
        try:
            _check_session_of(session, path, source, raw and front_end)
        except BaseException:
            session.close()
            raise
        return session, (
            f"reopened the session {path} of {source} ({_describe(session)}); delete it to "
            "start over from the map"
        )
    if raw and front_end:
        return _front_end(source, max_range, progress, bag)
    from hitl_slam.io.maps import load_map

    the_map = load_map(source, max_range=max_range, bag=bag)
    session = Session.new(the_map, path)
    return session, f"created the session {path} from {source} ({_describe(session)})"


def _check_session_of(session: Session, path: Path, source: Path, front_end: bool) -> None:
    """Refuses a session beside ``source`` that is not its session as asked for: made from a
    file of another name, or with the front end when the log's own poses were asked for (or the
    other way)."""
    stored = session.input_map.source
    if stored is not None and Path(stored).name != source.name:
        raise InputError(
            f"{path}: this session was made from {Path(stored).name}, not {source.name}; "
            f"serve {path} itself, or move it away to start a session of {source.name}"
        )
    built = _built_by_front_end(session)
    if not is_raw_log(source) or built == front_end:
        return
    if front_end:
        raise InputError(
            f"{path}: this session holds the log's own poses (made with --no-slam); serve it "
            "with --no-slam, or move it away to run the front end over the log"
        )
    raise InputError(
        f"{path}: this session holds the front end's map of the log; serve it without "
        "--no-slam, or move it away to serve the log's own poses"
    )


def _bind(host: str, port: int) -> socket.socket:
    try:
        infos = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
    except (OSError, UnicodeError) as exc:
        raise InputError(
            f"cannot listen on {host!r}: {exc}; give an address such as 127.0.0.1"
        ) from None
    last: OSError | None = None
    for family, kind, proto, _, address in infos:
        sock = socket.socket(family, kind, proto)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(address)
            sock.listen(128)
        except OSError as exc:
            sock.close()
            last = exc
            continue
        sock.set_inheritable(True)
        return sock
    reason = "" if last is None else f" ({last.strerror or last})"
    raise InputError(
        f"cannot listen on {host} port {port}{reason}; pick another port with --port "
        "(0: any free port)"
    )


def _url(sock: socket.socket, token: str | None) -> str:
    address = sock.getsockname()
    host, port = str(address[0]), int(address[1])
    with contextlib.suppress(ValueError):
        ip = ipaddress.ip_address(host)
        if ip.is_unspecified:
            # Listening on every interface: this machine reaches it on loopback.
            host = "127.0.0.1" if ip.version == 4 else "::1"
        if ip.version == 6:
            host = f"[{host}]"
    return f"http://{host}:{port}/" + ("" if token is None else f"?token={token}")


def run_server(
    target: str | os.PathLike[str] | None = None,
    *,
    demo: str | None = None,
    seed: int = 0,
    host: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    token: str | None = None,
    no_token: bool = False,
    journal: str | os.PathLike[str] | None = None,
    max_range: float | None = None,
    front_end: bool = True,
    progress: FrontEndProgress | None = None,
    bag: BagOptions | None = None,
    open_browser: bool = False,
    announce: Callable[[str], None] = lambda _message: None,
    poll_timeout: float = DEFAULT_POLL_TIMEOUT,
    max_body: int = DEFAULT_MAX_BODY,
) -> None:
    """Serve the web UI on ``host``:``port`` until interrupted (Ctrl-C or SIGTERM).

    ``target``/``demo``/``seed``/``front_end``/``bag``: the session, see :func:`open_session`;
    ``progress`` follows the front end over a raw log. ``token``: the access
    token (default: a new random one); ``no_token=True`` serves without one, allowed on a
    loopback ``host`` only. ``port=0`` picks a free port. ``journal``: a corrections file to step
    through. ``announce`` receives each line for the user, among them
    ``hitl-slam serve: listening on URL`` once the socket is bound (the URL carries the token).

    Raises:
        InputError: bad arguments (checked before anything is created), an unreadable file, or
            a port that cannot be bound.
    """
    if no_token and token is not None:
        raise InputError("give either --token or --no-token, not both")
    if token is not None:
        check_token(token)
    if no_token and not is_loopback(host):
        raise InputError(f"refusing to serve on {host} without an access token; drop --no-token")
    if (target is None) == (demo is None) or (
        not front_end and target is not None and not is_raw_log(target)
    ):
        # The one-line reason, before anything is bound.
        open_session(target, demo=demo, max_range=max_range, front_end=front_end, bag=bag)
    if not 0 <= port <= 65535:
        raise InputError(f"--port must be 0..65535 (0: any free port), got {port}")
    steps: list[Step] = []
    source = None
    if journal is not None:
        from hitl_slam.corrections_file import read_corrections

        steps = read_corrections(journal)
        source = os.path.basename(os.fspath(journal))
    secret = None if no_token else (token if token is not None else new_token())
    sock = _bind(host, port)
    try:
        session, how = open_session(
            target,
            demo=demo,
            seed=seed,
            max_range=max_range,
            front_end=front_end,
            progress=progress,
            bag=bag,
        )
        try:
            session_host = SessionHost(
                session, journal=steps, journal_source=source, poll_timeout=poll_timeout
            )
        except BaseException:
            session.close()
            raise
        try:
            app = create_app(session_host, token=secret, max_body=max_body, bind=host)
            announce(f"hitl-slam serve: {how}")
            if steps:
                announce(f"hitl-slam serve: {len(steps)} steps of {journal} ready (key l steps)")
            url = _url(sock, secret)
            announce(f"hitl-slam serve: listening on {url}")
            announce(f"hitl-slam serve: {_HINT}")
            if open_browser:
                import webbrowser

                threading.Thread(target=webbrowser.open, args=(url,), daemon=True).start()
            # What exists now (the map, its drawing, the modules, the app) lives as long as the
            # server: frozen out of the collector's sight, a full collection (50 ms over these
            # objects on the campus) does not land in the middle of a correction's answer.
            gc.collect()
            gc.freeze()
            _serve(app, sock, session_host)
        finally:
            session_host.close()
    finally:
        sock.close()


def _serve(app: FastAPI, sock: socket.socket, session_host: SessionHost) -> None:
    import uvicorn

    class _Server(uvicorn.Server):
        # A signal stops the server gracefully and is not raised again afterwards (uvicorn's own
        # handler re-raises it, which would turn a clean Ctrl-C into a KeyboardInterrupt).
        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            if self.should_exit and sig == signal.SIGINT:
                self.force_exit = True
            self.should_exit = True
            session_host.wake_all()

    config = uvicorn.Config(
        app,
        log_level="warning",
        access_log=False,
        lifespan="off",
        ws="none",
        proxy_headers=False,
        server_header=False,
        timeout_graceful_shutdown=2,
    )
    server = _Server(config)
    with contextlib.suppress(KeyboardInterrupt):
        server.run(sockets=[sock])
