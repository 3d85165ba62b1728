"""``hitl-slam export``: convert a map or session to another format, or a session to its
corrections."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from hitl_slam.cli.common import (
    BAGS_NOTE,
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
  hitl-slam export run.hitl -o run.covars        # the session's current map
  hitl-slam export run.hitl -o run.jsonl         # its applied corrections, replayable
  hitl-slam export run.clf.gz -o run.pgm         # occupancy grid (+ run.yaml for map_server)
  hitl-slam export map.covars -o map.txt         # trajectory, TUM: t x y z qx qy qz qw
  hitl-slam export run.hitl -o fixed.clf         # a CARMEN log with the corrected poses
  hitl-slam export run.hitl -o run.png           # a picture of the map (.png or .svg)

MAP_OR_SESSION is a .covars file, a CARMEN log (.clf/.log, optionally .gz/.bz2), a ROS bag (.bag,
.db3, .mcap or a ROS 2 bag directory) or a session (.hitl). OUT's extension picks the format:
.covars, .clf (the map's own CARMEN log with only its poses changed, or one ROBOTLASER1 line per
scan when the map did not come from one), .g2o, .txt, .pgm, .png or .svg (a figure, needs the
plot extra), or .jsonl (corrections; only from a session, whose file is read and never changed).
OUT may not be the input (the same file, also through a link) unless --force.
"""


def add_parser(sub: Commands) -> None:
    export = sub.add_parser(
        "export",
        help="convert a map or session to another format, or a session to its corrections",
        description="Write a map or a session's current map in another format.",
        epilog=EPILOG + BAGS_NOTE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    export.add_argument(
        "input",
        metavar="MAP_OR_SESSION",
        help="input map (.covars, .clf/.log, ROS bag) or session (.hitl)",
    )
    add_max_range(export)
    add_bag_options(export)
    export.add_argument("-o", "--output", required=True, metavar="OUT", help="output file")
    add_force(export)
    export.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    export.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    check_map_output(out, (".jsonl",))
    source = Path(args.input)
    refuse_overwriting_inputs(outputs_of(out), [source], args.force)
    if out.suffix.lower() == ".jsonl":
        from hitl_slam.session import Session

        if source.suffix.lower() != ".hitl":
            raise InputError(
                f"{source}: corrections (.jsonl) come from a session; give a .hitl session file "
                "as input"
            )
        with Session.open(source) as session:
            count = session.export_corrections(out)
        print(f"wrote {out}: {count} corrections from {source}")
        return 0
    from hitl_slam.io.export import export

    the_map = load_map(args, source)
    with_progress("writing", args.quiet, lambda: export(the_map, the_map.poses, out))
    print(f"wrote {out}: {the_map.num_poses} poses, {the_map.num_points} points from {source}")
    return 0
