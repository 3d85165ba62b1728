"""The pose graph as plain numpy arrays: what readers produce, the solver consumes, writers save.

Conventions (ARCHITECTURE.md, house rule 1): poses are ``(x, y, theta)`` rows, float64 C-contiguous
``(N, 3)``, theta in (-pi, pi]; edges are int64 ``(M, 2)`` row indices into ``poses``; each edge
carries its measurement ``t_i_j`` (pose of j in the frame of i) and a 3x3 information matrix in the
same ``(x, y, theta)`` order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError

if TYPE_CHECKING:
    from hitl_slam import _core
    from hitl_slam.io import LoadReport

__all__ = ["PoseGraph"]


def _as_array(
    name: str, value: object, dtype: type[np.generic], shape: tuple[int | None, ...]
) -> NDArray[Any]:
    array: NDArray[Any] = np.ascontiguousarray(value, dtype=dtype)
    if array.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(array.shape, shape, strict=False)
    ):
        dims = ", ".join("N" if s is None else str(s) for s in shape)
        raise InputError(f"{name} must have shape ({dims}), got {array.shape}")
    return array


@dataclass(eq=False)
class PoseGraph:
    """A 2D pose graph.

    Attributes:
        poses: ``(N, 3)`` initial guess, one ``(x, y, theta)`` row per vertex.
        edges: ``(M, 2)`` int64 row indices ``(i, j)`` into ``poses``.
        measurements: ``(M, 3)`` relative poses ``t_i_j``.
        information: ``(M, 3, 3)`` symmetric positive-definite information matrices.
        vertex_ids: ``(N,)`` int64 vertex ids as written in the source file.
        anchor: row index of the pose held fixed (the gauge), 0 by default.
        source: the file the graph was read from, if any.
        load_report: what :func:`hitl_slam.load_graph` met while reading it (skipped tags,
            merged vertices, dropped self-loops, poses chained from the odometry), if it was read.
    """

    poses: NDArray[np.float64]
    edges: NDArray[np.int64]
    measurements: NDArray[np.float64]
    information: NDArray[np.float64]
    vertex_ids: NDArray[np.int64] | None = None
    anchor: int = 0
    source: str | None = None
    load_report: LoadReport | None = field(default=None, repr=False)
    _engine: _core.Graph | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.poses = _as_array("poses", self.poses, np.float64, (None, 3))
        self.edges = _as_array("edges", self.edges, np.int64, (None, 2))
        m = self.edges.shape[0]
        self.measurements = _as_array("measurements", self.measurements, np.float64, (m, 3))
        self.information = _as_array("information", self.information, np.float64, (m, 3, 3))
        n = self.poses.shape[0]
        if self.vertex_ids is None:
            self.vertex_ids = np.arange(n, dtype=np.int64)
        else:
            self.vertex_ids = _as_array("vertex_ids", self.vertex_ids, np.int64, (n,))

    @property
    def num_poses(self) -> int:
        return int(self.poses.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])

    def engine(self) -> _core.Graph:
        """The Rust-side graph, built (and validated) once and cached.

        It owns the sparsity pattern and the symbolic Cholesky analysis, so every later solve of
        this graph reuses them.
        """
        if self._engine is None:
            from hitl_slam import _core

            self._engine = _core.Graph(
                self.poses.shape[0], self.edges, self.measurements, self.information, self.anchor
            )
        return self._engine
