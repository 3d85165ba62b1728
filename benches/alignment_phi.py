"""How far should a person's statements yield to the scans when the map is aligned with them?

An experiment for issue 11 (docs/ALGORITHM.md §I.11, "Which Phi"): each run of the full
evaluation (`hitl_slam.full_evaluation.evaluate_run`) is repaired by the careful person as there;
from the session's last state the scan-matching front end is run with the corrected poses as its
odometry, and every correction is solved again over its graph twice, with each relation's dynamic
covariance scaling at `Config.align_relation_dcs` (the statements yield to the scans) and at
`Config.relation_dcs` (as firm as in every other solve). `Session.align` keeps the solve with the
lower inconsistency; this compares that choice with each Phi alone, against the truth. Figures
are before the alignment's guards (a run they would refuse is still counted).

    python benches/alignment_phi.py --seed 1 -j 2              # the five real logs, all runs
    python benches/alignment_phi.py --seed 2 --maps Orebro Seattle
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from multiprocessing import Pool
from typing import Any

import numpy as np

# The real logs on which the front end closes loops (on Edmonton it keeps none, and the alignment
# is refused there whatever the Phi).
MAPS = ("Intel lab", "Freiburg 079", "Seattle", "Orebro", "Belgioioso")
NOISES = (0.05, 0.15)
SOLVES = ("yield", "firm", "kept")
FIGURES = ("ate", "angle", "spacing", "inc")


def run_one(spec: tuple[str, str, float, int]) -> dict[str, Any]:
    from hitl_slam.alignment import aligned_config
    from hitl_slam.config import DEFAULT
    from hitl_slam.full_evaluation import evaluate_run
    from hitl_slam.metrics import ate, inconsistency
    from hitl_slam.pipeline import solve_all
    from hitl_slam.slam import slam

    label, fault, noise, seed = spec
    out: dict[str, Any] = {"run": f"{label}/{fault}/{noise}", "seed": seed}

    def at_end(scenario: Any, session: Any) -> None:
        m, truth = scenario.map, scenario.truth
        first = inconsistency(m, m.poses, DEFAULT)

        def figures(poses: np.ndarray) -> dict[str, float]:
            e = scenario.errors(poses)
            return {
                "ate": float(ate(poses, truth, align=True)),
                "angle": float(np.nanmean(e.angular)),
                "spacing": float(np.nanmean(e.translational)),
                "inc": float(inconsistency(m, poses, DEFAULT, like=first).total_m2),
                # what the alignment judges by (each on its own grid, without the truth)
                "own_inc": float(inconsistency(m, poses, DEFAULT).total_m2),
            }

        poses, active = np.array(session.poses), list(session.active)
        out["before"] = figures(poses)
        front = slam(dataclasses.replace(m, poses=np.ascontiguousarray(poses)))
        out["loop_closures"] = int(front.loop_closures.accepted.sum())
        graph = front.accepted_map()
        for name, phi in (("yield", DEFAULT.align_relation_dcs), ("firm", DEFAULT.relation_dcs)):
            x, _, _ = solve_all(graph, active, aligned_config(DEFAULT, phi), start=graph.poses)
            out[name] = figures(np.asarray(x))
        firm_wins = out["firm"]["own_inc"] < out["yield"]["own_inc"]
        out["kept"] = out["firm" if firm_wins else "yield"]
        out["kept_phi"] = DEFAULT.relation_dcs if firm_wins else DEFAULT.align_relation_dcs

    evaluate_run(label, fault, noise, seed=seed, align=False, on_end=at_end)
    return out


def _firm(r: dict[str, Any]) -> bool:
    from hitl_slam.config import DEFAULT

    return bool(r["kept_phi"] == DEFAULT.relation_dcs)


def _beyond(r: dict[str, Any], name: str, factor: float) -> bool:
    b, a = r["before"], r[name]
    return bool(a["ate"] > factor * b["ate"] or a["angle"] > factor * b["angle"])


def table(results: Sequence[dict[str, Any]]) -> str:
    lines = [
        "| solve over the aligned graph | ATE (m) | wall angle (deg) | spacing (m) | "
        "inconsistency (m^2) | runs worse by > 5% (ATE or angle) | by more than double |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in ("before", *SOLVES):
        rows = [r[name] for r in results]
        mean = {k: float(np.mean([row[k] for row in rows])) for k in FIGURES}
        worse = double = "-"
        if name != "before":
            worse = str(sum(_beyond(r, name, 1.05) for r in results))
            double = str(sum(_beyond(r, name, 2.0) for r in results))
        lines.append(
            f"| {name} | {mean['ate']:.3f} | {mean['angle']:.2f} | {mean['spacing']:.3f} | "
            f"{mean['inc']:.0f} | {worse} | {double} |"
        )
    firm = sum(_firm(r) for r in results)
    lines.append("")
    lines.append(f"{len(results)} runs; the firm solve kept on {firm}.")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from hitl_slam.sim.fault_models import FULL_FAULTS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--maps", nargs="+", default=list(MAPS), choices=MAPS)
    parser.add_argument("-j", "--jobs", type=int, default=1)
    parser.add_argument("--json", help="also write every run's figures here")
    args = parser.parse_args(argv)
    specs = [
        (label, fault, noise, args.seed)
        for label in args.maps
        for fault in FULL_FAULTS
        for noise in NOISES
    ]
    results = []
    with Pool(args.jobs) as pool:
        for r in pool.imap(run_one, specs):
            kept = "firm" if _firm(r) else "yield"
            print(
                f"{r['run']}: ATE {r['before']['ate']:.3f} -> yield {r['yield']['ate']:.3f}, "
                f"firm {r['firm']['ate']:.3f}; kept {kept}",
                file=sys.stderr,
                flush=True,
            )
            results.append(r)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(results, f, indent=1)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
