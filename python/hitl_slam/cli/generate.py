"""``hitl-slam generate``: write a synthetic Manhattan-world pose graph (with ground truth)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands

EPILOG = """\
examples:
  hitl-slam generate manhattan.g2o                 # 1000 poses, seed 0
  hitl-slam generate big.g2o --poses 20000 --seed 3

Writes a Manhattan-world pose graph (a robot driving on a grid, noisy odometry, loop closures at
revisited cells) whose vertices are the composed odometry, and the ground truth next to it as
OUT.truth.txt (one "x y theta" line per pose).
"""


def add_parser(sub: Commands) -> None:
    generate = sub.add_parser(
        "generate",
        help="write a synthetic Manhattan-world pose graph (with ground truth)",
        description="Generate a synthetic 2D pose graph to try the solver on.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    generate.add_argument("output", metavar="OUT", help="output file (.g2o or .graph)")
    generate.add_argument("--poses", type=int, default=1000, metavar="N", help="default 1000")
    generate.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    generate.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from hitl_slam.io import save_graph
    from hitl_slam.io.atomic import atomic_outputs, atomic_write_text
    from hitl_slam.sim.synthetic import manhattan_world

    out = Path(args.output)
    graph, truth = manhattan_world(args.poses, seed=args.seed)
    truth_path = out.with_suffix(".truth.txt")
    with atomic_outputs():  # both files or neither
        save_graph(graph, graph.poses, out)
        text = "".join(f"{x!r} {y!r} {t!r}\n" for x, y, t in truth.tolist())
        atomic_write_text(truth_path, text)
    err = np.hypot(*(graph.poses[:, :2] - truth[:, :2]).T)
    print(
        f"wrote {out}: Manhattan world, {graph.num_poses} poses, {graph.num_edges} edges "
        f"(odometry drift up to {err.max():.2f} m), ground truth in {truth_path}"
    )
    return 0
