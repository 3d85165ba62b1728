"""Plane geometry, the only Python copy, with the Rust core's conventions (``rust/src/se2.rs``,
``rust/src/geometry.rs``):

* angles [rad] are kept in (-pi, pi] (:func:`wrap`: pi stays pi, -pi becomes pi);
* SE(2) poses are ``(x, y, theta)`` rows; ``t_world_robot`` maps robot-frame points to world
  points (:func:`compose`, :func:`between`, :func:`invert`, :func:`transform`,
  :func:`to_world`, :func:`chain_steps`, :func:`integrate`);
* lines are ``(phi, rho)``: unit normal ``(cos phi, sin phi)``, ``n . p = rho`` on the line,
  with ``rho >= 0`` (:func:`fit_line`); the angle between two lines is undirected
  (:func:`line_angle`).

Every function is vectorised: poses broadcast over rows (a ``(3,)`` pose against ``(K, 3)``
rows, or row by row), and :func:`wrap` takes scalars and arrays alike.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "between",
    "chain_steps",
    "compose",
    "compose_rows",
    "fit_line",
    "integrate",
    "invert",
    "line_angle",
    "principal_axes",
    "rotate",
    "to_robot",
    "to_world",
    "transform",
    "wrap",
]

FloatArray = NDArray[np.float64]
Angles = TypeVar("Angles", float, FloatArray)
"""A float (NumPy scalars included) or a float64 array: :func:`wrap` gives back the same kind."""

TAU = 2.0 * math.pi

ISOTROPIC = 1e-12
"""A scatter whose two eigenvalues differ by less than this fraction of their sum has no
principal direction (Rust's ``geometry::ISOTROPIC``)."""


def wrap(angles: Angles) -> Angles:
    """Angles [rad] wrapped to (-pi, pi], with the Rust core's arithmetic
    (``se2::wrap_angle``), so both sides agree to the bit.

    Angles already in (-pi, pi] are returned unchanged (bit for bit, so tiny angles keep their
    precision); any other ``a`` becomes ``r = a mod 2 pi`` in [0, 2 pi), less 2 pi when
    ``r > pi``. So ``wrap(pi) == pi``, ``wrap(-pi) == pi``, ``wrap(3 pi)`` and ``wrap(-3 pi)``
    are within an ulp of pi (whichever side the rounded input falls on), and a NaN or an
    infinity gives NaN. A Python or NumPy scalar (or a 0-d array) gives a ``float``; an array a
    new float64 array of the same shape.
    """
    if isinstance(angles, float | int):
        a = float(angles)
        if -math.pi < a <= math.pi:
            return a
        if not math.isfinite(a):
            return math.nan
        r = a % TAU  # Python's float modulo is fmod made non-negative: Rust's rem_euclid
        return r - TAU if r > math.pi else r
    x = np.array(angles, dtype=np.float64)
    outside = ~((x > -math.pi) & (x <= math.pi))
    if outside.any():
        with np.errstate(invalid="ignore"):
            r = np.mod(x[outside], TAU)
        x[outside] = np.where(r > math.pi, r - TAU, r)
    if x.ndim == 0:
        return float(x)  # type: ignore[return-value]
    return x


def _rows(poses: ArrayLike) -> FloatArray:
    p = np.asarray(poses, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"poses must be (x, y, theta) rows, got shape {p.shape}")
    return p


def compose(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a * b`` over rows: ``a`` and ``b`` are poses ``(3,)`` or ``(K, 3)`` (broadcast, so one
    pose against many rows, or row by row); heading in (-pi, pi]."""
    p, q = _rows(a), _rows(b)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    out: FloatArray = np.stack(
        [
            p[..., 0] + (c * q[..., 0] - s * q[..., 1]),
            p[..., 1] + (s * q[..., 0] + c * q[..., 1]),
            wrap(p[..., 2] + q[..., 2]),
        ],
        axis=-1,
    )
    return out


def compose_rows(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Row by row ``a[k] * b[k]`` for poses ``(K, 3)``: :func:`compose`."""
    return compose(a, b)


def invert(poses: ArrayLike) -> FloatArray:
    """``x^-1`` over rows for poses ``(3,)`` or ``(K, 3)``, heading in (-pi, pi]."""
    p = _rows(poses)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    x, y = p[..., 0], p[..., 1]
    out: FloatArray = np.stack([-(c * x + s * y), s * x - c * y, wrap(-p[..., 2])], axis=-1)
    return out


def between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a^-1 * b`` over rows (pose ``b`` in the frame of pose ``a``), broadcast like
    :func:`compose`; heading ``wrap(theta_b - theta_a)``."""
    p, q = _rows(a), _rows(b)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    dx, dy = q[..., 0] - p[..., 0], q[..., 1] - p[..., 1]
    out: FloatArray = np.stack(
        [c * dx + s * dy, -s * dx + c * dy, wrap(q[..., 2] - p[..., 2])], axis=-1
    )
    return out


def chain_steps(poses: ArrayLike) -> FloatArray:
    """``(N - 1, 3)`` steps ``x_k^-1 x_(k+1)`` between consecutive poses ``(N, 3)``."""
    p = _rows(poses).reshape(-1, 3)
    return between(p[:-1], p[1:])


def integrate(start: ArrayLike, steps: ArrayLike) -> FloatArray:
    """``(M + 1, 3)`` poses ``x_0 = start``, ``x_(k+1) = x_k * steps[k]`` for steps ``(M, 3)``,
    vectorised with cumulative sums (the inverse of :func:`chain_steps`)."""
    x0 = _rows(start).reshape(3)
    z = _rows(steps).reshape(-1, 3)
    theta = x0[2] + np.concatenate([[0.0], np.cumsum(z[:, 2])])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    step = np.stack([c * z[:, 0] - s * z[:, 1], s * z[:, 0] + c * z[:, 1]], axis=1)
    out = np.empty((z.shape[0] + 1, 3), dtype=np.float64)
    out[:, :2] = x0[:2] + np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    out[:, 2] = wrap(theta)
    return out


def rotate(angles: ArrayLike, vectors: ArrayLike) -> FloatArray:
    """``R(angle) v`` over rows: vectors ``(2,)`` or ``(K, 2)`` turned by angles (scalar or
    ``(K,)``), e.g. robot-frame normals into the world."""
    t = np.asarray(angles, dtype=np.float64)
    v = np.asarray(vectors, dtype=np.float64)
    c, s = np.cos(t), np.sin(t)
    out: FloatArray = np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)
    return out


def transform(poses: ArrayLike, points: ArrayLike) -> FloatArray:
    """Robot-to-world ``R(theta) p + t`` over rows: points ``(2,)`` or ``(K, 2)`` by poses
    ``(3,)`` or ``(K, 3)`` (broadcast)."""
    x = _rows(poses)
    p = np.asarray(points, dtype=np.float64)
    c, s = np.cos(x[..., 2]), np.sin(x[..., 2])
    out: FloatArray = np.stack(
        [c * p[..., 0] - s * p[..., 1] + x[..., 0], s * p[..., 0] + c * p[..., 1] + x[..., 1]],
        axis=-1,
    )
    return out


def to_robot(poses: ArrayLike, points: ArrayLike) -> FloatArray:
    """World-to-robot ``R(theta)^T (p - t)`` over rows, the inverse of :func:`transform`."""
    x = _rows(poses)
    p = np.asarray(points, dtype=np.float64)
    c, s = np.cos(x[..., 2]), np.sin(x[..., 2])
    dx, dy = p[..., 0] - x[..., 0], p[..., 1] - x[..., 1]
    out: FloatArray = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)
    return out


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
    eigenvalues (their signs are arbitrary; :func:`fit_line` orients the normal)."""
    centre: FloatArray = points.mean(axis=0)
    d = points - centre
    _, vecs = np.linalg.eigh(d.T @ d)
    return centre, vecs[:, 0], vecs[:, 1]


def line_angle(phi_a: Angles, phi_b: Angles) -> Angles:
    """The angle [rad] between undirected lines of normal angles ``phi_a`` and ``phi_b``, in
    [0, pi/2] (lines 10 and 190 degrees apart are parallel); scalars or arrays (a scalar pair
    by ``math.remainder``, exactly)."""
    if isinstance(phi_a, float | int) and isinstance(phi_b, float | int):
        return abs(math.remainder(float(phi_a) - float(phi_b), math.pi))
    d = np.asarray(phi_a, dtype=np.float64) - np.asarray(phi_b, dtype=np.float64)
    return np.abs(d - math.pi * np.round(d / math.pi))


def fit_line(points: ArrayLike) -> tuple[float, float]:
    """Total-least-squares line ``(phi, rho)`` through world points ``(K, 2)``: normal
    ``(cos phi, sin phi)``, ``n . p = rho`` on the line, ``rho >= 0``.

    The same closed form as the Rust core's ``geometry::fit_line``: the normal of the principal
    axis of the scatter about the centroid, first oriented towards +x (kept when ``n_x = 0``),
    then flipped with ``rho`` when ``rho < 0``; a line through the origin (``rho == 0``) keeps
    the +x orientation. A set without a principal direction (one point, an isotropic cloud)
    gets the normal (1, 0), flipped likewise. ``phi`` is in (-pi, pi] (the normal (-1, 0) has
    ``phi = pi``).

    Raises:
        ValueError: no points, or a point that is not finite.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] == 0 or not np.isfinite(p).all():
        raise ValueError("a line needs at least one point, all finite")
    centre = p.mean(axis=0)
    d = p - centre
    sxx, sxy, syy = float(d[:, 0] @ d[:, 0]), float(d[:, 0] @ d[:, 1]), float(d[:, 1] @ d[:, 1])
    spread = math.hypot(sxx - syy, 2.0 * sxy)
    if spread > ISOTROPIC * (sxx + syy):
        theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
        nx, ny = -math.sin(theta), math.cos(theta)
        if nx < 0.0:  # oriented like (1, 0)
            nx, ny = -nx, -ny
    else:
        nx, ny = 1.0, 0.0
    rho = nx * float(centre[0]) + ny * float(centre[1])
    if rho < 0.0:
        nx, ny, rho = -nx, -ny, -rho
    # wrap: atan2 gives -pi for a flipped (1, 0), whose y is -0.0
    return wrap(math.atan2(ny, nx)), rho
