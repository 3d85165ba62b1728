"""What the ``hitl-slam`` commands share: the options several take (``--max-range``, the ROS bag
options, ``--force``), loading a command's map with a progress display, checking its outputs
against its inputs, and turning the library's errors into one-line messages and exit codes.
"""

from __future__ import annotations

import argparse
import contextvars
import logging
import os
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from hitl_slam.errors import HitlSlamError, InputError, SolverError

if TYPE_CHECKING:
    from typing import TypeAlias

    from hitl_slam.io.rosbag import BagOptions
    from hitl_slam.map import Map

    Commands: TypeAlias = argparse._SubParsersAction[argparse.ArgumentParser]
    """What each command module's ``add_parser`` adds its subcommand to."""

T = TypeVar("T")

BAGS_NOTE = """
ROS bags (needs the ros extra: pip install 'hitl-slam[ros]'): the scans of the bag's
sensor_msgs/LaserScan topic (--scan-topic when it has several), the odometry from /tf
(--odom-frame -> --base-frame) or a nav_msgs/Odometry topic (--odom-topic), interpolated at each
scan's stamp, and the laser's mounting from /tf_static. When /tf has map -> odom (slam_toolbox,
Cartographer), the poses are the SLAM's own trajectory; --map-frame '' keeps the odometry's.
Points are kept in the robot's frame (base_link).
"""
"""The epilog paragraph of the commands that read ROS bags."""


# -- arguments ---------------------------------------------------------------------------------


def add_max_range(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--max-range",
        type=float,
        metavar="M",
        help="the laser's maximum range in metres (CARMEN logs, ROS bags): readings at or "
        "beyond it are no-returns, not obstacles; default: a bag's range_max, a log's PARAM "
        "robot_front_laser_max, else inferred from readings piled at the largest value, else 80",
    )


def add_bag_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "ROS bags", "what to read from a .bag, .db3, .mcap or ROS 2 bag directory"
    )
    group.add_argument(
        "--scan-topic",
        metavar="TOPIC",
        help="the sensor_msgs/LaserScan topic (default: the bag's only one)",
    )
    group.add_argument(
        "--odom-topic",
        metavar="TOPIC",
        help="take the odometry from this nav_msgs/Odometry topic (default: /tf odom -> "
        "base_link, else the bag's only Odometry topic)",
    )
    group.add_argument(
        "--odom-frame", default="odom", metavar="FRAME", help="the odometry frame (default odom)"
    )
    group.add_argument(
        "--base-frame",
        default="base_link",
        metavar="FRAME",
        help="the robot's frame, in which the points are kept (default base_link)",
    )
    group.add_argument(
        "--map-frame",
        default="map",
        metavar="FRAME",
        help="the SLAM's map frame: when /tf has FRAME -> odom, the poses are the SLAM's "
        "trajectory (default map; '' for the odometry's)",
    )


def bag_options(args: argparse.Namespace) -> BagOptions | None:
    """The ROS bag options of a command that has them, or None."""
    if not hasattr(args, "scan_topic"):
        return None
    from hitl_slam.io.rosbag import BagOptions

    return BagOptions(
        scan_topic=args.scan_topic,
        odom_topic=args.odom_topic,
        odom_frame=args.odom_frame,
        base_frame=args.base_frame,
        map_frame=args.map_frame or None,
    )


def add_force(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--force",
        action="store_true",
        help="write the output even when it is one of the input files (replacing that input)",
    )


# -- progress and input ------------------------------------------------------------------------


def with_progress(label: str, quiet: bool, work: Callable[[], T]) -> T:
    """Runs ``work`` (which releases the GIL) in a thread; shows elapsed time on a terminal."""
    if quiet or not sys.stderr.isatty():
        return work()
    from tqdm import tqdm

    result: list[T] = []
    error: list[BaseException] = []

    def run() -> None:
        try:
            result.append(work())
        except BaseException as exc:  # re-raised in the caller's thread
            error.append(exc)

    # The worker runs in this thread's context, so an atomic_outputs() group reaches it.
    context = contextvars.copy_context()
    thread = threading.Thread(target=context.run, args=(run,), daemon=True)
    thread.start()
    with tqdm(desc=label, total=None, unit="", leave=False, file=sys.stderr) as bar:
        while thread.is_alive():
            thread.join(0.1)
            bar.update(0)
            bar.refresh()
    if error:
        raise error[0]
    return result[0]


def load_map(args: argparse.Namespace, source: str | Path) -> Map:
    """The map of a command's MAP argument, with ``--max-range``; says on stderr how the laser's
    maximum range was found when the log stated none (once: when the log is read, not at every
    command on a session made from it, which carries the same note in its metadata)."""
    from hitl_slam.io.maps import load_map, map_kind

    max_range = getattr(args, "max_range", None)
    bag = bag_options(args)
    the_map = with_progress(
        "loading", args.quiet, lambda: load_map(source, max_range=max_range, bag=bag)
    )
    how = the_map.metadata.get("max_range_source")
    if isinstance(how, str) and how.startswith("inferred") and map_kind(source) != "a session":
        print(f"hitl-slam: {source}: maximum laser range {how}", file=sys.stderr)
    return the_map


# -- outputs -----------------------------------------------------------------------------------


def check_map_output(out: Path, extra: tuple[str, ...] = ()) -> None:
    """An InputError unless ``out``'s extension is an export format (or one of ``extra``)."""
    from hitl_slam.io.export import EXPORT_EXTENSIONS

    if out.suffix.lower() not in EXPORT_EXTENSIONS + extra:
        supported = ", ".join(EXPORT_EXTENSIONS + extra)
        raise InputError(f"{out}: unsupported output extension {out.suffix!r}; use {supported}")


def outputs_of(out: Path) -> list[Path]:
    """The files writing ``out`` creates: a .pgm brings its .yaml."""
    return [out, out.with_suffix(".yaml")] if out.suffix.lower() == ".pgm" else [out]


def refuse_overwriting_inputs(
    outputs: Sequence[Path], inputs: Sequence[str | Path | None], force: bool
) -> None:
    """An InputError when an output is an existing input file (the same file, by name, symbolic
    link or hard link), unless ``force``."""
    if force:
        return
    for out in outputs:
        for source in inputs:
            if source is None:
                continue
            try:
                same = os.path.samefile(out, source)
            except OSError:  # one of them does not exist (yet): nothing to overwrite
                continue
            if same:
                also = "" if str(out) == str(source) else f" as the input {source}"
                raise InputError(
                    f"{out}: is the same file{also}; writing it would replace the input: "
                    "give another output name, or pass --force to overwrite the input"
                )


def one_line(text: str) -> str:
    return " ".join(text.split())


# -- notices and errors ------------------------------------------------------------------------


class StderrNotices(logging.Handler):
    """Prints, as ``hitl-slam: ...`` lines on the current stderr, every WARNING (and worse) of
    the ``hitl_slam`` loggers (a reader's skipped lines, covariances it replaced, ...) and the
    INFO notices of :mod:`hitl_slam.io.atomic` (stale temporary files removed)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or record.name == "hitl_slam.io.atomic"

    def emit(self, record: logging.LogRecord) -> None:
        try:
            print(f"hitl-slam: {one_line(record.getMessage())}", file=sys.stderr)
        except Exception:
            self.handleError(record)


def run_command(args: argparse.Namespace) -> int:
    """The exit code of the parsed command ``args``: its own, or the one of the error it raised
    (after a one-line message on stderr)."""
    try:
        code: int = args.func(args)
    except InputError as exc:
        print(f"hitl-slam: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except SolverError as exc:
        print(f"hitl-slam: solver failed: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    except HitlSlamError as exc:
        print(f"hitl-slam: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    except OSError as exc:
        # Reading or writing a file failed outside the readers' and writers' own checks.
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"hitl-slam: error: {where}{one_line(exc.strerror or str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hitl-slam: interrupted; no output was written", file=sys.stderr)
        return 130
    return code
