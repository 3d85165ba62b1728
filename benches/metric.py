#!/usr/bin/env python
"""Speed of the inconsistency metric (docs/ALGORITHM.md §6) on the Freiburg 079 corrected log
(4791 scans, 1.69 M points): one core and all cores, median of repeats. Meant to run as

    python benches/metric.py --write benches/README.md
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hitl_slam.io.carmen import read_carmen
from hitl_slam.metrics import inconsistency

ROOT = Path(__file__).resolve().parents[1]
FR079 = ROOT.parent / "shared" / "datasets" / "laser" / "freiburg-079-corrected.log.gz"


def main(argv: Sequence[str] | None = None) -> int:
    import compare_gtsam as shared

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--write", type=Path, metavar="README")
    args = parser.parse_args(argv)
    if not FR079.is_file():
        print(f"{FR079} not found", file=sys.stderr)
        return 2
    m = read_carmen(FR079)
    rows = []
    for threads, label in ((1, "one core"), (0, "all cores (rayon)")):
        times, value = [], 0.0
        for _ in range(args.repeats):
            t = time.perf_counter()
            value = inconsistency(m, threads=threads).total_m2
            times.append(time.perf_counter() - t)
        rows.append(
            f"| {label} | {statistics.median(times):.3f} | {min(times):.3f} | {value:.1f} |"
        )
    body = "\n".join(
        [
            *shared.provenance(),
            "",
            f"Freiburg 079 corrected log: {m.num_poses} scans, {m.num_points} points, grid 0.05 m; "
            f"median of {args.repeats} (target: under 1 s on one core).",
            "",
            "| threads | median (s) | best (s) | inconsistency (m^2) |",
            "|---|---|---|---|",
            *rows,
            "",
            "Data: Freiburg building 079 (Kuemmerle et al. 2009, via Radish); thanks to its "
            "authors.",
        ]
    )
    print(body)
    if args.write:
        shared.replace_section(args.write, "metric", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
