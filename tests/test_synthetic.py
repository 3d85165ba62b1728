"""Tests of the generated pose graphs: determinism, structure, and that the noise is what it says.

chi2 is computed here by a small numpy reference of the SE(2) residual (cross-checked against GTSAM
when it is installed) and, when the compiled core is built, by ``hitl_slam.chi2`` too.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from hitl_slam.errors import InputError
from hitl_slam.graph import PoseGraph
from hitl_slam.sim.synthetic import chain_with_loops, manhattan_world
from reference import reference_chi2
from reference import wrap as _wrap

Generator = Callable[..., tuple[PoseGraph, NDArray[np.float64]]]
GENERATORS: list[Generator] = [manhattan_world, chain_with_loops]


def _num_closures(graph: PoseGraph) -> int:
    return graph.num_edges - (graph.num_poses - 1)


def _is_connected(graph: PoseGraph) -> bool:
    n = graph.num_poses
    ones = np.ones(graph.num_edges)
    adjacency = coo_matrix((ones, (graph.edges[:, 0], graph.edges[:, 1])), shape=(n, n))
    count, _ = connected_components(adjacency, directed=False)
    return bool(count == 1)


def _check_structure(graph: PoseGraph, truth: NDArray[np.float64]) -> None:
    n, m = graph.num_poses, graph.num_edges
    assert graph.poses.shape == (n, 3)
    assert graph.poses.dtype == np.float64
    assert graph.poses.flags.c_contiguous
    assert truth.shape == (n, 3)
    assert truth.dtype == np.float64
    assert graph.edges.shape == (m, 2)
    assert graph.edges.dtype == np.int64
    assert graph.measurements.shape == (m, 3)
    assert graph.information.shape == (m, 3, 3)
    assert graph.anchor == 0
    np.testing.assert_array_equal(graph.poses[0], truth[0])
    for angles in (graph.poses[:, 2], truth[:, 2], graph.measurements[:, 2]):
        assert np.all(angles > -math.pi)
        assert np.all(angles <= math.pi)
    # Odometry first, then closures j -> i with j < i - 1, no duplicates.
    chain = np.arange(n - 1)
    np.testing.assert_array_equal(graph.edges[: n - 1], np.stack([chain, chain + 1], axis=1))
    closures = graph.edges[n - 1 :]
    assert np.all(closures[:, 0] >= 0)
    assert np.all(closures[:, 1] < n)
    assert np.all(closures[:, 0] < closures[:, 1] - 1)
    assert len({tuple(e) for e in closures.tolist()}) == closures.shape[0]
    # Information: symmetric positive definite.
    np.testing.assert_array_equal(graph.information, np.swapaxes(graph.information, 1, 2))
    assert np.all(np.linalg.eigvalsh(graph.information) > 0)
    assert _is_connected(graph)


# --- determinism ------------------------------------------------------------------------------


@pytest.mark.parametrize("make", GENERATORS)
def test_same_seed_same_graph(make: Generator) -> None:
    g1, t1 = make(500, seed=7)
    g2, t2 = make(500, seed=7)
    for name in ("poses", "edges", "measurements", "information"):
        np.testing.assert_array_equal(getattr(g1, name), getattr(g2, name))
    np.testing.assert_array_equal(t1, t2)


@pytest.mark.parametrize("make", GENERATORS)
def test_different_seed_different_graph(make: Generator) -> None:
    g1, t1 = make(500, seed=1)
    g2, t2 = make(500, seed=2)
    assert not np.array_equal(t1, t2)
    assert not np.array_equal(g1.poses, g2.poses)


def test_noise_does_not_change_the_walk() -> None:
    """The ground truth and the edges do not depend on the noise level or on add_noise."""
    g1, t1 = manhattan_world(400, seed=3)
    g2, t2 = manhattan_world(400, seed=3, sigma_xy=0.2, sigma_theta=0.05, add_noise=False)
    np.testing.assert_array_equal(t1, t2)
    np.testing.assert_array_equal(g1.edges, g2.edges)


# --- structure --------------------------------------------------------------------------------


@pytest.mark.parametrize("make", GENERATORS)
def test_structure(make: Generator) -> None:
    graph, truth = make(1000)
    _check_structure(graph, truth)


def test_defaults_give_a_m3500_like_graph() -> None:
    graph, _ = manhattan_world()
    assert graph.num_poses == 1000
    # A useful number of closures: M3500 has 0.6 per pose.
    assert 0.3 * graph.num_poses <= _num_closures(graph) <= 1.0 * graph.num_poses


def test_ground_truth_walks_the_grid() -> None:
    grid = 2.5
    _, truth = manhattan_world(800, grid=grid, world_size=10)
    cells = truth[:, :2] / grid
    np.testing.assert_allclose(cells, np.round(cells), atol=1e-12)
    steps = np.abs(np.diff(np.round(cells), axis=0)).sum(axis=1)
    np.testing.assert_array_equal(steps, 1)  # one cell per step, never diagonal, never standing
    quarter_turns = truth[:, 2] / (0.5 * math.pi)
    np.testing.assert_allclose(quarter_turns, np.round(quarter_turns), atol=1e-12)
    # The robot moves along its heading.
    direction = np.diff(truth[:, :2], axis=0)
    heading = np.stack([np.cos(truth[1:, 2]), np.sin(truth[1:, 2])], axis=1) * grid
    np.testing.assert_allclose(direction, heading, atol=1e-12)
    # It stays in the 10 x 10 world.
    assert np.ptp(np.round(cells), axis=0).max() <= 9


@pytest.mark.parametrize("radius", [0.0, 1.0, 2.5])
def test_manhattan_closures_are_within_the_radius(radius: float) -> None:
    grid = 0.5
    graph, truth = manhattan_world(1500, grid=grid, loop_closure_radius=radius * grid)
    closures = graph.edges[graph.num_poses - 1 :]
    assert closures.shape[0] > 0
    distance = np.linalg.norm(truth[closures[:, 0], :2] - truth[closures[:, 1], :2], axis=1)
    assert np.all(distance <= radius * grid + 1e-9)


def test_manhattan_closures_per_pose_cap() -> None:
    graph, _ = manhattan_world(1500, loop_closure_radius=2.0, max_closures_per_pose=3)
    closures = graph.edges[graph.num_poses - 1 :]
    counts = np.bincount(closures[:, 1])
    assert counts.max() == 3
    none, _ = manhattan_world(1500, max_closures_per_pose=0)
    assert _num_closures(none) == 0


@pytest.mark.parametrize(
    ("num_poses", "loop_fraction"),
    [(1000, 0.1), (1000, 0.0), (777, 0.333), (2000, 0.6), (500, 1.5)],
)
def test_chain_has_exactly_the_requested_closures(num_poses: int, loop_fraction: float) -> None:
    graph, truth = chain_with_loops(num_poses, loop_fraction=loop_fraction)
    assert graph.num_poses == num_poses
    assert _num_closures(graph) == round(loop_fraction * num_poses)
    _check_structure(graph, truth)
    closures = graph.edges[num_poses - 1 :]
    if closures.shape[0]:
        distance = np.linalg.norm(truth[closures[:, 0], :2] - truth[closures[:, 1], :2], axis=1)
        assert distance.max() <= 3.0 + 1e-9  # "near": at most the widest search, 3 cells


def test_chain_too_many_closures_is_an_input_error() -> None:
    with pytest.raises(InputError, match="loop closures"):
        chain_with_loops(200, loop_fraction=5.0, world_size=1000)


def test_chain_builds_the_100k_scale_graph() -> None:
    # Its speed is measured by benches/scale.py, not asserted here.
    graph, _ = chain_with_loops(100_000, loop_fraction=0.1)
    assert graph.num_poses == 100_000
    assert _num_closures(graph) == 10_000
    assert _is_connected(graph)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"num_poses": 1},
        {"grid": 0.0},
        {"grid": math.nan},
        {"sigma_xy": 0.0},
        {"sigma_theta": -1.0},
        {"turn_probability": 1.5},
        {"world_size": 1},
    ],
)
@pytest.mark.parametrize("make", GENERATORS)
def test_bad_arguments_are_input_errors(make: Generator, kwargs: dict[str, float]) -> None:
    with pytest.raises(InputError):
        make(**({"num_poses": 50} | kwargs))


def test_bad_loop_arguments_are_input_errors() -> None:
    with pytest.raises(InputError):
        manhattan_world(50, loop_closure_radius=-1.0)
    with pytest.raises(InputError):
        manhattan_world(50, max_closures_per_pose=-1)
    with pytest.raises(InputError):
        chain_with_loops(50, loop_fraction=-0.1)


# --- noise and chi2 ---------------------------------------------------------------------------


@pytest.mark.parametrize("make", GENERATORS)
def test_noise_free_ground_truth_has_zero_chi2(make: Generator) -> None:
    graph, truth = make(2000, add_noise=False)
    assert reference_chi2(graph, truth) < 1e-12 * graph.num_edges
    # Exact odometry composes to the ground truth.
    np.testing.assert_allclose(graph.poses[:, :2], truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(_wrap(graph.poses[:, 2] - truth[:, 2]), 0.0, atol=1e-9)


@pytest.mark.parametrize("make", GENERATORS)
def test_information_is_the_inverse_noise_covariance(make: Generator) -> None:
    graph, _ = make(300, sigma_xy=0.2, sigma_theta=0.04)
    expected = np.diag([1 / 0.2**2, 1 / 0.2**2, 1 / 0.04**2])
    np.testing.assert_allclose(
        graph.information, np.broadcast_to(expected, (graph.num_edges, 3, 3))
    )


@pytest.mark.parametrize("make", GENERATORS)
@pytest.mark.parametrize("seed", [0, 1])
def test_chi2_of_the_ground_truth_is_chi_square(make: Generator, seed: int) -> None:
    """At the ground truth r = -n exactly, so chi2 ~ chi-square with 3M degrees of freedom."""
    graph, truth = make(3000, seed=seed, sigma_xy=0.1, sigma_theta=0.03)
    dof = 3 * graph.num_edges
    chi2 = reference_chi2(graph, truth)
    assert abs(chi2 - dof) < 5.0 * math.sqrt(2.0 * dof), (chi2, dof)
    # The odometry guess is far worse than the ground truth.
    assert reference_chi2(graph, graph.poses) > 2.0 * chi2


def test_reference_chi2_matches_gtsam() -> None:
    gtsam = pytest.importorskip("gtsam")
    graph, truth = manhattan_world(300, sigma_xy=0.1, sigma_theta=0.05)
    factors = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, (x, y, theta) in enumerate(truth.tolist()):
        values.insert(k, gtsam.Pose2(x, y, theta))
    for (i, j), z, omega in zip(graph.edges, graph.measurements, graph.information, strict=True):
        noise = gtsam.noiseModel.Gaussian.Information(omega)
        factors.add(gtsam.BetweenFactorPose2(int(i), int(j), gtsam.Pose2(*z), noise))
    assert reference_chi2(graph, truth) == pytest.approx(2.0 * factors.error(values), rel=1e-10)


def test_package_chi2_matches_the_reference() -> None:
    import hitl_slam

    for graph, truth in (manhattan_world(500), chain_with_loops(500, loop_fraction=0.2)):
        for poses in (truth, graph.poses):
            ours = hitl_slam.chi2(graph, poses)
            assert ours == pytest.approx(reference_chi2(graph, poses), rel=1e-9)
    quiet, truth = manhattan_world(500, add_noise=False)
    assert hitl_slam.chi2(quiet, truth) < 1e-12 * quiet.num_edges


def test_optimizing_recovers_the_ground_truth() -> None:
    import hitl_slam

    graph, truth = manhattan_world(600, seed=4)
    poses, report = hitl_slam.optimize(graph)
    dof = 3 * (graph.num_edges - graph.num_poses + 1)
    assert report.final_chi2 < 1.5 * dof < report.initial_chi2
    assert report.final_chi2 <= reference_chi2(graph, truth)
    ate = float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))
    odometry_ate = float(np.sqrt(np.mean(np.sum((graph.poses[:, :2] - truth[:, :2]) ** 2, axis=1))))
    assert ate < 0.2 < odometry_ate


# --- properties over many small graphs --------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    num_poses=st.integers(min_value=2, max_value=300),
    radius=st.sampled_from([0.0, 1.0, 1.5, 2.0]),
    per_pose=st.integers(min_value=0, max_value=3),
    world_size=st.one_of(st.none(), st.integers(min_value=2, max_value=12)),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_manhattan_properties(
    num_poses: int, radius: float, per_pose: int, world_size: int | None, seed: int
) -> None:
    graph, truth = manhattan_world(
        num_poses,
        loop_closure_radius=radius,
        max_closures_per_pose=per_pose,
        world_size=world_size,
        seed=seed,
    )
    assert graph.num_poses == num_poses
    _check_structure(graph, truth)
    closures = graph.edges[num_poses - 1 :]
    if closures.shape[0]:
        assert np.bincount(closures[:, 1]).max() <= per_pose
        distance = np.linalg.norm(truth[closures[:, 0], :2] - truth[closures[:, 1], :2], axis=1)
        assert np.all(distance <= radius + 1e-9)


@settings(max_examples=60, deadline=None)
@given(
    num_poses=st.integers(min_value=4, max_value=400),
    loop_fraction=st.floats(min_value=0.0, max_value=0.5),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_chain_properties(num_poses: int, loop_fraction: float, seed: int) -> None:
    graph, truth = chain_with_loops(num_poses, loop_fraction=loop_fraction, seed=seed)
    assert _num_closures(graph) == round(loop_fraction * num_poses)
    _check_structure(graph, truth)
