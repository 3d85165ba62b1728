"""Would a true correction still make its map worse if the engine knew what the person meant?

An experiment for issue 11's no-harm target (docs/ALGORITHM.md §I.14). The full evaluation
(`hitl_slam.full_evaluation.run_full`, the careful person, every map, fault and noise) is run with
up to three appliers, and the share of accepted corrections that made their map worse is compared:

- `pipeline`: hitl-slam's own (`hitl_slam.pipeline.apply_correction`), as `hitl-slam evaluate
  --full`;
- `oracle`: perfect data association: each drawing's observation sets are the labelled points of
  the two passes the person drew on, applied by the paper's explicit correction, back-propagation
  and joint solve, with no guard (`hitl_slam.sim.oracle.oracle_applier`);
- `oracle-model`: the same, with the odometry's information the truth's too (the noise the
  simulation drew, and each fault's own variance on the steps it hit).

    python benches/harm_oracle.py --seed 0 -j 2                          # all three, every map
    python benches/harm_oracle.py --seed 1 -j 2 --variants oracle --maps Seattle Orebro
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Sequence
from pathlib import Path

VARIANTS = ("pipeline", "oracle", "oracle-model")


def applier_for(variant: str) -> object:
    from hitl_slam.sim.oracle import oracle_applier

    if variant == "pipeline":
        return None
    return functools.partial(oracle_applier, error_model=variant == "oracle-model")


def row(variant: str, runs: Sequence[object]) -> str:
    from hitl_slam.full_evaluation import NOISE_FLOOR, summary

    s = summary(runs)  # type: ignore[arg-type]
    accepted = [d for r in runs for d in r.drawings if d.accepted]  # type: ignore[attr-defined]
    big = sum(
        d.ate[1] - d.ate[0] > 5 * NOISE_FLOOR[0] or d.angle[1] - d.angle[0] > 5 * NOISE_FLOOR[1]
        for d in accepted
    )
    n = max(len(accepted), 1)
    ate = sum(r.ate[1] for r in runs) / max(len(runs), 1)  # type: ignore[attr-defined]
    return (
        f"| {variant} | {s['accepted']:.0f} of {s['drawings']:.0f} | "
        f"{s['worse']:.0f} ({100 * s['worse'] / n:.1f}%) | "
        f"{s['worse_beyond_noise']:.0f} ({100 * s['worse_beyond_noise'] / n:.1f}%) | "
        f"{big} | {100 * s['achieved']:.0f}% | {s['angle_after']:.2f} | "
        f"{s['spacing_after']:.3f} | {ate:.3f} |"
    )


def _progress(variant: str, run: object) -> None:
    print(f"{variant}: {run.map}, {run.fault}, {run.noise_m}", file=sys.stderr)  # type: ignore[attr-defined]


def main(argv: Sequence[str] | None = None) -> int:
    from hitl_slam.full_evaluation import FULL_MAPS, run_full, runs_json

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--maps", nargs="+", default=list(FULL_MAPS), choices=FULL_MAPS)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("-j", "--jobs", type=int, default=1)
    parser.add_argument("--json", type=Path, help="write each variant's runs to DIR/VARIANT.json")
    args = parser.parse_args(argv)
    lines = [
        "| applier | accepted | worse (> 5%) | worse beyond the noise | by > 0.1 m or 1 deg "
        "| inconsistency reduction, of the achievable | angle (deg) | spacing (m) | ATE (m) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for variant in args.variants:
        runs = run_full(
            seed=args.seed,
            maps=args.maps,
            jobs=args.jobs,
            applier=applier_for(variant),  # type: ignore[arg-type]
            log=functools.partial(_progress, variant),
        )
        if args.json is not None:
            args.json.mkdir(parents=True, exist_ok=True)
            (args.json / f"{variant}.json").write_text(runs_json(runs))
        lines.append(row(variant, runs))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
