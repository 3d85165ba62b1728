#!/usr/bin/env python
"""The front end from ROS bags made from the raw Intel log (issue 14): the log's scans and
odometry written as a ROS 1 bag and a ROS 2 bag (sqlite3) with rosbags' writers (TF layout:
`/tf` odom -> base_link, the laser at base_link), each run through `hitl_slam.slam.slam` as a
user would (`hitl-slam slam intel.bag`), scored against the log's relations next to the run
from the CARMEN log itself. Meant to run as

    python benches/frontend_bags.py --write benches/README.md

Needs the [ros] extra. Intel data: D. Haehnel, via the SLAM benchmark of Kuemmerle et al. 2009.
"""

from __future__ import annotations

import argparse
import bz2
import math
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LASER = ROOT.parent / "shared" / "datasets" / "laser"
sys.path.insert(0, str(ROOT / "tests"))


def intel_bag(folder: Path, kind: str) -> Path:
    from bag_support import Bag, Scan, Transform, seconds_to_ns, write_bag
    from hitl_slam.io.carmen import read_carmen

    reference = read_carmen(LASER / "intel.clf.bz2")
    limit = float(reference.metadata["flaser_max_range"]) - 1e-3
    scans, tf = [], []
    with bz2.open(LASER / "intel.clf.bz2", "rt") as f:
        k = 0
        for line in f:
            tokens = line.split()
            if not tokens or tokens[0] != "FLASER":
                continue
            n = int(tokens[1])
            r = np.array(tokens[2 : 2 + n], dtype=np.float64)
            step = math.pi / (n - 1) if n in (181, 361) else math.pi / n
            stamp = seconds_to_ns(float(tokens[8 + n]))
            valid = np.isfinite(r) & (r > 0) & (r < limit)
            record = 10**18 + k * 10**7  # the log's order (Intel's stamps are not monotone)
            scans.append(
                Scan(
                    stamp=stamp,
                    ranges=np.where(valid, r, np.inf),
                    angle_min=-math.pi / 2,
                    angle_increment=step,
                    range_min=0.0,
                    range_max=limit + 1e-3,
                    frame="base_link",
                    record=record,
                )
            )
            pose = reference.poses[k]
            tf.append([Transform(stamp, "odom", "base_link", tuple(pose), record=record)])
            k += 1
    bag = Bag(scans=scans)
    bag.tf = tf
    return write_bag(bag, folder / f"intel-{kind}", kind)


def main(argv: Sequence[str] | None = None) -> int:
    import compare_gtsam as shared
    from hitl_slam.io.relations import read_relations
    from hitl_slam.metrics import relations_error
    from hitl_slam.slam import slam

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--write", type=Path, metavar="README", help="replace the section")
    args = parser.parse_args(argv)
    relations = read_relations(LASER / "intel.relations")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sources = [("CARMEN log intel.clf.bz2", LASER / "intel.clf.bz2")]
        for kind, label in (("ros1", "ROS 1 bag (.bag)"), ("sqlite3", "ROS 2 bag (sqlite3)")):
            print(f"writing the {label} ...", file=sys.stderr)
            sources.append((label, intel_bag(Path(tmp), kind)))
        for label, path in sources:
            print(f"front end on the {label} ...", file=sys.stderr)
            result = slam(path)
            err = relations_error(result.map, None, relations)
            rows.append((label, result, err))
    base = float(rows[0][2].translation.mean())
    lines = [
        "| input | scans | keyframes | loop closures kept / rejected | translation (m) | "
        "rotation (deg) | translation / the log's |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, result, err in rows:
        loops = result.loop_closures
        lines.append(
            f"| {label} | {result.map.num_poses} | {result.keyframes.size} | "
            f"{int(loops.accepted.sum())} / {int((~loops.accepted).sum())} | "
            f"{err.translation.mean():.4f} +- {err.translation.std():.4f} | "
            f"{err.rotation_deg.mean():.3f} +- {err.rotation_deg.std():.3f} | "
            f"{err.translation.mean() / base:.3f} |"
        )
    body = "\n".join(
        [
            *shared.provenance(),
            "",
            "The raw Intel log, and ROS bags written from it by rosbags' writers (TF layout), "
            "each through the front end with its defaults; relation errors against "
            "intel.relations (Kuemmerle et al. 2009; Intel data: D. Haehnel). Target: the bags "
            "within 5% of each other.",
            "",
            *lines,
        ]
    )
    print(body)
    if args.write:
        shared.replace_section(args.write, "frontend-bags", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
