#!/usr/bin/env python
"""Odometry chains, side by side with GTSAM: a bad initial guess, and up to a million poses.

1. Jittered chains: a 10 000-pose chain of exact odometry (unit steps forward with small random
   turns, information diag(100, 100, 1000)) whose initial guess is the truth perturbed per pose
   by N(0, 1 m) on x and y and N(0, 1 rad), resp. N(0, 3 rad), on theta. hitl-slam from that
   guess and with ``init="tree"`` / ``"chordal"`` against GTSAM's LM from the guess and from its
   own LAGO initialization (``gtsam.lago.initialize``), in this one process pinned to one core,
   alternating; the optimum is chi2 = 0.
2. Big chains (100 000 and 1 000 000 poses): time and peak memory, one fresh subprocess per
   solver and size (pinned to one core): hitl-slam with ``init="tree"`` and from the noisy guess,
   GTSAM's LM from the noisy guess and LAGO + LM. A child that runs longer than ``--timeout`` or
   uses more than ``--child-memory-limit-gib`` is stopped and reported as such.

    python benches/chains.py --write benches/README.md
    python benches/chains.py --big-sizes 100000        # skip the million
    python benches/chains.py --child hitl-tree --num-poses 1000000   # one solve, JSON out

Exit status 1 when a hitl-slam child exceeds ``--memory-limit-gib`` (4 GiB) or fails.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import resource
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

# The sibling script: importable because Python puts this script's folder on sys.path. It imports
# numpy, GTSAM and hitl_slam lazily, so the process can be pinned before they load.
import compare_gtsam as shared

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from hitl_slam.graph import PoseGraph

INFORMATION = (100.0, 100.0, 1000.0)
# Big-chain solvers: (label, which library, where LM starts).
CHILD_SOLVERS = {
    "hitl-tree": ("hitl-slam", "init tree (odometry composed), then LM"),
    "hitl-given": ("hitl-slam", "LM from the noisy guess"),
    "gtsam-given": ("GTSAM", "LM from the noisy guess"),
    "gtsam-lago": ("GTSAM", "LAGO (lago.initialize), then LM"),
}


# --- the chains ----------------------------------------------------------------------------------


def jittered_chain(
    num_poses: int, turn_sigma: float, sigma_xy: float, sigma_thetas: Sequence[float], seed: int
) -> tuple[list[PoseGraph], NDArray[np.float64]]:
    """An exact odometry chain and, per heading noise in ``sigma_thetas``, its jittered graph.

    Step k is (1 m, 0, turn_k) with turn_k ~ N(0, turn_sigma); the measurements are exact, the
    information is diag(INFORMATION). The initial guess of every pose but the anchor (pose 0) is
    the truth plus N(0, sigma_xy) on x and y and N(0, sigma_theta) on theta (the same standard
    normal draws, scaled, for every sigma_theta). Returns the graphs and the true poses.
    """
    import numpy as np

    from hitl_slam.geometry import wrap
    from hitl_slam.graph import PoseGraph

    rng = np.random.default_rng(seed)
    turns = rng.normal(0.0, turn_sigma, num_poses - 1)
    heading = np.concatenate([[0.0], np.cumsum(turns)])
    truth = np.column_stack(
        [
            np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]))]),
            np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]))]),
            wrap(heading),
        ]
    )
    edges = np.column_stack([np.arange(num_poses - 1), np.arange(1, num_poses)]).astype(np.int64)
    measurements = np.column_stack([np.ones(num_poses - 1), np.zeros(num_poses - 1), turns])
    information = np.broadcast_to(np.diag(INFORMATION), (num_poses - 1, 3, 3))
    noise_xy = rng.normal(0.0, sigma_xy, (num_poses - 1, 2))
    noise_theta = rng.normal(0.0, 1.0, num_poses - 1)
    graphs = []
    for sigma_theta in sigma_thetas:
        guess = truth.copy()
        guess[1:, :2] += noise_xy
        guess[1:, 2] = wrap(guess[1:, 2] + sigma_theta * noise_theta)
        graphs.append(PoseGraph(guess, edges, measurements, information))
    return graphs, truth


# --- 1. jittered chains, in this process ---------------------------------------------------------


@dataclasses.dataclass
class JitterRow:
    sigma_theta: float
    solver: str
    start: str
    solves: list[shared.Solve]
    ate: float


def run_jittered(
    args: argparse.Namespace, tolerances: shared.Tolerances, log: Callable[[str], None]
) -> tuple[list[JitterRow], int, int]:
    """All solvers on each jittered chain, alternating solve by solve; one warm-up each."""
    import numpy as np
    from tqdm import tqdm

    import hitl_slam
    from hitl_slam.metrics import ate

    graphs, truth = jittered_chain(
        args.num_poses, args.turn_sigma, args.sigma_xy, args.sigma_theta, args.seed
    )
    rows: list[JitterRow] = []
    total = len(graphs) * 5 * (args.repeats + 1)
    progress = tqdm(total=total, desc="jittered chains", unit="solve", file=sys.stderr)
    for sigma_theta, graph in zip(args.sigma_theta, graphs, strict=True):
        problem = shared.GtsamProblem(graph, tolerances, args.prior_sigma)
        solvers: list[tuple[str, str, Callable[[], shared.Solve]]] = [
            (
                "hitl-slam",
                f"init {init}",
                functools.partial(
                    shared.solve_hitl, hitl_slam.optimize, graph, tolerances, init=init
                ),
            )
            for init in ("given", "tree", "chordal")
        ]
        solvers += [
            ("GTSAM", "LM from the guess", problem.solve),
            ("GTSAM", "LAGO, then LM", functools.partial(problem.solve, lago=True)),
        ]
        results: list[list[shared.Solve]] = [[] for _ in solvers]
        for k in range(args.repeats + 1):
            for (who, start, solve), out in zip(solvers, results, strict=True):
                progress.set_postfix_str(f"{sigma_theta:g} rad, {who} {start}")
                result = solve()
                if k > 0:
                    out.append(result)
                progress.update()
        for (who, start, _), out in zip(solvers, results, strict=True):
            finite = bool(np.all(np.isfinite(out[-1].poses)))
            error = ate(out[-1].poses, truth) if finite else math.nan
            rows.append(JitterRow(sigma_theta, who, start, out, error))
            log(
                f"sigma_theta {sigma_theta:g}: {who} {start}: "
                f"{statistics.median(s.seconds for s in out) * 1e3:.1f} ms, "
                f"{out[-1].iterations} it, chi2 {out[-1].final_chi2:.3g}"
            )
    progress.close()
    return rows, graphs[0].num_poses, graphs[0].num_edges


def jittered_table(rows: Sequence[JitterRow]) -> str:
    lines = [
        "| heading noise (rad) | solver | start | time (ms) | iterations | chi2 at LM start "
        "| chi2 after | converged | ATE vs truth (m) |",
        "|" + "---|" * 9,
    ]
    for row in rows:
        last = row.solves[-1]
        cells = [
            f"{row.sigma_theta:g}",
            row.solver,
            row.start,
            f"{statistics.median(s.seconds for s in row.solves) * 1e3:.1f}",
            "/".join(str(c) for c in sorted({s.iterations for s in row.solves})),
            f"{last.initial_chi2:.4g}",
            f"{last.final_chi2:.3g}",
            ("yes" if last.converged else "**no**") + f" ({last.termination})",
            f"{row.ate:.3g}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --- 2. big chains, one child process per solver and size ---------------------------------------


def child(args: argparse.Namespace) -> int:
    """One solve of the chain in this (fresh) process; prints a JSON line with the numbers."""
    shared.pin_to_one_core()

    def peak_mib() -> float:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    tolerances = shared.Tolerances(
        args.relative_tolerance, args.absolute_tolerance, args.max_iterations
    )
    start = time.perf_counter()
    (graph,), _ = jittered_chain(
        args.num_poses, args.turn_sigma, args.sigma_xy, [args.big_sigma_theta], args.seed
    )
    library = CHILD_SOLVERS[args.child][0]
    if library == "hitl-slam":
        import hitl_slam

        graph.engine()  # built outside the clock, as in compare_gtsam (solve_hitl copies it)
        init = "tree" if args.child == "hitl-tree" else "given"
        build_s, built_mib = time.perf_counter() - start, peak_mib()
        result = shared.solve_hitl(hitl_slam.optimize, graph, tolerances, init=init)
    else:
        problem = shared.GtsamProblem(graph, tolerances, args.prior_sigma)
        build_s, built_mib = time.perf_counter() - start, peak_mib()
        result = problem.solve(lago=args.child == "gtsam-lago")
    print(
        json.dumps(
            {
                "build_s": build_s,
                "solve_s": result.seconds,
                "iterations": result.iterations,
                "initial_chi2": result.initial_chi2,
                "final_chi2": result.final_chi2,
                "termination": result.termination,
                "converged": result.converged,
                "built_mib": built_mib,
                "peak_mib": peak_mib(),
            }
        ),
        flush=True,
    )
    return 0


@dataclasses.dataclass
class BigRow:
    num_poses: int
    solver: str
    status: str  # "ok", or why there are no numbers
    wall_s: float
    peak_mib: float  # the child's own ru_maxrss, or the last VmHWM seen when it was stopped
    numbers: dict[str, Any]


def _vm_hwm_mib(pid: int) -> float:
    """The peak RSS of a running process so far (0 if it is gone)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0
    for line in status.splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return 0.0


@contextlib.contextmanager
def stack_limit(mib: int) -> Iterator[None]:
    """Set this process's soft stack limit while children are started (they inherit it, and
    their main thread's stack gets it at exec); ``mib`` 0: unlimited, negative: unchanged."""
    soft, hard = resource.getrlimit(resource.RLIMIT_STACK)
    if mib < 0:
        yield
        return
    want = resource.RLIM_INFINITY if mib == 0 else mib * 2**20
    if hard != resource.RLIM_INFINITY and (want == resource.RLIM_INFINITY or want > hard):
        want = hard
    resource.setrlimit(resource.RLIMIT_STACK, (want, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_STACK, (soft, hard))


def run_child(args: argparse.Namespace, solver: str, num_poses: int) -> BigRow:
    """Run one child, watching its peak memory and time; stop it past the limits."""
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        solver,
        "--num-poses",
        str(num_poses),
        "--seed",
        str(args.seed),
        "--turn-sigma",
        repr(args.turn_sigma),
        "--sigma-xy",
        repr(args.sigma_xy),
        "--big-sigma-theta",
        repr(args.big_sigma_theta),
        "--relative-tolerance",
        repr(args.relative_tolerance),
        "--absolute-tolerance",
        repr(args.absolute_tolerance),
        "--max-iterations",
        str(args.max_iterations),
        "--prior-sigma",
        repr(args.prior_sigma),
    ]
    limit_mib = args.child_memory_limit_gib * 1024.0
    start = time.perf_counter()
    with stack_limit(args.stack_limit_mib):
        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
    seen_mib, status = 0.0, "ok"
    while True:
        try:
            out, err = process.communicate(timeout=0.25)
            break
        except subprocess.TimeoutExpired:
            seen_mib = max(seen_mib, _vm_hwm_mib(process.pid))
            elapsed = time.perf_counter() - start
            if elapsed > args.timeout:
                status = f"stopped after {args.timeout:g} s (--timeout)"
            elif seen_mib > limit_mib:
                status = f"stopped at {seen_mib:.0f} MiB (--child-memory-limit-gib)"
            else:
                continue
            process.kill()
            out, err = process.communicate()
            break
    wall = time.perf_counter() - start
    numbers: dict[str, Any] = {}
    if status == "ok":
        if process.returncode != 0:
            if process.returncode < 0:
                name = signal.Signals(-process.returncode).name
                status = f"crashed ({name})"
            else:
                status = f"failed (exit status {process.returncode})"
            tail = err.strip().splitlines()[-1:] if err else []
            if tail:
                status += f": {tail[0][:120]}"
        else:
            numbers = json.loads(out.strip().splitlines()[-1])
    peak = float(numbers.get("peak_mib", seen_mib))
    return BigRow(num_poses, solver, status, wall, peak, numbers)


def big_table(rows: Sequence[BigRow]) -> str:
    lines = [
        "| poses | solver | start | result | build (s) | solve (s) | iterations | ms/iteration "
        "(LM from the guess) "
        "| chi2 after | converged | peak RSS (MiB) | RSS after building (MiB) |",
        "|" + "---|" * 12,
    ]
    for row in rows:
        who, start = CHILD_SOLVERS[row.solver]
        n = row.numbers
        if n:
            iterations = int(n["iterations"])
            from_guess = row.solver.endswith("-given") and iterations > 0
            per = n["solve_s"] / iterations * 1e3 if from_guess else math.nan
            cells = [
                f"{row.num_poses:,}",
                who,
                start,
                "ok",
                f"{n['build_s']:.2f}",
                f"{n['solve_s']:.2f}",
                str(iterations),
                "-" if math.isnan(per) else f"{per:.0f}",
                f"{n['final_chi2']:.3g}",
                ("yes" if n["converged"] else "**no**") + f" ({n['termination']})",
                f"{row.peak_mib:.0f}",
                f"{n['built_mib']:.0f}",
            ]
        else:
            seen = f">= {row.peak_mib:.0f} (seen)" if row.peak_mib > 0 else "-"
            cells = [f"{row.num_poses:,}", who, start, f"**{row.status}**"]
            cells += ["-"] * 6 + [seen, "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_big(args: argparse.Namespace, log: Callable[[str], None]) -> list[BigRow]:
    from tqdm import tqdm

    plan = [(n, s) for n in args.big_sizes for s in args.big_solvers]
    rows: list[BigRow] = []
    for num_poses, solver in tqdm(plan, desc="big chains", unit="child", file=sys.stderr):
        row = run_child(args, solver, num_poses)
        rows.append(row)
        n = row.numbers
        summary = (
            f"{n['solve_s']:.2f} s, {n['iterations']} it, chi2 {n['final_chi2']:.3g}"
            if n
            else row.status
        )
        log(f"{num_poses} poses, {solver}: {summary}, peak {row.peak_mib:.0f} MiB")
    return rows


# --- the section ---------------------------------------------------------------------------------


def section(
    args: argparse.Namespace,
    pinning: shared.Pinning,
    jittered: Sequence[JitterRow],
    size: tuple[int, int],
    big: Sequence[BigRow],
    memory_failures: list[str],
) -> str:
    stack = (
        "the inherited stack limit"
        if args.stack_limit_mib < 0
        else "the stack limit raised to "
        + ("unlimited" if args.stack_limit_mib == 0 else f"{args.stack_limit_mib} MiB")
        + " (`--stack-limit-mib`; GTSAM's `lago.initialize` recurses along the chain)"
    )
    common = (
        f"Chains: unit steps forward with turns ~ N(0, {args.turn_sigma:g} rad), exact "
        f"measurements, information diag{INFORMATION}, pose 0 held fixed (GTSAM: a prior of "
        f"sigma {args.prior_sigma:g}), seed {args.seed}; the optimum is chi2 = 0. LM stops when "
        f"chi2 decreases by less than {args.absolute_tolerance:g} or by a fraction less than "
        f"{args.relative_tolerance:g}, at most {args.max_iterations} iterations, as in section 1. "
        "Converged: hitl-slam's `report.converged` (its termination in brackets); GTSAM: "
        "stopped by its tolerances, not by the iteration limit or its lambda bound."
    )
    lines = [*shared.provenance(pinning), "", common, ""]
    if jittered:
        poses, edges = size
        lines += [
            f"Jittered chains ({poses} poses, {edges} edges): the initial guess is the truth plus "
            f"N(0, {args.sigma_xy:g} m) on x and y and N(0, sigma) on theta per pose (pose 0 "
            "exact). Both solvers in this process on one core, alternating; times are medians "
            f"of {args.repeats} solves after one warm-up each and include the initialization "
            "(hitl-slam: `init` is computed inside `optimize`; GTSAM: `lago.initialize` plus "
            "LM); ATE: rigidly aligned position RMSE against the truth.",
            "",
            jittered_table(jittered),
            "",
        ]
    if big:
        limit = (
            f"Check: hitl-slam's peak RSS at most {args.memory_limit_gib:g} GiB at every size: "
            + ("**failed**: " + "; ".join(memory_failures) if memory_failures else "passed")
            + "."
        )
        lines += [
            f"Big chains: the same construction with N(0, {args.sigma_xy:g} m) / "
            f"N(0, {args.big_sigma_theta:g} rad) noise on the guess; one fresh process per "
            "solver and size, pinned to one core, with "
            f"{stack}. Build: generating the chain and building the solver's graph (hitl-slam: "
            "`PoseGraph` and its core graph; GTSAM: the factor graph and `Values`); solve: "
            "the timed call as in section 1, one solve. Peak RSS: the child's `ru_maxrss` (the "
            "whole process: Python, numpy, the graph and the solver). A child is stopped after "
            f"{args.timeout:g} s or above {args.child_memory_limit_gib:g} GiB.",
            "",
            big_table(big),
            "",
            limit,
            "",
        ]
    lines.append("Data: generated by this script; comparison: GTSAM (BSD licence).")
    return "\n".join(lines)


# --- command line --------------------------------------------------------------------------------


def parse_arguments(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Odometry chains side by side with GTSAM: a 10k-pose chain from a jittered "
        "guess (hitl-slam init given / tree / chordal vs GTSAM LM and LAGO), and 100k / 1M-pose "
        "chains for time and peak memory (one subprocess per solver and size).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--num-poses", type=int, default=10_000, help="jittered chain length")
    parser.add_argument("--seed", type=int, default=0, help="seed of the turns and the noise")
    parser.add_argument("--turn-sigma", type=float, default=0.1, help="rad, per step")
    parser.add_argument("--sigma-xy", type=float, default=1.0, help="guess noise on x, y (m)")
    parser.add_argument(
        "--sigma-theta",
        type=float,
        nargs="+",
        default=[1.0, 3.0],
        help="guess noise on theta (rad), one jittered chain each",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed solves per solver (jittered)")
    parser.add_argument(
        "--big-sizes",
        type=int,
        nargs="*",
        default=[100_000, 1_000_000],
        help="big chain lengths (none: skip the big chains)",
    )
    parser.add_argument(
        "--big-solvers",
        nargs="+",
        choices=tuple(CHILD_SOLVERS),
        default=list(CHILD_SOLVERS),
        help="solvers of the big chains",
    )
    parser.add_argument(
        "--big-sigma-theta", type=float, default=1.0, help="guess noise on theta of the big chains"
    )
    parser.add_argument("--no-jittered", action="store_true", help="skip the jittered chains")
    parser.add_argument(
        "--timeout", type=float, default=300.0, help="seconds before a big-chain child is stopped"
    )
    parser.add_argument(
        "--memory-limit-gib",
        type=float,
        default=4.0,
        help="hitl-slam's peak RSS must stay at or under this (exit status 1 otherwise)",
    )
    parser.add_argument(
        "--child-memory-limit-gib",
        type=float,
        default=12.0,
        help="a big-chain child is stopped above this peak RSS",
    )
    parser.add_argument(
        "--stack-limit-mib",
        type=int,
        default=1024,
        help="stack limit of the children (0: unlimited, -1: inherit); GTSAM's lago.initialize "
        "recurses along the chain and overflows the usual 8 MiB at 100k poses",
    )
    shared.add_solver_arguments(parser)
    parser.add_argument(
        "--child",
        choices=tuple(CHILD_SOLVERS),
        help="internal: solve one --num-poses chain with this solver and print JSON",
    )
    parser.add_argument(
        "--write",
        type=Path,
        metavar="README",
        help="replace the chains section of this Markdown file with the results",
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    if args.num_poses < 2:
        parser.error("--num-poses must be >= 2")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_arguments(argv)
    if args.child is not None:
        return child(args)
    pinning = shared.pin_to_one_core()  # before numpy, GTSAM and hitl_slam are imported

    from tqdm import tqdm

    def log(message: str) -> None:
        tqdm.write(message, file=sys.stderr)

    try:
        import gtsam  # noqa: F401
    except ImportError:
        log("GTSAM is not installed (pip install gtsam).")
        return 2
    tolerances = shared.Tolerances(
        args.relative_tolerance, args.absolute_tolerance, args.max_iterations
    )
    jittered: list[JitterRow] = []
    size = (0, 0)
    if not args.no_jittered:
        jittered, poses, edges = run_jittered(args, tolerances, log)
        size = (poses, edges)
    big = run_big(args, log) if args.big_sizes else []
    limit_mib = args.memory_limit_gib * 1024.0
    memory_failures = [
        f"{row.num_poses:,} poses, {row.solver}: "
        + (f"{row.peak_mib:.0f} MiB" if row.status == "ok" else row.status)
        for row in big
        if CHILD_SOLVERS[row.solver][0] == "hitl-slam"
        and (row.status != "ok" or row.peak_mib > limit_mib)
    ]
    body = section(args, pinning, jittered, size, big, memory_failures)
    print(body)
    if args.write is not None:
        shared.replace_section(args.write, "chains", body)
        log(f"wrote the chains section of {args.write}")
    if memory_failures:
        log(f"FAILED: {memory_failures}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
