#!/usr/bin/env python
"""The scan-matching front end (`hitl_slam.slam.slam`, default settings, no human drawing) on a
test bed of log variants: the raw Intel and Freiburg 079 logs scored against their benchmark
relations (Kuemmerle et al. 2009), the same logs damaged in known ways (scans dropped, odometry
bent or stretched, a shorter and narrower laser, float32 ranges, range noise), the four corrected
Radish logs made raw again with the project's odometry damage model (scored by ATE against their
corrected poses), and every unmodified log as a ROS 1 and a ROS 2 bag read back by the project's
reader. Meant to run as

    python benches/frontend_testbed.py --write benches/README.md

(the whole bed: 64 runs, about an hour of CPU on one core). Pieces of it:

    python benches/frontend_testbed.py --logs intel --variants raw,every5,bias3
    python benches/frontend_testbed.py --logs seattle,orebro --json rows.json
    python benches/frontend_testbed.py --variants noise5mm      # the five noise seeds

Logs (`--logs`, comma list): intel, fr079 (raw logs with relations), seattle, orebro,
belgioioso, edmonton (corrected logs, made raw). Variants (`--variants`, comma list; default:
all the raw logs' on intel and fr079, all the corrected logs' on the others; an explicit list
applies to every log given it fits, and `raw` is always run, as the baseline of the ratios):

    raw             the log as read (the corrected logs: made raw, see below)
    every2/3/5      scans 0, k, 2k, ... only (the others are dropped, with their odometry)
    bias1, bias3    +1 / +3 degrees of heading per metre travelled added to every odometry
                    step (HeadingDrift of hitl_slam.sim.odometry, no noise), poses recomposed
    scale3          every odometry step's translation x1.03 (ScaleError, no noise)
    short8m-180deg  points beyond 8 m range, or outside +-90 degrees of the laser's forward
                    axis, dropped (every log here has a 180-degree FLASER laser, so only the
                    range cut drops points; the notes under the table count them)
    float32         every point moved along its beam to r = float32(r)
    noise5mm-s0..s4 every point moved along its beam by N(0, 5 mm), numpy seed 0..4
                    (`noise5mm` names all five)
    damage-s1..s4   (the corrected logs) made raw with numpy seed 1..4 instead of 0: the same
                    damage model, other wheels (`damage` names all four); the ATE target holds
                    for each, and the table gives worst/best over the five seeds
    reference-odometry
                    (the corrected logs) the corrected poses themselves as the odometry: what
                    the matching alone leaves against the reference, which is another SLAM
                    system's estimate, not ground truth (a diagnostic, no target); its note
                    says how far the reference sits from the scan-matching optimum (every
                    step matched again by ICP from the reference's own step, chained with
                    exact loop closures on the front end's pairs: the ATE of that chain)
    A+B             two variants applied left to right (every3+bias3: every third scan,
                    then the heading bias on what is left: big steps and a drifting heading
                    at once, as on a log recorded at a low rate with poor wheels)
    ros1, ros2      the unmodified scans and odometry written as a ROS 1 bag / a ROS 2 bag
                    (sqlite3) with rosbags' writers (/tf odom -> base_link, the laser at
                    base_link), read back with load_map; a log
                    whose scans share a stamp (Orebro, Belgioioso: all 0) is re-stamped 0.1 s
                    apart, as TF is looked up by stamp

`-j N` runs N at a time (timing is less clean then, and the table says so); `--json OUT` writes
the raw rows; `--max-scans N` (a check of the bench, not a measurement) crops every log to its
first N scans.

Each run is its own process (its peak memory, ru_maxrss, is its own: reading the input, making
the variant, the front end), with RAYON_NUM_THREADS=1; CPU time (time.process_time) is the
`slam()` call's only, and real time is the log's duration over it. Variants are made in memory,
bags in a temporary directory: nothing is written into the repository except by --write.
Needs the data in ../shared/datasets/laser and, for the bags, the [ros] extra.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from hitl_slam.io.relations import Relations
    from hitl_slam.map import Map

ROOT = Path(__file__).resolve().parents[1]
LASER = ROOT.parent / "shared" / "datasets" / "laser"
SECTION = "frontend-testbed"


@dataclass(frozen=True)
class Log:
    title: str
    file: str
    relations: str | None  # None: a corrected log, made raw and scored by ATE
    target: float  # [m] the raw run's acceptance: relation translation mean, or ATE
    credit: str


LOGS = {
    "intel": Log("Intel Research Lab", "intel.clf.bz2", "intel.relations", 0.0229, "D. Haehnel"),
    "fr079": Log("Freiburg bldg 79", "fr079.clf.bz2", "fr079.relations", 0.0452, "C. Stachniss"),
    "seattle": Log("Seattle", "seattle-corrected.log.gz", None, 0.10, "Radish"),
    "orebro": Log("Orebro", "orebro-corrected.log.gz", None, 0.10, "Radish"),
    "belgioioso": Log("Belgioioso", "belgioioso-corrected.log.gz", None, 0.10, "Radish"),
    "edmonton": Log("Edmonton", "edmonton-corrected.log.gz", None, 0.10, "Radish"),
}
NOISE_SEEDS = tuple(f"noise5mm-s{k}" for k in range(5))
BAGS = {"ros1": "ros1", "ros2": "sqlite3"}  # variant -> bag_support kind
VARIANTS = (
    "raw",
    "every2",
    "every3",
    "every5",
    "bias1",
    "bias3",
    "scale3",
    "short8m-180deg",
    "float32",
    *NOISE_SEEDS,
    *BAGS,
)
DAMAGE_SEEDS = tuple(f"damage-s{k}" for k in range(1, 5))
REFERENCE_ODOMETRY = "reference-odometry"
CORRECTED_VARIANTS = ("raw", *DAMAGE_SEEDS, REFERENCE_ODOMETRY, *BAGS)
CORRECTED_DEFAULT = CORRECTED_VARIANTS

# The corrected logs made raw: a wheel odometer worse than the project's default one (2 % of
# the distance, 5 % of the rotation and 1 degree per metre of heading noise per step) with a
# heading drift of 1 degree per metre over the whole run, numpy seed 0, applied to the corrected
# poses (hitl_slam.sim.odometry.odometry).
MADE_RAW_K_T = 0.02
MADE_RAW_K_THETA = 0.05
MADE_RAW_K_THETA_T_DEG = 1.0  # [deg/m]
MADE_RAW_DRIFT_DEG = 1.0  # [deg/m]
MADE_RAW_SEED = 0
MADE_RAW_TEXT = (
    "`odometry(corrected poses, numpy.random.default_rng(0), OdometryNoise(k_t=0.02, "
    "k_theta=0.05, k_theta_t=radians(1.0)), [HeadingDrift(0, N, radians(1.0))])`: per step "
    "Gaussian noise of 2 % of the distance on x and y, 5 % of the rotation plus 1 deg per metre "
    "on the heading, and a heading drift of +1 deg per metre travelled over the whole run"
)

# The acceptance.
VARIANT_RATIO = 1.5  # a variant's error over its unmodified log's, at most
VARIANT_MAX_ROTATION_DEG = 10.0  # no relation rotation error above this in a variant
BAG_TOLERANCE = 0.10  # a bag's error within this fraction of the log's
NOISE_SPREAD = 1.3  # worst / best error over the noise seeds, at most
REAL_TIME = 20.0  # real-time factor (CPU), at least

RANGE_CUT = 8.0  # [m] short8m-180deg
HALF_FOV = math.pi / 2  # [rad] short8m-180deg
NOISE_SIGMA = 0.005  # [m] noise5mm
STRETCH = 1.03  # scale3
BAG_PERIOD_NS = 100_000_000  # a re-stamped bag's scan period (when the log's stamps repeat)


# --- the variants (in the run's process) ------------------------------------------------------


def _scans(m: Map) -> list[NDArray[np.float64]]:
    return list(np.split(m.points, m.offsets[1:-1]))


def _subset(m: Map, keep: NDArray[np.int64], poses: NDArray[np.float64] | None = None) -> Map:
    """The scans ``keep`` of ``m`` (with ``poses``, default theirs) as a map of their own."""
    from hitl_slam.map import Map

    scans = _scans(m)
    out = Map.from_poses_and_scans(
        m.poses[keep] if poses is None else poses,
        [scans[k] for k in keep.tolist()],
        timestamps=None if m.timestamps is None else m.timestamps[keep],
        name=m.name,
        source=m.source,
    )
    out.metadata.update(m.metadata)
    if "scan_lines" in m.metadata:
        out.metadata["scan_lines"] = np.asarray(m.metadata["scan_lines"])[keep]
    return out


def _with_points(m: Map, points: NDArray[np.float64], keep: NDArray[np.bool_] | None) -> Map:
    """``m`` with its points replaced (the same number, or those where ``keep``)."""
    import dataclasses

    offsets = m.offsets
    if keep is not None:
        owner = m.pose_of_point()[keep]
        counts = np.bincount(owner, minlength=m.num_poses)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        points = points[keep]
    return dataclasses.replace(m, points=points, offsets=offsets, metadata=dict(m.metadata))


def _along_beam(m: Map, ranges: NDArray[np.float64]) -> Map:
    """Every point moved along its beam to the new range."""
    r = np.hypot(m.points[:, 0], m.points[:, 1])
    scale = np.divide(ranges, r, out=np.ones_like(r), where=r > 0)
    return _with_points(m, m.points * scale[:, None], None)


def make_variant(m: Map, variant: str) -> tuple[Map, NDArray[np.int64], dict[str, Any]]:
    """The variant of ``m`` (odometry poses, the log's scans): the map, which of ``m``'s scans it
    holds, and notes on what changed."""
    from hitl_slam.sim.odometry import NO_NOISE, HeadingDrift, ScaleError, odometry

    if "+" in variant:
        # A combination, applied left to right (every3+bias3: every third scan, then the bias).
        first, rest = variant.split("+", 1)
        out, keep, notes = make_variant(m, first)
        out, inner, more = make_variant(out, rest)
        return out, keep[inner], {**notes, **more}
    n = m.num_poses
    everything = np.arange(n, dtype=np.int64)
    if variant == "raw":
        return m, everything, {}
    if variant.startswith("every"):
        keep = np.arange(0, n, int(variant.removeprefix("every")), dtype=np.int64)
        return _subset(m, keep), keep, {}
    if variant in ("bias1", "bias3", "scale3"):
        fault: HeadingDrift | ScaleError
        if variant == "scale3":
            fault = ScaleError(0, n, STRETCH)
        else:
            fault = HeadingDrift(0, n, math.radians(float(variant.removeprefix("bias"))))
        poses = odometry(m.poses, np.random.default_rng(0), NO_NOISE, [fault])
        return _subset(m, everything, poses), everything, {}
    r = np.hypot(m.points[:, 0], m.points[:, 1])
    if variant == "short8m-180deg":
        far = r > RANGE_CUT
        aside = np.abs(np.arctan2(m.points[:, 1], m.points[:, 0])) > HALF_FOV + 1e-9
        notes = {
            "points_dropped_range": int(far.sum()),
            "points_dropped_fov": int((aside & ~far).sum()),
            "points_before": int(r.size),
            "empty_scans": 0,
        }
        out = _with_points(m, m.points, ~(far | aside))
        notes["empty_scans"] = int(np.count_nonzero(np.diff(out.offsets) == 0))
        return out, everything, notes
    if variant == "float32":
        r32 = r.astype(np.float32).astype(np.float64)
        return _along_beam(m, r32), everything, {"max_shift_m": float(np.abs(r32 - r).max())}
    if variant in NOISE_SEEDS:
        rng = np.random.default_rng(int(variant.removeprefix("noise5mm-s")))
        noisy = np.maximum(r + rng.normal(0.0, NOISE_SIGMA, r.shape), 1e-3)
        return _along_beam(m, noisy), everything, {}
    raise ValueError(f"unknown variant {variant!r}")


def base_map(
    key: str, max_scans: int | None, seed: int = MADE_RAW_SEED
) -> tuple[Map, NDArray[np.float64] | None, Any]:
    """The log's map with odometry poses (a corrected log: made raw with numpy seed ``seed``),
    cropped to its first ``max_scans`` scans; the corrected poses (None for a raw log); the
    uncropped log's timestamps (relations are matched to the whole log's scans)."""
    from hitl_slam.io.carmen import read_carmen
    from hitl_slam.sim.odometry import HeadingDrift, OdometryNoise, odometry

    log = LOGS[key]
    m = read_carmen(LASER / log.file)
    whole = m.timestamps
    if max_scans is not None and max_scans < m.num_poses:
        m = _subset(m, np.arange(max_scans, dtype=np.int64))
    if log.relations is not None:
        return m, None, whole
    truth = m.poses.copy()
    noise = OdometryNoise(
        k_t=MADE_RAW_K_T,
        k_theta=MADE_RAW_K_THETA,
        k_theta_t=math.radians(MADE_RAW_K_THETA_T_DEG),
    )
    drift = HeadingDrift(0, m.num_poses, math.radians(MADE_RAW_DRIFT_DEG))
    raw = odometry(truth, np.random.default_rng(seed), noise, [drift])
    return _subset(m, np.arange(m.num_poses, dtype=np.int64), raw), truth, whole


# --- ROS bags (in a process of their own, before the run) ------------------------------------


def write_log_bag(key: str, kind: str, folder: Path, max_scans: int | None) -> dict[str, Any]:
    """The log's scans (its FLASER lines' ranges) and odometry poses (a corrected log's: made
    raw) as a bag (/tf odom -> base_link, the laser at base_link); the log's own stamps unless
    two scans share one (the Radish logs with all zero stamps), then 0.1 s apart."""
    sys.path.insert(0, str(ROOT / "tests"))
    from bag_support import Bag, Scan, Transform, seconds_to_ns, write_bag
    from hitl_slam.io.textfile import read_lines

    m, _, _ = base_map(key, max_scans)
    if m.metadata.get("laser") != "FLASER" or m.timestamps is None:
        raise SystemExit(f"{key}: only logs of FLASER lines are written as bags here")
    limit = float(m.metadata["flaser_max_range"]) - 1e-3
    stamps = [seconds_to_ns(float(t)) for t in m.timestamps]
    restamped = len(set(stamps)) < len(stamps)
    if restamped:
        stamps = [10**9 + k * BAG_PERIOD_NS for k in range(len(stamps))]
    lines = read_lines(LASER / LOGS[key].file)
    scans, tf = [], []
    for k, number in enumerate(np.asarray(m.metadata["scan_lines"]).tolist()):
        tokens = lines[number - 1].split()
        n = int(tokens[1])
        r = np.array(tokens[2 : 2 + n], dtype=np.float64)
        step = math.pi / (n - 1) if n in (181, 361) else math.pi / n
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(r) & (r > 0) & (r < limit)
        record = 10**18 + k * 10**7  # the log's order (Intel's stamps are not monotone)
        scans.append(
            Scan(
                stamp=stamps[k],
                ranges=np.where(valid, r, np.inf),
                angle_min=-math.pi / 2,
                angle_increment=step,
                range_min=0.0,
                range_max=limit + 1e-3,
                frame="base_link",
                record=record,
            )
        )
        x, y, theta = (float(v) for v in m.poses[k])
        tf.append([Transform(stamps[k], "odom", "base_link", (x, y, theta), record=record)])
    bag = Bag(scans=scans)
    bag.tf = tf
    path = write_bag(bag, folder / f"{key}-{kind}", kind)
    return {"path": str(path), "restamped": restamped}


# --- one run (in its own process) ------------------------------------------------------------


def _aligned_heading_deg(est: NDArray[np.float64], truth: NDArray[np.float64]) -> NDArray[Any]:
    """Heading errors [deg] after the rigid alignment hitl_slam.metrics.ate makes."""
    pc = est[:, :2] - est[:, :2].mean(axis=0)
    qc = truth[:, :2] - truth[:, :2].mean(axis=0)
    angle = math.atan2(
        float(np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0])),
        float(np.sum(pc[:, 0] * qc[:, 0] + pc[:, 1] * qc[:, 1])),
    )
    d = est[:, 2] + angle - truth[:, 2]
    return np.degrees(np.abs(np.mod(d + math.pi, 2 * math.pi) - math.pi))


def _relations_for(
    relations: Relations, whole: Any, keep: NDArray[np.int64], stamps: NDArray[np.float64]
) -> tuple[Relations, NDArray[np.int64], NDArray[np.int64]]:
    """The relations whose two scans (matched to the whole log's scans by time, 1 ms) are both
    among ``keep``, re-timed to those scans' ``stamps`` in the run's map (so that a dropped scan
    is never stood in for by a kept one whose stamp happens to be within the tolerance, and a
    re-stamped bag is scored on the same scans); their rows in ``relations``; their scans in
    the run's map."""
    from hitl_slam.io.relations import Relations, nearest_scans

    match = nearest_scans(relations, whole)
    where = np.full(len(whole), -1, dtype=np.int64)
    where[keep] = np.arange(keep.size)
    a, b = where[match.pairs[:, 0]], where[match.pairs[:, 1]]
    both = (a >= 0) & (b >= 0)
    rows = match.rows[both]
    pairs = np.stack([a[both], b[both]], axis=1)
    subset = Relations(
        t1=stamps[pairs[:, 0]],
        t2=stamps[pairs[:, 1]],
        relative=relations.relative[rows],
        lines=relations.lines[rows],
        source=relations.source,
    )
    return subset, rows, pairs


def _naive_match(relations: Relations, stamps: NDArray[np.float64], correct: set[int]) -> Any:
    """What relations_error alone would score on the run's map: how many relations, and how many
    of them are not among the correct ones (a time matched to a scan that is not its own)."""
    from hitl_slam.errors import InputError
    from hitl_slam.io.relations import nearest_scans

    try:
        match = nearest_scans(relations, stamps)
    except InputError:
        return {"naive_matched": 0, "naive_wrong": 0, "naive_skipped": len(relations)}
    rows = set(match.rows.tolist())
    return {
        "naive_matched": len(rows),
        "naive_wrong": len(rows - correct),
        "naive_skipped": int(match.skipped.size),
    }


def run_one(key: str, variant: str, max_scans: int | None, bag: str | None) -> dict[str, Any]:
    from hitl_slam.io.maps import load_map
    from hitl_slam.io.relations import read_relations
    from hitl_slam.metrics import ate, relations_error
    from hitl_slam.slam import slam

    log = LOGS[key]
    notes: dict[str, Any] = {}
    if bag is not None:
        # The bag alone is read before the front end (the peak memory is the bag's run); the
        # log, for the scoring, after it.
        run_map = load_map(bag)
        base = truth = whole = None
    elif log.relations is None:
        # A corrected log: made raw at another damage seed, or with its corrected poses as the
        # odometry (what the matching alone leaves against the reference).
        seed = int(variant.removeprefix("damage-s")) if variant in DAMAGE_SEEDS else MADE_RAW_SEED
        base, truth, whole = base_map(key, max_scans, seed)
        own = variant in DAMAGE_SEEDS or variant == REFERENCE_ODOMETRY
        run_map, keep, notes = make_variant(base, "raw" if own else variant)
        if variant == REFERENCE_ODOMETRY:
            assert truth is not None
            run_map = _subset(base, keep, truth)
    else:
        if variant in DAMAGE_SEEDS or variant == REFERENCE_ODOMETRY:
            raise SystemExit(f"variant {variant!r} is for the corrected logs, not {key}")
        base, truth, whole = base_map(key, max_scans)
        run_map, keep, notes = make_variant(base, variant)
    wall, cpu = time.perf_counter(), time.process_time()
    result = slam(run_map)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if base is None:
        base, truth, whole = base_map(key, max_scans)
        keep = np.arange(base.num_poses, dtype=np.int64)
        if run_map.num_poses != base.num_poses:
            raise SystemExit(
                f"{bag}: {run_map.num_poses} scans read back, the log has {base.num_poses}"
            )
        scans_dropped = run_map.metadata.get("scans_dropped")
        notes["bag_scans_dropped"] = scans_dropped if isinstance(scans_dropped, int) else None
    duration = None
    if base.timestamps is not None and keep.size > 1:
        stamps = base.timestamps[keep]
        span = float(stamps[-1] - stamps[0])
        duration = span if span >= 1e-3 * (keep.size - 1) else None  # else no robot clock
    loops = result.loop_closures
    # The front end's own judgement, where it gives one (a newer front end: on the result, or
    # in the map's metadata as the web app reads it).
    verdict = getattr(result, "verdict", None)
    doubtful = getattr(result, "doubtful", ())
    if verdict is None:
        verdict = result.map.metadata.get("front_end_verdict")
    has_doubtful = hasattr(result, "doubtful") or "front_end_doubtful" in result.map.metadata
    if not hasattr(result, "doubtful"):
        doubtful = result.map.metadata.get("front_end_doubtful", ())
    row: dict[str, Any] = {
        "log": key,
        "variant": variant,
        "max_scans": max_scans,
        "cropped": whole is not None and len(whole) > base.num_poses,
        "scans": run_map.num_poses,
        "keyframes": int(result.keyframes.size),
        "loops": int(loops.accepted.sum()),
        "rejected": int((~loops.accepted).sum()),
        "cpu_s": cpu,
        "wall_s": wall,
        "duration_s": duration,
        "real_time": None if duration is None or cpu <= 0 else duration / cpu,
        "peak_mib": peak,
        "verdict": None if verdict is None else str(getattr(verdict, "value", verdict)),
        "doubtful": len(list(doubtful if doubtful is not None else ())) if has_doubtful else None,
        "notes": notes,
    }
    if log.relations is None:
        assert truth is not None
        reference = truth[keep]
        if variant == REFERENCE_ODOMETRY:
            notes.update(_reference_at_the_optimum(result.map, reference))
        heading = _aligned_heading_deg(result.map.poses, reference)
        row.update(
            score="ate",
            scored=int(keep.size),
            error=ate(result.map.poses, reference),
            rot_mean=float(heading.mean()),
            rot_max=float(heading.max()),
            odometry_error=ate(run_map.poses, reference),
        )
        return row
    relations = read_relations(LASER / log.relations)
    assert run_map.timestamps is not None
    subset, rows, pairs = _relations_for(relations, whole, keep, run_map.timestamps)
    if bag is None:
        row.update(_naive_match(relations, run_map.timestamps, set(rows.tolist())))
    if len(subset) == 0:  # no relation between two kept scans (a short crop, thinned)
        nan = math.nan
        row.update(score="relations", scored=0, error=nan, error_std=nan, rot_mean=nan)
        row.update(rot_max=nan, odometry_error=nan, relation_rows=[], relation_translation=[])
        return row
    err = relations_error(result.map, None, subset)
    odo = relations_error(run_map, None, subset)
    row.update(
        score="relations",
        scored=int(err.translation.size),
        error=float(err.translation.mean()),
        error_std=float(err.translation.std()),
        rot_mean=float(err.rotation_deg.mean()),
        rot_max=float(err.rotation_deg.max()),
        odometry_error=float(odo.translation.mean()),
        skipped=int(err.skipped),
        mismatched=int(np.count_nonzero(np.any(err.pairs != pairs[err.rows], axis=1))),
        relation_rows=rows.tolist(),
        relation_translation=np.round(err.translation, 7).tolist(),
    )
    return row


def _reference_at_the_optimum(front_end: Map, reference: NDArray[np.float64]) -> dict[str, Any]:
    """How far the reference's own steps sit from the scan-matching optimum: every step of the
    front end's map matched again scan to scan by ICP started at the reference's step (no
    rotation fan), and those steps chained with the front end's loop closure pairs measured at
    the reference (exact closures), solved with DCS; the median move of a step, and the ATE of
    that chain against the reference. A front end whose every match reached its optimum would
    end about that far from the reference even with perfect loop closures."""
    import dataclasses

    from hitl_slam import _core
    from hitl_slam.geometry import between, chain_steps, wrap
    from hitl_slam.metrics import ate
    from hitl_slam.solve import optimize

    n = front_end.num_poses
    steps = np.ascontiguousarray(chain_steps(reference))
    ok, found, _, _ = _core.match_consecutive(
        np.ascontiguousarray(front_end.points), front_end.offsets, steps, search_deg=0.0
    )
    moved = found - steps
    moved[:, 2] = wrap(moved[:, 2])
    graph = front_end.pose_graph(reference.copy())
    z = graph.measurements.copy()
    z[: n - 1] = np.where(ok[:, None], found, steps)
    loops = graph.edges[n - 1 :]
    z[n - 1 :] = between(reference[loops[:, 0]], reference[loops[:, 1]])
    poses, _ = optimize(dataclasses.replace(graph, measurements=z), robust="dcs:10")
    return {
        "optimum_steps_matched": int(ok.sum()),
        "optimum_step_move_m": float(np.median(np.hypot(moved[ok, 0], moved[ok, 1]))),
        "optimum_step_turn_deg": float(np.degrees(np.median(np.abs(moved[ok, 2])))),
        "optimum_ate": ate(poses, reference),
    }


# --- the bed (the parent process) ------------------------------------------------------------


@dataclass(frozen=True)
class Job:
    log: str
    variant: str


def _child(args: list[str], max_scans: int | None) -> dict[str, Any]:
    env = {**os.environ, "RAYON_NUM_THREADS": "1"}
    crop = [] if max_scans is None else ["--max-scans", str(max_scans)]
    done = subprocess.run(
        [sys.executable, __file__, *args, *crop], capture_output=True, text=True, env=env
    )
    if done.returncode != 0:
        tail = " ".join(done.stderr.strip().splitlines()[-3:])
        raise RuntimeError(f"exit status {done.returncode}: {tail}")
    out: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return out


def run_job(job: Job, folder: Path, max_scans: int | None) -> dict[str, Any]:
    try:
        extra: list[str] = []
        bag_info: dict[str, Any] = {}
        if job.variant in BAGS:
            bag_info = _child(["--make-bag", job.log, BAGS[job.variant], str(folder)], max_scans)
            extra = ["--bag", bag_info["path"]]
        row = _child(["--one", job.log, job.variant, *extra], max_scans)
        if bag_info:
            row["notes"]["bag_restamped"] = bag_info["restamped"]
        return row
    except (RuntimeError, json.JSONDecodeError, IndexError) as exc:
        return {"log": job.log, "variant": job.variant, "failed": str(exc)}


def _plan(logs: Sequence[str], variants: Sequence[str] | None) -> list[Job]:
    jobs = []
    for key in logs:
        if variants is None:
            chosen = list(VARIANTS if LOGS[key].relations is not None else CORRECTED_DEFAULT)
        else:
            chosen = ["raw", *[v for v in variants if v != "raw"]]
            if LOGS[key].relations is not None:  # the corrected logs' own variants: not here
                chosen = [v for v in chosen if v not in (*DAMAGE_SEEDS, REFERENCE_ODOMETRY)]
        jobs += [Job(key, v) for v in chosen]
    return jobs


def _fmt(value: float | None, digits: int, suffix: str = "") -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}{suffix}"


def _ratios(rows: list[dict[str, Any]]) -> None:
    """Each row's error over its log's raw run's, on the same relations (a variant that drops
    scans is scored on the relations between kept scans: the raw run's error on those), or the
    whole trajectories' ATE; and the noise seeds' spread."""
    raw = {r["log"]: r for r in rows if r["variant"] == "raw" and "failed" not in r}
    for r in rows:
        base = raw.get(r["log"])
        if "failed" in r or base is None:
            continue
        if r["score"] == "relations":
            errors = dict(zip(base["relation_rows"], base["relation_translation"], strict=True))
            same = [errors[k] for k in r["relation_rows"] if k in errors]
            mine = [
                e
                for k, e in zip(r["relation_rows"], r["relation_translation"], strict=True)
                if k in errors
            ]
            r["baseline"] = float(np.mean(same)) if same else None
            r["ratio"] = float(np.mean(mine)) / r["baseline"] if same and r["baseline"] else None
        else:
            r["baseline"] = base["error"]
            r["ratio"] = r["error"] / base["error"] if base["error"] > 0 else None
    # The noise seeds' spread, and the damage seeds' (the raw run is damage seed 0).
    for family, with_raw in ((NOISE_SEEDS, False), (DAMAGE_SEEDS, True)):
        by_log: dict[str, list[float]] = {}
        for r in rows:
            seed_zero = with_raw and r["variant"] == "raw" and r.get("score") == "ate"
            if "failed" not in r and (r["variant"] in family or seed_zero):
                by_log.setdefault(r["log"], []).append(r["error"])
        for r in rows:
            seeds = by_log.get(r["log"], [])
            if r["variant"] in family and len(seeds) > 1 and min(seeds) > 0:
                r["spread"] = max(seeds) / min(seeds)
                r["seeds"] = len(seeds)


def _checks(r: dict[str, Any]) -> str:
    if "failed" in r:
        return "FAIL (run failed)"
    log, variant = LOGS[r["log"]], r["variant"]
    failed = []
    if not r["scored"]:
        failed.append("nothing scored")
    elif variant == REFERENCE_ODOMETRY:
        failed = []  # a diagnostic: no target
    elif variant == "raw" or variant in DAMAGE_SEEDS:
        what = "ATE" if r["score"] == "ate" else "translation"
        if not r["error"] <= log.target:
            failed.append(f"{what} {r['error']:.4f} > {log.target:g} m")
    elif variant in BAGS:
        ratio = r.get("ratio")
        if ratio is None or abs(ratio - 1.0) > BAG_TOLERANCE:
            failed.append(f"{_fmt(ratio, 3)}x the log's, not within {BAG_TOLERANCE:.0%}")
    else:
        ratio = r.get("ratio")
        if ratio is None or ratio > VARIANT_RATIO:
            failed.append(f"{_fmt(ratio, 2)}x > {VARIANT_RATIO}x")
        if not r["rot_max"] <= VARIANT_MAX_ROTATION_DEG:
            failed.append(f"rotation max {r['rot_max']:.1f} > {VARIANT_MAX_ROTATION_DEG:g} deg")
        if variant in NOISE_SEEDS and r.get("spread", 1.0) > NOISE_SPREAD:
            failed.append(f"seeds worst/best {r['spread']:.2f} > {NOISE_SPREAD}")
    if r["real_time"] is not None and r["real_time"] < REAL_TIME:
        failed.append(f"real time {r['real_time']:.0f}x < {REAL_TIME:.0f}x")
    verdict = "FAIL: " + "; ".join(failed) if failed else "PASS"
    if variant == REFERENCE_ODOMETRY:
        verdict = "(no target)" if not failed else verdict
    return verdict + (" (cropped)" if r.get("cropped") else "")


def _table(rows: list[dict[str, Any]]) -> list[str]:
    judged = any(r.get("verdict") is not None or r.get("doubtful") is not None for r in rows)
    head = [
        "log",
        "variant",
        "scans",
        "keyframes",
        "loop closures kept / rejected",
        "scored on",
        "translation mean (m) / ATE (m)",
        "rotation mean (deg)",
        "rotation max (deg)",
        "odometry's error (m)",
        "ratio to the log's",
        "CPU (s)",
        "real time (CPU)",
        "peak (MiB)",
        *(["verdict", "doubtful stretches"] if judged else []),
        "acceptance",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        name = LOGS[r["log"]].title
        if "failed" in r:
            cells = [name, r["variant"], *["-"] * (len(head) - 3), _checks(r)]
            lines.append("| " + " | ".join(cells).replace("\n", " ") + " |")
            continue
        ratio = _fmt(r.get("ratio"), 3)
        if r["variant"] == "raw":
            ratio = "1"
        elif "spread" in r:
            ratio += f" (seeds worst/best {r['spread']:.3f}, {r['seeds']} seeds)"
        elif r["variant"].startswith("every") and r["score"] == "relations":
            ratio += f" (the log's on these relations: {_fmt(r.get('baseline'), 4)})"
        scored = (
            f"{r['scored']} relations" if r["score"] == "relations" else f"{r['scored']} poses, ATE"
        )
        cells = [
            name,
            r["variant"],
            str(r["scans"]),
            str(r["keyframes"]),
            f"{r['loops']} / {r['rejected']}",
            scored,
            _fmt(r["error"], 4),
            _fmt(r["rot_mean"], 3),
            _fmt(r["rot_max"], 2),
            _fmt(r["odometry_error"], 3),
            ratio,
            f"{r['cpu_s']:.1f}",
            _fmt(r["real_time"], 0, "x"),
            f"{r['peak_mib']:.0f}",
            *([str(r.get("verdict") or "-"), _fmt(r.get("doubtful"), 0)] if judged else []),
            _checks(r),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _notes(rows: list[dict[str, Any]]) -> list[str]:
    out = []
    for r in rows:
        n = r.get("notes", {})
        what = f"{LOGS[r['log']].title} {r['variant']}"
        if "points_before" in n:
            out.append(
                f"- {what}: {n['points_dropped_range']} of {n['points_before']} points beyond "
                f"{RANGE_CUT:g} m and {n['points_dropped_fov']} more outside +-90 deg dropped; "
                f"{n['empty_scans']} scans left without a point."
            )
        if n.get("bag_restamped"):
            out.append(
                f"- {what}: the log's scans share timestamps (a log without a clock), so the bag "
                f"has them {BAG_PERIOD_NS / 1e9:g} s apart (TF is looked up by stamp)."
            )
        if r.get("naive_wrong"):
            out.append(
                f"- {what}: relations_error on this map alone would score {r['naive_matched']} "
                f"relations, {r['naive_wrong']} of them on a scan that is not the relation's "
                "(a dropped scan's time within 1 ms of a kept scan's); the table scores "
                f"{r['scored']}, the relations between kept scans."
            )
        if "optimum_ate" in n:
            out.append(
                f"- {what}: the reference at the scan-matching optimum: ICP from the reference's "
                f"own steps moves them a median {n['optimum_step_move_m']:.4f} m and "
                f"{n['optimum_step_turn_deg']:.3f} deg ({n['optimum_steps_matched']} of "
                f"{r['scans'] - 1} steps matched); chained with exact loop closures on the front "
                f"end's pairs they end {n['optimum_ate']:.3f} m ATE from the reference."
            )
        if r.get("mismatched"):
            out.append(f"- {what}: {r['mismatched']} relations matched another scan than meant.")
        if "failed" in r:
            out.append(f"- {what}: the run failed: {r['failed']}")
    return out


def body_text(rows: list[dict[str, Any]], args: argparse.Namespace, provenance: list[str]) -> str:
    cropped = args.max_scans is not None
    cores = len(os.sched_getaffinity(0))
    timing = (
        f"Runs went {args.jobs} at a time on {cores} cores: the CPU times and real-time factors "
        "are less clean than one at a time (shared caches and memory bandwidth)."
        if args.jobs > 1
        else "Runs went one at a time."
    )
    logs = sorted({r["log"] for r in rows}, key=list(LOGS).index)
    credits = []
    if "intel" in logs:
        credits.append("the Intel Research Lab log (D. Haehnel)")
    if "fr079" in logs:
        credits.append("the Freiburg building 079 log (C. Stachniss)")
    raw_logs = [k for k in logs if LOGS[k].relations is not None]
    if raw_logs:
        whose = "their" if len(raw_logs) > 1 else "its"
        credits.append(f"{whose} relations from the SLAM benchmark of Kuemmerle et al. 2009")
    corrected = [LOGS[k].title for k in logs if LOGS[k].relations is None]
    if corrected:
        plural = "s" if len(corrected) > 1 else ""
        credits.append(
            f"the corrected {', '.join(corrected)} log{plural} from Radish, as distributed by "
            "acschaefer/ple"
        )
    text = [
        *provenance,
        "",
        "The front end alone, default settings (`hitl_slam.slam.slam`), on the test bed "
        "(benches/frontend_testbed.py's docstring says exactly what each variant does); each "
        "run in its own process with RAYON_NUM_THREADS=1. CPU: the `slam()` call's; real time: "
        "the log's duration (its first to last kept scan) over that CPU time, `-` for a log "
        "without a clock (all stamps equal). Peak: the run's process (reading, making the "
        f"variant, the front end). {timing}",
        "",
        "Intel and Freiburg 079: relation errors against the benchmark relations (translation "
        "mean; rotation mean and max over the relations). Relations are matched to the whole "
        "log's scans by time (1 ms); a variant that drops scans is scored on the relations "
        "whose two scans it kept, and its ratio is against the raw run's error on those same "
        "relations. Odometry's error: the same score of the run's input poses.",
        "",
        "Seattle, Orebro, Belgioioso, Edmonton: the corrected logs (their poses a SLAM "
        f"system's) made raw by the project's odometry damage model, {MADE_RAW_TEXT}; scored "
        "by ATE (hitl_slam.metrics.ate, rigidly aligned) of the front end's poses against the "
        "corrected poses (pseudo ground truth, not independent), rotation: the heading error "
        "after that alignment, mean and max over the poses.",
        "",
        f"Acceptance: raw Intel <= {LOGS['intel'].target} m, raw Freiburg <= "
        f"{LOGS['fr079'].target} m; every variant <= {VARIANT_RATIO}x its log's error and no "
        f"rotation error above {VARIANT_MAX_ROTATION_DEG:g} deg; made-raw ATE <= "
        f"{LOGS['seattle'].target} m; bags within {BAG_TOLERANCE:.0%} of the log; noise seeds "
        f"worst/best <= {NOISE_SPREAD}; real time >= {REAL_TIME:.0f}x.",
    ]
    if cropped:
        text += [
            "",
            f"**Logs longer than {args.max_scans} scans cropped to their first "
            f"{args.max_scans}** (`--max-scans`; the rows marked cropped): a check of the "
            "bench, not a measurement; the targets are for the whole logs.",
        ]
    text += ["", *_table(rows)]
    notes = _notes(rows)
    if notes:
        text += ["", *notes]
    if not any(r.get("verdict") is not None for r in rows):
        text += ["", "(This front end reports no verdict or doubtful stretches.)"]
    text += ["", "Data: " + "; ".join(credits) + ". Thanks to their authors."]
    return "\n".join(text)


def _names(text: str, known: Sequence[str], what: str) -> list[str]:
    out = []
    for name in (t.strip() for t in text.split(",")):
        if not name:
            continue
        if name in ("noise5mm", "damage") and what == "variant":
            family = NOISE_SEEDS if name == "noise5mm" else DAMAGE_SEEDS
            out += [v for v in family if v not in out]
            continue
        if "+" in name and all(part in known for part in name.split("+")):
            out.append(name)
            continue
        if name not in known:
            raise SystemExit(f"unknown {what} {name!r}; known: {', '.join(known)}")
        if name not in out:
            out.append(name)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--logs", default=",".join(LOGS), help="comma list (default: all)")
    parser.add_argument("--variants", help="comma list (default: see above)")
    parser.add_argument("-j", "--jobs", type=int, default=1, help="runs at a time (default 1)")
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the raw rows here")
    parser.add_argument("--write", type=Path, metavar="README", help="replace the section")
    parser.add_argument("--max-scans", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--bag", help=argparse.SUPPRESS)
    parser.add_argument("--make-bag", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.max_scans is not None and args.max_scans < 2:
        parser.error("--max-scans must be at least 2")
    if args.make_bag:
        key, kind, folder = args.make_bag
        print(json.dumps(write_log_bag(key, kind, Path(folder), args.max_scans)))
        return 0
    if args.one:
        print(json.dumps(run_one(args.one[0], args.one[1], args.max_scans, args.bag)))
        return 0
    if args.jobs < 1:
        parser.error("-j must be at least 1")

    import compare_gtsam as shared

    logs = _names(args.logs, list(LOGS), "log")
    known = [*VARIANTS, *DAMAGE_SEEDS, REFERENCE_ODOMETRY]
    variants = None if args.variants is None else _names(args.variants, known, "variant")
    present = []
    for key in logs:
        if (LASER / LOGS[key].file).is_file():
            present.append(key)
        else:
            print(f"skipping {key}: {LASER / LOGS[key].file} not found", file=sys.stderr)
    jobs = _plan(present, variants)
    if not jobs:
        print("nothing to run", file=sys.stderr)
        return 1
    provenance = shared.provenance()
    print(f"{len(jobs)} runs, {args.jobs} at a time", file=sys.stderr)
    rows: list[dict[str, Any] | None] = [None] * len(jobs)
    with (
        tempfile.TemporaryDirectory(prefix="frontend-testbed-") as tmp,
        concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool,
    ):
        futures = {
            pool.submit(run_job, job, Path(tmp), args.max_scans): k for k, job in enumerate(jobs)
        }
        for future in concurrent.futures.as_completed(futures):
            k = futures[future]
            row = rows[k] = future.result()
            job = jobs[k]
            if "failed" in row:
                said = f"FAILED: {row['failed']}"
            else:
                said = f"{row['error']:.4f} m, {row['cpu_s']:.1f} s CPU"
            print(f"{job.log} {job.variant}: {said}", file=sys.stderr)
    done = [r for r in rows if r is not None]
    _ratios(done)
    body = body_text(done, args, provenance)
    print(body)
    if args.json:
        args.json.write_text(json.dumps(done, indent=1) + "\n")
    if args.write:
        shared.replace_section(args.write, SECTION, body)
    failed = sum("failed" in r for r in done)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
