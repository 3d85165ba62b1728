"""How well one scan's points on a wall place its pose (docs/ALGORITHM.md §I.20).

For every pass of the evaluation's maps by a wall (the simulated person's visits, on the TRUE
poses), fit the pass's line and take, per pose, the mean offset of that pose's points from it.
If a pose's points were independent with their own scatter, the offsets would spread as
scatter / sqrt(n). The excess is the error all of a scan's points share (the wall's bends and
roughness, the sensor's calibration, the pseudo ground truth's pose errors on real logs):

    sigma_scan^2 = mean(offset^2 - within_variance / n)

    python benches/scan_floor.py              # every map of the full evaluation
    python benches/scan_floor.py --maps Seattle Orebro
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np


def scan_floor(label: str, seed: int = 0) -> dict[str, float]:
    """The figures of one map: pose-passes, median points per pose, median point scatter,
    RMS pose offset and the shared error [m]."""
    from hitl_slam.full_evaluation import _base_scenario
    from hitl_slam.sim.careful import CarefulPerson
    from hitl_slam.sim.scenario import Scenario, fit_points

    scenario = _base_scenario(label, seed)
    assert isinstance(scenario, Scenario)
    person = CarefulPerson(scenario, 0)
    m = scenario.map
    owner = m.pose_of_point()
    offsets, within, counts = [], [], []
    for visit in person.visits:
        lo, hi = m.offsets[visit.first], m.offsets[visit.last + 1]
        idx = lo + np.flatnonzero(scenario.wall_of_point[lo:hi] == visit.wall)
        pts = person._points(scenario.truth, visit)
        fit = fit_points(pts)
        d = (pts - np.asarray(fit.centre)) @ np.asarray(fit.normal)
        own = owner[idx]
        for i in np.unique(own):
            di = d[own == i]
            if di.size >= 8:
                offsets.append(float(di.mean()))
                within.append(float(di.var(ddof=1)))
                counts.append(di.size)
    o, w, n = (np.asarray(v, dtype=np.float64) for v in (offsets, within, counts))
    shared = float(np.mean(o**2 - w / n))
    return {
        "pose_passes": float(o.size),
        "median_points": float(np.median(n)),
        "scatter": float(np.sqrt(np.median(w))),
        "offset_rms": float(np.sqrt(np.mean(o**2))),
        "sigma_scan": float(np.sqrt(max(shared, 0.0))),
    }


def main(argv: Sequence[str] | None = None) -> int:
    from hitl_slam.full_evaluation import FULL_MAPS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--maps", nargs="+", default=list(FULL_MAPS), choices=FULL_MAPS)
    ap.add_argument("--seed", type=int, default=0, help="the generated worlds' seed")
    args = ap.parse_args(argv)
    print(
        "| map | pose-passes | median points per pose | point scatter (cm) "
        "| pose offset RMS (cm) | shared, sigma_scan (cm) |"
    )
    print("|---|---|---|---|---|---|")
    for label in args.maps:
        f = scan_floor(label, args.seed)
        print(
            f"| {label} | {f['pose_passes']:.0f} | {f['median_points']:.0f} | "
            f"{100 * f['scatter']:.1f} | {100 * f['offset_rms']:.2f} | "
            f"{100 * f['sigma_scan']:.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
