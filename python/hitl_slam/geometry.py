"""Plane geometry, the only Python copy: SE(2) poses as ``(x, y, theta)`` rows (compose, steps
between consecutive poses, robot-to-world points, angle wrapping) and total-least-squares lines.
The Rust core has its own single copy (``rust/src/se2.rs``, ``rust/src/geometry.rs``); Python
uses these for vectorized work on whole maps.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "chain_steps",
    "compose",
    "compose_rows",
    "fit_line",
    "invert",
    "principal_axes",
    "to_world",
    "wrap",
]

FloatArray = NDArray[np.float64]


def wrap(angles: FloatArray) -> FloatArray:
    """Angles [rad] wrapped to [-pi, pi)."""
    return np.mod(angles + np.pi, 2 * np.pi) - np.pi


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rows of ``a * b`` for one pose ``a`` (3,) and rows ``b`` (K, 3), heading in (-pi, pi]."""
    c, s = np.cos(a[2]), np.sin(a[2])
    theta = b[:, 2] + a[2]
    theta = np.where(theta > np.pi, theta - 2 * np.pi, theta)
    theta = np.where(theta <= -np.pi, theta + 2 * np.pi, theta)
    return np.stack(
        [a[0] + c * b[:, 0] - s * b[:, 1], a[1] + s * b[:, 0] + c * b[:, 1], theta], axis=1
    )


def _half_open(theta: FloatArray) -> FloatArray:
    """Angles already within one turn of (-pi, pi] moved into it."""
    theta = np.where(theta > np.pi, theta - 2 * np.pi, theta)
    return np.where(theta <= -np.pi, theta + 2 * np.pi, theta)


def compose_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row by row ``a[k] * b[k]`` for poses ``(K, 3)``, heading in (-pi, pi]."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.stack(
        [
            a[:, 0] + (c * b[:, 0] - s * b[:, 1]),
            a[:, 1] + (s * b[:, 0] + c * b[:, 1]),
            _half_open(a[:, 2] + b[:, 2]),
        ],
        axis=1,
    )


def invert(poses: FloatArray) -> FloatArray:
    """Row by row ``x^-1`` for poses ``(K, 3)``, heading in (-pi, pi]."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x, y = poses[:, 0], poses[:, 1]
    return np.stack([-(c * x + s * y), s * x - c * y, _half_open(-poses[:, 2])], axis=1)


def chain_steps(poses: FloatArray) -> FloatArray:
    """``(N - 1, 3)`` steps ``x_k^-1 x_(k+1)`` between consecutive poses ``(N, 3)``, heading
    wrapped to [-pi, pi)."""
    a, b = poses[:-1], poses[1:]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    dth = wrap(b[:, 2] - a[:, 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dth], axis=1)


def to_world(poses: FloatArray, owners: NDArray[np.int64], points: FloatArray) -> FloatArray:
    """``p_world = R(theta) p + t`` for robot-frame ``points`` (K, 2) seen by ``poses[owners]``."""
    # cos/sin once per pose, not once per point: maps have ~100 points per pose.
    c, s = np.cos(poses[:, 2])[owners], np.sin(poses[:, 2])[owners]
    x, y = points[:, 0], points[:, 1]
    out = np.empty((points.shape[0], 2), dtype=np.float64)
    out[:, 0] = c * x - s * y + poses[owners, 0]
    out[:, 1] = s * x + c * y + poses[owners, 1]
    return out


def principal_axes(points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(centre, normal, direction)`` of the total-least-squares line through ``points``
    ``(K, 2)``: the centroid, and the unit eigenvectors of the scatter's smallest and largest
    eigenvalues."""
    centre: FloatArray = points.mean(axis=0)
    d = points - centre
    _, vecs = np.linalg.eigh(d.T @ d)
    return centre, vecs[:, 0], vecs[:, 1]


def fit_line(points: FloatArray) -> tuple[float, float]:
    """Total-least-squares line ``(phi, rho)`` through world points ``(K, 2)``: normal
    ``(cos phi, sin phi)``, ``n . p = rho`` on the line."""
    centre, normal, _ = principal_axes(points)
    return float(math.atan2(normal[1], normal[0])), float(normal @ centre)
