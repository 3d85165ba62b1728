"""Would matching the scans again, after the person's corrections, bring the map to the truth?

An experiment for issue 11 (docs/ALGORITHM.md §I.7), not a feature: each run of the full
evaluation (`hitl_slam.full_evaluation.evaluate_run`) is repaired by the careful person as there;
from the session's last state the scan-matching front end (docs/ALGORITHM.md §F,
`hitl_slam.slam.slam`) is run with the corrected poses as its odometry (its map alone is one
row), then the session aligns the map with its scans (`Session.align`, §I.11: that front end's
graph replaces the map's factors and every correction is solved again over it), or its guard
refuses. Reported per run: ATE, mean wall-angle error, mean spacing error and inconsistency, and
the figure the guard judges by without the truth: the share of the map's odometry steps the
poses contradict beyond the 99.9% chi2 bound (3 degrees of freedom) under the odometry's own
information.

    python benches/scan_alignment.py                      # the default runs
    python benches/scan_alignment.py --runs "Seattle/jump/0.05" "campus/drift/0.05"
    python benches/scan_alignment.py --write benches/README.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RUNS = (
    "Seattle/jump/0.05",
    "Intel lab/drift/0.15",
    "Orebro/jump/0.05",
    "Edmonton/jump/0.05",
    "Belgioioso/bend/0.15",
    "lost poses room/jump/0.15",
    "campus/drift/0.05",
)


def run_one(spec: str) -> dict[str, Any]:
    from hitl_slam.alignment import AlignmentRefused, contradicted
    from hitl_slam.config import DEFAULT
    from hitl_slam.full_evaluation import evaluate_run
    from hitl_slam.metrics import ate, inconsistency
    from hitl_slam.slam import slam

    label, fault, noise = spec.split("/")
    out: dict[str, Any] = {"run": spec}

    def at_end(scenario: Any, session: Any) -> None:
        m, truth = scenario.map, scenario.truth
        first = inconsistency(m, m.poses, DEFAULT)

        def share(k: int, n: int) -> float:
            return k / max(n, 1)

        def score(name: str, poses: np.ndarray) -> None:
            e = scenario.errors(poses)
            out[name] = {
                "ate": float(ate(poses, truth)),
                "angle": float(np.nanmean(e.angular)),
                "spacing": float(np.nanmean(e.translational)),
                "inc": float(inconsistency(m, poses, DEFAULT, like=first).total_m2),
                "contradicted": share(*contradicted(m, poses)),
            }

        corrected = np.array(session.poses)
        score("truth", truth)
        score("corrected", corrected)
        front = slam(dataclasses.replace(m, poses=corrected))
        score("front end", front.map.poses)
        try:
            session.align()
        except AlignmentRefused as exc:
            out["refused"] = str(exc)
            score("aligned (refused)", corrected)
        else:
            score("aligned", np.array(session.poses))

    evaluate_run(label, fault, float(noise), seed=0, on_end=at_end, align=False)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    import compare_gtsam as shared

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", nargs="+", default=list(DEFAULT_RUNS), metavar="MAP/FAULT/NOISE")
    parser.add_argument("--write", type=Path, metavar="README", help="replace the section")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one)))
        return 0
    lines = [
        "| run | map | ATE (m) | angle (deg) | spacing (m) | inconsistency (m^2) "
        "| odometry steps contradicted |",
        "|---|---|---|---|---|---|---|",
    ]
    for spec in args.runs:
        print(f"{spec} ...", file=sys.stderr, flush=True)
        text = subprocess.run(
            [sys.executable, __file__, "--one", spec],
            check=True,
            capture_output=True,
            text=True,
            env={"PYTHONPATH": str(ROOT / "benches"), **dict(__import__("os").environ)},
        ).stdout
        r = json.loads(text.strip().splitlines()[-1])
        for name in ("truth", "corrected", "front end", "aligned", "aligned (refused)"):
            if name not in r:
                continue
            v = r[name]
            lines.append(
                f"| {spec.replace('/', ', ')} | {name} | {v['ate']:.3f} | {v['angle']:.2f} | "
                f"{v['spacing']:.3f} | {v['inc']:.1f} | {100 * v['contradicted']:.1f}% |"
            )
        print("\n".join(lines[-4:]), file=sys.stderr, flush=True)
    body = "\n".join(
        [
            *shared.provenance(),
            "",
            "Seed 0 of the full evaluation; noise is the person's endpoint noise in m. "
            "`corrected`: the map after the careful person's corrections; `front end`: the "
            "scan-matching front end run again from it, alone; `aligned`: `Session.align` (that "
            "graph with every correction in effect), or `aligned (refused)` where its guard "
            "refused (the map stays as corrected). The last column: the share of the damaged "
            "map's odometry steps that the poses contradict beyond the 99.9% chi2 bound (that "
            "guard refuses above 5%; the others refuse without a loop closure kept, or without "
            "a fall in inconsistency).",
            "",
            *lines,
            "",
            "Data: the Intel Research Lab, Freiburg building 079, Seattle, Orebro, Belgioioso and "
            "Edmonton corrected logs, via Radish (thanks to their authors: D. Haehnel, "
            "C. Stachniss, and the Freiburg SLAM benchmark of Kuemmerle et al. 2009; the "
            "corrected CARMEN versions from the acschaefer/ple repository).",
        ]
    )
    print(body)
    if args.write:
        shared.replace_section(args.write, "scan_alignment", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
