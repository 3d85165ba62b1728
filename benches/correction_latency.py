#!/usr/bin/env python
"""Latency of one human correction end to end (interpret + explicit correction + back-propagation +
joint solve with every earlier correction), as a person waits for it in the UI.

Two maps: a generated corridor building (3,000 poses, ~300,000 points, 15 earlier corrections made
by a simulated human drawing on the current map, as a person would), and the Freiburg 079 log
(4791 scans; ../shared/datasets/laser/freiburg-079-corrected.log.gz) damaged by heading faults and
repaired by the same simulated human. The timed correction is applied repeatedly to the same
state; the table gives the median and the spread. Meant to run as

    python benches/correction_latency.py --write benches/README.md
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam import pipeline
from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.errors import CorrectionRejected

try:
    from hitl_slam.geometry import wrap
except ImportError:  # an older build timed with --baseline: it only replays saved states
    from hitl_slam.map import wrap  # type: ignore[attr-defined,no-redef]
from hitl_slam.map import Map
from hitl_slam.pipeline import apply_correction

try:
    from hitl_slam.workspace import Workspace
except ImportError:  # a build before workspaces, timed with --baseline
    Workspace = None  # type: ignore[assignment,misc]
from hitl_slam.sim.corridor import (
    OUTER_BOTTOM,
    OUTER_LEFT,
    OUTER_RIGHT,
    OUTER_TOP,
    corridor_loop,
    drawn_segment,
)

ROOT = Path(__file__).resolve().parents[1]
FR079 = ROOT.parent / "shared" / "datasets" / "laser" / "freiburg-079-corrected.log.gz"
FloatArray = NDArray[np.float64]


def _time(apply: Callable[[], object], repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        _forget_analyses()
        t = time.perf_counter()
        apply()
        out.append(time.perf_counter() - t)
    return out


HELD: dict[int, Any] = {}
"""Per map (by its number of poses: one map per case), the workspace its corrections share, as
a session's do (builds from before workspaces keep their engines themselves)."""


def _apply(m: Map, poses: FloatArray, drawn: Correction, active: Sequence[Interpretation]) -> Any:
    """``apply_correction`` as a session calls it: with the map's workspace."""
    if Workspace is None:
        return apply_correction(m, poses, drawn, active, DEFAULT)
    held = HELD.setdefault(m.num_poses, Workspace(m))
    return apply_correction(m, poses, drawn, active, DEFAULT, workspace=held)


def _forget_analyses() -> None:
    """Each timed correction pays for its own symbolic analysis, as a new correction in a
    session does (the engine keeps the analyses of recent structures, which would make every
    repeat after the first a cache hit). Builds without an engine have nothing to forget."""
    for held in HELD.values():
        for engine in held.engines():
            engine.clear_cache()
    for entry in getattr(pipeline, "_ENGINES", {}).values():  # builds before workspaces
        entry[1].clear_cache()


TIMERS: dict[str, Callable[[], object]] = {}
"""Per case, the timed correction as a call, for ``--serve``."""

STATES: dict[str, tuple[FloatArray, list[Interpretation], Correction]] = {}
LOADED: dict[str, tuple[FloatArray, list[Interpretation], Correction]] = {}
"""The state each case timed its correction on (poses, earlier corrections, the drawing), kept
for ``--save-state`` so that another build can be timed on exactly the same work."""


def _build_history(
    m: Map,
    candidates: Sequence[Callable[[FloatArray], Correction]],
    wanted: int,
    log: Callable[[str], None],
) -> tuple[FloatArray, list[Interpretation], list[Callable[[FloatArray], Correction]]]:
    """Applies drawings one at a time on the current map until ``wanted`` were accepted; returns
    the map, the accepted interpretations and the drawings not used yet."""
    poses = m.poses.copy()
    active: list[Interpretation] = []
    remaining = list(candidates)
    while remaining and len(active) < wanted:
        draw = remaining.pop(0)
        try:
            result = _apply(m, poses, draw(poses), active)
        except (CorrectionRejected, ValueError) as exc:
            log(f"  (skipped a drawing: {str(exc).splitlines()[0]})")
            continue
        poses = result.poses
        active.append(result.interpretation)
        log(
            f"  correction {len(active)}: {result.interpretation.mode.value}, "
            f"{1e3 * result.time_s:.1f} ms"
        )
    return poses, active, remaining


def corridor_case(repeats: int, log: Callable[[str], None]) -> dict[str, object]:
    world = corridor_loop(seed=3, laps=11.6, beams=120, max_range=6.0, fault_at=400)
    m = world.map
    rng = np.random.default_rng(7)
    lap = 260
    walls = [OUTER_BOTTOM, OUTER_RIGHT, OUTER_TOP, OUTER_LEFT]
    first_visit = {
        OUTER_BOTTOM: (0, 60),
        OUTER_RIGHT: (70, 120),
        OUTER_TOP: (135, 190),
        OUTER_LEFT: (200, 250),
    }
    candidates: list[Callable[[FloatArray], Correction]] = []
    for k in range(1, 12):
        for wall in walls:
            lo, hi = first_visit[wall]
            if (hi + k * lap) > m.num_poses:
                continue

            def draw(
                poses: FloatArray, wall: int = wall, lo: int = lo, hi: int = hi, k: int = k
            ) -> Correction:
                a = drawn_segment(world, poses, wall, (lo, hi), rng)
                b = drawn_segment(world, poses, wall, (lo + k * lap, hi + k * lap), rng)
                return Correction.make(a, b, Mode.COLOCATION)

            candidates.append(draw)
    log(f"corridor: {m.num_poses} poses, {m.num_points} points")
    timed = None
    if "corridor" in LOADED:
        poses, active, timed = LOADED["corridor"]
    else:
        poses, active, remaining = _build_history(m, candidates, 15, log)
        for draw in remaining:
            drawing = draw(poses)
            try:
                _apply(m, poses, drawing, active)
            except CorrectionRejected:
                continue
            timed = drawing
            break
    if timed is None:
        raise RuntimeError("no drawing left for the timed correction")
    STATES["corridor"] = (poses, active, timed)
    TIMERS["corridor"] = lambda: _apply(m, poses, timed, active)
    times = _time(lambda: _apply(m, poses, timed, active), repeats)
    last = _apply(m, poses, timed, active)
    return {
        "case": "corridor",
        "map": "generated corridor building (hitl_slam.sim.corridor_loop, 11.6 laps)",
        "poses": m.num_poses,
        "points": m.num_points,
        "earlier": len(active),
        "times": times,
        "interpret_ms": 1e3 * last.time_interpret_s,
        "solve_ms": 1e3 * last.time_solve_s,
        "iterations": last.iterations,
    }


def fr079_case(repeats: int, log: Callable[[str], None]) -> dict[str, object] | None:
    if not FR079.is_file():
        log(f"skipping Freiburg 079: {FR079} not found")
        return None
    from hitl_slam.io.carmen import read_carmen

    m = read_carmen(FR079)
    truth = m.poses.copy()
    n = m.num_poses
    # Damage: a heading fault every 400 scans (+-2 degrees), as a failing gyro would cause.
    damaged = truth.copy()
    for k, fault in enumerate(range(400, n, 400)):
        ang = math.radians(2.0 if k % 2 == 0 else -1.5)
        c = damaged[fault]
        rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        damaged[fault:, :2] = (damaged[fault:, :2] - c[:2]) @ rot.T + c[:2]
        damaged[fault:, 2] = wrap(damaged[fault:, 2] + ang)
    scans = [m.points[m.offsets[i] : m.offsets[i + 1]] for i in range(n)]
    m = Map.from_poses_and_scans(damaged, scans, name="fr079-damaged")
    fault = 400
    from revisits import WallDrawer, revisit_pairs

    # Revisits: pairs (early i, late j) whose TRUE positions are within 0.5 m.
    pairs = revisit_pairs(truth)
    del fault
    drawer = WallDrawer(m, truth, 11)
    candidates = [lambda poses, i=i, j=j: drawer.draw(poses, i, j) for i, j in pairs]
    log(f"fr079: {n} poses, {m.num_points} points, {len(pairs)} revisit pairs")
    timed = None
    if "fr079" in LOADED:
        poses, active, timed = LOADED["fr079"]
    else:
        poses, active, remaining = _build_history(m, candidates, 15, log)
        for draw in remaining:
            try:
                drawing = draw(poses)
                _apply(m, poses, drawing, active)
            except (CorrectionRejected, ValueError):
                continue
            timed = drawing
            break
    if timed is None:
        log("fr079: no drawing left for the timed correction")
        return None
    STATES["fr079"] = (poses, active, timed)
    TIMERS["fr079"] = lambda: _apply(m, poses, timed, active)
    times = _time(lambda: _apply(m, poses, timed, active), repeats)
    last = _apply(m, poses, timed, active)
    return {
        "case": "fr079",
        "map": (
            "Freiburg 079 (corrected log damaged by heading faults of +2 / -1.5 degrees "
            "every 400 scans)"
        ),
        "poses": n,
        "points": m.num_points,
        "earlier": len(active),
        "times": times,
        "interpret_ms": 1e3 * last.time_interpret_s,
        "solve_ms": 1e3 * last.time_solve_s,
        "iterations": last.iterations,
    }


def table(rows: Sequence[dict[str, object]]) -> str:
    out = [
        "| map | poses | points | earlier corrections | median (ms) | min - max (ms) "
        "| interpret (ms) | solve (ms) | LM iterations |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t = [1e3 * x for x in r["times"]]  # type: ignore[attr-defined]
        out.append(
            f"| {r['map']} | {r['poses']} | {r['points']} | {r['earlier']} "
            f"| {statistics.median(t):.1f} | {min(t):.1f} - {max(t):.1f} "
            f"| {r['interpret_ms']:.1f} | {r['solve_ms']:.1f} | {r['iterations']} |"
        )
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    import compare_gtsam as shared

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--write", type=Path, metavar="README", help="replace the latency section of this file"
    )
    parser.add_argument(
        "--baseline",
        metavar="PYTHONPATH",
        help="also time another build (its python/ folder, with its _core extension in it) on "
        "exactly the same states, alternating with this build in separate processes, and report "
        "the ratio",
    )
    parser.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="with --baseline: each build times each case rounds x repeats times, taking turns",
    )
    parser.add_argument("--save-state", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--load-state", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    log = lambda msg: print(msg, file=sys.stderr)  # noqa: E731
    if args.baseline:
        body = side_by_side(args.baseline, args.rounds, args.repeats, log)
        print(body)
        if args.write:
            shared.replace_section(args.write, "latency-vs", body)
        return 0
    if args.load_state:
        with args.load_state.open("rb") as f:
            LOADED.update(pickle.load(f))
    rows = [corridor_case(args.repeats, log)]
    fr = fr079_case(args.repeats, log)
    if fr is not None:
        rows.append(fr)
    if args.save_state:
        with args.save_state.open("wb") as f:
            pickle.dump(STATES, f)
    if args.json:
        print(json.dumps(rows), flush=True)
        if args.serve:
            _serve()
        return 0
    body = "\n".join(
        [
            *shared.provenance(),
            "",
            f"One correction end to end, timed {args.repeats} times on the same state "
            "(interpret + explicit + back-propagate + joint solve with all earlier corrections; "
            "each time with its own symbolic analysis, as a new correction); the target is a "
            "median under 100 ms.",
            "",
            table(rows),
            "",
            "Freiburg 079 data: the Freiburg SLAM benchmark (Kuemmerle et al. 2009), via Radish; "
            "thanks to its authors.",
        ]
    )
    print(body)
    if args.write:
        shared.replace_section(args.write, "latency", body)
    return 0


def _serve() -> None:
    """A worker of ``side_by_side``: times one correction of the case named on each line of
    standard input and answers with its seconds, until standard input closes."""
    for line in sys.stdin:
        apply = TIMERS[line.strip()]
        _forget_analyses()
        t = time.perf_counter()
        apply()
        print(repr(time.perf_counter() - t), flush=True)


def _run(pythonpath: str, extra: list[str], log: Callable[[str], None]) -> list[dict[str, object]]:
    env = {**os.environ, "PYTHONPATH": f"{pythonpath}{os.pathsep}{ROOT / 'benches'}"}
    out = subprocess.run(
        [sys.executable, __file__, *extra, "--json"],
        env=env,
        check=True,
        stdout=subprocess.PIPE,
        stderr=None if os.environ.get("LATENCY_VERBOSE") else subprocess.DEVNULL,
        text=True,
    ).stdout
    rows: list[dict[str, object]] = json.loads(out.strip().splitlines()[-1])
    return rows


def _worker(pythonpath: str, state: Path) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": f"{pythonpath}{os.pathsep}{ROOT / 'benches'}"}
    return subprocess.Popen(
        [
            sys.executable,
            __file__,
            "--repeats",
            "1",
            "--load-state",
            str(state),
            "--json",
            "--serve",
        ],
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=None if os.environ.get("LATENCY_VERBOSE") else subprocess.DEVNULL,
        text=True,
    )


def side_by_side(baseline: str, rounds: int, repeats: int, log: Callable[[str], None]) -> str:
    """This build and ``baseline`` timed on the same states (made once by this build): one
    worker process per build holds the maps, and the two take turns correction by correction
    (ABBA order), so that a slow spell of a shared machine falls on both alike; medians over
    ``rounds * repeats`` corrections each."""
    import compare_gtsam as shared

    this = str(ROOT / "python")
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state.pickle"
        log("building the states (15 corrections per map) with this build ...")
        _run(this, ["--repeats", "1", "--save-state", str(state)], log)
        workers = {}
        info: dict[str, dict[str, object]] = {}
        for name, path in (("baseline", baseline), ("this", this)):
            log(f"loading the maps in the {name} build ...")
            w = _worker(path, state)
            assert w.stdout is not None
            rows = json.loads(w.stdout.readline())
            for row in rows:
                info.setdefault(str(row["case"]), row)
            workers[name] = w
        times: dict[str, dict[str, list[float]]] = {"baseline": {}, "this": {}}
        try:
            for case in info:
                for k in range(rounds * repeats):
                    order = ("baseline", "this") if k % 2 == 0 else ("this", "baseline")
                    for name in order:
                        w = workers[name]
                        assert w.stdin is not None
                        assert w.stdout is not None
                        w.stdin.write(case + "\n")
                        w.stdin.flush()
                        times[name].setdefault(case, []).append(float(w.stdout.readline()))
                log(f"{case}: timed")
        finally:
            for w in workers.values():
                if w.stdin is not None:
                    w.stdin.close()
                w.wait()
    lines = [
        "| map | poses | points | earlier corrections | baseline median (ms) | this build "
        "median (ms) | ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, row in info.items():
        b = 1e3 * statistics.median(times["baseline"][key])
        t = 1e3 * statistics.median(times["this"][key])
        lines.append(
            f"| {row['map']} | {row['poses']} | {row['points']} | {row['earlier']} | {b:.1f} "
            f"| {t:.1f} | {t / b:.2f} |"
        )
    return "\n".join(
        [
            *shared.provenance(),
            "",
            f"The same correction on the same state (made once by this build) timed in both "
            f"builds, {rounds * repeats} times each: one process per build, taking turns "
            f"correction by correction (ABBA); medians. Baseline: `{baseline}`. Each timed "
            f"correction pays for its own symbolic analysis.",
            "",
            *lines,
        ]
    )


if __name__ == "__main__":
    sys.exit(main())
