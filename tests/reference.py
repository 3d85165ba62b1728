"""The tests' one reference plane geometry, and an independent numpy implementation of the
pose-graph cost built on it, for cross-checking the core and :mod:`hitl_slam.geometry`.

Written from the definitions (GTSAM's Pose2 conventions), sharing no code with the package: other
formulas where the package has its own (``wrap`` here is ``pi - (pi - a) mod 2 pi``, the line
fit an eigen-decomposition), so a test that compares the two checks something. Poses are
``(x, y, theta)`` rows, ``(3,)`` or ``(K, 3)`` (broadcast); headings in (-pi, pi].
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hitl_slam.graph import PoseGraph

FloatArray = NDArray[np.float64]


def wrap(theta: FloatArray) -> FloatArray:
    """Angles to (-pi, pi]."""
    return np.asarray(math.pi - np.mod(math.pi - theta, 2.0 * math.pi))


def _pair(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
    p, q = np.broadcast_arrays(np.atleast_2d(a), np.atleast_2d(b))
    return np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)


def between(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rows of a^-1 * b."""
    a, b = _pair(a, b)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[:, 2] - a[:, 2])], axis=1)


def log(p: FloatArray) -> FloatArray:
    """SE(2) logarithm, as GTSAM's Pose2.Logmap."""
    w = p[:, 2]
    small = np.abs(w) < 1e-10
    safe = np.where(small, 1.0, w)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.0, (1.0 - np.cos(safe)) / safe)
    det = a * a + b * b
    vx = (a * p[:, 0] + b * p[:, 1]) / det
    vy = (-b * p[:, 0] + a * p[:, 1]) / det
    return np.stack([vx, vy, w], axis=1)


def exp(v: FloatArray) -> FloatArray:
    """SE(2) exponential of rows (vx, vy, w)."""
    w = v[:, 2]
    small = np.abs(w) < 1e-10
    safe = np.where(small, 1.0, w)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.0, (1.0 - np.cos(safe)) / safe)
    return np.stack([a * v[:, 0] - b * v[:, 1], b * v[:, 0] + a * v[:, 1], wrap(w)], axis=1)


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rows of a * b."""
    a, b = _pair(a, b)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.stack(
        [
            a[:, 0] + c * b[:, 0] - s * b[:, 1],
            a[:, 1] + s * b[:, 0] + c * b[:, 1],
            wrap(a[:, 2] + b[:, 2]),
        ],
        axis=1,
    )


def inverse(a: FloatArray) -> FloatArray:
    """Rows of a^-1: the pose whose composition with a is the identity."""
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    x, y = a[:, 0], a[:, 1]
    return np.stack([-c * x - s * y, s * x - c * y, wrap(-a[:, 2])], axis=1)


def transform_points(pose: FloatArray, points: FloatArray) -> FloatArray:
    """Robot-frame ``points`` (K, 2) in the world, R p + t, seen from one ``pose`` (3,) or row
    by row from ``poses`` (K, 3)."""
    x, p = np.asarray(pose, dtype=np.float64), np.asarray(points, dtype=np.float64)
    c, s = np.cos(x[..., 2]), np.sin(x[..., 2])
    u, v = p[..., 0], p[..., 1]
    return np.stack([x[..., 0] + c * u - s * v, x[..., 1] + s * u + c * v], axis=-1)


def fit_line(points: FloatArray) -> tuple[float, float]:
    """Total-least-squares line ``(phi, rho)`` of ``points`` (K, 2): the scatter's eigenvector of
    the smallest eigenvalue as the normal, pointing to +x (to +y when it is vertical), then
    turned so that ``rho >= 0``. For points with a principal direction."""
    centre = points.mean(axis=0)
    d = points - centre
    _, vectors = np.linalg.eigh(d.T @ d)
    n = vectors[:, 0]
    if n[0] < -1e-12 or (abs(n[0]) <= 1e-12 and n[1] < 0):
        n = -n
    rho = float(n @ centre)
    if rho < 0:
        n, rho = -n, -rho
    return math.atan2(n[1], n[0]), rho


def residuals(graph: PoseGraph, poses: FloatArray) -> FloatArray:
    """Unwhitened residuals Log(z_ij^-1 * (x_i^-1 * x_j)), one row per edge."""
    t_i_j = between(poses[graph.edges[:, 0]], poses[graph.edges[:, 1]])
    return log(between(graph.measurements, t_i_j))


def whitened(graph: PoseGraph, poses: FloatArray) -> FloatArray:
    """Whitened residuals U r (Omega = U^T U), flattened: chi2 = |whitened|^2."""
    r = residuals(graph, poses)
    upper = np.swapaxes(np.linalg.cholesky(graph.information), 1, 2)
    return np.einsum("mij,mj->mi", upper, r).ravel()


def reference_chi2(graph: PoseGraph, poses: FloatArray) -> float:
    """Sum of r^T Omega r with r = Log(z_ij^-1 * (x_i^-1 * x_j))."""
    r = residuals(graph, poses)
    return float(np.einsum("mi,mij,mj->", r, graph.information, r))
