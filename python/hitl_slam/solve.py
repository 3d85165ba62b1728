"""Optimizing a pose graph: the Python face of the Rust solver.

Keyword arguments in, numpy arrays and a report out; the work happens in ``hitl_slam._core``
with the GIL released. Each graph keeps its symbolic analysis between solves.
"""

from __future__ import annotations

import enum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hitl_slam._core import SolveReport
from hitl_slam.errors import InputError
from hitl_slam.graph import PoseGraph

__all__ = ["Method", "chi2", "marginals", "optimize"]


class Method(enum.Enum):
    """The nonlinear least-squares algorithm."""

    LEVENBERG_MARQUARDT = "lm"
    GAUSS_NEWTON = "gn"


def _method(method: Method | str) -> Method:
    if isinstance(method, Method):
        return method
    try:
        return Method(method)
    except ValueError:
        choices = ", ".join(repr(m.value) for m in Method)
        raise InputError(f"unknown method {method!r}; use one of {choices}") from None


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
    method: Method | str = Method.LEVENBERG_MARQUARDT,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-6,
    absolute_tolerance: float = 1e-6,
    error_tolerance: float = 0.0,
    lambda_initial: float = 1e-5,
    diagonal_damping: bool = False,
) -> tuple[NDArray[np.float64], SolveReport]:
    """Minimize chi2 = sum of r^T Omega r over all edges, with ``graph.anchor`` held fixed.

    Args:
        graph: the pose graph; ``graph.poses`` is the initial guess unless ``initial`` is given.
        initial: optional ``(N, 3)`` initial guess.
        method: ``"lm"`` (Levenberg-Marquardt, default) or ``"gn"`` (Gauss-Newton).
        max_iterations: budget of accepted steps.
        relative_tolerance, absolute_tolerance: stop when chi2 decreases by less than this
            fraction / amount between accepted steps (GTSAM's test, on chi2 = 2 x GTSAM's error).
        error_tolerance: stop when chi2 falls below this.
        lambda_initial: initial LM damping; ``diagonal_damping`` scales it by diag(J^T J).

    Returns:
        The optimized ``(N, 3)`` poses (theta in (-pi, pi]) and a :class:`SolveReport`
        (iterations, initial and final chi2, termination reason, times, per-step history).

    Raises:
        InputError: bad arguments or a graph that cannot be solved as given.
        SolverError: the solver could not produce a solution.
    """
    if max_iterations < 0:
        raise InputError(f"max_iterations must be >= 0, got {max_iterations}")
    start = _poses(graph, initial)
    return graph.engine().optimize(
        start,
        method=_method(method).value,
        max_iterations=max_iterations,
        relative_tolerance=relative_tolerance,
        absolute_tolerance=absolute_tolerance,
        error_tolerance=error_tolerance,
        lambda_initial=lambda_initial,
        diagonal_damping=diagonal_damping,
    )


def chi2(graph: PoseGraph, poses: ArrayLike | None = None) -> float:
    """chi2 = sum over edges of r^T Omega r at ``poses`` (default: the graph's own poses)."""
    return graph.engine().chi2(_poses(graph, poses))


def marginals(graph: PoseGraph, poses: ArrayLike | None, indices: ArrayLike) -> NDArray[np.float64]:
    """Marginal covariances ``(K, 3, 3)`` of the poses ``indices`` at ``poses``.

    Each is expressed in the pose's own frame, ``(x, y, theta)`` order, as GTSAM's
    ``Marginals.marginalCovariance``; the anchored pose has a zero covariance.
    """
    idx = np.ascontiguousarray(np.atleast_1d(np.asarray(indices)), dtype=np.int64)
    if idx.ndim != 1:
        raise InputError(f"indices must be a 1-D sequence of pose indices, got shape {idx.shape}")
    return graph.engine().marginals(_poses(graph, poses), idx)
