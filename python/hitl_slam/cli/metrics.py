"""``hitl-slam metrics``: score a map: inconsistency (m^2), and the error against
ground-truth relations."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hitl_slam.cli.common import (
    BAGS_NOTE,
    add_bag_options,
    add_force,
    add_max_range,
    load_map,
    refuse_overwriting_inputs,
    with_progress,
)
from hitl_slam.errors import InputError
from hitl_slam.extras import require

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands

EPILOG = """\
examples:
  hitl-slam metrics fixed.covars
  hitl-slam metrics fr079.clf.bz2 --relations fr079.relations
  hitl-slam metrics restamped.bag --relations fr079.relations --tolerance 0.05
  hitl-slam metrics run.hitl --heat-map run-heat.png

MAP is a .covars file, a CARMEN log (.clf/.log, optionally .gz/.bz2), a ROS bag (.bag, .db3,
.mcap or a ROS 2 bag directory) or a session (.hitl, its current map). Inconsistency (Nashed and
Biswas 2018): summed over ordered pairs of scans, the area one scan sees as free space and the
other as occupied, on a grid of --resolution cells, in m^2 (lower is better; a perfect map scores
near zero). With --relations (Kuemmerle et al. 2009, "t1 t2 dx dy dz roll pitch yaw" lines
matched to the nearest scans by timestamp): mean +- standard deviation of |t_est - t_true| (m)
and |yaw_est - yaw_true| (deg) of the relative poses. A relation with a timestamp farther than
--tolerance (default 0.001 s) from every scan is skipped: the line says how many were matched and
how many skipped, so a cut log scores on what it kept, and a larger --tolerance scores a log whose
stamps moved (e.g. re-stamped by 0.02 s: --tolerance 0.05, below half the scan period).
--heat-map draws the per-cell count of contradicting scan pairs over the map as a PNG.
"""


def add_parser(sub: Commands) -> None:
    metrics = sub.add_parser(
        "metrics",
        help="score a map: inconsistency (m^2), and the error against ground-truth relations",
        description="Measure a map's global consistency and, given relations, its accuracy.",
        epilog=EPILOG + BAGS_NOTE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    metrics.add_argument(
        "map", metavar="MAP", help="input map (.covars, .clf/.log, ROS bag, .hitl)"
    )
    add_max_range(metrics)
    add_bag_options(metrics)
    metrics.add_argument(
        "--relations", metavar="R", help="ground-truth relations (.relations) for the map's log"
    )
    metrics.add_argument(
        "--tolerance",
        type=float,
        metavar="SECONDS",
        help="match each relation's timestamps to the nearest scan within this many seconds "
        "(default 0.001); relations farther from every scan are skipped and counted",
    )
    metrics.add_argument("--heat-map", metavar="OUT.png", help="write the per-cell heat map")
    metrics.add_argument(
        "--resolution", type=float, metavar="M", help="grid cell size in metres (default 0.05)"
    )
    add_force(metrics)
    metrics.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    metrics.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hitl_slam.config import DEFAULT
    from hitl_slam.io.relations import read_relations
    from hitl_slam.metrics import inconsistency, relations_error

    heat_path = None if args.heat_map is None else Path(args.heat_map)
    if heat_path is not None and heat_path.suffix.lower() != ".png":
        raise InputError(f"{heat_path}: the heat map is written as PNG; give a .png file name")
    if heat_path is not None:
        require("plot", "hitl-slam metrics --heat-map")
        refuse_overwriting_inputs([heat_path], [args.map, args.relations], args.force)
    config = DEFAULT
    if args.resolution is not None:
        if not (math.isfinite(args.resolution) and args.resolution > 0):
            raise InputError(
                f"--resolution must be a positive number of metres, got {args.resolution}"
            )
        config = DEFAULT.replace(grid_resolution=args.resolution)
    if args.tolerance is not None and args.relations is None:
        raise InputError("--tolerance goes with --relations; add the relations file, or drop it")
    tolerance = 1e-3 if args.tolerance is None else args.tolerance
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise InputError(f"--tolerance must be a number of seconds >= 0, got {args.tolerance}")
    # Read before the (slower) map, so a bad relations file fails fast.
    relations = None if args.relations is None else read_relations(args.relations)
    the_map = load_map(args, args.map)
    if the_map.num_points == 0:
        # The metric counts disagreeing points; with none it would read a perfect 0.
        raise InputError(
            f"{args.map}: the map has no points ({the_map.num_poses} poses, every reading a "
            "no-return or invalid), so its inconsistency cannot be scored: check the laser's "
            "range fields (or --max-range) and the file"
        )
    # Matched before the metric runs, so relations that do not fit the map fail before any output.
    err = (
        None
        if relations is None
        else relations_error(the_map, None, relations, tolerance=tolerance)
    )
    t0 = time.perf_counter()
    result = with_progress(
        "inconsistency", args.quiet, lambda: inconsistency(the_map, None, config)
    )
    elapsed = time.perf_counter() - t0
    height, width = result.heat.shape
    print(f"{args.map}: {the_map.num_poses} poses, {the_map.num_points} points")
    print(
        f"inconsistency: {result.total_m2:.3f} m^2 ({width} x {height} cells of "
        f"{result.resolution:g} m, {elapsed:.2f} s)"
    )
    if err is not None:
        print(
            f"relations: {err.matched} matched, {err.skipped} skipped (no scan within "
            f"{err.tolerance:g} s), translation {err.translation_mean:.4f} +- "
            f"{err.translation_std:.4f} m (max {err.translation_max:.4f}), rotation "
            f"{err.rotation_mean_deg:.3f} +- {err.rotation_std_deg:.3f} deg "
            f"(max {err.rotation_max_deg:.3f})"
        )
    if heat_path is not None:
        from hitl_slam.plot import write_inconsistency_heat_map

        write_inconsistency_heat_map(the_map, result, heat_path)
        print(f"wrote {heat_path}")
    return 0
