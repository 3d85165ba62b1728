"""`hitl-slam evaluate`: the paper's Results, reproduced in kind. Each scenario is a damaged map
with known truth; a simulated person repairs it one drawing at a time; we score the map before and
after (Table 1: angles and spacings between known wall pairs; the inconsistency metric; ATE) and
write a Markdown report with figures.

Scenarios: three generated worlds (the lost-poses room, parallel corridors, a campus) and the two
corrected real logs in ../shared/datasets/laser damaged by injected faults, whose walls are found
in the corrected map (pseudo ground truth) by RANSAC.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.map import Map

__all__ = ["ScenarioResult", "real_log_scenario", "run_evaluation", "table", "targets"]

FloatArray = NDArray[np.float64]
LASER = Path(__file__).resolve().parents[2].parent / "shared" / "datasets" / "laser"


@dataclass(frozen=True)
class ScenarioResult:
    name: str
    poses: int
    travel_m: float
    angle_samples: int
    spacing_samples: int
    angle_before: float
    angle_after: float
    spacing_before: float
    spacing_after: float
    inconsistency_before: float
    inconsistency_after: float
    inconsistency_truth: float  # the map on its true poses: what no repair can remove
    ate_before: float
    ate_after: float
    corrections: int
    rejections: int
    finished: bool
    time_s: float
    figure: Path | None
    real_log: bool = False  # a real log damaged by injected faults (else a generated world)

    @property
    def inconsistency_reduction(self) -> float:
        if self.inconsistency_before <= 0:
            return 0.0
        return 1.0 - self.inconsistency_after / self.inconsistency_before

    @property
    def achieved_fraction(self) -> float:
        """The reduction as a fraction of what the true poses reach,
        ``(before - after) / (before - truth)``: 1 is a repair as consistent as the truth (the
        real logs' scans disagree even on their true poses, so a plain reduction cannot reach 1
        there). NaN when the damage did not raise the inconsistency above the truth's."""
        gain = self.inconsistency_before - self.inconsistency_truth
        if gain <= 0:
            return float("nan")
        return (self.inconsistency_before - self.inconsistency_after) / gain

    @property
    def best_reduction(self) -> float:
        """The reduction the true poses themselves show: the most a perfect repair reaches."""
        if self.inconsistency_before <= 0:
            return 0.0
        return 1.0 - self.inconsistency_truth / self.inconsistency_before


MIN_SPACING = 0.5
"""A spacing pair on a real log is at least this far apart [m]: a corridor's or a room's width,
not two segments of one thick or doubled wall."""

MIN_FACING_OVERLAP = 1.0
"""... and its two walls face each other over at least this length [m] (or half the shorter
wall): the paper's spacings are widths across a corridor or a room, and between corridors
"constant along the length of the building". Two parallel walls tens of metres apart along
their direction do not measure a spacing: their centres' distance to each other's line is
dominated by the angle between them times that distance (0.3 deg over 57 m is 0.3 m), which
the angle pairs already score."""


def facing_overlap(points_a: FloatArray, points_b: FloatArray, phi: float) -> float:
    """How long [m] two nearly parallel walls face each other: the overlap of their points'
    extents (5th to 95th percentile) along the direction of a line with normal angle ``phi``."""
    direction = np.array([-math.sin(phi), math.cos(phi)])
    pa, pb = points_a @ direction, points_b @ direction
    lo = max(np.percentile(pa, 5), np.percentile(pb, 5))
    hi = min(np.percentile(pa, 95), np.percentile(pb, 95))
    return float(hi - lo)


def real_log_scenario(
    path: Path,
    *,
    faults: Callable[[int], Sequence[object]],
    name: str,
    seed: int = 0,
    max_pairs: int = 40,
    min_wall_length: float = 2.0,
    min_travel: float = 0.25,
    min_rotation: float = math.radians(10.0),
) -> object:
    """A :class:`~hitl_slam.sim.Scenario` from a corrected CARMEN log: the log's poses are the
    (pseudo) truth, the scans are the real ones, the map to repair is dead-reckoned from the
    true motions with odometry noise and ``faults(number of poses)``; walls and point labels
    come from RANSAC on the true map, and the known pairs are long walls that are parallel or
    perpendicular there (within 1 degree), with their measured angle as the true value, and the
    spacing of parallel walls that face each other (:data:`MIN_FACING_OVERLAP`,
    :data:`MIN_SPACING`). Scans are kept every ``min_travel`` metres or ``min_rotation``
    radians (keyframes), as SLAM front ends do."""
    from hitl_slam.io.carmen import read_carmen
    from hitl_slam.sim import FeaturePair, Floorplan, Lidar, Scenario
    from hitl_slam.sim.odometry import DEFAULT_NOISE, odometry
    from hitl_slam.sim.scenario import angle_between, fit_points, spacing_between
    from hitl_slam.sim.walls import extract_walls

    log = read_carmen(path, min_travel=min_travel, min_rotation=min_rotation)
    truth = log.poses.copy()
    injected = list(faults(log.num_poses))
    walls, labels = extract_walls(log.world_points(truth), seed=seed)
    rng = np.random.default_rng(seed)
    estimate = odometry(truth, rng, DEFAULT_NOISE, injected)  # type: ignore[arg-type]
    scans = [log.points[log.offsets[i] : log.offsets[i + 1]] for i in range(log.num_poses)]
    damaged = Map.from_poses_and_scans(estimate, scans, name=name, source=str(path))
    world = log.world_points(truth)
    fits, wall_points = {}, {}
    for w in range(len(walls)):
        pts = world[labels == w]
        length = math.hypot(walls[w, 2] - walls[w, 0], walls[w, 3] - walls[w, 1])
        if len(pts) >= 200 and length >= min_wall_length:
            fits[w], wall_points[w] = fit_points(pts), pts
    pairs, facing = [], []
    keys = sorted(fits)
    for x, i in enumerate(keys):
        for j in keys[x + 1 :]:
            ang = angle_between(fits[i], fits[j])
            if ang < 1.0:
                pairs.append(FeaturePair(i, j, "parallel", ang))
                spacing = FeaturePair(i, j, "spacing", spacing_between(fits[i], fits[j]))
                # every parallel pair stays a candidate of the draw below, so the angle pairs
                # drawn do not depend on which of them face each other
                pairs.append(spacing)
                overlap = facing_overlap(wall_points[i], wall_points[j], fits[i].phi)
                shorter = min(fits[i].extent, fits[j].extent)
                if spacing.value >= MIN_SPACING and overlap >= min(
                    MIN_FACING_OVERLAP, 0.5 * shorter
                ):
                    facing.append(spacing)
            elif ang > 89.0:
                pairs.append(FeaturePair(i, j, "perpendicular", ang))
    if not pairs:
        raise InputError(f"{path}: no long parallel or perpendicular walls found to score against")
    if len(pairs) > max_pairs:
        pick = np.sort(rng.choice(len(pairs), size=max_pairs, replace=False))
        pairs = [pairs[k] for k in pick]
    if len(facing) > max_pairs // 2:
        pick = np.sort(np.random.default_rng([seed, 1]).choice(len(facing), max_pairs // 2, False))
        facing = [facing[k] for k in pick]
    pairs = [p for p in pairs if p.kind != "spacing"] + facing
    names = tuple(f"wall{w}" for w in range(len(walls)))
    plan = Floorplan(name, walls, names, tuple(pairs))
    return Scenario(
        name=name,
        map=damaged,
        truth=truth,
        walls=walls,
        wall_names=names,
        wall_of_point=labels,
        feature_pairs=tuple(pairs),
        floorplan=plan,
        lidar=Lidar(),
        faults=tuple(injected),  # type: ignore[arg-type]
        seed=seed,
    )


def _ate(estimate: FloatArray, truth: FloatArray) -> float:
    from hitl_slam.metrics import ate

    return float(ate(estimate, truth, align=True))


def evaluate_scenario(
    scenario: object,
    out_dir: Path | None,
    *,
    seed: int = 0,
    max_corrections: int = 60,
    config: Config = DEFAULT,
    figures: bool = True,
    quick_human: bool = False,
) -> ScenarioResult:
    """Repairs one scenario with the simulated person and scores it before and after.

    ``quick_human``: the person commits each drawing after one look (no zooming in to redraw,
    each pair tried once), which keeps large real maps to minutes instead of tens of minutes."""
    from hitl_slam.metrics import inconsistency
    from hitl_slam.sim import Scenario, SimulatedHuman, repair

    if not isinstance(scenario, Scenario):
        raise InputError("evaluate_scenario needs a hitl_slam.sim.Scenario")
    start = time.perf_counter()
    m = scenario.map
    before = m.poses.copy()
    human = SimulatedHuman(
        scenario,
        seed,
        config=config,
        max_redraws=0 if quick_human else 2,
        max_attempts=1 if quick_human else 2,
    )
    result = repair(scenario, human, max_corrections=max_corrections)
    after = result.poses
    e0, e1 = scenario.errors(before), scenario.errors(after)
    inc0 = inconsistency(m, before, config)
    inc1 = inconsistency(m, after, config, like=inc0)
    inc_truth = inconsistency(m, scenario.truth, config, like=inc0)
    figure = None
    if figures and out_dir is not None:
        from hitl_slam.plot import write_before_after

        slug = re.sub(r"[^a-z0-9]+", "-", scenario.name.lower()).strip("-")
        figure = write_before_after(
            m,
            before,
            after,
            out_dir / f"{slug}.png",
            interpretations=[s.interpretation for s in result.corrections],
            drawn=[s.drawn for s in result.corrections],
            titles=(f"{scenario.name}: damaged", f"after {result.used} corrections"),
        )
    return ScenarioResult(
        name=scenario.name,
        poses=m.num_poses,
        travel_m=scenario.travel,
        angle_samples=int(e0.angular.size),
        spacing_samples=int(e0.translational.size),
        angle_before=_nanmean(e0.angular),
        angle_after=_nanmean(e1.angular),
        spacing_before=_nanmean(e0.translational),
        spacing_after=_nanmean(e1.translational),
        inconsistency_before=inc0.total_m2,
        inconsistency_after=inc1.total_m2,
        inconsistency_truth=inc_truth.total_m2,
        ate_before=_ate(before, scenario.truth),
        ate_after=_ate(after, scenario.truth),
        corrections=result.used,
        rejections=result.rejections,
        finished=result.finished,
        time_s=time.perf_counter() - start,
        figure=figure,
    )


def _nanmean(values: FloatArray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else math.nan


def table(results: Sequence[ScenarioResult]) -> str:
    """The Table-1-style summary, plus inconsistency (with what the true poses score), ATE and
    effort."""
    head = (
        "| map | poses | angle samples | angle error in (deg) | angle error out (deg) "
        "| spacing samples | spacing error in (m) | spacing error out (m) "
        "| inconsistency in (m^2) | out (m^2) | truth (m^2) | reduction | best possible "
        "| of achievable | ATE in (m) | ATE out (m) | corrections | time (s) |"
    )
    rows = [head, "|" + "---|" * 18]
    for r in results:
        rows.append(
            f"| {r.name} | {r.poses} | {r.angle_samples} "
            f"| {r.angle_before:.2f} | {r.angle_after:.2f} "
            f"| {r.spacing_samples} | {r.spacing_before:.3f} | {r.spacing_after:.3f} "
            f"| {r.inconsistency_before:.1f} | {r.inconsistency_after:.1f} "
            f"| {r.inconsistency_truth:.1f} | {100 * r.inconsistency_reduction:.0f}% "
            f"| {100 * r.best_reduction:.0f}% | {100 * r.achieved_fraction:.0f}% "
            f"| {r.ate_before:.3f} | {r.ate_after:.3f} | {r.corrections} | {r.time_s:.1f} |"
        )
    if results:
        ang = _nanmean(np.array([r.angle_after for r in results]))
        sp = _nanmean(np.array([r.spacing_after for r in results]))
        red = float(np.mean([r.inconsistency_reduction for r in results]))
        best = float(np.mean([r.best_reduction for r in results]))
        achieved = _nanmean(np.array([r.achieved_fraction for r in results]))
        rows.append(
            f"| **mean** | | | {_nanmean(np.array([r.angle_before for r in results])):.2f} | "
            f"**{ang:.2f}** | | {_nanmean(np.array([r.spacing_before for r in results])):.3f} | "
            f"**{sp:.3f}** | | | | {100 * red:.0f}% | {100 * best:.0f}% "
            f"| **{100 * achieved:.0f}%** | | | {sum(r.corrections for r in results)} | |"
        )
    return "\n".join(rows)


TARGET_ANGLE_DEG = 1.0
TARGET_SPACING_M = 0.03
TARGET_ACHIEVED = 0.80
"""Mean inconsistency reduction as a fraction of what the true poses reach (issue 11; it replaces
issue 4's plain 91 % reduction, which the real logs cannot reach even on their true poses)."""


def targets(results: Sequence[ScenarioResult]) -> str:
    """The evaluation's targets: mean corrected angular error <= 1.0 degree, mean translational
    error <= 0.03 m, and the inconsistency reduced by >= 80 % of what the true poses reach
    (``(before - after) / (before - truth)``), each with the measured value and whether it is
    met; the plain reduction and its ceiling are shown beside it."""
    if not results:
        return ""
    ang = _nanmean(np.array([r.angle_after for r in results]))
    sp = _nanmean(np.array([r.spacing_after for r in results]))
    red = float(np.mean([r.inconsistency_reduction for r in results]))
    best = float(np.mean([r.best_reduction for r in results]))
    achieved = _nanmean(np.array([r.achieved_fraction for r in results]))
    lines = [
        "| target | measured | met |",
        "|---|---|---|",
        f"| mean corrected angular error <= {TARGET_ANGLE_DEG:.1f} deg | {ang:.2f} deg "
        f"| {'yes' if ang <= TARGET_ANGLE_DEG else 'no'} |",
        f"| mean corrected translational error <= {TARGET_SPACING_M:.2f} m | {sp:.3f} m "
        f"| {'yes' if sp <= TARGET_SPACING_M else 'no'} |",
        f"| mean inconsistency reduction >= {100 * TARGET_ACHIEVED:.0f}% of the achievable "
        f"| {100 * achieved:.0f}% | {'yes' if achieved >= TARGET_ACHIEVED else 'no'} |",
    ]
    notes = [
        f"Plain reduction {100 * red:.0f}% on average; the true poses themselves reach "
        f"{100 * best:.0f}% (the real logs' scans disagree even on their corrected poses: moving "
        "people, glass, the corrected log's own residual error)."
    ]
    return "\n".join([*lines, "", *notes])


def scenarios(
    *, seed: int = 0, quick: bool = False
) -> list[tuple[str, Callable[[], object], bool]]:
    """The evaluation's scenarios, as (name, builder, is a real log) in order; real logs only
    when present."""
    from hitl_slam.sim import campus, lost_poses_room, parallel_corridors
    from hitl_slam.sim.odometry import HeadingDrift, HeadingJump

    out: list[tuple[str, Callable[[], object], bool]] = [
        ("lost poses room", lambda: lost_poses_room(seed), False),
        ("parallel corridors", lambda: parallel_corridors(seed), False),
    ]
    if quick:
        return out
    out.append(("campus", lambda: campus(seed), False))

    def damage(n: int) -> list[object]:
        # A 10 degree heading jump at 3/8 of the run, and a corridor bending by 0.5 degree per
        # metre over the 5/8 - 3/4 stretch.
        return [
            HeadingJump(3 * n // 8, math.radians(10.0)),
            HeadingDrift(5 * n // 8, 3 * n // 4, math.radians(0.5)),
        ]

    for file, label in (
        ("freiburg-079-corrected.log.gz", "Freiburg 079 (damaged)"),
        ("intel-corrected.log.gz", "Intel lab (damaged)"),
    ):
        path = LASER / file
        if path.is_file():
            out.append(
                (
                    label,
                    partial(real_log_scenario, path, name=label, seed=seed, faults=damage),
                    True,
                )
            )
    return out


def provenance(seed: int, flags: str, seconds: float) -> str:
    """One line on how, when and where the report was made."""
    import datetime
    import os
    import platform

    from hitl_slam import __version__

    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (
        f"Written by `hitl-slam evaluate{flags} --seed {seed}` (hitl-slam {__version__}) on "
        f"{when}, on {os.cpu_count()} cores of {cpu}, Python {platform.python_version()}; "
        f"{seconds / 60:.1f} minutes of repairs in all."
    )


def run_evaluation(
    out_dir: Path,
    *,
    seed: int = 0,
    quick: bool = False,
    config: Config = DEFAULT,
    log: Callable[[str], None] = lambda _m: None,
) -> tuple[list[ScenarioResult], Path]:
    """Runs every scenario and writes ``out_dir/report.md`` with the table and figures."""
    out_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for name, build, real in scenarios(seed=seed, quick=quick):
        log(f"{name}: building")
        scenario = build()
        r = evaluate_scenario(scenario, out_dir, seed=seed, config=config, quick_human=real)
        r = dataclasses.replace(r, real_log=real)
        log(
            f"{name}: {r.corrections} corrections, "
            f"angle {r.angle_before:.2f} -> {r.angle_after:.2f} deg, "
            f"spacing {r.spacing_before:.3f} -> {r.spacing_after:.3f} m, inconsistency "
            f"-{100 * r.inconsistency_reduction:.0f}%, {r.time_s:.1f} s"
        )
        results.append(r)
    report = out_dir / "report.md"
    from hitl_slam.io.atomic import atomic_write_text

    lines = [
        "# hitl-slam evaluation",
        "",
        provenance(seed, " --quick" if quick else "", sum(r.time_s for r in results)),
        "",
        "Each map is damaged (odometry noise plus injected faults: heading jumps, slow drift),",
        "then repaired by a simulated person who draws one noisy correction at a time on the",
        "current map (5 cm endpoint noise). Errors are between known wall pairs (the paper's",
        "Table 1): angles between walls known parallel or perpendicular, spacings between",
        "parallel walls.",
        "",
        table(results),
        "",
        "## Targets",
        "",
        targets(results),
        "",
        "The paper (Nashed and Biswas, AAAI 2018), Table 1: mean angular error 6.74 -> 1.4",
        "degrees, mean translational error 2.71 -> 0.04 m; LGRC inconsistency reduced by 91% on",
        "average.",
        "",
        "Real logs: Freiburg building 079 and the Intel Research Lab (corrected logs via Radish;",
        "thanks to their authors, C. Stachniss, D. Haehnel and the Freiburg SLAM benchmark of",
        "Kuemmerle et al. 2009). Their corrected poses serve as pseudo ground truth; walls are",
        "found in the corrected map by RANSAC.",
        "",
    ]
    for r in results:
        if r.figure is not None:
            lines += [f"## {r.name}", "", f"![{r.name}]({r.figure.name})", ""]
    atomic_write_text(report, "\n".join(lines))
    return results, report
