"""Optimizing a pose graph: the Python face of the Rust solver.

Keyword arguments in, numpy arrays and a report out; the work happens in ``hitl_slam._core``
with the GIL released. Each graph keeps its symbolic analysis between solves.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam._core import SolveReport
from hitl_slam.errors import InputError
from hitl_slam.geometry import compose_rows, invert, wrap
from hitl_slam.graph import PoseGraph

__all__ = [
    "EDGE_CLASSES",
    "Init",
    "Method",
    "RobustSpec",
    "chi2",
    "downweighted",
    "edge_chi2",
    "marginals",
    "optimize",
    "robust_pairs",
]

EDGE_CLASSES = ("odometry", "loop", "human", "relation", "prior")
"""Edge classes a robust kernel can be chosen for: ``odometry`` (consecutive poses, |i - j| = 1),
``loop`` (any other relative pose), ``human`` (a correction's point-to-line factors),
``relation`` (a correction's relation between its two lines), ``prior``."""

RobustSpec = str | Mapping[str, str] | None
"""``"dcs:1"`` (on loop closures), ``{"loop": "dcs:1", "odometry": "huber:2"}``, or None."""


class Method(enum.Enum):
    """The nonlinear least-squares algorithm."""

    LEVENBERG_MARQUARDT = "lm"
    GAUSS_NEWTON = "gn"
    DOGLEG = "dogleg"


class Init(enum.Enum):
    """Where the solve starts.

    ``given``: the graph's own poses (right for human corrections: the current map is the best
    guess there, and for files whose vertices come from a SLAM front end). ``tree``: measurements
    composed along a spanning tree from the anchor, odometry first (g2o's and TORO's guess):
    cheap, exact on trees, drifts with the odometry. ``chordal``: rotations first by chordal
    relaxation, then positions, both linear (Carlone et al. 2015; GTSAM's LAGO): the choice when
    the given poses are unknown or wildly off (headings wrong by radians).
    """

    GIVEN = "given"
    TREE = "tree"
    CHORDAL = "chordal"


E = TypeVar("E", Method, Init)


def _choice(kind: type[E], value: E | str, what: str) -> E:
    """An enum member from itself or its value; anything else is an InputError listing them."""
    if isinstance(value, kind):
        return value
    try:
        return kind(value)
    except ValueError:
        choices = ", ".join(repr(m.value) for m in kind)
        raise InputError(f"unknown {what} {value!r}; use one of {choices}") from None


def robust_pairs(robust: RobustSpec) -> list[tuple[str, str]]:
    """``(edge class, kernel)`` pairs from a robust specification (see :data:`RobustSpec`).

    A bare kernel applies to loop closures; ``"odometry=huber:2"`` names the class in a string.
    Kernels: ``huber[:k]`` (default k 1.345), ``cauchy[:k]`` (2.3849), ``dcs[:phi]`` (1), with k in
    sigmas of the whitened residual and phi in chi2 units, as GTSAM's ``noiseModel.mEstimator``.
    """
    if robust is None:
        return []
    if isinstance(robust, str):
        items: list[tuple[str, str]] = []
        for part in robust.split(","):
            part = part.strip()
            if not part:
                continue
            cls, sep, kernel = part.partition("=")
            items.append((cls.strip(), kernel.strip()) if sep else ("loop", cls.strip()))
        pairs = items
    elif isinstance(robust, Mapping):
        pairs = [(str(k), str(v)) for k, v in robust.items()]
    else:
        raise InputError(
            f"robust must be a string such as 'dcs:1' or a mapping such as "
            f"{{'loop': 'dcs:1'}}, got {type(robust).__name__}"
        )
    for cls, _ in pairs:
        if cls not in EDGE_CLASSES:
            raise InputError(
                f"unknown edge class {cls!r} for a robust kernel; use one of "
                f"{', '.join(EDGE_CLASSES)}"
            )
    return pairs


def downweighted(report: SolveReport, threshold: float = 0.5) -> NDArray[np.int64]:
    """Indices of the factors (for a :class:`PoseGraph`, its edges) whose robust weight at the
    solution is below ``threshold``: the measurements the solve treated as outliers."""
    weights = np.asarray(report.weights)
    return np.flatnonzero(weights < threshold).astype(np.int64)


def _poses(graph: PoseGraph, poses: ArrayLike | None) -> NDArray[np.float64]:
    if poses is None:
        return graph.poses
    array = np.ascontiguousarray(poses, dtype=np.float64)
    if array.shape != graph.poses.shape:
        raise InputError(
            f"poses must have shape {graph.poses.shape} (one (x, y, theta) row per vertex), "
            f"got {array.shape}"
        )
    return array


def optimize(
    graph: PoseGraph,
    *,
    initial: ArrayLike | None = None,
    init: Init | str = Init.GIVEN,
    method: Method | str = Method.LEVENBERG_MARQUARDT,
    robust: RobustSpec = None,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-6,
    absolute_tolerance: float = 1e-6,
    error_tolerance: float = 0.0,
    gradient_tolerance: float = 1e-12,
    step_tolerance: float = 1e-12,
    lambda_initial: float = 1e-5,
    diagonal_damping: bool = False,
    watchdog_steps: int = 3,
) -> tuple[NDArray[np.float64], SolveReport]:
    """Minimize chi2 = sum of r^T Omega r over all edges (or its robust version), with
    ``graph.anchor`` held fixed.

    Args:
        graph: the pose graph; ``graph.poses`` is the initial guess unless ``initial`` is given.
        initial: optional ``(N, 3)`` initial guess.
        init: ``"given"`` (default: start from the poses as they are), ``"tree"`` or
            ``"chordal"`` (compute a start from the measurements; see :class:`Init`).
        method: ``"lm"`` (Levenberg-Marquardt, default), ``"gn"`` (Gauss-Newton) or
            ``"dogleg"`` (Powell's dogleg).
        robust: robust kernels per edge class, e.g. ``"dcs:1"`` (loop closures) or
            ``{"loop": "cauchy", "odometry": "huber:3"}`` (see :func:`robust_pairs`).
        max_iterations: budget of accepted steps.
        relative_tolerance, absolute_tolerance: function tolerance: stop when an undamped step
            lowers the cost by less than this fraction / amount (GTSAM's test, on chi2 = 2 x
            GTSAM's error).
        error_tolerance: stop when the cost falls below this.
        gradient_tolerance, step_tolerance: the gradient and step tests.
        lambda_initial: initial LM damping; ``diagonal_damping`` scales it by diag(J^T J).
        watchdog_steps: Gauss-Newton steps LM and dogleg may look ahead from a rejected step
            (0 turns the watchdog off).

    Returns:
        The optimized ``(N, 3)`` poses (theta in (-pi, pi]) and a :class:`SolveReport`:
        iterations, initial and final cost and chi2, ``termination`` (``function_tolerance``,
        ``gradient_tolerance``, ``step_tolerance`` when converged; ``max_iterations``,
        ``stalled`` or ``non_finite`` otherwise) with ``termination_detail``, per-edge robust
        ``weights``, times and the per-step history.

    Raises:
        InputError: bad arguments or a graph that cannot be solved as given.
        SolverError: the solver could not produce a solution.
    """
    if max_iterations < 0:
        raise InputError(f"max_iterations must be >= 0, got {max_iterations}")
    if watchdog_steps < 0:
        raise InputError(f"watchdog_steps must be >= 0, got {watchdog_steps}")
    start = _poses(graph, initial)
    return graph.engine().optimize(
        start,
        method=_choice(Method, method, "method").value,
        init=_choice(Init, init, "init").value,
        robust=robust_pairs(robust),
        max_iterations=max_iterations,
        relative_tolerance=relative_tolerance,
        absolute_tolerance=absolute_tolerance,
        error_tolerance=error_tolerance,
        gradient_tolerance=gradient_tolerance,
        step_tolerance=step_tolerance,
        lambda_initial=lambda_initial,
        diagonal_damping=diagonal_damping,
        watchdog_steps=watchdog_steps,
    )


def chi2(graph: PoseGraph, poses: ArrayLike | None = None) -> float:
    """chi2 = sum over edges of r^T Omega r at ``poses`` (default: the graph's own poses)."""
    return graph.engine().chi2(_poses(graph, poses))


def edge_chi2(graph: PoseGraph, poses: ArrayLike | None = None) -> NDArray[np.float64]:
    """``(M,)`` per edge ``r^T Omega r`` at ``poses`` (default: the graph's own poses), in numpy,
    with ``r`` the relative pose error ``t_i_j^-1 (x_i^-1 x_j)`` as ``(x, y, theta)`` (heading
    wrapped): to find the edges that carry the error (where a damaged vertex or edge shows).

    Not exactly the terms of :func:`chi2`: the solver's residual is the error's SE(2) logarithm,
    whose translation is ``V(theta)^-1`` times this one (its length larger by
    ``(theta/2) / sin(theta/2)``, 0.5% at 0.35 rad), so the two agree to first order in the
    error's angle and their sums differ a little. Unlike :func:`chi2` it never builds the
    engine, so it also takes a graph the solver refuses or one whose values are damaged: a
    non-finite value gives a non-finite term (no warning).
    """
    start = _poses(graph, poses)
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    with np.errstate(all="ignore"):
        predicted = compose_rows(invert(start[i]), start[j])
        r = compose_rows(invert(graph.measurements), predicted)
        r[:, 2] = wrap(r[:, 2])
        per_edge: NDArray[np.float64] = np.einsum("ei,eij,ej->e", r, graph.information, r)
    return per_edge


def marginals(graph: PoseGraph, poses: ArrayLike | None, indices: ArrayLike) -> NDArray[np.float64]:
    """Marginal covariances ``(K, 3, 3)`` of the poses ``indices`` at ``poses``.

    Each is expressed in the pose's own frame, ``(x, y, theta)`` order, as GTSAM's
    ``Marginals.marginalCovariance``; the anchored pose has a zero covariance.
    """
    idx = np.ascontiguousarray(np.atleast_1d(np.asarray(indices)), dtype=np.int64)
    if idx.ndim != 1:
        raise InputError(f"indices must be a 1-D sequence of pose indices, got shape {idx.shape}")
    return graph.engine().marginals(_poses(graph, poses), idx)
