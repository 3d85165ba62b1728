"""Pose graphs the package makes itself, so the demo, the tests and the benches need no files.

A robot drives on a Manhattan grid (one cell forward per step, sometimes a 90 degree turn, like
Olson's M3500), its odometry and loop closures are the true relative poses perturbed by Gaussian
noise, and the initial guess is the composed noisy odometry. Everything is a function of ``seed``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hitl_slam.errors import InputError
from hitl_slam.geometry import between, compose, integrate, wrap
from hitl_slam.graph import PoseGraph

__all__ = ["chain_with_loops", "manhattan_world"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# Unit steps for headings 0, 1, 2, 3 (times pi/2), and the headings themselves as (-pi, pi] angles.
_STEP_X = (1, 0, -1, 0)
_STEP_Y = (0, 1, 0, -1)
_HEADING = np.array([0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi])


def manhattan_world(
    num_poses: int = 1000,
    *,
    grid: float = 1.0,
    loop_closure_radius: float = 0.0,
    max_closures_per_pose: int = 1,
    world_size: int | None = None,
    turn_probability: float = 0.2,
    sigma_xy: float = 0.05,
    sigma_theta: float = 0.01,
    add_noise: bool = True,
    seed: int = 0,
) -> tuple[PoseGraph, FloatArray]:
    """A Manhattan-world pose graph in the style of Olson's M3500.

    The robot starts at the origin facing +x. Each step it turns by +-90 degrees with probability
    ``turn_probability`` and moves one cell (``grid`` metres) along its new heading; it stays in a
    square of ``world_size`` x ``world_size`` cells around the origin (turning, or reversing in a
    corner, at the border) so that it keeps revisiting places. Edges:

    - odometry ``i -> i+1`` for every pose;
    - loop closures ``j -> i`` (``j < i - 1``) whenever pose ``i`` is within
      ``loop_closure_radius`` metres of earlier poses (0: the same grid cell), to at most
      ``max_closures_per_pose`` of them, drawn at random.

    Every measurement is ``t_i_j = between(gt_i, gt_j) * Exp(n)`` with ``n ~ N(0, diag(sigma_xy^2,
    sigma_xy^2, sigma_theta^2))``, and its information matrix is the inverse of that covariance.

    Args:
        num_poses: number of poses N (>= 2).
        grid: cell size in metres.
        loop_closure_radius: how close (metres, ground truth) two poses must be to be linked.
        max_closures_per_pose: cap on the loop closures that end at one pose.
        world_size: side of the square world in cells; default ``max(4, round(sqrt(N) / 2))``.
        turn_probability: chance of a 90 degree turn at each step.
        sigma_xy: standard deviation of the translation noise (metres, per axis).
        sigma_theta: standard deviation of the rotation noise (radians).
        add_noise: False gives exact measurements (same information matrices), so the ground
            truth has zero chi2; useful in tests.
        seed: seed of the ``numpy.random.Generator``; equal seeds give equal graphs.

    Returns:
        ``(graph, ground_truth)``: the graph, whose ``poses`` are the composed odometry with pose 0
        at the ground truth (the anchor), and the ``(N, 3)`` ground-truth poses.
    """
    _check_common(num_poses, grid, turn_probability, sigma_xy, sigma_theta)
    if not math.isfinite(loop_closure_radius) or loop_closure_radius < 0.0:
        raise InputError(
            f"loop_closure_radius must be a finite distance >= 0 m, got {loop_closure_radius}"
        )
    if max_closures_per_pose < 0:
        raise InputError(f"max_closures_per_pose must be >= 0, got {max_closures_per_pose}")
    rng = np.random.default_rng(seed)
    cells, headings = _walk(num_poses, _world_size(num_poses, world_size), turn_probability, rng)
    closures = _loop_candidates(
        cells, loop_closure_radius / grid, max_closures_per_pose, rng.random(num_poses)
    )
    return _assemble(cells, headings, closures, grid, sigma_xy, sigma_theta, add_noise, rng)


def chain_with_loops(
    num_poses: int = 100_000,
    *,
    loop_fraction: float = 0.10,
    grid: float = 1.0,
    world_size: int | None = None,
    turn_probability: float = 0.2,
    sigma_xy: float = 0.02,
    sigma_theta: float = 0.005,
    add_noise: bool = True,
    seed: int = 0,
) -> tuple[PoseGraph, FloatArray]:
    """A long Manhattan walk with exactly ``round(loop_fraction * num_poses)`` loop closures.

    Made for scale tests: 100 000 poses take well under a second. The walk is the one of
    :func:`manhattan_world`; every pose that revisits a cell (or, if that is not enough, a
    neighbouring cell) offers one or more candidate closures to earlier poses there, and the
    closures are drawn from the candidates uniformly without replacement. Odometry edges come first
    (edge ``k`` is ``k -> k+1``), then the closures in order of their later pose.

    Args:
        num_poses: number of poses N (>= 2).
        loop_fraction: loop closures per pose; the count is ``round(loop_fraction * N)``.
        grid, world_size, turn_probability, add_noise, seed: as in :func:`manhattan_world`.
        sigma_xy, sigma_theta: as in :func:`manhattan_world`, with smaller defaults: over 100 000
            steps, 0.01 rad per step drifts the odometry so far (sqrt(N) * sigma_theta ~ 3 rad)
            that Levenberg-Marquardt from the odometry guess stops in a local minimum.

    Returns:
        ``(graph, ground_truth)`` as in :func:`manhattan_world`.

    Raises:
        InputError: on bad arguments, or when the walk has too few revisits for the requested
            number of closures (use a smaller ``world_size`` or ``loop_fraction``).
    """
    _check_common(num_poses, grid, turn_probability, sigma_xy, sigma_theta)
    if not math.isfinite(loop_fraction) or loop_fraction < 0.0:
        raise InputError(f"loop_fraction must be a finite number >= 0, got {loop_fraction}")
    wanted = round(loop_fraction * num_poses)
    rng = np.random.default_rng(seed)
    cells, headings = _walk(num_poses, _world_size(num_poses, world_size), turn_probability, rng)
    uniforms = rng.random(num_poses)
    # Widen the search (same cell, then 4-neighbours, then 8, ...) and allow more closures per pose
    # until there are enough candidates; the first round almost always suffices.
    per_pose = max(1, math.ceil(wanted / num_poses))
    closures = np.empty((0, 2), dtype=np.int64)
    for radius_cells in (0.0, 1.0, math.sqrt(2.0), 2.0, 3.0):
        closures = _loop_candidates(cells, radius_cells, per_pose, uniforms)
        if closures.shape[0] >= wanted:
            break
    if closures.shape[0] < wanted:
        raise InputError(
            f"the walk offers only {closures.shape[0]} loop closures, {wanted} were asked for; "
            "use a smaller world_size or loop_fraction"
        )
    chosen = np.sort(rng.choice(closures.shape[0], size=wanted, replace=False))
    return _assemble(cells, headings, closures[chosen], grid, sigma_xy, sigma_theta, add_noise, rng)


def _check_common(
    num_poses: int, grid: float, turn_probability: float, sigma_xy: float, sigma_theta: float
) -> None:
    if num_poses < 2:
        raise InputError(f"num_poses must be >= 2, got {num_poses}")
    if not math.isfinite(grid) or grid <= 0.0:
        raise InputError(f"grid must be a positive cell size in metres, got {grid}")
    if not 0.0 <= turn_probability <= 1.0:
        raise InputError(f"turn_probability must be in [0, 1], got {turn_probability}")
    for name, sigma in (("sigma_xy", sigma_xy), ("sigma_theta", sigma_theta)):
        # The information matrix is 1 / sigma^2: zero noise is asked for with add_noise=False.
        if not math.isfinite(sigma) or sigma <= 0.0:
            raise InputError(
                f"{name} must be > 0 (it sets the information matrix), got {sigma}; "
                "pass add_noise=False for exact measurements"
            )


def _world_size(num_poses: int, world_size: int | None) -> int:
    if world_size is None:
        return max(4, round(math.sqrt(num_poses) / 2.0))
    if world_size < 2:
        raise InputError(f"world_size must be >= 2 cells, got {world_size}")
    return world_size


def _walk(
    num_poses: int, world_size: int, turn_probability: float, rng: np.random.Generator
) -> tuple[IntArray, IntArray]:
    """Integer cells ``(N, 2)`` and headings ``(N,)`` (multiples of pi/2) of the robot's walk."""
    turns = np.where(
        rng.random(num_poses) < turn_probability, rng.choice(np.array([1, 3]), num_poses), 0
    ).tolist()
    coin = (rng.random(num_poses) < 0.5).tolist()
    lo = -(world_size // 2)
    hi = lo + world_size - 1
    cells = np.zeros((num_poses, 2), dtype=np.int64)
    headings = np.zeros(num_poses, dtype=np.int64)
    # Sequential by nature (the border decides the next turn), but only integer work per step.
    x = y = h = 0
    xs = [0] * num_poses
    ys = [0] * num_poses
    hs = [0] * num_poses
    for k in range(1, num_poses):
        first = turns[k]
        # The wanted turn, then the other two non-reversing ones, then reversing (in a corner).
        others = (3, 1) if first == 0 else (0, 4 - first)
        options = (first, *(others if coin[k] else others[::-1]), 2)
        for turn in options:
            nh = (h + turn) % 4
            nx = x + _STEP_X[nh]
            ny = y + _STEP_Y[nh]
            if lo <= nx <= hi and lo <= ny <= hi:
                break
        x, y, h = nx, ny, nh
        xs[k], ys[k], hs[k] = x, y, h
    cells[:, 0] = xs
    cells[:, 1] = ys
    headings[:] = hs
    return cells, headings


def _loop_candidates(
    cells: IntArray, radius_cells: float, per_pose: int, uniforms: FloatArray
) -> IntArray:
    """Pairs ``(j, i)``, ``j < i - 1``, with pose j within ``radius_cells`` of pose i.

    A hash of visited cells makes this linear in N. Each pose links to at most ``per_pose`` earlier
    poses, drawn with the given uniforms so the result depends only on the seed.
    """
    if per_pose == 0:
        return np.empty((0, 2), dtype=np.int64)
    reach = math.floor(radius_cells + 1e-9)
    offsets = [
        (dx, dy)
        for dx in range(-reach, reach + 1)
        for dy in range(-reach, reach + 1)
        if dx * dx + dy * dy <= radius_cells * radius_cells + 1e-9
    ]
    visits: dict[tuple[int, int], list[int]] = {}
    pairs: list[tuple[int, int]] = []
    xs = cells[:, 0].tolist()
    ys = cells[:, 1].tolist()
    draws = uniforms.tolist()
    for i, (x, y, u) in enumerate(zip(xs, ys, draws, strict=True)):
        # The candidates are the concatenation of the visit lists around (x, y), never built: a
        # revisited cell may hold thousands of visits. The odometry predecessor i - 1 is not a
        # loop closure; being the latest visit of its cell, it can only be a list's last entry.
        lists: list[list[int]] = []
        lengths: list[int] = []
        for dx, dy in offsets:
            seen = visits.get((x + dx, y + dy))
            if seen:
                usable = len(seen) - (seen[-1] == i - 1)
                if usable:
                    lists.append(seen)
                    lengths.append(usable)
        count = sum(lengths)
        start = int(u * count)
        # A random run of consecutive candidates (wrapping): distinct, and O(per_pose) to draw.
        pairs.extend(
            (_nth(lists, lengths, (start + k) % count), i) for k in range(min(per_pose, count))
        )
        visits.setdefault((x, y), []).append(i)
    if not pairs:
        return np.empty((0, 2), dtype=np.int64)
    out = np.array(pairs, dtype=np.int64)
    # Each pose's closures in increasing order of the earlier pose (stable, seed-independent).
    return out[np.lexsort((out[:, 0], out[:, 1]))]


def _nth(lists: list[list[int]], lengths: list[int], n: int) -> int:
    """Entry ``n`` of the concatenation of ``lists[k][: lengths[k]]``."""
    for seen, length in zip(lists, lengths, strict=True):
        if n < length:
            return seen[n]
        n -= length
    raise IndexError(n)  # unreachable: callers pass n < sum(lengths)


def _assemble(
    cells: IntArray,
    headings: IntArray,
    closures: IntArray,
    grid: float,
    sigma_xy: float,
    sigma_theta: float,
    add_noise: bool,
    rng: np.random.Generator,
) -> tuple[PoseGraph, FloatArray]:
    num_poses = cells.shape[0]
    truth = np.empty((num_poses, 3), dtype=np.float64)
    truth[:, :2] = cells * grid
    truth[:, 2] = _HEADING[headings]

    chain = np.arange(num_poses - 1, dtype=np.int64)
    edges = np.concatenate([np.stack([chain, chain + 1], axis=1), closures]).astype(np.int64)
    t_i_j = between(truth[edges[:, 0]], truth[edges[:, 1]])
    sigmas = np.array([sigma_xy, sigma_xy, sigma_theta])
    if add_noise:
        noise = rng.standard_normal(t_i_j.shape) * sigmas
        measurements = compose(t_i_j, _exp(noise))
    else:
        measurements = t_i_j
    information = np.broadcast_to(np.diag(1.0 / sigmas**2), (edges.shape[0], 3, 3)).copy()

    graph = PoseGraph(
        poses=integrate(truth[0], measurements[: num_poses - 1]),
        edges=edges,
        measurements=measurements,
        information=information,
        anchor=0,
    )
    return graph, truth


def _exp(v: FloatArray) -> FloatArray:
    """Row-wise SE(2) exponential of tangent vectors ``(vx, vy, w)`` (as GTSAM's Pose2.Expmap)."""
    w = v[:, 2]
    small = np.abs(w) < 1e-5
    safe = np.where(small, 1.0, w)
    # sin(w)/w and (1 - cos(w))/w, with their Taylor series near 0 where the division is unstable.
    a = np.where(small, 1.0 - w * w / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 * w - w**3 / 24.0, (1.0 - np.cos(safe)) / safe)
    out = np.empty_like(v)
    out[:, 0] = a * v[:, 0] - b * v[:, 1]
    out[:, 1] = b * v[:, 0] + a * v[:, 1]
    out[:, 2] = wrap(w)
    return out
