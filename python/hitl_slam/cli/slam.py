"""``hitl-slam slam``: build a map from a raw laser log with the scan-matching front end."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hitl_slam.cli.common import (
    add_bag_options,
    add_force,
    add_max_range,
    check_map_output,
    load_map,
    outputs_of,
    refuse_overwriting_inputs,
    with_progress,
)
from hitl_slam.errors import InputError

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands

EPILOG = """\
examples:
  hitl-slam slam intel.clf.bz2 -o intel.hitl          # then: hitl-slam serve intel.hitl
  hitl-slam slam fr079.clf.bz2 -o fr079.g2o
  hitl-slam metrics intel.hitl --relations intel.relations

The output map's poses are the front end's; its factors are the matched steps between
consecutive scans and the loop closures the final solve kept. The summary line starts with the
front end's verdict: "good map", or "DOUBTFUL map" with the stretches of scans to look at first
(scans it could not match, matches far weaker than the ones before them, scans placed far from
the odometry by an unclear match, or steps the final solve bent away from their matches;
docs/ALGORITHM.md §F.5). A doubtful map is still written:
it is the starting point to repair (`hitl-slam serve OUT.hitl` shows those stretches). The
summary also counts unmatched and ambiguous scans, keyframes, loop closures accepted, rejected
and set aside as inconsistent with the others found with them, and the speed against the log's
own duration.
"""


def add_parser(sub: Commands) -> None:
    slam_cmd = sub.add_parser(
        "slam",
        help="build a map from a raw laser log with the scan-matching front end",
        description=(
            "Run the scan-matching front end over a raw laser log (CARMEN .clf/.log, optionally "
            ".gz/.bz2, or a ROS 1 / ROS 2 bag, read from its odometry whatever map -> odom it "
            "holds): every scan matched to the local map (correlative search, then "
            "point-to-line ICP), keyframes and submaps, loop closures found by branch and bound "
            "and weighed by dynamic covariance scaling. Writes the map: a session (.hitl, ready "
            "for `hitl-slam serve`) or any export format."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    slam_cmd.add_argument(
        "log", metavar="LOG", help="the raw log: CARMEN .clf/.log[.gz|.bz2], or a ROS bag"
    )
    add_max_range(slam_cmd)
    add_bag_options(slam_cmd)
    slam_cmd.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUT",
        help="output: .hitl (a session), .clf (a CARMEN log), .covars, .g2o, .pgm, ...",
    )
    slam_cmd.add_argument(
        "--keyframe-distance",
        type=float,
        default=0.2,
        metavar="M",
        help="a scan that moved this far since the last keyframe becomes one (default 0.2)",
    )
    slam_cmd.add_argument(
        "--keyframe-angle",
        type=float,
        default=10.0,
        metavar="DEG",
        help="... or turned this much (default 10)",
    )
    slam_cmd.add_argument(
        "--match-range",
        type=float,
        default=20.0,
        metavar="M",
        help="points farther than this are not matched (default 20)",
    )
    slam_cmd.add_argument(
        "--loop-min-score",
        type=float,
        default=0.55,
        metavar="S",
        help="a loop closure needs this correlative score, 0..1 (default 0.55)",
    )
    add_force(slam_cmd)
    slam_cmd.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    slam_cmd.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hitl_slam.slam import slam

    for option, value in (
        ("--keyframe-distance", args.keyframe_distance),
        ("--match-range", args.match_range),
        ("--loop-min-score", args.loop_min_score),
    ):
        # Checked here so that the message names the option typed, not the library's argument.
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"{option} must be a positive number, got {value:g}")
    out = Path(args.output)
    check_map_output(out, (".hitl",))
    refuse_overwriting_inputs(outputs_of(out), [args.log], args.force)
    if out.suffix.lower() == ".hitl" and out.exists():
        raise InputError(
            f"{out}: already exists; a session file is never overwritten: choose another name or "
            "delete the old one"
        )
    from hitl_slam.io.rosbag import is_rosbag

    if is_rosbag(args.log):
        args.map_frame = ""  # the front end starts from the odometry, not the bag's own SLAM
    raw = load_map(args, args.log)
    if not args.quiet:
        print(f"{args.log}: {raw.num_poses} scans, {raw.num_points} points")
    bar = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=raw.num_poses, desc="front end", unit="scan", file=sys.stderr)
    duration = (
        None
        if raw.timestamps is None or raw.num_poses < 2
        else float(raw.timestamps[-1] - raw.timestamps[0])
    )
    started = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if bar is None:
            return
        bar.n = done
        elapsed = time.perf_counter() - started
        if duration is not None and elapsed > 0 and total > 0:
            bar.set_postfix_str(f"{duration * done / total / elapsed:.1f}x real time")
        bar.refresh()

    try:
        result = slam(
            raw,
            progress=progress,
            keyframe_distance=args.keyframe_distance,
            keyframe_angle_deg=args.keyframe_angle,
            max_range=args.match_range,
            loop_min_score=args.loop_min_score,
        )
    finally:
        if bar is not None:
            bar.close()
    if out.suffix.lower() == ".hitl":
        from hitl_slam.session import Session

        with Session.new(result.map) as session:
            session.write_journal(out)
    else:
        from hitl_slam.io.export import export

        kept = result.accepted_map()  # a pose graph holds what the front end trusted
        with_progress("writing", args.quiet, lambda: export(kept, kept.poses, out))
    print(f"{result.summary()}; wrote {out}")
    return 0
