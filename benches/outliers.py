#!/usr/bin/env python
"""Outlier benchmark (Vertigo style): M3500 with random false loop closures added.

For each fraction of false loop closures (10%, 20%, 50% of the true ones by default) and seed,
adds that many random loop closures to ``manhattanOlson3500.g2o`` and solves the corrupted graph
from the file's initial guess with hitl-slam and with GTSAM, side by side in this one process
pinned to one core: plain Levenberg-Marquardt and LM with robust kernels on the loop closures
(DCS, Cauchy). Reports the absolute trajectory error against the ground truth, its ratio to the
outlier-free solution's, times, iterations, convergence, and how well the edges each solver
down-weighted match the injected outliers.

    python benches/outliers.py                          # seed 0
    python benches/outliers.py --seeds 0 1 2 --write benches/README.md

Exit status 1 when hitl-slam's ATE with the checked kernel (``--check``, DCS by default) exceeds
``--max-ratio`` (1.10) times the outlier-free ATE in any case, so it can serve as a check.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

# The sibling script: importable because Python puts this script's folder on sys.path. It imports
# numpy, GTSAM and hitl_slam lazily, so the process can be pinned before they load.
import compare_gtsam as shared

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from hitl_slam.graph import PoseGraph

DEFAULT_GRAPH = shared.DATASETS / "manhattanOlson3500.g2o"
DEFAULT_TRUTH = shared.DATASETS / "manhattanOlson3500_groundtruth_poses.txt"
PLAIN = "none"


# --- the corrupted graphs ------------------------------------------------------------------------


def loop_closures(graph: PoseGraph) -> NDArray[np.bool_]:
    """Which edges are loop closures (hitl-slam's ``loop`` class: |i - j| != 1)."""
    import numpy as np

    return np.asarray(np.abs(graph.edges[:, 0] - graph.edges[:, 1]) != 1)


def add_outliers(
    graph: PoseGraph, fraction: float, seed: int, translation: float
) -> tuple[PoseGraph, NDArray[np.int64]]:
    """``graph`` with ``round(fraction * loop closures)`` random false loop closures appended.

    Each joins a random pair of poses (i, j) with |i - j| > 1, drawn uniformly; its measurement
    is uniform in [-translation, translation] m on x and y and in [-pi, pi) rad on theta; its
    information is the one the dataset's loop closures have (the most common one, if they
    differ). Returns the new graph and the indices of the added edges.
    """
    import numpy as np

    from hitl_slam.graph import PoseGraph

    rng = np.random.default_rng(seed)
    loops = loop_closures(graph)
    count = round(fraction * int(loops.sum()))
    n = graph.num_poses
    pairs = np.empty((0, 2), dtype=np.int64)
    while len(pairs) < count:  # rejection sampling of |i - j| > 1
        draw = rng.integers(0, n, size=(count - len(pairs), 2), dtype=np.int64)
        pairs = np.concatenate([pairs, draw[np.abs(draw[:, 0] - draw[:, 1]) > 1]])
    measurements = np.column_stack(
        [
            rng.uniform(-translation, translation, size=(count, 2)),
            rng.uniform(-math.pi, math.pi, size=count),
        ]
    )
    matrices, counts = np.unique(
        graph.information[loops].reshape(-1, 9), axis=0, return_counts=True
    )
    information = np.broadcast_to(matrices[np.argmax(counts)].reshape(3, 3), (count, 3, 3))
    corrupted = PoseGraph(
        poses=graph.poses.copy(),
        edges=np.concatenate([graph.edges, pairs]),
        measurements=np.concatenate([graph.measurements, measurements]),
        information=np.concatenate([graph.information, information]),
        vertex_ids=graph.vertex_ids,
        anchor=graph.anchor,
        source=graph.source,
    )
    return corrupted, np.arange(graph.num_edges, corrupted.num_edges, dtype=np.int64)


def load_truth(path: Path, graph: PoseGraph) -> NDArray[np.float64]:
    """Ground-truth poses in the graph's row order (the file's line index is the vertex id)."""
    import numpy as np

    truth = np.loadtxt(path, ndmin=2)[:, :3]
    ids = np.asarray(graph.vertex_ids)
    if ids.min() < 0 or ids.max() >= len(truth):
        raise ValueError(f"{path}: {len(truth)} poses, but the graph has vertex id {ids.max()}")
    return np.asarray(truth[ids])


# --- one solver's result on one case --------------------------------------------------------------


@dataclasses.dataclass
class Outcome:
    """What the table shows for one solver on one (fraction, seed, kernel) case."""

    ate: float
    ratio: float  # ate / the same solver's outlier-free plain-LM ATE
    milliseconds: float  # median
    iterations: str
    converged: bool
    downweighted: int
    precision: float
    recall: float


def outcome(
    solves: Sequence[shared.Solve],
    truth: NDArray[np.float64],
    outliers: NDArray[np.int64],
    baseline: float | None,
    threshold: float,
) -> Outcome | None:
    """One solver's outcome on a case from its timed solves (None when it did not run)."""
    import numpy as np

    from hitl_slam.metrics import ate

    if not solves or baseline is None:
        return None
    last = solves[-1]
    error = ate(last.poses, truth) if np.all(np.isfinite(last.poses)) else math.nan
    weights = last.weights if last.weights is not None else np.ones(0)
    flagged = np.flatnonzero(weights < threshold)
    hits = int(np.isin(flagged, outliers).sum())
    return Outcome(
        ate=error,
        ratio=error / baseline,
        milliseconds=statistics.median(s.seconds for s in solves) * 1e3,
        iterations="/".join(str(c) for c in sorted({s.iterations for s in solves})),
        converged=all(s.converged for s in solves),
        downweighted=len(flagged),
        precision=hits / len(flagged) if len(flagged) else math.nan,
        recall=hits / len(outliers) if len(outliers) else math.nan,
    )


@dataclasses.dataclass
class Case:
    fraction: float
    seed: int
    kernel: str
    num_outliers: int
    hitl: Outcome | None
    gtsam: Outcome | None
    cost_check: float | None  # |hitl's robust cost - GTSAM's evaluation of it| / cost
    weight_check: float | None  # max |hitl's weight - GTSAM's weight at hitl's poses|


def conventions_check(row: shared.Row) -> dict[str, float | None]:
    """How far GTSAM's evaluation of hitl-slam's solution is from hitl-slam's own report."""
    import numpy as np

    checks: dict[str, float | None] = {"cost_check": None, "weight_check": None}
    if row.hitl and row.hitl_cost_by_gtsam is not None:
        reported = row.hitl[-1].final_cost
        checks["cost_check"] = abs(row.hitl_cost_by_gtsam - reported) / max(abs(reported), 1e-300)
    weights = row.hitl[-1].weights if row.hitl else None
    if weights is not None and row.hitl_weights_by_gtsam is not None:
        checks["weight_check"] = float(np.max(np.abs(weights - row.hitl_weights_by_gtsam)))
    return checks


# --- reporting -----------------------------------------------------------------------------------


def _f(value: float, digits: int) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def _show(o: Outcome | None, show: Callable[[Outcome], str]) -> str:
    return show(o) if o is not None else "n/a"


def _yes(flag: bool) -> str:
    return "yes" if flag else "**no**"


def _kernel_name(kernel: str) -> str:
    if kernel == PLAIN:
        return "none (plain LM)"
    name, _, value = kernel.partition(":")
    default = shared.KERNEL_DEFAULTS.get(name)
    return f"{kernel} (default {default:g})" if not value and default is not None else kernel


def detail_table(cases: Sequence[Case]) -> str:
    header = (
        "| outliers | seed | kernel on loop closures | ATE hitl (m) | / outlier-free "
        "| ATE GTSAM (m) | / outlier-free | hitl (ms) | GTSAM (ms) | hitl/GTSAM "
        "| iterations hitl / GTSAM | converged hitl / GTSAM | down-weighted hitl / GTSAM "
        "| precision hitl / GTSAM | recall hitl / GTSAM |"
    )
    lines = [header, "|" + "---|" * 15]
    for c in cases:
        h, g = c.hitl, c.gtsam

        def both(
            show: Callable[[Outcome], str], h: Outcome | None = h, g: Outcome | None = g
        ) -> str:
            return f"{_show(h, show)} / {_show(g, show)}"

        cells = [
            f"{c.num_outliers} ({c.fraction:.0%})",
            str(c.seed),
            _kernel_name(c.kernel),
            _show(h, lambda o: f"{o.ate:.4f}"),
            _show(h, lambda o: f"{o.ratio:.3f}"),
            _show(g, lambda o: f"{o.ate:.4f}"),
            _show(g, lambda o: f"{o.ratio:.3f}"),
            _show(h, lambda o: f"{o.milliseconds:.1f}"),
            _show(g, lambda o: f"{o.milliseconds:.1f}"),
            f"{h.milliseconds / g.milliseconds:.2f}" if h and g else "n/a",
            both(lambda o: o.iterations),
            both(lambda o: _yes(o.converged)),
            both(lambda o: str(o.downweighted)),
            both(lambda o: _f(o.precision, 3)),
            both(lambda o: _f(o.recall, 3)),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary_table(cases: Sequence[Case], max_ratio: float) -> str:
    """Worst ATE ratio over the seeds, per kernel (rows) and fraction (columns)."""
    fractions = sorted({c.fraction for c in cases})
    kernels = list(dict.fromkeys(c.kernel for c in cases))
    header = "| kernel | " + " | ".join(f"{f:.0%} outliers" for f in fractions) + " |"
    lines = [header, "|" + "---|" * (len(fractions) + 1)]

    def worst(selected: list[Outcome]) -> str:
        if not selected:
            return "n/a"
        value = max(o.ratio for o in selected)
        text = f"{value:.3f}"
        return f"**{text}**" if not value <= max_ratio else text

    for kernel in kernels:
        cells = [_kernel_name(kernel)]
        for f in fractions:
            chosen = [c for c in cases if c.kernel == kernel and c.fraction == f]
            h = worst([c.hitl for c in chosen if c.hitl is not None])
            g = worst([c.gtsam for c in chosen if c.gtsam is not None])
            cells.append(f"{h} / {g}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def section(
    cases: Sequence[Case],
    args: argparse.Namespace,
    pinning: shared.Pinning,
    graph: PoseGraph,
    baselines: dict[str, float],
    failures: list[str],
) -> str:
    num_loops = int(loop_closures(graph).sum())
    setup = (
        f"Graph: `{args.graph.name}` ({graph.num_poses} poses, {graph.num_edges} edges, "
        f"{num_loops} loop closures), ground truth `{args.truth.name}`. For each fraction f of "
        f"false loop closures and each seed ({', '.join(map(str, args.seeds))}), round(f x "
        f"{num_loops}) random pose pairs (i, j) with |i - j| > 1 get a loop closure with a "
        f"measurement uniform in [-{args.translation:g}, {args.translation:g}] m (x, y) and "
        "[-pi, pi) (theta) and the dataset's loop-closure information. Both solvers start from "
        "the file's initial guess; the kernel is on the loop closures only (true and false), "
        "odometry stays Gaussian; GTSAM gets `noiseModel.Robust.Create(mEstimator.X.Create(k), "
        "Gaussian.Information(omega))` with the same k and its anchor held by a prior of sigma "
        f"{args.prior_sigma:g}. LM stops when the objective decreases by less than "
        f"{args.absolute_tolerance:g} or by a fraction less than {args.relative_tolerance:g}, "
        f"at most {args.max_iterations} iterations (GTSAM: the same test on its error, as in "
        "section 1). Times: median of "
        f"{args.repeats} alternating solves after one warm-up each, one core."
    )
    metrics = (
        "ATE: RMSE of the positions after the best rigid 2D alignment (rotation and translation, "
        "no scale) to the ground truth (`hitl_slam.metrics.ate`); '/ outlier-free' divides it by "
        "the same solver's plain-LM ATE without false loop closures ("
        + ", ".join(f"{who} {value:.4f} m" for who, value in baselines.items())
        + "). Down-weighted: edges whose robust weight at the solution is below "
        f"{args.threshold:g} (hitl-slam: `report.weights`, `hitl_slam.solve.downweighted`; GTSAM: "
        "`mEstimator.weight(sqrt(r^T Omega r))` at its solution); precision and recall are "
        "against the injected false loop closures. Converged: hitl-slam's `report.converged`; "
        "GTSAM: stopped by its tolerances, not by the iteration limit or its lambda bound."
    )
    check = (
        f"Check: hitl-slam with `{args.check}` keeps the ATE within {args.max_ratio:g} x the "
        "outlier-free ATE in every case: "
        + ("**failed** in " + "; ".join(failures) if failures else "passed")
        + "."
    )
    cost_checks = [c.cost_check for c in cases if c.cost_check is not None]
    weight_checks = [c.weight_check for c in cases if c.weight_check is not None]
    conventions = (
        (
            "Same kernels on both sides: hitl-slam's final poses re-evaluated by GTSAM give its "
            f"reported robust cost to a relative {max(cost_checks):.1e} at worst, and GTSAM's "
            f"weights at those poses differ from hitl-slam's by at most {max(weight_checks):.1e}."
        )
        if cost_checks and weight_checks
        else ""
    )
    lines = [
        *shared.provenance(pinning),
        "",
        setup,
        "",
        metrics,
        "",
        check,
        "",
        "Worst ATE / outlier-free ATE over the seeds, hitl-slam / GTSAM:",
        "",
        summary_table(cases, args.max_ratio),
        "",
        "Every case:",
        "",
        detail_table(cases),
        "",
    ]
    if conventions:
        lines += [conventions, ""]
    thanks = shared.CREDITS.get(args.graph.name, args.graph.name)
    lines.append(
        f"Data: {thanks}; the false loop closures are generated by this script. Comparison: "
        "GTSAM (BSD licence). Thanks to the authors."
    )
    return "\n".join(lines)


# --- command line --------------------------------------------------------------------------------


def parse_arguments(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Add random false loop closures to M3500 (seeded) and solve it with "
        "hitl-slam and GTSAM side by side on one core, plain and with robust kernels; report "
        "ATE against the ground truth, its ratio to the outlier-free ATE, time, iterations and "
        "the precision / recall of the down-weighted edges. Exits 1 if hitl-slam with --check "
        "exceeds --max-ratio x the outlier-free ATE.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--graph", type=Path, default=DEFAULT_GRAPH, help="g2o file")
    parser.add_argument(
        "--truth",
        type=Path,
        default=DEFAULT_TRUTH,
        help="ground truth: one 'x y theta' line per vertex, line index = vertex id",
    )
    parser.add_argument(
        "--fractions",
        type=float,
        nargs="+",
        default=[0.1, 0.2, 0.5],
        help="false loop closures, as fractions of the true loop closures (the outlier-free "
        "graph is always solved too)",
    )
    parser.add_argument(
        "--seeds", "--seed", type=int, nargs="+", default=[0], help="seeds of the outliers"
    )
    parser.add_argument(
        "--kernels",
        nargs="+",
        default=[PLAIN, "dcs:1", "cauchy", "cauchy:1"],
        help=f"robust kernels on the loop closures, as hitl-slam's robust= ('{PLAIN}': plain LM)",
    )
    parser.add_argument(
        "--translation",
        type=float,
        default=10.0,
        help="false measurements are uniform in [-T, T] m on x and y",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed solves per solver and case")
    parser.add_argument(
        "--threshold", type=float, default=0.5, help="an edge is down-weighted below this weight"
    )
    parser.add_argument(
        "--check", default="dcs:1", help="the kernel whose ATE ratio decides the exit status"
    )
    parser.add_argument(
        "--max-ratio", type=float, default=1.10, help="largest acceptable ATE / outlier-free ATE"
    )
    shared.add_solver_arguments(parser)
    parser.add_argument(
        "--only", choices=("both", "hitl", "gtsam"), default="both", help="run one side only"
    )
    parser.add_argument("--verbose", action="store_true", help="log every solve")
    parser.add_argument(
        "--write",
        type=Path,
        metavar="README",
        help="replace the outliers section of this Markdown file with the results",
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    if any(not f > 0.0 for f in args.fractions):
        parser.error("--fractions must be positive")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_arguments(argv)
    pinning = shared.pin_to_one_core()  # before numpy, GTSAM and hitl_slam are imported

    from tqdm import tqdm

    import hitl_slam
    from hitl_slam.metrics import ate

    def log(message: str) -> None:
        tqdm.write(message, file=sys.stderr)

    if args.only != "hitl":
        try:
            import gtsam  # noqa: F401
        except ImportError:
            log("GTSAM is not installed (pip install gtsam), or use --only hitl.")
            return 2
    for path in (args.graph, args.truth):
        if not path.is_file():
            log(f"{path}: no such file")
            return 2
    graph = shared.load(args.graph)
    truth = load_truth(args.truth, graph)
    tolerances = shared.Tolerances(
        args.relative_tolerance, args.absolute_tolerance, args.max_iterations
    )
    # Plain LM first: its outlier-free solve is the baseline of every ratio.
    kernels = [PLAIN, *dict.fromkeys(k for k in args.kernels if k != PLAIN)]

    plans: list[tuple[float, int]] = [(0.0, args.seeds[0])]
    plans += [(f, seed) for f in args.fractions for seed in args.seeds]
    cases: list[Case] = []
    baselines: dict[str, float] = {}
    progress = tqdm(total=len(plans) * len(kernels), desc="cases", unit="case", file=sys.stderr)
    for fraction, seed in plans:
        corrupted, outliers = add_outliers(graph, fraction, seed, args.translation)
        for kernel in kernels:
            progress.set_postfix_str(f"{fraction:.0%} seed {seed} {kernel}")
            robust = None if kernel == PLAIN else kernel
            row = shared.run_graph(
                f"{fraction:.0%}/{seed}/{kernel}",
                corrupted,
                optimize=hitl_slam.optimize,
                tolerances=tolerances,
                repeats=args.repeats,
                only=args.only,
                prior_sigma=args.prior_sigma,
                log=log if args.verbose else lambda _: None,
                robust=robust,
            )
            if fraction == 0.0 and kernel == PLAIN:
                for who, solves in (("hitl-slam", row.hitl), ("GTSAM", row.gtsam)):
                    if solves:
                        baselines[who] = ate(solves[-1].poses, truth)

            case = Case(
                fraction=fraction,
                seed=seed,
                kernel=kernel,
                num_outliers=len(outliers),
                hitl=outcome(row.hitl, truth, outliers, baselines.get("hitl-slam"), args.threshold),
                gtsam=outcome(row.gtsam, truth, outliers, baselines.get("GTSAM"), args.threshold),
                **conventions_check(row),
            )
            cases.append(case)
            h, g = case.hitl, case.gtsam
            log(
                f"{fraction:4.0%} seed {seed} {kernel:>9}: ATE ratio hitl "
                f"{h.ratio if h else math.nan:.3f}, GTSAM {g.ratio if g else math.nan:.3f}"
            )
            progress.update()
    progress.close()

    failures = [
        f"{c.fraction:.0%} seed {c.seed} (ratio {c.hitl.ratio:.3f})"
        for c in cases
        if c.kernel == args.check and c.hitl is not None and not c.hitl.ratio <= args.max_ratio
    ]
    body = section(cases, args, pinning, graph, baselines, failures)
    print(body)
    if args.write is not None:
        shared.replace_section(args.write, "outliers", body)
        log(f"wrote the outliers section of {args.write}")
    checked = any(c.kernel == args.check and c.hitl is not None for c in cases)
    if not checked:
        log(f"note: no hitl-slam results with {args.check}; nothing checked")
    if failures:
        log(f"FAILED: hitl-slam with {args.check} exceeds {args.max_ratio:g} x: {failures}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
