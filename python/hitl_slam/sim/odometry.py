"""Odometry from a true trajectory: the true relative motions plus Gaussian noise that grows with
the distance and the rotation of each step (as the motion model of docs/ALGORITHM.md §1.3
assumes), and injectable faults: a heading jump (a sensor failure), a slow heading drift (a bent
hallway), a slip (the wheels spin or the robot is pushed: one step's translation is wrong) or a
scale error (a wheel's radius is off: every step's distance is too long or too short).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.geometry import chain_steps, integrate

__all__ = [
    "DEFAULT_NOISE",
    "NO_NOISE",
    "Fault",
    "HeadingDrift",
    "HeadingJump",
    "OdometryNoise",
    "ScaleError",
    "Slip",
    "compose_motions",
    "odometry",
    "relative_motions",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class OdometryNoise:
    """Per-step standard deviations: ``sigma_t = sigma_t0 + k_t |dt|`` on each of x and y,
    ``sigma_theta = sigma_theta0 + k_theta |dtheta| + k_theta_t |dt|`` on the heading.

    Attributes (units in brackets): k_t [m/m], k_theta [rad/rad], k_theta_t [rad/m],
    sigma_t0 [m], sigma_theta0 [rad]. The defaults are a good wheel odometer: 1 % of the
    distance, 2 % of the rotation, 0.1 degree of heading per metre.
    """

    k_t: float = 0.01
    k_theta: float = 0.02
    k_theta_t: float = math.radians(0.1)
    sigma_t0: float = 0.0
    sigma_theta0: float = 0.0

    def __post_init__(self) -> None:
        for name in ("k_t", "k_theta", "k_theta_t", "sigma_t0", "sigma_theta0"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"odometry noise {name} must be a finite number >= 0")


DEFAULT_NOISE = OdometryNoise()
"""The default odometer (see :class:`OdometryNoise`)."""

NO_NOISE = OdometryNoise(0.0, 0.0, 0.0)
"""Perfect odometry: only the faults remain."""


@dataclass(frozen=True)
class HeadingJump:
    """The heading estimate jumps by ``angle`` [rad] between pose ``pose - 1`` and ``pose``
    (the paper's sensor failure: "incorrectly estimate its heading by roughly 30 degrees")."""

    pose: int
    angle: float


@dataclass(frozen=True)
class HeadingDrift:
    """A constant heading drift of ``rate`` [rad per metre travelled] on every step between
    poses ``start`` and ``stop - 1``: a corridor that bends slowly in the map."""

    start: int
    stop: int
    rate: float


@dataclass(frozen=True)
class Slip:
    """The step from pose ``pose - 1`` to ``pose`` is off by ``(dx, dy)`` [m] in the robot's frame
    at ``pose - 1`` (the wheels spun, or the robot was pushed, and the odometer did not see it)."""

    pose: int
    dx: float
    dy: float


@dataclass(frozen=True)
class ScaleError:
    """Every step's translation between poses ``start`` and ``stop - 1`` is ``factor`` times the
    true one (a wheel radius off by ``factor - 1``)."""

    start: int
    stop: int
    factor: float


Fault = HeadingJump | HeadingDrift | Slip | ScaleError


def relative_motions(poses: FloatArray) -> FloatArray:
    """``(N - 1, 3)`` steps ``z_k = x_k^-1 x_{k+1}`` between consecutive poses (N, 3)."""
    return chain_steps(np.asarray(poses, dtype=np.float64).reshape(-1, 3))


def compose_motions(start: FloatArray, motions: FloatArray) -> FloatArray:
    """``(M + 1, 3)`` poses from ``start`` (3,) composed with the steps ``motions`` (M, 3)."""
    return integrate(start, motions)


def odometry(
    truth: FloatArray,
    rng: np.random.Generator,
    noise: OdometryNoise = DEFAULT_NOISE,
    faults: Sequence[Fault] = (),
) -> FloatArray:
    """The dead-reckoned estimate ``(N, 3)`` of a true trajectory (N, 3): its steps with noise
    and ``faults``, composed from the true first pose (the map's frame is the truth's).

    Raises:
        InputError: a fault names a pose outside the trajectory.
    """
    x = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    z = relative_motions(x)
    dist = np.hypot(z[:, 0], z[:, 1])
    sigma_t = noise.sigma_t0 + noise.k_t * dist
    sigma_th = noise.sigma_theta0 + noise.k_theta * np.abs(z[:, 2]) + noise.k_theta_t * dist
    draws = rng.normal(0.0, 1.0, z.shape)
    z = z + draws * np.stack([sigma_t, sigma_t, sigma_th], axis=1)
    n = x.shape[0]
    for fault in faults:
        if isinstance(fault, HeadingJump):
            if not 1 <= fault.pose < n:
                raise InputError(f"heading jump at pose {fault.pose}: poses are 1..{n - 1}")
            z[fault.pose - 1, 2] += fault.angle
        elif isinstance(fault, Slip):
            if not 1 <= fault.pose < n:
                raise InputError(f"slip at pose {fault.pose}: poses are 1..{n - 1}")
            z[fault.pose - 1, 0] += fault.dx
            z[fault.pose - 1, 1] += fault.dy
        elif isinstance(fault, ScaleError):
            if not (0 <= fault.start <= fault.stop <= n and fault.factor > 0):
                raise InputError(
                    f"scale error {fault.factor} over poses {fault.start}..{fault.stop}: poses "
                    f"are 0..{n} and the factor is > 0"
                )
            k = slice(fault.start, max(fault.start, fault.stop - 1))
            z[k, :2] *= fault.factor
        else:
            if not 0 <= fault.start <= fault.stop <= n:
                raise InputError(f"heading drift over poses {fault.start}..{fault.stop}: 0..{n}")
            k = slice(fault.start, max(fault.start, fault.stop - 1))
            z[k, 2] += fault.rate * dist[k]
    return compose_motions(x[0], z)
