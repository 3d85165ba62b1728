"""``hitl-slam serve``: the browser UI: draw corrections on a map, undo, save (127.0.0.1 only)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import TYPE_CHECKING, Any

from hitl_slam.cli.common import add_bag_options, add_max_range, bag_options
from hitl_slam.errors import InputError
from hitl_slam.extras import require

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands

EPILOG = """\
examples:
  hitl-slam serve --demo                       # the damaged lost-poses room, ./hitl-demo/
  hitl-slam serve --demo --demo-world campus   # the 3,380-pose campus instead
  hitl-slam serve run.clf.gz                   # a raw log: the front end builds the map first,
                                               # then run.hitl beside it (reopened next time)
  hitl-slam serve run.bag                      # a ROS bag: its own SLAM's map when /tf has
                                               # map -> odom, else the front end's
  hitl-slam serve run.bag --slam               # the front end's map even so, compared with
                                               # the bag's own by their inconsistency
  hitl-slam serve corrected.log.gz --no-slam   # a log whose poses are already a map: as logged
  hitl-slam serve lab.covars                   # a map: lab.hitl beside it
  hitl-slam serve run.hitl --journal fixes.jsonl   # step through a corrections file with l
  hitl-slam serve run.hitl --port 0 --open     # any free port; open the browser

Open the printed URL (http://127.0.0.1:8765/?token=...): the token keeps other pages and other
users of this machine out; the page remembers it in a cookie. In the page, p toggles correction
mode; then a drag draws a segment, its mode from the keys held: Ctrl colocation, Shift collinear,
Shift+Alt perpendicular, Shift+Ctrl parallel. Two segments of one mode show what they select;
p again applies the correction. u undoes, Shift+U redoes, v saves, ? lists every key.

A raw log (CARMEN .clf/.log, also .gz/.bz2, or a ROS bag) is a robot's odometry and scans: serve
runs the scan-matching front end over it first (progress on stderr; docs/ALGORITHM.md §F) and
serves the map it builds, with its loop closures drawn between the poses they join (green:
trusted, amber: down-weighted, red dashed: rejected; c shows or hides them). Click one to select
it (n / N step through them), x rejects or reinstates it: the map re-solves at once, and the
step is journaled and undone like a correction. Every .clf/.log is taken as raw: a log whose
logged poses are already a good map (a corrected log, another SLAM's output) is served as logged
with --no-slam (no loop closures then). Stretches the front end doubts, when it names any, are
drawn in purple and listed in the status bar.

A ROS bag recorded with a SLAM running (slam_toolbox, Cartographer, gmapping, AMCL: /tf has
map -> odom) is the map you came to repair: serve starts from the SLAM's own trajectory
(map -> base_link), its factors the chain of steps between consecutive scans (no loop closures),
and says so. --slam rebuilds it with the front end from the bag's odometry instead (over the
same scans) and shows both maps' inconsistency side by side in the status bar (lower is more
consistent). --map-frame '' ignores the bag's SLAM (the front end's map, or with --no-slam the
odometry as recorded). --slam and --no-slam together are an error. A session beside the log is
reopened only when it holds the poses asked for (else one line saying which it holds and how to
serve it).

Every correction is journaled in the session file (.hitl) before the map changes, so Ctrl-C (or
a crash) loses nothing acknowledged; serving the same file again continues where you left off.
Save (v) writes NAME.txt (TUM), .g2o, .pgm and .yaml beside the session file.

The server listens on 127.0.0.1 only, unless --host says otherwise; --no-token is allowed on
loopback only.
"""


def add_parser(sub: Commands) -> None:
    serve = sub.add_parser(
        "serve",
        help="the browser UI: draw corrections on a map, undo, save (127.0.0.1 only)",
        description=(
            "Serve a map or session in the browser on this machine: draw corrections, see what "
            "they select, apply, undo and redo them, save the corrected map."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    serve.add_argument(
        "target",
        nargs="?",
        metavar="MAP_OR_SESSION",
        help=(
            "a raw log (.clf/.log[.gz|.bz2], a ROS bag: the front end builds the map first, "
            "unless the bag has its own SLAM's map frame), a map (.covars), or a .hitl; the "
            "session <stem>.hitl goes beside a log or map"
        ),
    )
    serve.add_argument(
        "--slam",
        action="store_true",
        help=(
            "a bag with its own SLAM (map -> odom on /tf): rebuild the map with the front end from "
            "the bag's odometry instead of serving the SLAM's trajectory, and show the "
            "inconsistency of both; a .clf/.log or a bag without one gets the front end anyway"
        ),
    )
    serve.add_argument(
        "--no-slam",
        action="store_true",
        help=(
            "serve a .clf/.log or bag with its own poses as the map (logged poses; a bag's own "
            "SLAM trajectory, else its odometry), without the front end (for a corrected log or "
            "another SLAM's output); not with --slam"
        ),
    )
    serve.add_argument(
        "--demo", action="store_true", help="serve a generated damaged map in ./hitl-demo/"
    )
    serve.add_argument(
        "--demo-world",
        choices=["lost-poses", "campus"],
        help="which generated map --demo serves (default lost-poses)",
    )
    serve.add_argument("--seed", type=int, default=0, help="random seed of --demo (default 0)")
    serve.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)"
    )
    serve.add_argument(
        "--port", type=int, default=8765, help="port (default 8765; 0 picks a free one)"
    )
    access = serve.add_mutually_exclusive_group()
    access.add_argument("--token", metavar="T", help="the access token (default: a random one)")
    access.add_argument(
        "--no-token", action="store_true", help="no access token (loopback addresses only)"
    )
    serve.add_argument(
        "--journal", metavar="C.jsonl", help="a corrections file to step through (key l)"
    )
    serve.add_argument("--open", action="store_true", help="open the page in the web browser")
    add_max_range(serve)
    add_bag_options(serve)
    serve.set_defaults(func=run)


class _ServeProgress:
    """How far the front end is over a raw log `hitl-slam serve` was given: a tqdm bar on a
    terminal, else a line on stderr at most every 5 s and at the end (scans done, real-time
    factor)."""

    EVERY_S = 5.0

    def __init__(self) -> None:
        self._bar: Any = None
        self._last = -math.inf
        self._done = False

    def __call__(self, done: int, total: int, rtf: float | None) -> None:
        speed = "" if rtf is None else f"{rtf:.1f}x real time"
        if sys.stderr.isatty():
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=total, desc="front end", unit="scan", file=sys.stderr)
            self._bar.n = done
            if speed:
                self._bar.set_postfix_str(speed)
            self._bar.refresh()
            return
        now = time.monotonic()
        if done < total and now - self._last < self.EVERY_S:
            return
        if done >= total and self._done:
            return
        self._last = now
        self._done = done >= total
        print(
            f"hitl-slam serve: front end {done}/{total} scans" + (f", {speed}" if speed else ""),
            file=sys.stderr,
            flush=True,
        )

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def run(args: argparse.Namespace) -> int:
    require("web", "hitl-slam serve")
    from hitl_slam.web.server import run_server

    if args.demo_world is not None and not args.demo:
        raise InputError("--demo-world goes with --demo; add --demo, or drop --demo-world")
    if args.demo and args.target is not None:
        raise InputError(f"give {args.target} or --demo, not both")
    if args.slam and args.no_slam:
        raise InputError(
            "give --slam (the front end rebuilds the map from the log's odometry) or --no-slam "
            "(the log's own poses as they are), not both"
        )
    if args.demo and (args.slam or args.no_slam):
        flag = "--slam" if args.slam else "--no-slam"
        raise InputError(
            f"{flag} chooses how a raw log becomes a map; --demo has none: drop {flag}"
        )

    def announce(message: str) -> None:
        print(message, flush=True)

    progress = _ServeProgress()
    try:
        run_server(
            args.target,
            max_range=args.max_range,
            front_end=True if args.slam else False if args.no_slam else None,
            progress=progress,
            bag=bag_options(args),
            demo=(args.demo_world or "lost-poses") if args.demo else None,
            seed=args.seed,
            host=args.host,
            port=args.port,
            token=args.token,
            no_token=args.no_token,
            journal=args.journal,
            open_browser=args.open,
            announce=announce,
        )
    finally:
        progress.close()
    print("hitl-slam serve: stopped; every acknowledged change is in the session file", flush=True)
    return 0
