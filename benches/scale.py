#!/usr/bin/env python
"""Scale test: one hitl-slam solve of a generated 100 000-pose graph with 10 000 loop closures.

Generates ``chain_with_loops`` (a Manhattan walk; see hitl_slam.sim.synthetic), solves it from its
odometry guess, and reports time, iterations, chi2, the trajectory error against the ground truth
and the peak memory. Meant to run as

    /usr/bin/time -v python benches/scale.py --write benches/README.md
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

import hitl_slam
from hitl_slam.sim.synthetic import chain_with_loops

_THREAD_VARIABLES = ("RAYON_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def absolute_trajectory_error(
    estimate: NDArray[np.float64], truth: NDArray[np.float64]
) -> tuple[float, float]:
    """Position RMSE (m): as estimated (both share the anchor), and after the best rigid 2D fit.

    The fit is the closed-form least-squares rotation and translation (Umeyama without scale).
    """
    raw = float(np.sqrt(np.mean(np.sum((estimate[:, :2] - truth[:, :2]) ** 2, axis=1))))
    p = estimate[:, :2] - estimate[:, :2].mean(axis=0)
    q = truth[:, :2] - truth[:, :2].mean(axis=0)
    # The rotation angle maximizing sum q_k . R p_k.
    angle = math.atan2(
        float(np.sum(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0])),
        float(np.sum(p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1])),
    )
    c, s = math.cos(angle), math.sin(angle)
    rotated = np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1)
    aligned = float(np.sqrt(np.mean(np.sum((rotated - q) ** 2, axis=1))))
    return raw, aligned


def _pair(errors: tuple[float, float]) -> str:
    return f"{errors[0]:.3f} m / {errors[1]:.3f} m"


def parse_arguments(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Generate chain_with_loops(N) and solve it once with hitl_slam.optimize; "
        "print time, iterations, chi2, ATE and peak RSS.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--num-poses", type=int, default=100_000)
    parser.add_argument("--loop-fraction", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--relative-tolerance", type=float, default=1e-6)
    parser.add_argument("--absolute-tolerance", type=float, default=1e-6)
    parser.add_argument("--max-iterations", type=int, default=100)
    parser.add_argument(
        "--write",
        type=Path,
        metavar="README",
        help="replace the scale section of this Markdown file with the results",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    # The sibling script: importable because Python puts this script's folder on sys.path.
    import compare_gtsam as shared

    args = parse_arguments(argv)
    optimize = getattr(hitl_slam, "optimize", None)
    chi2 = getattr(hitl_slam, "chi2", None)
    if optimize is None or chi2 is None:
        print(
            "hitl_slam.optimize is not available; build the core (maturin develop --release)",
            file=sys.stderr,
        )
        return 2

    start = time.perf_counter()
    graph, truth = chain_with_loops(
        args.num_poses, loop_fraction=args.loop_fraction, seed=args.seed
    )
    generate_s = time.perf_counter() - start
    rss_generated = peak_rss_mib()
    odometry_ate = absolute_trajectory_error(graph.poses, truth)

    start = time.perf_counter()
    poses, report = optimize(
        graph,
        method="lm",
        max_iterations=args.max_iterations,
        relative_tolerance=args.relative_tolerance,
        absolute_tolerance=args.absolute_tolerance,
    )
    solve_s = time.perf_counter() - start
    rss_end = peak_rss_mib()

    ate = absolute_trajectory_error(np.asarray(poses), truth)
    truth_chi2 = float(chi2(graph, truth))
    closures = graph.num_edges - (graph.num_poses - 1)
    dof = 3 * (graph.num_edges - graph.num_poses + 1)
    threads = ", ".join(f"{v}={os.environ[v]}" for v in _THREAD_VARIABLES if v in os.environ)
    termination = getattr(report.termination, "value", report.termination)
    lines = [
        f"Measured {shared.now_utc()} with:",
        "",
        "```",
        shared.command_line(),
        "```",
        "",
        *shared.machine_description(None),
        f"- Threads: {threads or 'library defaults (no thread variables set)'}",
        "",
        (
            f"Graph: `chain_with_loops({args.num_poses}, loop_fraction={args.loop_fraction}, "
            f"seed={args.seed})`: {graph.num_poses} poses, {graph.num_edges} edges "
            f"({closures} loop closures), generated in {generate_s:.2f} s. Levenberg-Marquardt "
            f"from the odometry guess, relative tolerance {args.relative_tolerance:g}, absolute "
            f"tolerance {args.absolute_tolerance:g} on chi2, at most {args.max_iterations} "
            "iterations."
        ),
        "",
        "| quantity | value |",
        "|---|---|",
        f"| solve time (optimize call, wall) | {solve_s:.2f} s |",
        f"| time reported by the solver | {float(report.time_s):.2f} s |",
        f"| iterations | {report.iterations} ({termination}) |",
        f"| chi2 before | {float(report.initial_chi2):.6g} |",
        f"| chi2 after | {float(report.final_chi2):.6g} |",
        f"| chi2 of the ground truth | {truth_chi2:.6g} |",
        f"| degrees of freedom 3 (edges - poses + 1) | {dof} |",
        f"| ATE RMSE odometry (anchored / rigidly aligned) | {_pair(odometry_ate)} |",
        f"| ATE RMSE solution (anchored / rigidly aligned) | {_pair(ate)} |",
        f"| peak RSS after generating the graph | {rss_generated:.0f} MiB |",
        f"| peak RSS at the end (ru_maxrss) | {rss_end:.0f} MiB |",
        "",
        (
            "The measurement noise is drawn from the edges' covariances, so at the global optimum "
            "chi2 is close to the degrees of freedom; a chi2 far above them means a local minimum."
        ),
    ]
    body = "\n".join(lines)
    print(body)
    if args.write is not None:
        shared.replace_section(args.write, "scale", body)
        print(f"wrote the scale section of {args.write}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
