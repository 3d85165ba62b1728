"""Starting the web UI: open or create the session (a map file, a ``.hitl`` file, a raw log run
through the front end first, a ROS bag's own SLAM trajectory, or the demo room), bind the socket,
build the app and run uvicorn until Ctrl-C. Everything the user is told goes through the
``announce`` and ``progress`` callbacks (the CLI prints them); this module never prints.
"""

from __future__ import annotations

import contextlib
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
from hitl_slam.map import Map
from hitl_slam.own_slam import COMPARISON, compare, trajectory_of
from hitl_slam.session import Session
from hitl_slam.web.app import DEFAULT_MAX_BODY, create_app
from hitl_slam.web.host import DEFAULT_POLL_TIMEOUT, SessionHost
from hitl_slam.web.origin import check_session_of, describe
from hitl_slam.web.security import check_token, is_loopback, new_token
from hitl_slam.web.verdict import summary as verdict_summary

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


def _front_end(
    source: Path,
    raw: Map,
    progress: FrontEndProgress | None,
    own: Map | None = None,
) -> tuple[Session, str]:
    """Runs the front end over ``raw`` (the odometry map of the raw log ``source``) and starts its
    session beside the log. ``own``: the bag's own SLAM trajectory the front end's map replaces;
    the two are then compared by the inconsistency metric (stored in the map's metadata)."""
    from hitl_slam.slam import slam

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
    compared = ""
    if own is not None:
        comparison = compare(own, result.map)
        result.map.metadata[COMPARISON] = comparison
        compared = (
            f"; inconsistency: the bag's own SLAM trajectory {comparison['bag_slam_m2']:.2f} m^2, "
            f"the front end's map {comparison['front_end_m2']:.2f} m^2"
        )
    path = session_path_for(source)
    session = Session.new(result.map, path)
    start = "from the bag's odometry, in place of its own SLAM trajectory " if own else ""
    # The front end's summary gives its verdict on the map, if any.
    return session, (
        f"ran the front end over {source} {start}({result.summary()}{compared}) and created the "
        f"session {path} ({_describe(session)})"
    )


def _new_session(the_map: Map, path: Path) -> Session:
    """:meth:`Session.new` of ``the_map`` at ``path``, showing on a terminal how far the check of
    its odometry against its scans is (made once, when the session starts; a map the front end
    built needs none)."""
    import sys

    if not sys.stderr.isatty():
        return Session.new(the_map, path)
    from tqdm import tqdm

    with tqdm(desc="odometry check", unit="step", leave=False, file=sys.stderr) as bar:

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        return Session.new(the_map, path, progress=progress)


def _from_raw_log(
    source: Path,
    front_end: bool | None,
    max_range: float | None,
    progress: FrontEndProgress | None,
    bag: BagOptions | None,
) -> tuple[Session, str]:
    """The new session of the raw log ``source`` (no session beside it yet), with the poses
    ``front_end`` asks for (see :mod:`hitl_slam.web.origin`)."""
    from hitl_slam.io.maps import load_map
    from hitl_slam.io.rosbag import BagOptions, is_rosbag
    from hitl_slam.own_slam import has_own_slam, odometry_map, own_slam_map

    options = (bag or BagOptions()) if is_rosbag(source) else bag
    # A bag is read once, with its map frame: its own SLAM trajectory, if it has one, and the
    # odometry beside it, which the front end starts from (over the same scans, so they compare).
    loaded = load_map(source, max_range=max_range, bag=options)
    path = session_path_for(source)
    if options is not None and has_own_slam(loaded):
        own = own_slam_map(loaded)
        if front_end is True:
            return _front_end(source, odometry_map(loaded, options.odom_frame), progress, own)
        session = _new_session(own, path)
        frames = trajectory_of(own).removeprefix("slam (").removesuffix(")")
        return session, (
            f"{source}: starting from the bag's own SLAM trajectory ({frames}, {own.num_poses} "
            "scans); --slam rebuilds it with the front end; created the session "
            f"{path} ({_describe(session)})"
        )
    if front_end is False:
        session = _new_session(loaded, path)
        return session, (
            f"created the session {path} from {source} ({describe(loaded)}; {_describe(session)})"
        )
    return _front_end(source, loaded, progress)


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
    front_end: bool | None = None,
    progress: FrontEndProgress | None = None,
    bag: BagOptions | None = None,
) -> tuple[Session, str]:
    """The session to serve and a sentence saying where it came from (and which poses it holds).

    ``target``: a ``.hitl`` file (reopened) or a map file (its session ``<stem>.hitl`` beside it
    is created, or reopened when it exists). A raw log (:func:`is_raw_log`) becomes a map as
    ``front_end`` says: None (the default) a ROS bag's own SLAM trajectory when ``/tf`` has
    ``map -> odom`` (``bag.map_frame``; its chain of steps measured from its poses, no loop
    closures: :func:`hitl_slam.own_slam.own_slam_map`), else the front end's map built from the
    log's odometry (``progress`` is told how far it is); True (``--slam``) the front end's map
    always (on a bag with its own SLAM, from the odometry over the same scans, and the two are
    compared by the inconsistency metric: ``metadata["trajectory_comparison"]``); False
    (``--no-slam``) the log's own poses (a bag's own SLAM trajectory, else its odometry), as for a
    log that is already a corrected map. An existing session is reopened only when it was made
    from a file of this name and holds the poses asked for (:mod:`hitl_slam.web.origin`).
    ``demo``: one of :data:`DEMO_WORLDS`, kept in ``<cwd>/hitl-demo/<world>.hitl`` (reopened when
    present). Exactly one of them. ``bag``: what to read from a ROS bag (topics, frames).

    Raises:
        InputError: neither or both given, an unknown demo world, a missing or unreadable file,
            ``front_end`` True or False for a target that is not a raw log, an existing session
            that is not this log's (made from another file, or holding other poses).
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
        session = _new_session(scenario.map, path)
        return session, (
            f"created the demo session {path}: the generated {demo} world, damaged and not yet "
            f"corrected (seed {seed}; {_describe(session)})"
        )
    assert target is not None  # checked above
    source = Path(target)
    raw = is_raw_log(source)
    _check_flags(source, raw, front_end)
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
            check_session_of(
                session,
                path,
                source,
                raw=raw,
                front_end=front_end,
                map_frame="map" if bag is None else bag.map_frame,
            )
        except BaseException:
            session.close()
            raise
        said = verdict_summary(session.input_map)
        return session, (
            f"reopened the session {path} of {source} ({describe(session.input_map)}; "
            f"{_describe(session)}); delete it to start over from the map"
            + (f"; {said}" if said else "")
        )
    if raw:
        return _from_raw_log(source, front_end, max_range, progress, bag)
    from hitl_slam.io.maps import load_map

    the_map = load_map(source, max_range=max_range, bag=bag)
    session = _new_session(the_map, path)
    return session, f"created the session {path} from {source} ({_describe(session)})"


def _check_flags(source: Path, raw: bool, front_end: bool | None) -> None:
    """--slam and --no-slam choose how a raw log becomes a map; on anything else, an error."""
    if front_end is None or raw:
        return
    flag = "--slam" if front_end else "--no-slam"
    raise InputError(
        f"{source}: {flag} applies to raw logs (.clf, .log, ROS bags), which the front end "
        f"would turn into a map; this is not one: drop {flag}"
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
    front_end: bool | None = None,
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
        front_end is not None and target is not None and not is_raw_log(target)
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
        # What the first correction needs, made while the page opens and the person looks.
        session.prepare()
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
