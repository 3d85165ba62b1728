"""The ``hitl-slam`` command line: argument parsing, progress, tables, exit codes.

The only module that prints. Exit codes: 0 success, 2 bad input or an output that cannot be
written (one-line reason on stderr; then no output was written), 1 a solver failure, 3
(``solve``) the solve did not converge (the best estimate is still written). A command's outputs
appear together or not at all (:func:`hitl_slam.io.atomic.atomic_outputs`), and an output that
is one of its inputs (the same file, also through a link) is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import contextvars
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from hitl_slam import __version__
from hitl_slam.errors import HitlSlamError, InputError, SolverError
from hitl_slam.extras import require

if TYPE_CHECKING:
    from hitl_slam.graph import PoseGraph
    from hitl_slam.io.rosbag import BagOptions
    from hitl_slam.map import Map
    from hitl_slam.metrics import Inconsistency
    from hitl_slam.session import Session

T = TypeVar("T")

_SLAM_EPILOG = """\
examples:
  hitl-slam slam intel.clf.bz2 -o intel.hitl          # then: hitl-slam serve intel.hitl
  hitl-slam slam fr079.clf.bz2 -o fr079.g2o
  hitl-slam metrics intel.hitl --relations intel.relations

The output map's poses are the front end's; its factors are the matched steps between
consecutive scans and the loop closures the final solve kept. The summary line starts with the
front end's verdict: "good map", or "DOUBTFUL map" with the stretches of scans to look at first
(scans it could not match, matches far weaker than the ones before them, scans placed far from
the odometry by an unclear match, or steps the final solve bent away from their matches;
docs/ALGORITHM.md §F.5). A doubtful map is still written:
it is the starting point to repair (`hitl-slam serve OUT.hitl` shows those stretches). The
summary also counts unmatched and ambiguous scans, keyframes, loop closures accepted, rejected
and set aside as inconsistent with the others found with them, and the speed against the log's
own duration.
"""

_SOLVE_EPILOG = """\
examples:
  hitl-slam solve M3500.g2o -o M3500-optimized.g2o
  hitl-slam solve w100.graph -o w100-optimized.graph --method gn
  hitl-slam solve raw.g2o -o out.g2o --init chordal          # vertices unknown or far off
  hitl-slam solve frontend.g2o -o out.g2o --robust dcs       # some loop closures are wrong
  hitl-slam solve run.g2o -o out.g2o --robust loop=cauchy --robust odometry=huber:3
  hitl-slam solve city10000.g2o -o out.g2o --max-iterations 20 --quiet

The input is a g2o (VERTEX_SE2/EDGE_SE2) or TORO (VERTEX2/EDGE2) 2D pose graph; its first vertex
(or a g2o FIX line) is held fixed. The output format follows the output file's extension (.g2o
or .graph). chi2 is sum r^T Omega r over all edges.

Where to start (--init): `given` uses the file's vertices (the default; right when they come
from a SLAM front end or a map being corrected); `tree` composes the measurements along a
spanning tree from the fixed vertex, odometry first (g2o's and TORO's guess); `chordal` solves
the rotations first by chordal relaxation, then the positions (as GTSAM's LAGO): pick it when
the vertices are unknown, or off by radians.

Robust kernels (--robust [CLASS=]KIND[:PARAM], repeatable): KIND is huber (PARAM k, default
1.345), cauchy (k, default 2.3849) or dcs (dynamic covariance scaling, phi, default 1); k is in
sigmas of the whitened residual, phi in chi2 units (GTSAM's mEstimator conventions). CLASS is
loop (the default: edges between non-consecutive poses), odometry (consecutive poses) or prior.
Edges whose final weight is below 0.5 are listed as down-weighted.

The summary names why the solve stopped: converged by the function, gradient or step tolerance,
or not: max_iterations, stalled (no step decreases the cost), non_finite (diverged). Exit
status: 0 converged, 3 not converged (the best estimate is still written), 2 bad input (nothing
written), 1 solver failure.
"""

_GENERATE_EPILOG = """\
examples:
  hitl-slam generate manhattan.g2o                 # 1000 poses, seed 0
  hitl-slam generate big.g2o --poses 20000 --seed 3

Writes a Manhattan-world pose graph (a robot driving on a grid, noisy odometry, loop closures at
revisited cells) whose vertices are the composed odometry, and the ground truth next to it as
OUT.truth.txt (one "x y theta" line per pose).
"""

_CORRECT_EPILOG = """\
examples:
  hitl-slam correct map.covars --corrections fixes.jsonl -o fixed.covars
  hitl-slam correct run.clf.gz --corrections fixes.jsonl -o fixed.g2o --session run.hitl
  hitl-slam correct map.covars --corrections fixes.jsonl -o fixed.pgm --keep-going

MAP is a .covars file, a CARMEN log (.clf/.log, optionally .gz/.bz2), a ROS bag (.bag, .db3,
.mcap or a ROS 2 bag directory; see "ROS bags" below) or a session (.hitl, its current map). The
corrections file has one JSON object per line, applied in order, each on the
map as it stands after the previous ones:

  {"mode": "collinear", "a": [[1.20, 3.40], [4.10, 3.45]], "b": [[10.0, 3.9], [13.2, 4.0]]}
  {"mode": "colocation", "a": [[0, 0], [0, 2]], "b": [[5, 1], [5, 3]], "sigma_h": 0.08}
  {"action": "undo"}

mode is colocation, collinear, perpendicular or parallel; a and b are the two drawn segments
(world frame, metres); sigma_h is the drawing accuracy in metres. Blank lines are skipped; there
are no comments. A session's applied corrections are exported in this form by
`hitl-slam export SESSION.hitl -o C.jsonl`.

A correction that cannot be interpreted (no observations under a segment, interleaved pose sets),
an undo with nothing to undo and a redo with nothing to redo are rejected. Without --keep-going
the run stops at the first one with exit code 2 and writes nothing; with --keep-going they are
skipped and listed, and the rest still apply (exit code 0 once OUT is written).

--align, once every line is done, aligns the map with its scans (docs/ALGORITHM.md §I.11): the
scan-matching front end runs again from the corrected poses, its matched steps and loop closures
replace the map's factors, and every correction is solved again over them. The person's
statements bring copies of a wall together; the scans then close the last centimetres. Where the
aligned map contradicts the robot's odometry at more than 5% of the steps (scan matching gone
wrong: few features, a fault not yet corrected), where the scans found no loop closure between
the passes, or where the aligned map is no more consistent than the map, it is refused with the
figures: exit code 2, nothing written.

OUT's extension picks its format (.covars, .clf CARMEN log, .g2o, .txt TUM, .pgm + .yaml
occupancy grid, .png or .svg figure). --session also keeps the whole run as a session file (a new
file; an existing one is never overwritten) that `hitl-slam serve` or `hitl-slam export` can
open. OUT and the session file are written together or not at all; OUT may not be MAP or C.jsonl
(the same file, also through a link) unless --force. "moved" counts the poses a step moved by
more than 1 mm or 1 mrad.
"""

_EXPORT_EPILOG = """\
examples:
  hitl-slam export run.hitl -o run.covars        # the session's current map
  hitl-slam export run.hitl -o run.jsonl         # its applied corrections, replayable
  hitl-slam export run.clf.gz -o run.pgm         # occupancy grid (+ run.yaml for map_server)
  hitl-slam export map.covars -o map.txt         # trajectory, TUM: t x y z qx qy qz qw
  hitl-slam export run.hitl -o fixed.clf         # a CARMEN log with the corrected poses
  hitl-slam export run.hitl -o run.png           # a picture of the map (.png or .svg)

MAP_OR_SESSION is a .covars file, a CARMEN log (.clf/.log, optionally .gz/.bz2), a ROS bag (.bag,
.db3, .mcap or a ROS 2 bag directory) or a session (.hitl). OUT's extension picks the format:
.covars, .clf (the map's own CARMEN log with only its poses changed, or one ROBOTLASER1 line per
scan when the map did not come from one), .g2o, .txt, .pgm, .png or .svg (a figure, needs the
plot extra), or .jsonl (corrections; only from a session, whose file is read and never changed).
OUT may not be the input (the same file, also through a link) unless --force.
"""

_METRICS_EPILOG = """\
examples:
  hitl-slam metrics fixed.covars
  hitl-slam metrics fr079.clf.bz2 --relations fr079.relations
  hitl-slam metrics restamped.bag --relations fr079.relations --tolerance 0.05
  hitl-slam metrics run.hitl --heat-map run-heat.png

MAP is a .covars file, a CARMEN log (.clf/.log, optionally .gz/.bz2), a ROS bag (.bag, .db3,
.mcap or a ROS 2 bag directory) or a session (.hitl, its current map). Inconsistency (Nashed and
Biswas 2018): summed over ordered pairs of scans, the area one scan sees as free space and the
other as occupied, on a grid of --resolution cells, in m^2 (lower is better; a perfect map scores
near zero). With --relations (Kuemmerle et al. 2009, "t1 t2 dx dy dz roll pitch yaw" lines
matched to the nearest scans by timestamp): mean +- standard deviation of |t_est - t_true| (m)
and |yaw_est - yaw_true| (deg) of the relative poses. A relation with a timestamp farther than
--tolerance (default 0.001 s) from every scan is skipped: the line says how many were matched and
how many skipped, so a cut log scores on what it kept, and a larger --tolerance scores a log whose
stamps moved (e.g. re-stamped by 0.02 s: --tolerance 0.05, below half the scan period).
--heat-map draws the per-cell count of contradicting scan pairs over the map as a PNG.
"""

_BAGS_NOTE = """
ROS bags (needs the ros extra: pip install 'hitl-slam[ros]'): the scans of the bag's
sensor_msgs/LaserScan topic (--scan-topic when it has several), the odometry from /tf
(--odom-frame -> --base-frame) or a nav_msgs/Odometry topic (--odom-topic), interpolated at each
scan's stamp, and the laser's mounting from /tf_static. When /tf has map -> odom (slam_toolbox,
Cartographer), the poses are the SLAM's own trajectory; --map-frame '' keeps the odometry's.
Points are kept in the robot's frame (base_link).
"""


def _with_progress(label: str, quiet: bool, work: Callable[[], T]) -> T:
    """Runs ``work`` (which releases the GIL) in a thread; shows elapsed time on a terminal."""
    if quiet or not sys.stderr.isatty():
        return work()
    from tqdm import tqdm

    result: list[T] = []
    error: list[BaseException] = []

    def run() -> None:
        try:
            result.append(work())
        except BaseException as exc:  # re-raised in the caller's thread
            error.append(exc)

    # The worker runs in this thread's context, so an atomic_outputs() group reaches it.
    context = contextvars.copy_context()
    thread = threading.Thread(target=context.run, args=(run,), daemon=True)
    thread.start()
    with tqdm(desc=label, total=None, unit="", leave=False, file=sys.stderr) as bar:
        while thread.is_alive():
            thread.join(0.1)
            bar.update(0)
            bar.refresh()
    if error:
        raise error[0]
    return result[0]


def _load_map(args: argparse.Namespace, source: str | Path) -> Map:
    """The map of a command's MAP argument, with ``--max-range``; says on stderr how the laser's
    maximum range was found when the log stated none."""
    from hitl_slam.io.maps import load_map

    max_range = getattr(args, "max_range", None)
    bag = _bag_options(args)
    the_map = _with_progress(
        "loading", args.quiet, lambda: load_map(source, max_range=max_range, bag=bag)
    )
    how = the_map.metadata.get("max_range_source")
    if isinstance(how, str) and how.startswith("inferred"):
        print(f"hitl-slam: {source}: maximum laser range {how}", file=sys.stderr)
    return the_map


def _add_max_range(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--max-range",
        type=float,
        metavar="M",
        help="the laser's maximum range in metres (CARMEN logs, ROS bags): readings at or "
        "beyond it are no-returns, not obstacles; default: a bag's range_max, a log's PARAM "
        "robot_front_laser_max, else inferred from readings piled at the largest value, else 80",
    )


def _add_bag_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "ROS bags", "what to read from a .bag, .db3, .mcap or ROS 2 bag directory"
    )
    group.add_argument(
        "--scan-topic",
        metavar="TOPIC",
        help="the sensor_msgs/LaserScan topic (default: the bag's only one)",
    )
    group.add_argument(
        "--odom-topic",
        metavar="TOPIC",
        help="take the odometry from this nav_msgs/Odometry topic (default: /tf odom -> "
        "base_link, else the bag's only Odometry topic)",
    )
    group.add_argument(
        "--odom-frame", default="odom", metavar="FRAME", help="the odometry frame (default odom)"
    )
    group.add_argument(
        "--base-frame",
        default="base_link",
        metavar="FRAME",
        help="the robot's frame, in which the points are kept (default base_link)",
    )
    group.add_argument(
        "--map-frame",
        default="map",
        metavar="FRAME",
        help="the SLAM's map frame: when /tf has FRAME -> odom, the poses are the SLAM's "
        "trajectory (default map; '' for the odometry's)",
    )


def _bag_options(args: argparse.Namespace) -> BagOptions | None:
    """The ROS bag options of a command that has them, or None."""
    if not hasattr(args, "scan_topic"):
        return None
    from hitl_slam.io.rosbag import BagOptions

    return BagOptions(
        scan_topic=args.scan_topic,
        odom_topic=args.odom_topic,
        odom_frame=args.odom_frame,
        base_frame=args.base_frame,
        map_frame=args.map_frame or None,
    )


def _add_force(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--force",
        action="store_true",
        help="write the output even when it is one of the input files (replacing that input)",
    )


def _outputs_of(out: Path) -> list[Path]:
    """The files writing ``out`` creates: a .pgm brings its .yaml."""
    return [out, out.with_suffix(".yaml")] if out.suffix.lower() == ".pgm" else [out]


def _refuse_overwriting_inputs(
    outputs: Sequence[Path], inputs: Sequence[str | Path | None], force: bool
) -> None:
    """An InputError when an output is an existing input file (the same file, by name, symbolic
    link or hard link), unless ``force``."""
    if force:
        return
    for out in outputs:
        for source in inputs:
            if source is None:
                continue
            try:
                same = os.path.samefile(out, source)
            except OSError:  # one of them does not exist (yet): nothing to overwrite
                continue
            if same:
                also = "" if str(out) == str(source) else f" as the input {source}"
                raise InputError(
                    f"{out}: is the same file{also}; writing it would replace the input: "
                    "give another output name, or pass --force to overwrite the input"
                )


_MAP_KINDS = {
    ".clf": "a CARMEN log",
    ".log": "a CARMEN log",
    ".bag": "a ROS bag",
    ".db3": "a ROS bag",
    ".mcap": "a ROS bag",
    ".covars": "a .covars map",
    ".hitl": "a session",
}
_CARMEN_WORDS = (b"PARAM", b"ODOM", b"FLASER", b"RLASER", b"ROBOTLASER1", b"RAWLASER", b"TRUEPOS")


def _map_kind(path: Path) -> str | None:
    """What kind of map (not pose graph) ``path`` names by its extension, or None."""
    suffixes = [x.lower() for x in path.suffixes]
    if suffixes and suffixes[-1] in (".gz", ".bz2"):
        suffixes.pop()
    return _MAP_KINDS.get(suffixes[-1]) if suffixes else None


def _looks_like_carmen(path: Path) -> bool:
    """Whether the first data line of the (uncompressed) file starts with a CARMEN keyword."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return False
    for line in head.splitlines():
        words = line.split()
        if words and not words[0].startswith(b"#"):
            return words[0] in _CARMEN_WORDS
    return False


def _not_a_pose_graph(path: Path, kind: str) -> InputError:
    stem = path.name.split(".")[0] or "map"
    return InputError(
        f"{path}: {kind} (poses and laser scans) is a map, not a pose graph; `hitl-slam solve` "
        f"reads .g2o / .graph pose graphs. Correct the map with `hitl-slam correct {path} "
        f"--corrections C.jsonl -o OUT` or `hitl-slam serve {path}`, or write its pose graph "
        f"with `hitl-slam export {path} -o {stem}.g2o` and solve that"
    )


def _cmd_solve(args: argparse.Namespace) -> int:
    import numpy as np

    from hitl_slam.io import load_graph_with_report, save_graph
    from hitl_slam.solve import Init, Method, downweighted, optimize, robust_pairs

    out = Path(args.output)
    if out.suffix.lower() not in (".g2o", ".graph"):
        raise InputError(f"{out}: unsupported output extension {out.suffix!r}; use .g2o or .graph")
    source = Path(args.graph)
    kind = _map_kind(source)
    if kind is not None:
        raise _not_a_pose_graph(source, kind)
    _refuse_overwriting_inputs([out], [source], args.force)
    robust = robust_pairs(",".join(args.robust)) if args.robust else []
    t0 = time.perf_counter()
    try:
        graph, load = _with_progress(
            "loading", args.quiet, lambda: load_graph_with_report(args.graph)
        )
    except InputError:
        if _looks_like_carmen(source):
            raise _not_a_pose_graph(source, "a CARMEN log") from None
        raise
    t_load = time.perf_counter() - t0
    method = Method(args.method)
    poses, report = _with_progress(
        "solving",
        args.quiet,
        lambda: optimize(
            graph,
            init=Init(args.init),
            method=method,
            robust=dict(robust) if robust else None,
            max_iterations=args.max_iterations,
            relative_tolerance=args.relative_tolerance,
            absolute_tolerance=args.absolute_tolerance,
        ),
    )
    save_graph(graph, poses, out)
    start = args.init
    if args.init == "given" and load.poses_from_odometry:
        start = "given, chained from the edges (the file has no vertex lines)"
    if not args.quiet:
        print(
            f"{args.graph}: {graph.num_poses} poses, {graph.num_edges} edges "
            f"({load.format.value}, read in {t_load:.3f} s); start: {start}"
        )
        print(f"{'iter':>5} {'cost':>16} {'damping':>10} {'|step|':>10} {'ok':>3} {'ms':>9}")
        for rec in report.history:
            print(
                f"{rec.iteration:>5} {rec.chi2:>16.6f} {rec.damping:>10.2e} "
                f"{rec.step_norm:>10.3e} {'yes' if rec.accepted else 'no':>3} "
                f"{1e3 * rec.elapsed_s:>9.2f}"
            )
    if robust:
        bad = downweighted(report)
        ids = graph.vertex_ids if graph.vertex_ids is not None else np.arange(graph.num_poses)
        shown = ", ".join(
            f"{ids[graph.edges[k, 0]]}->{ids[graph.edges[k, 1]]} (w {report.weights[k]:.2g})"
            for k in bad[:10]
        )
        more = f", ... ({len(bad) - 10} more)" if len(bad) > 10 else ""
        kernels = ", ".join(f"{c}={k}" for c, k in robust)
        print(
            f"robust ({kernels}): cost {report.initial_cost:.6f} -> {report.final_cost:.6f}; "
            f"{len(bad)} of {graph.num_edges} edges down-weighted below 0.5"
            + (f": {shown}{more}" if len(bad) else "")
        )
    status = "converged" if report.converged else "NOT converged"
    print(
        f"{method.name.lower().replace('_', '-')}: chi2 {report.initial_chi2:.6f} -> "
        f"{report.final_chi2:.6f} in {report.iterations} iterations, {status} "
        f"({report.termination}: {report.termination_detail}), {1e3 * report.time_s:.1f} ms; "
        f"wrote {out}"
    )
    if not report.converged:
        # Exit 3 must not be silent on stderr (scripts often show only stderr).
        print(
            f"hitl-slam: {args.graph}: the solve did not converge ({report.termination}: "
            f"{_one_line(report.termination_detail)}); the estimate was written to {out} anyway"
            f"{_worst_edge(graph)}",
            file=sys.stderr,
        )
    return 0 if report.converged else 3


def _worst_edge(graph: PoseGraph) -> str:
    """``; the worst edge: ...`` naming the edge whose chi2 is largest at the start, where a
    damaged vertex or edge usually shows; "" when it cannot be said."""
    import numpy as np

    from hitl_slam.geometry import compose_rows, invert, wrap

    start = graph.poses
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    with np.errstate(all="ignore"):
        predicted = compose_rows(invert(start[i]), start[j])
        r = compose_rows(invert(graph.measurements), predicted)
        r[:, 2] = wrap(r[:, 2])
        per_edge = np.einsum("ei,eij,ej->e", r, graph.information, r)
    if per_edge.size == 0 or not np.isfinite(per_edge).any():
        return ""
    k = int(np.nanargmax(per_edge))
    ids = graph.vertex_ids if graph.vertex_ids is not None else np.arange(graph.num_poses)
    return (
        f"; the largest error at the start is on edge {ids[i[k]]} -> {ids[j[k]]} (chi2 "
        f"{per_edge[k]:.3g} of {np.nansum(per_edge):.3g}): check vertices {ids[i[k]]} and "
        f"{ids[j[k]]} and that edge for a damaged value"
    )


def _cmd_generate(args: argparse.Namespace) -> int:
    import numpy as np

    from hitl_slam.io import save_graph
    from hitl_slam.io.atomic import atomic_outputs, atomic_write_text
    from hitl_slam.sim.synthetic import manhattan_world

    out = Path(args.output)
    graph, truth = manhattan_world(args.poses, seed=args.seed)
    truth_path = out.with_suffix(".truth.txt")
    with atomic_outputs():  # both files or neither
        save_graph(graph, graph.poses, out)
        text = "".join(f"{x!r} {y!r} {t!r}\n" for x, y, t in truth.tolist())
        atomic_write_text(truth_path, text)
    err = np.hypot(*(graph.poses[:, :2] - truth[:, :2]).T)
    print(
        f"wrote {out}: Manhattan world, {graph.num_poses} poses, {graph.num_edges} edges "
        f"(odometry drift up to {err.max():.2f} m), ground truth in {truth_path}"
    )
    return 0


def _check_map_output(out: Path, extra: tuple[str, ...] = ()) -> None:
    from hitl_slam.io.export import EXPORT_EXTENSIONS

    if out.suffix.lower() not in EXPORT_EXTENSIONS + extra:
        supported = ", ".join(EXPORT_EXTENSIONS + extra)
        raise InputError(f"{out}: unsupported output extension {out.suffix!r}; use {supported}")


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _align_session(args: argparse.Namespace, session: Session) -> None:
    """``--align``: the session's map aligned with its scans, with a progress bar over the
    scans; a refusal stops the command (nothing written) with its figures."""
    from hitl_slam.alignment import AlignmentRefused
    from hitl_slam.session import moved_poses

    bar = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=session.input_map.num_poses, desc="aligning", unit="scan", file=sys.stderr)

    def progress(done: int, _total: int) -> None:
        if bar is not None:
            bar.n = done
            bar.refresh()

    before = session.poses
    try:
        step = session.align(progress=progress)
    except AlignmentRefused as exc:
        raise InputError(
            f"--align: {exc}; nothing was written (drop --align to write the corrected map)"
        ) from None
    finally:
        if bar is not None:
            bar.close()
    if not args.quiet:
        moved, _ = moved_poses(before, session.poses)
        print(
            f"{'':>5}  {'align':<14} {moved:>7} {step.stats.initial_chi2:>16.6f} "
            f"{step.stats.final_chi2:>16.6f} {1e3 * step.stats.time_s:>9.2f}"
        )
        print(
            f"       aligned with the scans: {step.loop_closures} loop closures kept "
            f"({step.loop_closures_rejected} rejected); the aligned map contradicts "
            f"{step.contradicted} of {step.steps} odometry steps beyond their 99.9% bound; "
            f"inconsistency {step.inconsistency[0]:.1f} -> {step.inconsistency[1]:.1f} m^2; "
            f"the statements carry DCS Phi {step.relation_dcs:g} (the more consistent solve)"
        )


def _cmd_correct(args: argparse.Namespace) -> int:
    from hitl_slam.corrections_file import Apply, read_corrections
    from hitl_slam.errors import CorrectionRejected
    from hitl_slam.session import Session, StepRefused, moved_poses

    out = Path(args.output)
    _check_map_output(out)
    _refuse_overwriting_inputs(_outputs_of(out), [args.map, args.corrections], args.force)
    session_path = None if args.session is None else Path(args.session)
    if session_path is not None:
        if session_path.suffix.lower() != ".hitl":
            raise InputError(f"{session_path}: a session file must end in .hitl; rename it")
        if session_path.exists():
            raise InputError(
                f"{session_path}: already exists; `hitl-slam correct` starts a new session and "
                "never overwrites one: choose another name or delete the old file"
            )
    steps = read_corrections(args.corrections)
    t_start = time.perf_counter()
    the_map = _load_map(args, args.map)
    rejected: list[tuple[int, str]] = []
    counts = {"applied": 0, "undo": 0, "redo": 0}

    def reject(line: int, name: str, reason: str) -> None:
        if not args.keep_going:
            raise InputError(
                f"{args.corrections}:{line}: {reason}; nothing was written (fix or delete the "
                "line, or pass --keep-going to skip it)"
            )
        rejected.append((line, reason))
        if not args.quiet:
            print(f"{line:>5}  {name:<14} {'rejected (listed below)':>24}")

    with Session.new(the_map) as session:
        if not args.quiet:
            print(
                f"{args.map}: {the_map.num_poses} poses, {the_map.num_points} points; "
                f"{len(steps)} steps in {args.corrections}"
            )
            print(
                f"{'line':>5}  {'step':<14} {'moved':>7} {'chi2 before':>16} "
                f"{'chi2 after':>16} {'ms':>9}"
            )
        for step in steps:
            before = session.poses
            name = step.drawn.mode.value if isinstance(step, Apply) else type(step).__name__.lower()
            try:
                result = _with_progress(
                    f"line {step.line}: {name}", args.quiet, partial(session.run_step, step)
                )
            except CorrectionRejected as exc:
                reject(step.line, name, f"{name} correction rejected: {_one_line(str(exc))}")
                continue
            except StepRefused as exc:
                reject(step.line, name, str(exc))
                continue
            counts["applied" if result.action == "apply" else result.action] += 1
            stats = result.entry.stats if result.action == "apply" else None
            chi2 = (
                f"{'-':>16} {'-':>16}"
                if stats is None
                else f"{stats.initial_chi2:>16.6f} {stats.final_chi2:>16.6f}"
            )
            moved, _ = moved_poses(before, session.poses)
            if not args.quiet:
                print(f"{step.line:>5}  {name:<14} {moved:>7} {chi2} {1e3 * result.time_s:>9.2f}")
        if args.align:
            _align_session(args, session)
        _write_correct_outputs(args, session, out, session_path)
    if rejected and not args.quiet:
        print(f"rejected ({len(rejected)}):")
        for line, reason in rejected:
            print(f"  {args.corrections}:{line}: {reason}")
    applied = counts["applied"]
    done = f"{applied} correction{'' if applied == 1 else 's'} applied"
    if args.align:
        done += ", then aligned with the scans"
    if counts["undo"] or counts["redo"]:
        done += f", {counts['undo']} undone, {counts['redo']} redone"
    if rejected:
        lines = ", ".join(str(line) for line, _ in rejected)
        done += f", {len(rejected)} rejected (line{'s' if len(rejected) > 1 else ''} {lines})"
    written = f"wrote {out}" + ("" if session_path is None else f" and {session_path}")
    print(f"{done} in {time.perf_counter() - t_start:.2f} s; {written}")
    return 0


def _write_correct_outputs(
    args: argparse.Namespace, session: Session, out: Path, session_path: Path | None
) -> None:
    """OUT (and its .yaml) and the new session file, all or none: OUT is prepared, the session
    file created, then OUT renamed into place; if that fails the session file is removed."""
    from hitl_slam.io.atomic import atomic_outputs

    created = False
    try:
        with atomic_outputs():
            _with_progress("writing", args.quiet, lambda: session.save(out))
            if session_path is not None:
                session.write_journal(session_path)
                created = True
    except BaseException as exc:
        if created and session_path is not None:
            try:
                os.unlink(session_path)
            except OSError as gone:
                exc.add_note(f"{session_path} could not be removed ({gone.strerror}): delete it")
        raise


def _cmd_slam(args: argparse.Namespace) -> int:
    from hitl_slam.slam import slam

    for option, value in (
        ("--keyframe-distance", args.keyframe_distance),
        ("--match-range", args.match_range),
        ("--loop-min-score", args.loop_min_score),
    ):
        # Checked here so that the message names the option typed, not the library's argument.
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"{option} must be a positive number, got {value:g}")
    out = Path(args.output)
    _check_map_output(out, (".hitl",))
    _refuse_overwriting_inputs(_outputs_of(out), [args.log], args.force)
    if out.suffix.lower() == ".hitl" and out.exists():
        raise InputError(
            f"{out}: already exists; a session file is never overwritten: choose another name or "
            "delete the old one"
        )
    from hitl_slam.io.rosbag import is_rosbag

    if is_rosbag(args.log):
        args.map_frame = ""  # the front end starts from the odometry, not the bag's own SLAM
    raw = _load_map(args, args.log)
    if not args.quiet:
        print(f"{args.log}: {raw.num_poses} scans, {raw.num_points} points")
    bar = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=raw.num_poses, desc="front end", unit="scan", file=sys.stderr)
    duration = (
        None
        if raw.timestamps is None or raw.num_poses < 2
        else float(raw.timestamps[-1] - raw.timestamps[0])
    )
    started = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if bar is None:
            return
        bar.n = done
        elapsed = time.perf_counter() - started
        if duration is not None and elapsed > 0 and total > 0:
            bar.set_postfix_str(f"{duration * done / total / elapsed:.1f}x real time")
        bar.refresh()

    try:
        result = slam(
            raw,
            progress=progress,
            keyframe_distance=args.keyframe_distance,
            keyframe_angle_deg=args.keyframe_angle,
            max_range=args.match_range,
            loop_min_score=args.loop_min_score,
        )
    finally:
        if bar is not None:
            bar.close()
    if out.suffix.lower() == ".hitl":
        from hitl_slam.session import Session

        with Session.new(result.map) as session:
            session.write_journal(out)
    else:
        from hitl_slam.io.export import export

        kept = result.accepted_map()  # a pose graph holds what the front end trusted
        _with_progress("writing", args.quiet, lambda: export(kept, kept.poses, out))
    print(f"{result.summary()}; wrote {out}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:

    out = Path(args.output)
    _check_map_output(out, (".jsonl",))
    source = Path(args.input)
    _refuse_overwriting_inputs(_outputs_of(out), [source], args.force)
    if out.suffix.lower() == ".jsonl":
        from hitl_slam.session import Session

        if source.suffix.lower() != ".hitl":
            raise InputError(
                f"{source}: corrections (.jsonl) come from a session; give a .hitl session file "
                "as input"
            )
        with Session.open(source) as session:
            count = session.export_corrections(out)
        print(f"wrote {out}: {count} corrections from {source}")
        return 0
    from hitl_slam.io.export import export

    the_map = _load_map(args, source)
    _with_progress("writing", args.quiet, lambda: export(the_map, the_map.poses, out))
    print(f"wrote {out}: {the_map.num_poses} poses, {the_map.num_points} points from {source}")
    return 0


def _cmd_recover(args: argparse.Namespace) -> int:
    from hitl_slam.session import Session

    source = Path(args.input)
    target = Path(args.output) if args.output else None
    with Session.recover(source, target) as session:
        kept = len(session.history)
        where = session.path
    print(
        f"wrote {where}: the last good checkpoint of {source} ({kept} step(s) in its history); "
        f"{source} is unchanged. Continue with: hitl-slam serve {where}"
    )
    return 0


def _cmd_metrics(args: argparse.Namespace) -> int:
    import math

    from hitl_slam.config import DEFAULT
    from hitl_slam.io.relations import read_relations
    from hitl_slam.metrics import inconsistency, relations_error

    heat_path = None if args.heat_map is None else Path(args.heat_map)
    if heat_path is not None and heat_path.suffix.lower() != ".png":
        raise InputError(f"{heat_path}: the heat map is written as PNG; give a .png file name")
    if heat_path is not None:
        require("plot", "hitl-slam metrics --heat-map")
        _refuse_overwriting_inputs([heat_path], [args.map, args.relations], args.force)
    config = DEFAULT
    if args.resolution is not None:
        if not (math.isfinite(args.resolution) and args.resolution > 0):
            raise InputError(
                f"--resolution must be a positive number of metres, got {args.resolution}"
            )
        config = DEFAULT.replace(grid_resolution=args.resolution)
    if args.tolerance is not None and args.relations is None:
        raise InputError("--tolerance goes with --relations; add the relations file, or drop it")
    tolerance = 1e-3 if args.tolerance is None else args.tolerance
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise InputError(f"--tolerance must be a number of seconds >= 0, got {args.tolerance}")
    # Read before the (slower) map, so a bad relations file fails fast.
    relations = None if args.relations is None else read_relations(args.relations)
    the_map = _load_map(args, args.map)
    if the_map.num_points == 0:
        # The metric counts disagreeing points; with none it would read a perfect 0.
        raise InputError(
            f"{args.map}: the map has no points ({the_map.num_poses} poses, every reading a "
            "no-return or invalid), so its inconsistency cannot be scored: check the laser's "
            "range fields (or --max-range) and the file"
        )
    # Matched before the metric runs, so relations that do not fit the map fail before any output.
    err = (
        None
        if relations is None
        else relations_error(the_map, None, relations, tolerance=tolerance)
    )
    t0 = time.perf_counter()
    result = _with_progress(
        "inconsistency", args.quiet, lambda: inconsistency(the_map, None, config)
    )
    elapsed = time.perf_counter() - t0
    height, width = result.heat.shape
    print(f"{args.map}: {the_map.num_poses} poses, {the_map.num_points} points")
    print(
        f"inconsistency: {result.total_m2:.3f} m^2 ({width} x {height} cells of "
        f"{result.resolution:g} m, {elapsed:.2f} s)"
    )
    if err is not None:
        print(
            f"relations: {err.matched} matched, {err.skipped} skipped (no scan within "
            f"{err.tolerance:g} s), translation {err.translation_mean:.4f} +- "
            f"{err.translation_std:.4f} m (max {err.translation_max:.4f}), rotation "
            f"{err.rotation_mean_deg:.3f} +- {err.rotation_std_deg:.3f} deg "
            f"(max {err.rotation_max_deg:.3f})"
        )
    if heat_path is not None:
        _write_heat_map(the_map, result, heat_path)
        print(f"wrote {heat_path}")
    return 0


def _write_heat_map(the_map: Map, result: Inconsistency, path: Path) -> None:
    """The heat map over the map's points, as a PNG (matplotlib imported only here)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.colors import LogNorm

    from hitl_slam.io.atomic import atomic_write_bytes

    heat = np.ma.masked_less_equal(result.heat, 0.0)
    world = the_map.world_points()
    left, right, bottom, top = result.extent
    aspect = (top - bottom) / max(right - left, 1e-9)
    fig, ax = plt.subplots(figsize=(10.0, max(3.0, min(10.0, 10.0 * aspect)) + 0.8))
    try:
        ax.scatter(world[:, 0], world[:, 1], s=0.05, c="0.75", linewidths=0, rasterized=True)
        if heat.count():
            image = ax.imshow(
                heat,
                origin="lower",
                extent=result.extent,
                cmap="inferno",
                norm=LogNorm(vmin=1.0, vmax=max(float(heat.max()), 1.0)),
                interpolation="nearest",
            )
            fig.colorbar(image, ax=ax, label="scan pairs (free vs occupied)", shrink=0.8)
        ax.set_xlim(left, right)
        ax.set_ylim(bottom, top)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(f"{the_map.name}: inconsistency {result.total_m2:.2f} m^2")
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=150, bbox_inches="tight")
    finally:
        plt.close(fig)
    # Rendered in memory first, then written atomically: a failure or a kill leaves no
    # half-written file under the name.
    atomic_write_bytes(path, buffer.getvalue())


_DEMO_EPILOG = """\
examples:
  hitl-slam demo                      # writes into ./hitl-slam-demo
  hitl-slam demo -o /tmp/demo --seed 3

Writes before_after.png (the paper's Fig. 8 in kind), information_matrix.png (Fig. 5),
inconsistency heat maps before and after, the corrected map (.g2o), the corrections
(corrections.jsonl, replayable with `hitl-slam correct`) and the session (lost-poses.hitl).
"""


def _cmd_demo(args: argparse.Namespace) -> int:
    require("plot", "hitl-slam demo")
    from hitl_slam.demo import run_demo

    out = Path(args.output)
    log = (lambda _m: None) if args.quiet else print
    result = _with_progress("demo", True, lambda: run_demo(out, seed=args.seed, log=log))
    print()
    print(result.table)
    print()
    if not args.quiet:
        print(
            f"{result.corrections} corrections ({result.rejections} drawings refused), "
            f"{result.time_s:.1f} s. Figures and files in {out}/:"
        )
        for f in result.files:
            print(f"  {f}")
        print(
            "Room from the paper's Results ('lost poses', Fig. 8); the paper reports 5.97 m -> "
            "6.31 m against the true 6.33 m."
        )
        print(f"To open the same map in the browser: hitl-slam serve {out / 'lost-poses.hitl'}")
    return 0


_SERVE_EPILOG = """\
examples:
  hitl-slam serve --demo                       # the damaged lost-poses room, ./hitl-demo/
  hitl-slam serve --demo --demo-world campus   # the 3,380-pose campus instead
  hitl-slam serve run.clf.gz                   # a raw log: the front end builds the map first,
                                               # then run.hitl beside it (reopened next time)
  hitl-slam serve run.bag                      # a ROS bag: its own SLAM's map when /tf has
                                               # map -> odom, else the front end's
  hitl-slam serve run.bag --slam               # the front end's map even so, compared with
                                               # the bag's own by their inconsistency
  hitl-slam serve corrected.log.gz --no-slam   # a log whose poses are already a map: as logged
  hitl-slam serve lab.covars                   # a map: lab.hitl beside it
  hitl-slam serve run.hitl --journal fixes.jsonl   # step through a corrections file with l
  hitl-slam serve run.hitl --port 0 --open     # any free port; open the browser

Open the printed URL (http://127.0.0.1:8765/?token=...): the token keeps other pages and other
users of this machine out; the page remembers it in a cookie. In the page, p toggles correction
mode; then a drag draws a segment, its mode from the keys held: Ctrl colocation, Shift collinear,
Shift+Alt perpendicular, Shift+Ctrl parallel. Two segments of one mode show what they select;
p again applies the correction. u undoes, Shift+U redoes, v saves, ? lists every key.

A raw log (CARMEN .clf/.log, also .gz/.bz2, or a ROS bag) is a robot's odometry and scans: serve
runs the scan-matching front end over it first (progress on stderr; docs/ALGORITHM.md §F) and
serves the map it builds, with its loop closures drawn between the poses they join (green:
trusted, amber: down-weighted, red dashed: rejected; c shows or hides them). Click one to select
it (n / N step through them), x rejects or reinstates it: the map re-solves at once, and the
step is journaled and undone like a correction. Every .clf/.log is taken as raw: a log whose
logged poses are already a good map (a corrected log, another SLAM's output) is served as logged
with --no-slam (no loop closures then). Stretches the front end doubts, when it names any, are
drawn in purple and listed in the status bar.

A ROS bag recorded with a SLAM running (slam_toolbox, Cartographer, gmapping, AMCL: /tf has
map -> odom) is the map you came to repair: serve starts from the SLAM's own trajectory
(map -> base_link), its factors the chain of steps between consecutive scans (no loop closures),
and says so. --slam rebuilds it with the front end from the bag's odometry instead (over the
same scans) and shows both maps' inconsistency side by side in the status bar (lower is more
consistent). --map-frame '' ignores the bag's SLAM (the front end's map, or with --no-slam the
odometry as recorded). --slam and --no-slam together are an error. A session beside the log is
reopened only when it holds the poses asked for (else one line saying which it holds and how to
serve it).

Every correction is journaled in the session file (.hitl) before the map changes, so Ctrl-C (or
a crash) loses nothing acknowledged; serving the same file again continues where you left off.
Save (v) writes NAME.txt (TUM), .g2o, .pgm and .yaml beside the session file.

The server listens on 127.0.0.1 only, unless --host says otherwise; --no-token is allowed on
loopback only.
"""


class _ServeProgress:
    """How far the front end is over a raw log `hitl-slam serve` was given: a tqdm bar on a
    terminal, else a line on stderr at most every 5 s and at the end (scans done, real-time
    factor)."""

    EVERY_S = 5.0

    def __init__(self) -> None:
        self._bar: Any = None
        self._last = -math.inf
        self._done = False

    def __call__(self, done: int, total: int, rtf: float | None) -> None:
        speed = "" if rtf is None else f"{rtf:.1f}x real time"
        if sys.stderr.isatty():
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=total, desc="front end", unit="scan", file=sys.stderr)
            self._bar.n = done
            if speed:
                self._bar.set_postfix_str(speed)
            self._bar.refresh()
            return
        now = time.monotonic()
        if done < total and now - self._last < self.EVERY_S:
            return
        if done >= total and self._done:
            return
        self._last = now
        self._done = done >= total
        print(
            f"hitl-slam serve: front end {done}/{total} scans" + (f", {speed}" if speed else ""),
            file=sys.stderr,
            flush=True,
        )

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _cmd_serve(args: argparse.Namespace) -> int:
    require("web", "hitl-slam serve")
    from hitl_slam.web.server import run_server

    if args.demo_world is not None and not args.demo:
        raise InputError("--demo-world goes with --demo; add --demo, or drop --demo-world")
    if args.demo and args.target is not None:
        raise InputError(f"give {args.target} or --demo, not both")
    if args.slam and args.no_slam:
        raise InputError(
            "give --slam (the front end rebuilds the map from the log's odometry) or --no-slam "
            "(the log's own poses as they are), not both"
        )
    if args.demo and (args.slam or args.no_slam):
        flag = "--slam" if args.slam else "--no-slam"
        raise InputError(
            f"{flag} chooses how a raw log becomes a map; --demo has none: drop {flag}"
        )

    def announce(message: str) -> None:
        print(message, flush=True)

    progress = _ServeProgress()
    try:
        run_server(
            args.target,
            max_range=args.max_range,
            front_end=True if args.slam else False if args.no_slam else None,
            progress=progress,
            bag=_bag_options(args),
            demo=(args.demo_world or "lost-poses") if args.demo else None,
            seed=args.seed,
            host=args.host,
            port=args.port,
            token=args.token,
            no_token=args.no_token,
            journal=args.journal,
            open_browser=args.open,
            announce=announce,
        )
    finally:
        progress.close()
    print("hitl-slam serve: stopped; every acknowledged change is in the session file", flush=True)
    return 0


_EVALUATE_EPILOG = """\
examples:
  hitl-slam evaluate                   # everything; a few minutes
  hitl-slam evaluate --quick -o /tmp/e # the lost-poses room and the corridors only
  hitl-slam evaluate --full -j 2       # the harder benchmark: 9 maps x 4 fault models x
                                       # 5 / 15 cm endpoint noise, a careful person
  hitl-slam evaluate --full --maps Orebro,Seattle --faults jump  # a part of it
  hitl-slam evaluate --full -j 2 --faults slip,scale --seed 3    # damage it was not built on

The full evaluation's maps: Intel lab, Freiburg 079, Seattle, Orebro, Belgioioso, Edmonton (real
logs), lost poses room, parallel corridors, campus; its fault models: jump (30 degrees), drift
(15 degrees over the run), bend (10 degrees along the straightest stretch), laps (two jumps:
three copies); with --faults also slip (one step 0.5-1.5 m off) and scale (every distance 3-6%
off). Exit status 0 when every target is met, 1 when one is not.

Real logs are used when ../shared/datasets/laser (beside the repository) is present.
"""


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from hitl_slam.evaluation import run_evaluation, table

    out = Path(args.output)
    if args.full:
        return _evaluate_full(args, out)
    if args.maps or args.faults or args.no_align:
        raise InputError(
            "--maps, --faults and --no-align are options of the full evaluation; add --full"
        )
    require("plot", "hitl-slam evaluate")  # the report's figures
    log = (lambda _m: None) if args.quiet else print
    results, report = run_evaluation(out, seed=args.seed, quick=args.quick, log=log)
    print(table(results))
    print(f"report: {report}")
    return 0


def _evaluate_full(args: argparse.Namespace, out: Path) -> int:

    from hitl_slam.evaluation import provenance
    from hitl_slam.full_evaluation import FULL_MAPS, full_report, run_full, runs_json, summary
    from hitl_slam.io.atomic import atomic_outputs, atomic_write_text
    from hitl_slam.sim.fault_models import FAULT_MODELS, FULL_FAULTS

    maps = [m.strip() for m in args.maps.split(",")] if args.maps else list(FULL_MAPS)
    faults = [f.strip() for f in args.faults.split(",")] if args.faults else list(FULL_FAULTS)
    for f in faults:
        if f not in FAULT_MODELS:
            raise InputError(
                f"--faults: unknown fault model {f!r}; they are: {', '.join(FAULT_MODELS)}"
            )
    total = len(maps) * len(faults) * 2
    done = [0]

    def log(r: object) -> None:
        done[0] += 1
        if not args.quiet:
            from hitl_slam.full_evaluation import Run

            assert isinstance(r, Run)
            print(
                f"[{done[0]}/{total}] {r.map}, {r.fault}, {100 * r.noise_m:.0f} cm: "
                f"{r.accepted}/{len(r.drawings)} accepted, "
                f"{sum(d.worse for d in r.drawings)} worse, "
                f"ATE {r.ate[0]:.3f} -> {r.ate[1]:.3f} m, "
                f"angle {r.angle[0]:.2f} -> {r.angle[1]:.2f} deg"
                + (f", alignment {r.alignment.split(':')[0]}" if r.alignment else "")
                + f", {r.time_s:.0f} s",
                flush=True,
            )

    start = time.perf_counter()
    runs = run_full(
        seed=args.seed,
        maps=maps,
        faults=faults,
        jobs=args.jobs,
        log=log,
        align=not args.no_align,
    )
    out.mkdir(parents=True, exist_ok=True)
    flags = " --full" + (f" --maps {args.maps}" if args.maps else "")
    flags += f" --faults {args.faults}" if args.faults else ""
    flags += " --no-align" if args.no_align else ""
    text = full_report(runs, provenance(args.seed, flags, time.perf_counter() - start))
    report = out / "full.md"
    with atomic_outputs():  # the report and its data together
        atomic_write_text(report, text)
        atomic_write_text(out / "full.json", runs_json(runs))
    s = summary(runs)
    print(
        f"accepted {100 * s['accepted_share']:.2f}% of {s['drawings']:.0f} drawings, "
        f"{s['worse']:.0f} made their map worse ({s['worse_beyond_noise']:.0f} beyond the noise), "
        f"{100 * s['achieved']:.0f}% of the achievable "
        f"inconsistency reduction, angle {s['angle_after']:.2f} deg, "
        f"spacing {s['spacing_after']:.3f} m"
    )
    print(f"report: {report}")
    met = (
        s["accepted_share"] >= 0.95
        and s["worse"] == 0
        and s["achieved"] >= 0.8
        and s["angle_after"] <= 1.0
        and s["spacing_after"] <= 0.03
    )
    return 0 if met else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hitl-slam",
        description=(
            "Human-in-the-Loop SLAM: repair a globally inconsistent 2D map by drawing a few lines "
            "(Nashed and Biswas, AAAI 2018). Start with `hitl-slam demo`."
        ),
    )
    parser.add_argument("--version", action="version", version=f"hitl-slam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    solve = sub.add_parser(
        "solve",
        help="optimize a g2o / TORO pose graph",
        description=(
            "Optimize a 2D pose graph (sparse Levenberg-Marquardt, Gauss-Newton or Powell's "
            "dogleg), from its vertices or a computed start, optionally with robust kernels."
        ),
        epilog=_SOLVE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    solve.add_argument("graph", metavar="GRAPH", help="input pose graph (.g2o or .graph)")
    solve.add_argument("-o", "--output", required=True, metavar="OUT", help="output file")
    solve.add_argument(
        "--method",
        choices=["lm", "gn", "dogleg"],
        default="lm",
        help="lm (Levenberg-Marquardt, default), gn (Gauss-Newton) or dogleg (Powell's dogleg)",
    )
    solve.add_argument(
        "--init",
        choices=["given", "tree", "chordal"],
        default="given",
        help="where to start: the file's vertices (default), a spanning tree of the "
        "measurements, or chordal relaxation (see below)",
    )
    solve.add_argument(
        "--robust",
        action="append",
        default=[],
        metavar="[CLASS=]KIND[:PARAM]",
        help="robust kernel, e.g. dcs, cauchy:2, odometry=huber:3 (repeatable; see below)",
    )
    solve.add_argument("--max-iterations", type=int, default=100, metavar="N", help="default 100")
    solve.add_argument(
        "--relative-tolerance",
        type=float,
        default=1e-6,
        metavar="R",
        help="stop when chi2 drops by less than this fraction (default 1e-6)",
    )
    solve.add_argument(
        "--absolute-tolerance",
        type=float,
        default=1e-6,
        metavar="A",
        help="stop when chi2 drops by less than this (default 1e-6)",
    )
    _add_force(solve)
    solve.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    solve.set_defaults(func=_cmd_solve)

    generate = sub.add_parser(
        "generate",
        help="write a synthetic Manhattan-world pose graph (with ground truth)",
        description="Generate a synthetic 2D pose graph to try the solver on.",
        epilog=_GENERATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    generate.add_argument("output", metavar="OUT", help="output file (.g2o or .graph)")
    generate.add_argument("--poses", type=int, default=1000, metavar="N", help="default 1000")
    generate.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    generate.set_defaults(func=_cmd_generate)

    correct = sub.add_parser(
        "correct",
        help="apply a file of human corrections (JSON Lines) to a map",
        description="Apply scripted corrections to a map, in order, as a person would in the UI.",
        epilog=_CORRECT_EPILOG + _BAGS_NOTE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    correct.add_argument(
        "map", metavar="MAP", help="input map (.covars, .clf/.log, ROS bag, .hitl)"
    )
    _add_max_range(correct)
    _add_bag_options(correct)
    correct.add_argument(
        "--corrections", required=True, metavar="C.jsonl", help="corrections, one per line"
    )
    correct.add_argument("-o", "--output", required=True, metavar="OUT", help="output map file")
    correct.add_argument(
        "--session", metavar="S.hitl", help="also write the run as a new session file"
    )
    correct.add_argument(
        "--keep-going",
        action="store_true",
        help="skip (and list) rejected corrections instead of stopping at the first",
    )
    correct.add_argument(
        "--align",
        action="store_true",
        help="after the corrections, align the map with its scans: match them again from the "
        "corrected poses and solve every correction over that graph (refused, and nothing "
        "written, where it contradicts the odometry, finds no loop closure or is no more "
        "consistent)",
    )
    _add_force(correct)
    correct.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    correct.set_defaults(func=_cmd_correct)

    slam_cmd = sub.add_parser(
        "slam",
        help="build a map from a raw laser log with the scan-matching front end",
        description=(
            "Run the scan-matching front end over a raw laser log (CARMEN .clf/.log, optionally "
            ".gz/.bz2, or a ROS 1 / ROS 2 bag, read from its odometry whatever map -> odom it "
            "holds): every scan matched to the local map (correlative search, then "
            "point-to-line ICP), keyframes and submaps, loop closures found by branch and bound "
            "and weighed by dynamic covariance scaling. Writes the map: a session (.hitl, ready "
            "for `hitl-slam serve`) or any export format."
        ),
        epilog=_SLAM_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    slam_cmd.add_argument(
        "log", metavar="LOG", help="the raw log: CARMEN .clf/.log[.gz|.bz2], or a ROS bag"
    )
    _add_max_range(slam_cmd)
    _add_bag_options(slam_cmd)
    slam_cmd.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUT",
        help="output: .hitl (a session), .clf (a CARMEN log), .covars, .g2o, .pgm, ...",
    )
    slam_cmd.add_argument(
        "--keyframe-distance",
        type=float,
        default=0.2,
        metavar="M",
        help="a scan that moved this far since the last keyframe becomes one (default 0.2)",
    )
    slam_cmd.add_argument(
        "--keyframe-angle",
        type=float,
        default=10.0,
        metavar="DEG",
        help="... or turned this much (default 10)",
    )
    slam_cmd.add_argument(
        "--match-range",
        type=float,
        default=20.0,
        metavar="M",
        help="points farther than this are not matched (default 20)",
    )
    slam_cmd.add_argument(
        "--loop-min-score",
        type=float,
        default=0.55,
        metavar="S",
        help="a loop closure needs this correlative score, 0..1 (default 0.55)",
    )
    _add_force(slam_cmd)
    slam_cmd.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    slam_cmd.set_defaults(func=_cmd_slam)

    export = sub.add_parser(
        "export",
        help="convert a map or session to another format, or a session to its corrections",
        description="Write a map or a session's current map in another format.",
        epilog=_EXPORT_EPILOG + _BAGS_NOTE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    export.add_argument(
        "input",
        metavar="MAP_OR_SESSION",
        help="input map (.covars, .clf/.log, ROS bag) or session (.hitl)",
    )
    _add_max_range(export)
    _add_bag_options(export)
    export.add_argument("-o", "--output", required=True, metavar="OUT", help="output file")
    _add_force(export)
    export.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    export.set_defaults(func=_cmd_export)

    recover = sub.add_parser(
        "recover",
        help="copy the intact part of a damaged session file to a new one",
        description=(
            "Open the last good checkpoint of a damaged session file: its map, configuration and "
            "every event before the first damaged one (checksums verified) are copied to a NEW "
            "session file (default: <stem>.recovered.hitl beside it). The damaged file is only "
            "read."
        ),
    )
    recover.add_argument("input", metavar="SESSION", help="the damaged session file (.hitl)")
    recover.add_argument(
        "-o", "--output", metavar="NEW", help="the new session file (must not exist)"
    )
    recover.set_defaults(func=_cmd_recover)

    metrics = sub.add_parser(
        "metrics",
        help="score a map: inconsistency (m^2), and the error against ground-truth relations",
        description="Measure a map's global consistency and, given relations, its accuracy.",
        epilog=_METRICS_EPILOG + _BAGS_NOTE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    metrics.add_argument(
        "map", metavar="MAP", help="input map (.covars, .clf/.log, ROS bag, .hitl)"
    )
    _add_max_range(metrics)
    _add_bag_options(metrics)
    metrics.add_argument(
        "--relations", metavar="R", help="ground-truth relations (.relations) for the map's log"
    )
    metrics.add_argument(
        "--tolerance",
        type=float,
        metavar="SECONDS",
        help="match each relation's timestamps to the nearest scan within this many seconds "
        "(default 0.001); relations farther from every scan are skipped and counted",
    )
    metrics.add_argument("--heat-map", metavar="OUT.png", help="write the per-cell heat map")
    metrics.add_argument(
        "--resolution", type=float, metavar="M", help="grid cell size in metres (default 0.05)"
    )
    _add_force(metrics)
    metrics.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    metrics.set_defaults(func=_cmd_metrics)

    demo = sub.add_parser(
        "demo",
        help="the paper's 'lost poses' room, broken and repaired, with figures (no files needed)",
        description=(
            "Generate a 6.33 m room seen with a 1.5 m laser (no two parallel walls ever in view), "
            "let a simulated person correct the drifted map one drawing at a time, and compare the "
            "result with the paper's figures."
        ),
        epilog=_DEMO_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument(
        "-o",
        "--output",
        default="hitl-slam-demo",
        metavar="DIR",
        help="where to write the figures, the session and the map (default ./hitl-slam-demo)",
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("-q", "--quiet", action="store_true", help="only the table")
    demo.set_defaults(func=_cmd_demo)

    serve = sub.add_parser(
        "serve",
        help="the browser UI: draw corrections on a map, undo, save (127.0.0.1 only)",
        description=(
            "Serve a map or session in the browser on this machine: draw corrections, see what "
            "they select, apply, undo and redo them, save the corrected map."
        ),
        epilog=_SERVE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    serve.add_argument(
        "target",
        nargs="?",
        metavar="MAP_OR_SESSION",
        help=(
            "a raw log (.clf/.log[.gz|.bz2], a ROS bag: the front end builds the map first, "
            "unless the bag has its own SLAM's map frame), a map (.covars), or a .hitl; the "
            "session <stem>.hitl goes beside a log or map"
        ),
    )
    serve.add_argument(
        "--slam",
        action="store_true",
        help=(
            "a bag with its own SLAM (map -> odom on /tf): rebuild the map with the front end from "
            "the bag's odometry instead of serving the SLAM's trajectory, and show the "
            "inconsistency of both; a .clf/.log or a bag without one gets the front end anyway"
        ),
    )
    serve.add_argument(
        "--no-slam",
        action="store_true",
        help=(
            "serve a .clf/.log or bag with its own poses as the map (logged poses; a bag's own "
            "SLAM trajectory, else its odometry), without the front end (for a corrected log or "
            "another SLAM's output); not with --slam"
        ),
    )
    serve.add_argument(
        "--demo", action="store_true", help="serve a generated damaged map in ./hitl-demo/"
    )
    serve.add_argument(
        "--demo-world",
        choices=["lost-poses", "campus"],
        help="which generated map --demo serves (default lost-poses)",
    )
    serve.add_argument("--seed", type=int, default=0, help="random seed of --demo (default 0)")
    serve.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)"
    )
    serve.add_argument(
        "--port", type=int, default=8765, help="port (default 8765; 0 picks a free one)"
    )
    access = serve.add_mutually_exclusive_group()
    access.add_argument("--token", metavar="T", help="the access token (default: a random one)")
    access.add_argument(
        "--no-token", action="store_true", help="no access token (loopback addresses only)"
    )
    serve.add_argument(
        "--journal", metavar="C.jsonl", help="a corrections file to step through (key l)"
    )
    serve.add_argument("--open", action="store_true", help="open the page in the web browser")
    _add_max_range(serve)
    _add_bag_options(serve)
    serve.set_defaults(func=_cmd_serve)

    evaluate = sub.add_parser(
        "evaluate",
        help="repair damaged worlds and real logs with a simulated person; write a report",
        description=(
            "The paper's Results in kind: Table 1 (angles and spacings between known wall pairs), "
            "the inconsistency metric and ATE, before and after a simulated person's corrections, "
            "on the lost-poses room, parallel corridors, a campus, and the corrected Freiburg 079 "
            "and Intel logs (../shared/datasets/laser) damaged by injected faults."
        ),
        epilog=_EVALUATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    evaluate.add_argument(
        "-o",
        "--output",
        default="hitl-slam-evaluation",
        metavar="DIR",
        help="where to write report.md and the figures (default ./hitl-slam-evaluation)",
    )
    evaluate.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    evaluate.add_argument(
        "--quick", action="store_true", help="only the two small generated scenarios"
    )
    evaluate.add_argument(
        "--full",
        action="store_true",
        help="the harder benchmark (issue 11): every map, every fault model, a careful person; "
        "writes DIR/full.md",
    )
    evaluate.add_argument(
        "--maps", metavar="A,B", help="with --full: only these maps (comma-separated names)"
    )
    evaluate.add_argument(
        "--faults",
        metavar="A,B",
        help="with --full: these fault models (default jump,drift,bend,laps, the issue's four; "
        "also slip: one step's translation off by 0.5-1.5 m, and scale: every distance 3-6%% "
        "off)",
    )
    evaluate.add_argument(
        "--no-align",
        action="store_true",
        help="with --full: the person does not align the map with its scans after drawing",
    )
    evaluate.add_argument(
        "-j", "--jobs", type=int, default=1, help="with --full: runs at once (default 1)"
    )
    evaluate.add_argument("-q", "--quiet", action="store_true", help="only the table")
    evaluate.set_defaults(func=_cmd_evaluate)
    return parser


class _StderrNotices(logging.Handler):
    """Prints, as ``hitl-slam: ...`` lines on the current stderr, every WARNING (and worse) of
    the ``hitl_slam`` loggers (a reader's skipped lines, covariances it replaced, ...) and the
    INFO notices of :mod:`hitl_slam.io.atomic` (stale temporary files removed)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or record.name == "hitl_slam.io.atomic"

    def emit(self, record: logging.LogRecord) -> None:
        try:
            print(f"hitl-slam: {_one_line(record.getMessage())}", file=sys.stderr)
        except Exception:
            self.handleError(record)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Only the CLI prints: the library's loggers keep their NullHandler (no output on import).
    package = logging.getLogger("hitl_slam")
    atomic = logging.getLogger("hitl_slam.io.atomic")
    handler = _StderrNotices(logging.INFO)
    levels = package.level, atomic.level
    package.addHandler(handler)
    if package.getEffectiveLevel() > logging.WARNING:
        package.setLevel(logging.WARNING)
    atomic.setLevel(logging.INFO)
    try:
        return _run(args)
    finally:
        package.removeHandler(handler)
        package.setLevel(levels[0])
        atomic.setLevel(levels[1])


def _run(args: argparse.Namespace) -> int:
    try:
        code: int = args.func(args)
    except InputError as exc:
        print(f"hitl-slam: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except SolverError as exc:
        print(f"hitl-slam: solver failed: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    except HitlSlamError as exc:
        print(f"hitl-slam: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    except OSError as exc:
        # Reading or writing a file failed outside the readers' and writers' own checks.
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"hitl-slam: error: {where}{_one_line(exc.strerror or str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hitl-slam: interrupted; no output was written", file=sys.stderr)
        return 130
    return code


if __name__ == "__main__":
    sys.exit(main())
