#!/usr/bin/env python
"""How long a person waits for their corrections in a session at building scale: the raw Intel
log (13,631 scans) through the front end (`hitl_slam.slam.slam`), the map bent by heading
faults the front end did not see, a session started on it (a `.hitl` file), then drawings as a
person makes them at revisits of a wall (benches/revisits.py), timed as `Session.apply` (the
journal's writes included); the session closed and reopened, and one more drawing timed; then
both again as `serve` has them, after `Session.prepare` (the scans in the core, the odometry
check and the engine made in the background as the page opens); and last, the session
reopened in a process of its own, as `hitl-slam serve intel.hitl` has it, whose memory the
front end never touched. One core (RAYON_NUM_THREADS=1, set here unless given). Meant to run as

    python benches/session_latency.py --write benches/README.md

The bent map: the front end's chain turned by +2 / -1.5 degrees at every 3,000th scan (in its
steps, as a gyro fault would: its loop closures then contradict the chain there), so that the
corrections have something to repair and solve like real ones. The revisits and walls are found
on the front end's own map.
"""

from __future__ import annotations

import os

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import argparse
import dataclasses
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hitl_slam.errors import CorrectionRejected
from hitl_slam.geometry import chain_steps, wrap
from hitl_slam.map import Map
from hitl_slam.session import Session

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT.parent / "shared" / "datasets" / "laser" / "intel.clf.bz2"
FAULT_EVERY = 3000
SECTION = "session-latency"


def bent(m: Map) -> Map:
    """``m`` with its chain turned at every :data:`FAULT_EVERY`-th scan (poses and the chain
    steps there; every other edge as it was)."""
    poses = m.poses.copy()
    for k, fault in enumerate(range(FAULT_EVERY, m.num_poses, FAULT_EVERY)):
        ang = math.radians(2.0 if k % 2 == 0 else -1.5)
        c = poses[fault - 1]
        rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        poses[fault:, :2] = (poses[fault:, :2] - c[:2]) @ rot.T + c[:2]
        poses[fault:, 2] = wrap(poses[fault:, 2] + ang)
    steps = chain_steps(poses)
    e = m.edges
    chain = np.flatnonzero(e[:, 1] == e[:, 0] + 1)
    measurements = m.measurements.copy()
    measurements[chain] = steps[e[chain, 0]]
    return dataclasses.replace(m, poses=poses, measurements=measurements)


def _joined(thread: Any) -> None:
    if thread is not None:
        thread.join()


def next_correction(
    session: Session, drawer: Any, pairs: list[tuple[int, int]]
) -> tuple[float, str] | None:
    """The next revisit's drawing applied to ``session``, timed (``Session.apply`` only): its
    time [s] and a note; revisits whose drawing is refused are skipped (taken from ``pairs``);
    None when none is left."""
    while pairs:
        i, j = pairs.pop(0)
        try:
            drawn = drawer.draw(np.array(session.poses), i, j)
            t = time.perf_counter()
            applied = session.apply(drawn)
        except (CorrectionRejected, ValueError):
            continue
        took = time.perf_counter() - t
        return took, f"{applied.iterations} iterations, revisit {i} / {j}"
    return None


def reopen_in_new_process(state: Path) -> int:
    """The child of ``--new-process``: the session reopened in a process of its own, as
    ``hitl-slam serve intel.hitl`` has it (prepared, then drawings); prints each correction's
    time and note as JSON."""
    import json
    import pickle

    from revisits import WallDrawer

    path, m, front_poses, pairs, count = pickle.loads(state.read_bytes())
    drawer = WallDrawer(m, front_poses, 11)
    out: list[tuple[float, str]] = []
    with Session.open(path) as session:
        _joined(session.prepare())
        while len(out) < count and (timed := next_correction(session, drawer, pairs)):
            out.append(timed)
    print(json.dumps(out))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    import compare_gtsam as shared
    from hitl_slam.slam import slam
    from revisits import WallDrawer, revisit_pairs

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--later", type=int, default=5, help="drawings timed after the first")
    parser.add_argument("--write", type=Path, metavar="README", help="replace the section")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        return reopen_in_new_process(args.child)
    log: Callable[[str], None] = lambda msg: print(msg, file=sys.stderr)  # noqa: E731
    if not INTEL.is_file():
        log(f"{INTEL} not found")
        return 1
    t = time.perf_counter()
    result = slam(str(INTEL))
    log(f"front end: {time.perf_counter() - t:.1f} s")
    front = result.map
    m = bent(front)
    drawer = WallDrawer(m, front.poses, 11)
    pairs = revisit_pairs(front.poses)
    log(f"{m.num_poses} scans, {len(pairs)} revisits")
    rows: list[tuple[str, float, str]] = []

    def correct(session: Session, what: str) -> bool:
        timed = next_correction(session, drawer, pairs)
        if timed is None:
            return False
        rows.append((what, *timed))
        log(f"{what}: {1e3 * timed[0]:.0f} ms ({timed[1]})")
        return True

    timings: dict[str, float] = {}

    def timed(what: str, f: Callable[[], Any]) -> Any:
        t = time.perf_counter()
        out = f()
        timings[what] = time.perf_counter() - t
        return out

    with tempfile.TemporaryDirectory(prefix="session-latency-") as tmp:
        path = Path(tmp) / "intel.hitl"
        with timed("new", lambda: Session.new(m, path)) as session:
            correct(session, "first after slam")
            for _ in range(args.later):
                correct(session, "later")
        with timed("open", lambda: Session.open(path)) as reopened:
            correct(reopened, "first after reopening")
        # As `serve` does: Session.prepare in the background while the page opens.
        with Session.new(m, Path(tmp) / "served.hitl") as served:
            timed("prepare", lambda: _joined(served.prepare()))
            correct(served, "first after slam, prepared")
        with Session.open(path) as served:
            timed("prepare again", lambda: _joined(served.prepare()))
            correct(served, "first after reopening, prepared")
        # As `hitl-slam serve intel.hitl` has it: a process of its own, whose memory the front
        # end never touched.
        import json
        import pickle
        import subprocess

        state = Path(tmp) / "state.pickle"
        state.write_bytes(pickle.dumps((path, m, front.poses, pairs, 1 + args.later)))
        child = subprocess.run(
            [sys.executable, __file__, "--child", str(state)],
            check=True,
            capture_output=True,
            text=True,
        )
        fresh = json.loads(child.stdout)
    later = [r[1] for r in rows if r[0] == "later"]
    firsts = {r[0]: r for r in rows if r[0] != "later"}

    def row(what: str, label: str) -> list[str]:
        if what not in firsts:
            return []
        _, took, note = firsts[what]
        return [f"| {label} | {1e3 * took:.0f} | {note} |"]

    table = [
        "| step | ms | notes |",
        "|---|---|---|",
        f"| Session.new (the map written, its odometry checked) | {1e3 * timings['new']:.0f} | |",
        *row("first after slam", "first correction after slam"),
    ]
    if later:
        table.append(
            f"| later corrections, median of {len(later)} | {1e3 * statistics.median(later):.0f} "
            f"| {min(later) * 1e3:.0f} - {max(later) * 1e3:.0f} ms |"
        )
    table += [
        f"| Session.open | {1e3 * timings['open']:.0f} | |",
        *row("first after reopening", "first correction after reopening"),
        f"| Session.prepare (serve: in the background as the page opens) | "
        f"{1e3 * timings['prepare']:.0f} | |",
        *row("first after slam, prepared", "first correction after slam, prepared"),
        f"| Session.prepare after reopening | {1e3 * timings['prepare again']:.0f} | |",
        *row("first after reopening, prepared", "first correction after reopening, prepared"),
    ]
    if fresh:
        took, note = fresh[0]
        table.append(
            f"| first correction after reopening in a new process (serve intel.hitl), prepared "
            f"| {1e3 * took:.0f} | {note} |"
        )
        rest = [t for t, _ in fresh[1:]]
        if rest:
            table.append(
                f"| later corrections in that process, median of {len(rest)} | "
                f"{1e3 * statistics.median(rest):.0f} | {min(rest) * 1e3:.0f} - "
                f"{max(rest) * 1e3:.0f} ms |"
            )
    body = "\n".join(
        [
            *shared.provenance(),
            "",
            "`python benches/session_latency.py` (one core): the raw Intel log through the front "
            f"end ({result.time_s:.0f} s), its chain turned by +2 / -1.5 degrees at every "
            f"{FAULT_EVERY}th scan, a session on it in a `.hitl` file; each correction is "
            "`Session.apply` of a colocation drawn at a revisit of a wall (journal writes "
            "included). Targets (issue 40): the first correction after slam and after "
            "reopening at most 300 ms, later ones at most 150 ms.",
            "",
            *table,
            "",
            "Data: the Intel Research Lab log (D. Haehnel), via the SLAM benchmark of "
            "Kuemmerle et al. 2009; thanks to its authors.",
        ]
    )
    print(body)
    if args.write:
        shared.replace_section(args.write, SECTION, body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
