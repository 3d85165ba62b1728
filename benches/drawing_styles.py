"""The full evaluation with a person who draws in another style (docs/ALGORITHM.md §I.16).

The careful person of `hitl-slam evaluate --full` puts each stroke's ends at the ends of the copy
they see, with Gaussian endpoint noise. People draw otherwise too: past the ends of a wall (a
stroke run on into the corner), and beside it (the whole stroke a little to one side). This runs
`hitl_slam.full_evaluation.run_full` with such a person (`CarefulPerson(overshoot=, side=)`) at a
seed and noise of your choice, and prints the acceptance figures, the refusal reasons and the
runs that ended worst, to compare with the standard person's (docs/evaluation/full*.md).

    python benches/drawing_styles.py --seed 5 --noise 0.10 --overshoot 0.4 --side 0.2 -j 2
    python benches/drawing_styles.py --seed 7 --noise 0.05 --side 0.2 --maps Seattle Orebro
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
from collections.abc import Sequence


def report(runs: Sequence[object]) -> str:
    from hitl_slam.full_evaluation import summary

    s = summary(runs)  # type: ignore[arg-type]
    lines = [
        f"drawings {s['drawings']:.0f}, accepted {100 * s['accepted_share']:.2f}%, "
        f"worse beyond the noise {s['worse_beyond_noise']:.0f}, "
        f"of the achievable {100 * s['achieved']:.0f}%, angle {s['angle_after']:.2f} deg, "
        f"spacing {s['spacing_after']:.3f} m"
    ]
    why: collections.Counter[str] = collections.Counter()
    for r in runs:
        for d in r.drawings:  # type: ignore[attr-defined]
            if not d.accepted:
                why[re.sub(r"[-0-9.]+", "#", d.reason)[:100]] += 1
    lines += [f"  refused {n}: {w}" for w, n in why.most_common(5)]
    worst = sorted(runs, key=lambda r: -r.angle[1])[:5]  # type: ignore[attr-defined]
    lines += [
        f"  {r.map}, {r.fault}: angle {r.angle[0]:.2f} -> {r.angle[1]:.2f} deg, "  # type: ignore[attr-defined]
        f"ATE {r.ate[0]:.3f} -> {r.ate[1]:.3f} m; alignment {r.alignment[:60]}"  # type: ignore[attr-defined]
        for r in worst
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from hitl_slam.full_evaluation import FULL_MAPS, run_full
    from hitl_slam.sim.careful import DrawingStyle

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--noise", type=float, default=0.10, help="endpoint noise [m]")
    ap.add_argument("--overshoot", type=float, default=0.4, help="[m] past each end, at most")
    ap.add_argument(
        "--side", type=float, default=0.2, help="[m] the stroke beside the wall, at most"
    )
    ap.add_argument("--maps", nargs="+", default=list(FULL_MAPS), choices=FULL_MAPS)
    ap.add_argument("-j", "--jobs", type=int, default=1)
    args = ap.parse_args(argv)
    runs = run_full(
        seed=args.seed,
        maps=args.maps,
        noises=(args.noise,),
        jobs=args.jobs,
        person_style=DrawingStyle(overshoot=args.overshoot, side=args.side),
        log=lambda r: print(f"{r.map}, {r.fault}: {r.angle[1]:.2f} deg", file=sys.stderr),
    )
    print(report(runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
