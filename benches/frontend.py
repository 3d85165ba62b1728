#!/usr/bin/env python
"""The scan-matching front end alone (no human drawing) on the raw Intel and Freiburg 079 logs,
scored against their benchmark relations (Kuemmerle et al. 2009), next to the published figures
of Hess et al. 2016 (Table II): relation error mean and std (translation m, rotation deg), wall
and CPU time, real-time factor, peak memory. Meant to run as

    python benches/frontend.py --write benches/README.md

Each log runs in its own process (peak memory is that process's), one at a time.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LASER = ROOT.parent / "shared" / "datasets" / "laser"
LOGS = {
    "Intel Research Lab": ("intel.clf.bz2", "intel.relations"),
    "Freiburg bldg 79": ("fr079.clf.bz2", "fr079.relations"),
}
# Hess, Kohler, Rapp, Andor: "Real-Time Loop Closure in 2D LIDAR SLAM", ICRA 2016, Table II.
PUBLISHED = {
    "Intel Research Lab": {
        "Cartographer": "0.0229 +- 0.0239 m, 0.453 +- 1.335 deg",
        "Graph Mapping": "0.031 +- 0.026 m, 1.3 +- 4.7 deg",
    },
    "Freiburg bldg 79": {
        "Cartographer": "0.0452 +- 0.0354 m, 0.538 +- 0.718 deg",
        "Graph Mapping": "0.056 +- 0.042 m, 0.6 +- 0.6 deg",
    },
}


def run_one(log: str, relations: str) -> dict[str, object]:
    from hitl_slam.io.carmen import read_carmen
    from hitl_slam.io.relations import read_relations
    from hitl_slam.metrics import relations_error
    from hitl_slam.slam import slam

    raw = read_carmen(LASER / log)
    wall, cpu = time.perf_counter(), time.process_time()
    result = slam(raw)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    err = relations_error(result.map, None, read_relations(LASER / relations))
    duration = float(raw.timestamps[-1] - raw.timestamps[0]) if raw.timestamps is not None else 0
    return {
        "scans": raw.num_poses,
        "keyframes": int(result.keyframes.size),
        "loops": int(result.loop_closures.accepted.sum()),
        "rejected": int((~result.loop_closures.accepted).sum()),
        "trans_mean": float(err.translation.mean()),
        "trans_std": float(err.translation.std()),
        "rot_mean": float(err.rotation_deg.mean()),
        "rot_std": float(err.rotation_deg.std()),
        "relations": int(err.translation.size),
        "wall_s": wall,
        "cpu_s": cpu,
        "duration_s": duration,
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def main(argv: Sequence[str] | None = None) -> int:
    import compare_gtsam as shared

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--write", type=Path, metavar="README", help="replace the section")
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(*args.one)))
        return 0
    rows = []
    for name, (log, rel) in LOGS.items():
        if not (LASER / log).is_file():
            print(f"skipping {name}: {LASER / log} not found", file=sys.stderr)
            continue
        print(f"{name} ...", file=sys.stderr)
        out = subprocess.run(
            [sys.executable, __file__, "--one", log, rel],
            check=True,
            capture_output=True,
            text=True,
            env={"PYTHONPATH": str(ROOT / "benches"), **dict(__import__("os").environ)},
        ).stdout
        rows.append((name, json.loads(out.strip().splitlines()[-1])))
    lines = [
        "| log | scans | keyframes | loop closures kept / rejected | relations | translation (m) "
        "| rotation (deg) | wall (s) | CPU (s) | real time (CPU) | peak memory (MiB) | published "
        "(Hess et al. 2016, Table II) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        pub = "; ".join(f"{k}: {v}" for k, v in PUBLISHED[name].items())
        lines.append(
            f"| {name} | {r['scans']} | {r['keyframes']} | {r['loops']} / {r['rejected']} | "
            f"{r['relations']} | {r['trans_mean']:.4f} +- {r['trans_std']:.4f} | "
            f"{r['rot_mean']:.3f} +- {r['rot_std']:.3f} | {r['wall_s']:.0f} | {r['cpu_s']:.0f} | "
            f"{r['duration_s'] / r['cpu_s']:.0f}x | {r['peak_mib']:.0f} | {pub} |"
        )
    body = "\n".join(
        [
            *shared.provenance(),
            "",
            "The front end alone, no human drawing, default settings (`hitl_slam.slam.slam`), "
            "each log in its own process; relation errors against the benchmark relations. "
            "Real time: the log's duration over the front end's CPU time (it runs on one core).",
            "",
            *lines,
            "",
            "Data: the Intel Research Lab (D. Haehnel) and Freiburg building 079 (C. Stachniss) "
            "logs and their relations, from the SLAM benchmark of Kuemmerle et al. 2009; thanks "
            "to their authors.",
        ]
    )
    print(body)
    if args.write:
        shared.replace_section(args.write, "frontend", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
