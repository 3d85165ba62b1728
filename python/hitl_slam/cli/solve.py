"""``hitl-slam solve``: optimize a g2o / TORO pose graph."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hitl_slam.cli.common import add_force, one_line, refuse_overwriting_inputs, with_progress
from hitl_slam.errors import InputError

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands
    from hitl_slam.graph import PoseGraph

EPILOG = """\
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


def add_parser(sub: Commands) -> None:
    solve = sub.add_parser(
        "solve",
        help="optimize a g2o / TORO pose graph",
        description=(
            "Optimize a 2D pose graph (sparse Levenberg-Marquardt, Gauss-Newton or Powell's "
            "dogleg), from its vertices or a computed start, optionally with robust kernels."
        ),
        epilog=EPILOG,
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
    add_force(solve)
    solve.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    solve.set_defaults(func=run)


def _not_a_pose_graph(path: Path, kind: str) -> InputError:
    stem = path.name.split(".")[0] or "map"
    return InputError(
        f"{path}: {kind} (poses and laser scans) is a map, not a pose graph; `hitl-slam solve` "
        f"reads .g2o / .graph pose graphs. Correct the map with `hitl-slam correct {path} "
        f"--corrections C.jsonl -o OUT` or `hitl-slam serve {path}`, or write its pose graph "
        f"with `hitl-slam export {path} -o {stem}.g2o` and solve that"
    )


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from hitl_slam.io import GraphFormat, load_graph, save_graph
    from hitl_slam.io.maps import looks_like_carmen, map_kind
    from hitl_slam.solve import Init, Method, downweighted, optimize, robust_pairs

    out = Path(args.output)
    if out.suffix.lower() not in tuple(f.extension for f in GraphFormat):
        raise InputError(f"{out}: unsupported output extension {out.suffix!r}; use .g2o or .graph")
    source = Path(args.graph)
    kind = map_kind(source)
    if kind is not None:
        raise _not_a_pose_graph(source, kind)
    refuse_overwriting_inputs([out], [source], args.force)
    robust = robust_pairs(",".join(args.robust)) if args.robust else []
    t0 = time.perf_counter()
    try:
        graph = with_progress("loading", args.quiet, lambda: load_graph(args.graph))
        load = graph.load_report
        assert load is not None  # load_graph always records it
    except InputError:
        if looks_like_carmen(source):
            raise _not_a_pose_graph(source, "a CARMEN log") from None
        raise
    t_load = time.perf_counter() - t0
    method = Method(args.method)
    poses, report = with_progress(
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
            f"{one_line(report.termination_detail)}); the estimate was written to {out} anyway"
            f"{_worst_edge(graph)}",
            file=sys.stderr,
        )
    return 0 if report.converged else 3


def _worst_edge(graph: PoseGraph) -> str:
    """``; the worst edge: ...`` naming the edge whose chi2 is largest at the start, where a
    damaged vertex or edge usually shows; "" when it cannot be said."""
    import numpy as np

    from hitl_slam.solve import edge_chi2

    per_edge = edge_chi2(graph)
    if per_edge.size == 0 or not np.isfinite(per_edge).any():
        return ""
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    k = int(np.nanargmax(per_edge))
    ids = graph.vertex_ids if graph.vertex_ids is not None else np.arange(graph.num_poses)
    return (
        f"; the largest error at the start is on edge {ids[i[k]]} -> {ids[j[k]]} (chi2 "
        f"{per_edge[k]:.3g} of {np.nansum(per_edge):.3g}): check vertices {ids[i[k]]} and "
        f"{ids[j[k]]} and that edge for a damaged value"
    )
