"""The ``hitl-slam`` command line: argument parsing, progress, tables, exit codes.

The only module that prints. Exit codes: 0 success, 2 bad input (one-line reason on stderr),
1 a solver failure.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from hitl_slam import __version__
from hitl_slam.errors import HitlSlamError, InputError, SolverError

T = TypeVar("T")

_SOLVE_EPILOG = """\
examples:
  hitl-slam solve M3500.g2o -o M3500-optimized.g2o
  hitl-slam solve w100.graph -o w100-optimized.graph --method gn
  hitl-slam solve city10000.g2o -o out.g2o --max-iterations 20 --quiet

The input is a g2o (VERTEX_SE2/EDGE_SE2) or TORO (VERTEX2/EDGE2) 2D pose graph; its vertices
are the initial guess and its first vertex (or a g2o FIX line) is held fixed. The output format
follows the output file's extension (.g2o or .graph). chi2 is sum r^T Omega r over all edges.
"""

_GENERATE_EPILOG = """\
examples:
  hitl-slam generate manhattan.g2o                 # 1000 poses, seed 0
  hitl-slam generate big.g2o --poses 20000 --seed 3

Writes a Manhattan-world pose graph (a robot driving on a grid, noisy odometry, loop closures at
revisited cells) whose vertices are the composed odometry, and the ground truth next to it as
OUT.truth.txt (one "x y theta" line per pose).
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

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    with tqdm(desc=label, total=None, unit="", leave=False, file=sys.stderr) as bar:
        while thread.is_alive():
            thread.join(0.1)
            bar.update(0)
            bar.refresh()
    if error:
        raise error[0]
    return result[0]


def _cmd_solve(args: argparse.Namespace) -> int:
    from hitl_slam.io import load_graph_with_report, save_graph
    from hitl_slam.solve import Method, optimize

    out = Path(args.output)
    if out.suffix.lower() not in (".g2o", ".graph"):
        raise InputError(f"{out}: unsupported output extension {out.suffix!r}; use .g2o or .graph")
    t0 = time.perf_counter()
    graph, load = _with_progress("loading", args.quiet, lambda: load_graph_with_report(args.graph))
    t_load = time.perf_counter() - t0
    method = Method(args.method)
    poses, report = _with_progress(
        "solving",
        args.quiet,
        lambda: optimize(
            graph,
            method=method,
            max_iterations=args.max_iterations,
            relative_tolerance=args.relative_tolerance,
            absolute_tolerance=args.absolute_tolerance,
        ),
    )
    save_graph(graph, poses, out)
    if not args.quiet:
        print(
            f"{args.graph}: {graph.num_poses} poses, {graph.num_edges} edges "
            f"({load.format.value}, read in {t_load:.3f} s)"
        )
        print(f"{'iter':>5} {'chi2':>16} {'damping':>10} {'|step|':>10} {'ok':>3} {'ms':>9}")
        for rec in report.history:
            print(
                f"{rec.iteration:>5} {rec.chi2:>16.6f} {rec.damping:>10.2e} "
                f"{rec.step_norm:>10.3e} {'yes' if rec.accepted else 'no':>3} "
                f"{1e3 * rec.elapsed_s:>9.2f}"
            )
    status = "converged" if report.converged else "NOT converged"
    print(
        f"{method.name.lower().replace('_', '-')}: chi2 {report.initial_chi2:.6f} -> "
        f"{report.final_chi2:.6f} in {report.iterations} iterations, {status} "
        f"({report.termination}), {1e3 * report.time_s:.1f} ms; wrote {out}"
    )
    return 0


def _cmd_generate(args: argparse.Namespace) -> int:
    import numpy as np

    from hitl_slam.io import save_graph
    from hitl_slam.io.atomic import atomic_write_text
    from hitl_slam.synthetic import manhattan_world

    out = Path(args.output)
    graph, truth = manhattan_world(args.poses, seed=args.seed)
    save_graph(graph, graph.poses, out)
    truth_path = out.with_suffix(".truth.txt")
    atomic_write_text(truth_path, "".join(f"{x!r} {y!r} {t!r}\n" for x, y, t in truth.tolist()))
    err = np.hypot(*(graph.poses[:, :2] - truth[:, :2]).T)
    print(
        f"wrote {out}: Manhattan world, {graph.num_poses} poses, {graph.num_edges} edges "
        f"(odometry drift up to {err.max():.2f} m), ground truth in {truth_path}"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hitl-slam",
        description=(
            "Human-in-the-Loop SLAM: repair a globally inconsistent 2D map by drawing a few lines "
            "(Nashed and Biswas, AAAI 2018). Start with `hitl-slam generate` and `hitl-slam solve`."
        ),
    )
    parser.add_argument("--version", action="version", version=f"hitl-slam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    solve = sub.add_parser(
        "solve",
        help="optimize a g2o / TORO pose graph",
        description="Optimize a 2D pose graph with sparse Levenberg-Marquardt or Gauss-Newton.",
        epilog=_SOLVE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    solve.add_argument("graph", metavar="GRAPH", help="input pose graph (.g2o or .graph)")
    solve.add_argument("-o", "--output", required=True, metavar="OUT", help="output file")
    solve.add_argument(
        "--method", choices=["lm", "gn"], default="lm", help="lm (default) or gn (Gauss-Newton)"
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
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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
    except KeyboardInterrupt:
        print("hitl-slam: interrupted; no output was written", file=sys.stderr)
        return 130
    return code


if __name__ == "__main__":
    sys.exit(main())
