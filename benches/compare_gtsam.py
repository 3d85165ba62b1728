#!/usr/bin/env python
"""Side-by-side benchmark: hitl-slam's Levenberg-Marquardt against GTSAM's, on the same graphs.

Both solvers run in this one process, pinned to one CPU core, alternating solve by solve, from the
file's initial guess to the same convergence test on chi2; we report medians and their ratio
(house rule 6: absolute times alone mean little on a shared machine).

    python benches/compare_gtsam.py                      # M3500, City10000, Intel, MIT Killian
    python benches/compare_gtsam.py --only gtsam a.g2o   # GTSAM alone (no compiled core needed)
    python benches/compare_gtsam.py --write benches/README.md
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import importlib.metadata
import math
import os
import platform
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

# numpy, GTSAM and hitl_slam are imported inside the functions that use them, so that main() can
# pin the process and limit the thread pools before any of them is loaded.
if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from hitl_slam.graph import PoseGraph
    from hitl_slam.solve import RobustSpec

_THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "RAYON_NUM_THREADS",
    "TBB_NUM_THREADS",
)


@dataclasses.dataclass(frozen=True)
class Pinning:
    """Where the benchmark ran: how many CPUs the process was allowed, and the one it kept."""

    allowed: int
    cpu: int


def pin_to_one_core() -> Pinning:
    """Pin this process to its first allowed CPU and ask every thread pool for one thread.

    Must run before numpy, GTSAM or the Rust core are imported: BLAS, OpenMP and rayon read these
    variables once, when their pools start. (The GTSAM wheel is built without TBB; it is
    single-threaded either way.)
    """
    already = [name for name in ("numpy", "gtsam", "hitl_slam") if name in sys.modules]
    if already:
        print(
            f"warning: {', '.join(already)} imported before pinning; their thread pools may "
            "ignore the one-thread limit",
            file=sys.stderr,
        )
    for name in _THREAD_VARIABLES:
        os.environ[name] = "1"
    allowed = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {allowed[0]})
    return Pinning(allowed=len(allowed), cpu=allowed[0])


REPO_ROOT = Path(__file__).resolve().parent.parent
DATASETS = REPO_ROOT.parent / "shared" / "datasets" / "pose_graphs"
DEFAULT_GRAPHS = tuple(
    DATASETS / name
    for name in ("M3500_carlone.g2o", "city10000.g2o", "intel.g2o", "mit_killian.g2o")
)
# The speed target: hitl-slam / GTSAM LM time at equal chi2 on these graphs.
TARGET_RATIO = 0.15
TARGET_GRAPHS = ("M3500_carlone.g2o", "city10000.g2o")

# Who to thank for each public dataset (../shared/datasets/README.md).
CREDITS = {
    "M3500_carlone.g2o": "M3500: E. Olson's Manhattan world, in the version distributed by "
    "L. Carlone (via MurpheyLab/DPGO)",
    "manhattanOlson3500.g2o": "manhattanOlson3500: E. Olson's Manhattan world and its ground "
    "truth, from N. Suenderhauf's Vertigo distribution (via OpenSLAM-org/openslam_vertigo)",
    "city10000.g2o": "City10000: M. Kaess (via david-m-rosen/SE-Sync)",
    "intel.g2o": "Intel Research Lab: D. Haehnel, Radish (via david-m-rosen/SE-Sync)",
    "mit_killian.g2o": "MIT Killian Court (via david-m-rosen/SE-Sync)",
    "ring.g2o": "ring: simulated, from OpenSLAM-org/openslam_vertigo",
}


# --- loading -------------------------------------------------------------------------------------


def _parse_g2o_fallback(path: Path) -> PoseGraph:
    """FALLBACK ONLY, for when hitl_slam.load_graph is not built yet: VERTEX_SE2 and EDGE_SE2 lines.

    No validation beyond what numpy does; the package's reader is the real one.
    """
    import numpy as np

    from hitl_slam.graph import PoseGraph

    index: dict[int, int] = {}
    poses: list[list[float]] = []
    edges: list[tuple[int, int]] = []
    measurements: list[list[float]] = []
    information: list[list[list[float]]] = []
    with path.open() as lines:
        for line in lines:
            fields = line.split()
            if fields and fields[0] == "VERTEX_SE2":
                index[int(fields[1])] = len(poses)
                poses.append([float(v) for v in fields[2:5]])
            elif fields and fields[0] == "EDGE_SE2":
                edges.append((int(fields[1]), int(fields[2])))
                measurements.append([float(v) for v in fields[3:6]])
                a, b, c, d, e, f = (float(v) for v in fields[6:12])
                information.append([[a, b, c], [b, d, e], [c, e, f]])
    rows = np.array([[index[i], index[j]] for i, j in edges], dtype=np.int64)
    pose_array = np.array(poses)
    meas_array = np.array(measurements)
    for array in (pose_array, meas_array):
        array[:, 2] = math.pi - np.mod(math.pi - array[:, 2], 2.0 * math.pi)
    return PoseGraph(
        poses=pose_array,
        edges=rows,
        measurements=meas_array,
        information=np.array(information),
        vertex_ids=np.array(list(index), dtype=np.int64),
        source=str(path),
    )


def load(path: Path) -> PoseGraph:
    """The package's reader when it exists, else the fallback parser above."""
    import hitl_slam

    load_graph: Callable[[str], PoseGraph] | None = getattr(hitl_slam, "load_graph", None)
    if load_graph is not None:
        return load_graph(str(path))
    return _parse_g2o_fallback(path)


# --- the two solvers -----------------------------------------------------------------------------


@dataclasses.dataclass
class Solve:
    """One timed solve."""

    seconds: float
    iterations: int
    initial_chi2: float
    final_chi2: float
    termination: str
    poses: NDArray[np.float64]
    # The objective that was minimized: chi2, or the robust cost (2 x GTSAM's error) with kernels.
    final_cost: float = math.nan
    converged: bool = True
    # Per-edge robust weights at the solution (1 without a kernel); None when not computed.
    weights: NDArray[np.float64] | None = None


@dataclasses.dataclass
class Tolerances:
    """Our convergence test, on chi2 = sum r^T Omega r."""

    relative: float
    absolute: float
    max_iterations: int


# hitl-slam's default kernel parameters (hitl_slam.solve.robust_pairs), given to GTSAM explicitly:
# GTSAM's mEstimator.*.Create(k) has no default.
KERNEL_DEFAULTS = {"huber": 1.345, "cauchy": 2.3849, "dcs": 1.0}


def edge_class(i: int, j: int) -> str:
    """hitl-slam's class of a relative-pose edge: ``odometry`` if |i - j| = 1, else ``loop``."""
    return "odometry" if abs(i - j) == 1 else "loop"


def gtsam_estimator(kernel: str) -> Any:
    """GTSAM's ``noiseModel.mEstimator`` for a hitl-slam kernel string (``dcs:1``, ``cauchy``...).

    Same conventions: k (Huber, Cauchy) in sigmas of the whitened residual, phi (DCS) in chi2 units.
    """
    import gtsam

    name, _, value = kernel.strip().lower().partition(":")
    factories = {
        "huber": gtsam.noiseModel.mEstimator.Huber,
        "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
        "dcs": gtsam.noiseModel.mEstimator.DCS,
    }
    if name not in factories:
        raise ValueError(f"no GTSAM counterpart for the kernel {kernel!r}")
    return factories[name].Create(float(value) if value else KERNEL_DEFAULTS[name])


class GtsamProblem:
    """The GTSAM side: factor graph and initial Values built once, outside the timed region.

    The gauge is a PriorFactorPose2 on the anchor with an isotropic sigma of ``prior_sigma``;
    chi2 is reported from a second graph without that prior, so it is comparable to ours.
    With ``robust`` (a hitl-slam robust specification such as ``"dcs:1"``), the edges of each
    named class get ``noiseModel.Robust.Create(mEstimator, gaussian)`` with GTSAM's matching
    mEstimator; chi2 is then evaluated on a plain Gaussian copy of the graph.
    """

    def __init__(
        self,
        graph: PoseGraph,
        tolerances: Tolerances,
        prior_sigma: float,
        robust: RobustSpec = None,
    ) -> None:
        import gtsam

        from hitl_slam.solve import robust_pairs

        self._gtsam = gtsam
        kernels = dict(robust_pairs(robust))
        estimators = {cls: gtsam_estimator(kernel) for cls, kernel in kernels.items()}
        # One noise model per distinct information matrix (and kernel): most graphs have one or
        # two, and a million-edge chain would otherwise hold a million copies.
        noise_models: dict[tuple[bytes, str | None], Any] = {}

        def noise_model(omega: NDArray[np.float64], cls: str | None) -> Any:
            key = (omega.tobytes(), cls)
            if key not in noise_models:
                gaussian = gtsam.noiseModel.Gaussian.Information(omega)
                noise_models[key] = (
                    gaussian
                    if cls is None
                    else gtsam.noiseModel.Robust.Create(estimators[cls], gaussian)
                )
            return noise_models[key]

        self.between = gtsam.NonlinearFactorGraph()
        self.gaussian = self.between if not estimators else gtsam.NonlinearFactorGraph()
        self.estimators: list[Any] = []
        for (i, j), z, omega in zip(
            graph.edges.tolist(), graph.measurements, graph.information, strict=True
        ):
            cls = edge_class(i, j)
            robust_cls = cls if cls in estimators else None
            self.estimators.append(estimators.get(cls))
            pose = gtsam.Pose2(*z)
            self.between.add(gtsam.BetweenFactorPose2(i, j, pose, noise_model(omega, robust_cls)))
            if self.gaussian is not self.between:
                self.gaussian.add(gtsam.BetweenFactorPose2(i, j, pose, noise_model(omega, None)))
        self.factors = gtsam.NonlinearFactorGraph()
        self.factors.push_back(self.between)
        anchor = graph.poses[graph.anchor]
        self.factors.add(
            gtsam.PriorFactorPose2(
                graph.anchor,
                gtsam.Pose2(*anchor),
                gtsam.noiseModel.Isotropic.Sigma(3, prior_sigma),
            )
        )
        self.initial = gtsam.Values()
        for k, pose in enumerate(graph.poses.tolist()):
            self.initial.insert(k, gtsam.Pose2(*pose))
        self.num_poses = graph.num_poses
        self.params = gtsam.LevenbergMarquardtParams()
        # GTSAM stops when (e_old - e_new) <= absoluteErrorTol or when
        # (e_old - e_new) / e_old <= relativeErrorTol, with e = chi2 / 2. The absolute test is
        # therefore halved to mean the same as ours; the relative one is scale-free and is not.
        self.params.setAbsoluteErrorTol(0.5 * tolerances.absolute)
        self.params.setRelativeErrorTol(tolerances.relative)
        self.params.setMaxIterations(tolerances.max_iterations)
        self.max_iterations = tolerances.max_iterations

    def values(self, poses: NDArray[np.float64]) -> Any:
        """GTSAM ``Values`` holding ``poses`` (row k = key k)."""
        values = self._gtsam.Values()
        for k, pose in enumerate(poses.tolist()):
            values.insert(k, self._gtsam.Pose2(*pose))
        return values

    def chi2(self, poses: NDArray[np.float64]) -> float:
        """chi2 of ``poses`` without the anchor prior, evaluated by GTSAM."""
        return 2.0 * float(self.gaussian.error(self.values(poses)))

    def cost(self, poses: NDArray[np.float64]) -> float:
        """The minimized objective at ``poses`` (robust cost, or chi2), evaluated by GTSAM."""
        return 2.0 * float(self.between.error(self.values(poses)))

    def weights(self, poses: NDArray[np.float64]) -> NDArray[np.float64]:
        """Each edge's robust weight at ``poses``: ``mEstimator.weight(sqrt(r^T Omega r))``."""
        import numpy as np

        values = self.values(poses)
        weights = np.ones(len(self.estimators))
        for k, estimator in enumerate(self.estimators):
            if estimator is not None:
                distance = math.sqrt(2.0 * float(self.gaussian.at(k).error(values)))
                weights[k] = float(estimator.weight(distance))
        return weights

    def solve(self, lago: bool = False) -> Solve:
        """One timed LM solve from the graph's poses, or with ``lago`` from GTSAM's own initial
        guess (``gtsam.lago.initialize``, Carlone et al.'s LAGO), whose time is included."""
        import numpy as np

        gtsam = self._gtsam
        start = time.perf_counter()
        initial = gtsam.lago.initialize(self.factors) if lago else self.initial
        # The constructor computes the COLAMD ordering: part of solving, as our symbolic analysis.
        optimizer = gtsam.LevenbergMarquardtOptimizer(self.factors, initial, self.params)
        result = optimizer.optimize()
        seconds = time.perf_counter() - start
        poses = np.array(
            [[p.x(), p.y(), p.theta()] for p in (result.atPose2(k) for k in range(self.num_poses))]
        )
        iterations = int(optimizer.iterations())
        if iterations >= self.max_iterations:
            termination = "max_iterations"
        elif float(optimizer.lambda_()) >= self.params.getlambdaUpperBound():
            # GTSAM gives up when no damping lowers the error: not a convergence.
            termination = "lambda_upper_bound"
        else:
            termination = "converged"
        final_cost = 2.0 * float(self.between.error(result))
        return Solve(
            seconds=seconds,
            iterations=iterations,
            initial_chi2=2.0 * float(self.gaussian.error(initial)),
            final_chi2=(
                final_cost
                if self.gaussian is self.between
                else 2.0 * float(self.gaussian.error(result))
            ),
            termination=termination,
            poses=poses,
            final_cost=final_cost,
            converged=termination == "converged" and math.isfinite(final_cost),
        )


Optimize = Callable[..., tuple[Any, Any]]


def solve_hitl(
    optimize: Optimize, graph: PoseGraph, tolerances: Tolerances, **options: Any
) -> Solve:
    """One hitl-slam solve on a fresh copy of ``graph``.

    The copy has no cached symbolic analysis, so the solve pays for it as GTSAM pays for its
    ordering. The copy and its core graph are made before the clock starts. ``options`` go to
    ``optimize`` as they are (``init``, ``robust``); an ``init`` other than ``given`` is computed
    inside the call and so is timed.
    """
    import numpy as np

    fresh = dataclasses.replace(graph)
    # Building the core's graph (validation, square-root information) is the counterpart of
    # building GTSAM's NonlinearFactorGraph, which is also outside the clock; the ordering and
    # symbolic analysis are not cached yet and are timed, as GTSAM's ordering is.
    fresh.engine()
    start = time.perf_counter()
    poses, report = optimize(
        fresh,
        method="lm",
        max_iterations=tolerances.max_iterations,
        relative_tolerance=tolerances.relative,
        absolute_tolerance=tolerances.absolute,
        **options,
    )
    seconds = time.perf_counter() - start
    return Solve(
        seconds=seconds,
        iterations=int(report.iterations),
        initial_chi2=float(report.initial_chi2),
        final_chi2=float(report.final_chi2),
        termination=str(getattr(report.termination, "value", report.termination)),
        poses=np.asarray(poses),
        final_cost=float(report.final_cost),
        converged=bool(report.converged),
        weights=np.asarray(report.weights, dtype=np.float64),
    )


# --- one graph -----------------------------------------------------------------------------------


@dataclasses.dataclass
class Row:
    """Everything the table shows about one graph."""

    name: str
    num_poses: int
    num_edges: int
    hitl: list[Solve]
    gtsam: list[Solve]
    hitl_chi2_by_gtsam: float | None = None
    # With robust kernels: hitl-slam's final poses re-evaluated by GTSAM (cost and weights).
    hitl_cost_by_gtsam: float | None = None
    hitl_weights_by_gtsam: NDArray[np.float64] | None = None


def run_graph(
    name: str,
    graph: PoseGraph,
    *,
    optimize: Optimize | None,
    tolerances: Tolerances,
    repeats: int,
    only: str,
    prior_sigma: float,
    log: Callable[[str], None],
    robust: RobustSpec = None,
) -> Row:
    """Warm-up once each, then ``repeats`` alternating timed solves (hitl-slam, GTSAM, ...).

    ``robust`` (e.g. ``"dcs:1"``) gives both solvers the same kernels on the same edge classes.
    """
    problem = GtsamProblem(graph, tolerances, prior_sigma, robust) if only != "hitl" else None
    row = Row(name, graph.num_poses, graph.num_edges, hitl=[], gtsam=[])
    for k in range(repeats + 1):
        label = "warm-up" if k == 0 else f"repeat {k}/{repeats}"
        if optimize is not None and only != "gtsam":
            result = solve_hitl(optimize, graph, tolerances, robust=robust)
            if k > 0:
                row.hitl.append(result)
            log(f"  {label}: hitl-slam {result.seconds * 1e3:9.1f} ms, {result.iterations} it")
        if problem is not None:
            result = problem.solve()
            if k > 0:
                row.gtsam.append(result)
            log(f"  {label}: GTSAM     {result.seconds * 1e3:9.1f} ms, {result.iterations} it")
    if row.hitl and problem is not None:
        # An independent check that both sides mean the same chi2.
        row.hitl_chi2_by_gtsam = problem.chi2(row.hitl[-1].poses)
    if robust is not None and problem is not None:
        # ... and the same robust cost and weights; GTSAM's weights at its own solution.
        if row.hitl:
            row.hitl_cost_by_gtsam = problem.cost(row.hitl[-1].poses)
            row.hitl_weights_by_gtsam = problem.weights(row.hitl[-1].poses)
        if row.gtsam:
            row.gtsam[-1].weights = problem.weights(row.gtsam[-1].poses)
    return row


# --- reporting -----------------------------------------------------------------------------------


def _median(solves: Sequence[Solve], value: Callable[[Solve], float]) -> float:
    return statistics.median(value(s) for s in solves)


def _iterations(solves: Sequence[Solve]) -> str:
    counts = sorted({s.iterations for s in solves})
    return "/".join(str(c) for c in counts)


def markdown_table(rows: Sequence[Row]) -> str:
    header = (
        "| graph | poses | edges | hitl-slam (ms) | GTSAM (ms) | hitl/GTSAM "
        "| iterations hitl | iterations GTSAM | chi2 hitl | chi2 GTSAM | rel. diff "
        "| ms/iter hitl | ms/iter GTSAM |"
    )
    lines = [header, "|" + "---|" * 13]
    na = "n/a"
    for row in rows:
        h, g = row.hitl, row.gtsam
        h_ms = _median(h, lambda s: s.seconds) * 1e3 if h else math.nan
        g_ms = _median(g, lambda s: s.seconds) * 1e3 if g else math.nan
        h_chi2 = _median(h, lambda s: s.final_chi2) if h else math.nan
        g_chi2 = _median(g, lambda s: s.final_chi2) if g else math.nan
        h_per = _median(h, lambda s: s.seconds / max(s.iterations, 1)) * 1e3 if h else math.nan
        g_per = _median(g, lambda s: s.seconds / max(s.iterations, 1)) * 1e3 if g else math.nan
        cells = [
            row.name,
            str(row.num_poses),
            str(row.num_edges),
            f"{h_ms:.1f}" if h else na,
            f"{g_ms:.1f}" if g else na,
            f"{h_ms / g_ms:.2f}" if h and g else na,
            _iterations(h) if h else na,
            _iterations(g) if g else na,
            f"{h_chi2:.4f}" if h else na,
            f"{g_chi2:.4f}" if g else na,
            f"{(h_chi2 - g_chi2) / g_chi2:+.1e}" if h and g else na,
            f"{h_per:.2f}" if h else na,
            f"{g_per:.2f}" if g else na,
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _read(path: str) -> str:
    try:
        return Path(path).read_text()
    except OSError:
        return ""


def machine_description(pinning: Pinning | None) -> list[str]:
    """CPU, cores, memory, OS and library versions, one Markdown bullet each."""
    cpuinfo = _read("/proc/cpuinfo")
    model = next(
        (ln.split(":", 1)[1].strip() for ln in cpuinfo.splitlines() if ln.startswith("model name")),
        platform.processor() or "unknown",
    )
    meminfo = _read("/proc/meminfo")
    mem_kib = next(
        (int(ln.split()[1]) for ln in meminfo.splitlines() if ln.startswith("MemTotal:")), 0
    )
    os_release = dict(ln.split("=", 1) for ln in _read("/etc/os-release").splitlines() if "=" in ln)
    os_name = os_release.get("PRETTY_NAME", platform.system()).strip('"')
    allowed = pinning.allowed if pinning else len(os.sched_getaffinity(0))
    pinned = f"; this run pinned to CPU {pinning.cpu}" if pinning else ""
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    return [
        f"- CPU: {model}; {os.cpu_count()} logical CPUs, {allowed} allowed to this process{pinned}"
        f"; load average at the start {load} (1, 5, 15 min)",
        f"- Memory: {mem_kib / 2**20:.1f} GiB",
        f"- OS: {os_name}, Linux {platform.release()}",
        (
            f"- Python {platform.python_version()}, numpy {_version('numpy')}, "
            f"GTSAM {_version('gtsam')}, hitl-slam {_version('hitl-slam')}"
        ),
    ]


def _version(distribution: str) -> str:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        if distribution == "hitl-slam":
            import hitl_slam

            return str(getattr(hitl_slam, "__version__", "(not installed; from source tree)"))
        return "not installed"


def command_line() -> str:
    return shlex.join(["python", *sys.argv])


def now_utc() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def provenance(pinning: Pinning | None = None, note: str = "") -> list[str]:
    """The lines every recorded section opens with: when, the exact command, the machine."""
    return [
        f"Measured {now_utc()}{note} with:",
        "",
        "```sh",
        command_line(),
        "```",
        "",
        *machine_description(pinning),
    ]


def replace_section(path: Path, name: str, body: str) -> None:
    """Replace the text between ``<!-- name:begin -->`` and ``<!-- name:end -->`` in ``path``.

    Appends the marked section when the markers are missing; writes atomically.
    """
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    text = path.read_text() if path.exists() else ""
    block = f"{begin}\n{body.strip()}\n{end}"
    if begin in text and end in text and text.index(begin) < text.index(end):
        head, rest = text.split(begin, 1)
        tail = rest.split(end, 1)[1]
        text = head + block + tail
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + block + "\n"
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    temporary.replace(path)


def target_lines(rows: Sequence[Row], equal_chi2: float = 1e-6) -> list[str]:
    """The issue's target, hitl/GTSAM <= TARGET_RATIO at equal chi2, on the TARGET_GRAPHS run."""
    verdicts = []
    for row in rows:
        if row.name not in TARGET_GRAPHS or not row.hitl or not row.gtsam:
            continue
        ratio = _median(row.hitl, lambda s: s.seconds) / _median(row.gtsam, lambda s: s.seconds)
        h_chi2 = _median(row.hitl, lambda s: s.final_chi2)
        g_chi2 = _median(row.gtsam, lambda s: s.final_chi2)
        equal = abs(h_chi2 - g_chi2) <= equal_chi2 * abs(g_chi2)
        met = ratio <= TARGET_RATIO and equal
        chi2_note = "" if equal else f", chi2 differs by more than {equal_chi2:g} relative"
        verdicts.append(f"{row.name} {ratio:.2f} ({'met' if met else 'not met'}{chi2_note})")
    if not verdicts:
        return []
    return [
        f"Target: hitl-slam / GTSAM time at most {TARGET_RATIO:g} at equal chi2 (relative "
        f"difference at most {equal_chi2:g}): " + "; ".join(verdicts) + ".",
        "",
    ]


def section(
    rows: Sequence[Row], args: argparse.Namespace, tolerances: Tolerances, pinning: Pinning
) -> str:
    """The Markdown written between the compare_gtsam markers: setup, machine, table, credits."""
    who = {"both": "hitl-slam and GTSAM", "hitl": "hitl-slam only", "gtsam": "GTSAM only"}
    settings = (
        f"Levenberg-Marquardt from each file's initial guess, stopping when chi2 decreases by less "
        f"than {tolerances.absolute:g} or by a fraction less than {tolerances.relative:g} "
        f"(GTSAM: absoluteErrorTol {0.5 * tolerances.absolute:g}, relativeErrorTol "
        f"{tolerances.relative:g}, on its error = chi2 / 2), at most {tolerances.max_iterations} "
        f"iterations; GTSAM's gauge is a prior of sigma {args.prior_sigma:g} on the anchor, left "
        f"out of its chi2. Times: median of {args.repeats} alternating solves after one warm-up "
        "each, perf_counter around the solve only (GTSAM: optimizer construction, which computes "
        "the ordering, plus optimize(); hitl-slam: optimize() on a graph without a cached engine)."
    )
    lines = [
        *provenance(pinning, f" ({who[args.only]})"),
        "",
        settings,
        "",
        markdown_table(rows),
        "",
    ]
    lines += target_lines(rows)
    checks = [
        f"{row.name}: {abs(row.hitl_chi2_by_gtsam - row.hitl[-1].final_chi2):.1e}"
        for row in rows
        if row.hitl_chi2_by_gtsam is not None
    ]
    if checks:
        lines += [
            "hitl-slam's final poses re-evaluated by GTSAM differ from its reported chi2 by "
            + "; ".join(checks)
            + ".",
            "",
        ]
    thanks = [CREDITS[row.name] for row in rows if row.name in CREDITS]
    if thanks:
        lines.append("Data: " + "; ".join(thanks) + ". Thanks to the authors.")
    return "\n".join(lines)


# --- command line --------------------------------------------------------------------------------


def add_solver_arguments(parser: argparse.ArgumentParser) -> None:
    """The stopping rule and GTSAM's gauge, shared by every side-by-side script."""
    parser.add_argument(
        "--relative-tolerance",
        type=float,
        default=1e-6,
        help="stop when chi2 decreases by a fraction less than this",
    )
    parser.add_argument(
        "--absolute-tolerance",
        type=float,
        default=1e-6,
        help="stop when chi2 decreases by less than this",
    )
    parser.add_argument("--max-iterations", type=int, default=100)
    parser.add_argument(
        "--prior-sigma",
        type=float,
        default=1e-6,
        help="isotropic sigma of GTSAM's prior on the anchor pose",
    )


def parse_arguments(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Time hitl-slam's and GTSAM's Levenberg-Marquardt side by side on one core, "
        "from each graph's initial guess to the same convergence test, and print a Markdown table.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "graphs",
        nargs="*",
        type=Path,
        help="g2o files (default: "
        + ", ".join(p.name for p in DEFAULT_GRAPHS)
        + f" from {DATASETS} when no graph and no --synthetic is given)",
    )
    parser.add_argument(
        "--synthetic",
        type=int,
        action="append",
        default=[],
        metavar="N",
        help="also a generated Manhattan world of N poses (repeatable)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the --synthetic graphs")
    parser.add_argument("--repeats", type=int, default=7, help="timed solves per solver and graph")
    add_solver_arguments(parser)
    parser.add_argument(
        "--only",
        choices=("both", "hitl", "gtsam"),
        default="both",
        help="run one side only (gtsam: works without the compiled core)",
    )
    parser.add_argument(
        "--write",
        type=Path,
        metavar="README",
        help="replace the compare_gtsam section of this Markdown file with the results",
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    return args


def _synthetic(num_poses: int, seed: int) -> PoseGraph:
    from hitl_slam.sim.synthetic import manhattan_world

    return manhattan_world(num_poses, seed=seed)[0]


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_arguments(argv)
    pinning = pin_to_one_core()  # before numpy, GTSAM and hitl_slam are imported

    def log(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    import hitl_slam

    optimize: Optimize | None = getattr(hitl_slam, "optimize", None)
    if args.only != "gtsam" and optimize is None:
        log("hitl_slam.optimize is not available (build the core: maturin develop --release);")
        log("use --only gtsam to time GTSAM alone.")
        return 2
    if args.only != "hitl":
        try:
            import gtsam  # noqa: F401
        except ImportError:
            log("GTSAM is not installed (pip install gtsam), or use --only hitl.")
            return 2

    tolerances = Tolerances(args.relative_tolerance, args.absolute_tolerance, args.max_iterations)
    sources: list[tuple[str, Callable[[], PoseGraph]]] = []
    paths: list[Path] = list(args.graphs)
    if not paths and not args.synthetic:
        paths = [p for p in DEFAULT_GRAPHS if p.exists()]
        if not paths:
            log(f"the default datasets are not in {DATASETS}; pass g2o files or --synthetic N")
            return 2
    for path in paths:
        if not path.is_file():
            log(f"{path}: no such file")
            return 2
        sources.append((path.name, functools.partial(load, path)))
    for n in args.synthetic:
        name = f"manhattan_world({n}, seed={args.seed})"
        sources.append((name, functools.partial(_synthetic, n, args.seed)))

    rows: list[Row] = []
    for name, make_graph in sources:
        graph = make_graph()
        log(f"{name}: {graph.num_poses} poses, {graph.num_edges} edges")
        rows.append(
            run_graph(
                name,
                graph,
                optimize=optimize,
                tolerances=tolerances,
                repeats=args.repeats,
                only=args.only,
                prior_sigma=args.prior_sigma,
                log=log,
            )
        )
    body = section(rows, args, tolerances, pinning)
    print(body)
    if args.write is not None:
        replace_section(args.write, "compare_gtsam", body)
        log(f"wrote the compare_gtsam section of {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
