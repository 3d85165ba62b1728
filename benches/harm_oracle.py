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
    python benches/harm_oracle.py --linear                               # the linear chain below

`--linear` is the same question on the simplest model where the answer is exact: a chain of N
headings dead-reckoned from independent unit-variance turns, and one true, noise-free statement
fixing the heading between poses i and j, applied by the exact Gaussian update (the minimum of
odometry plus statement). Over many draws it counts how often the error of the headings (RMS,
best constant offset removed, as ATE aligns) grows, and how often its Mahalanobis norm under the
odometry's covariance does: the update is the orthogonal projection onto the statement in that
norm, so that never grows, and every other norm can.
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


def linear(draws: int = 20000, n: int = 200, seed: int = 0) -> str:
    """The table of ``--linear`` (see the module's docstring)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    chain = np.tril(np.ones((n, n)))  # heading k = sum of the turns before it
    cov = chain @ chain.T
    weight = np.linalg.inv(cov)
    lines = [
        "| statement between poses | error grows by > 5% | grows at all | Mahalanobis norm grows "
        "| mean error after / before |",
        "|---|---|---|---|---|",
    ]

    def rms(e: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.sqrt(((e - e.mean(axis=1, keepdims=True)) ** 2).mean(axis=1))
        return out

    for i, j in ((20, 180), (50, 150), (90, 110), (10, 60)):
        h = np.zeros(n)
        h[j], h[i] = 1.0, -1.0
        gain = cov @ h / (h @ cov @ h)
        before = rng.normal(size=(draws, n)) @ chain.T  # dead reckoning minus the truth
        after = before - np.outer(before @ h, gain)
        r0, r1 = rms(before), rms(after)
        m0 = np.einsum("ti,ij,tj->t", before, weight, before)
        m1 = np.einsum("ti,ij,tj->t", after, weight, after)
        lines.append(
            f"| {i} and {j} | {np.mean(r1 > 1.05 * r0):.1%} | {np.mean(r1 > r0):.1%} | "
            f"{np.mean(m1 > m0 * (1 + 1e-9)):.1%} | {r1.mean() / r0.mean():.2f} |"
        )
    return "\n".join(lines)


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
    parser.add_argument("--linear", action="store_true", help="the linear chain only (seconds)")
    args = parser.parse_args(argv)
    if args.linear:
        print(linear())
        return 0
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
