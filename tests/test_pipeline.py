"""The correction pipeline without the interpreter: explicit correction, back-propagation and the
joint solve, on interpretations built from the generated world's ground-truth wall labels, and
the joint cost cross-checked against scipy.optimize.least_squares."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.optimize import least_squares

from hitl_slam import InputError, _core
from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Interpretation, Mode
from hitl_slam.geometry import fit_line
from hitl_slam.map import Map
from hitl_slam.pipeline import chain_variances, explicit_and_backpropagate, solve_all
from hitl_slam.sim.corridor import INNER_BOTTOM, OUTER_BOTTOM, OUTER_LEFT, World, corridor_loop
from reference import compose, exp, whitened, wrap

FloatArray = NDArray[np.float64]


def _rows(
    world: World, wall: int, lo: int, hi: int, x_range: tuple[float, float]
) -> NDArray[np.int64]:
    """(pose, point) rows of ``wall`` seen by poses lo..hi-1 whose TRUE x is in x_range."""
    m = world.map
    owner = m.pose_of_point()
    truth_pts = m.world_points(world.truth)
    sel = (world.wall_of_point == wall) & (owner >= lo) & (owner < hi)
    sel &= (truth_pts[:, 0] >= x_range[0]) & (truth_pts[:, 0] <= x_range[1])
    if wall == OUTER_LEFT:
        sel = (world.wall_of_point == wall) & (owner >= lo) & (owner < hi)
    idx = np.flatnonzero(sel)
    poses = owner[idx]
    keep = np.isin(poses, np.flatnonzero(np.bincount(poses, minlength=m.num_poses) >= 8))
    idx, poses = idx[keep], poses[keep]
    return np.stack([poses, idx - m.offsets[poses]], axis=1)


def _segment(
    m: Map, poses: FloatArray, rows: NDArray[np.int64]
) -> tuple[tuple[float, float], tuple[float, float]]:
    pts = m.world_points(poses)[m.offsets[rows[:, 0]] + rows[:, 1]]
    c = pts.mean(axis=0)
    _, vecs = np.linalg.eigh((pts - c).T @ (pts - c))
    d = vecs[:, 1]
    proj = (pts - c) @ d
    a, b = c + proj.min() * d, c + proj.max() * d
    return (float(a[0]), float(a[1])), (float(b[0]), float(b[1]))


def _interpretation(
    world: World, mode: Mode, a: NDArray[np.int64], b: NDArray[np.int64]
) -> Interpretation:
    m = world.map
    return Interpretation(
        mode=mode,
        line_a=_segment(m, m.poses, a),
        line_b=_segment(m, m.poses, b),
        s_a=a,
        s_b=b,
        x_a=np.unique(a[:, 0]),
        x_b=np.unique(b[:, 0]),
    )


CASES = {
    Mode.COLOCATION: ((OUTER_BOTTOM, 0, 60, (4.0, 9.0)), (OUTER_BOTTOM, 265, 325, (4.0, 9.0))),
    Mode.COLLINEAR: ((OUTER_BOTTOM, 0, 60, (2.0, 7.0)), (OUTER_BOTTOM, 265, 325, (8.0, 13.0))),
    Mode.PARALLEL: ((OUTER_BOTTOM, 0, 60, (2.0, 10.0)), (INNER_BOTTOM, 265, 325, (4.0, 12.0))),
    Mode.PERPENDICULAR: ((OUTER_BOTTOM, 0, 60, (2.0, 10.0)), (OUTER_LEFT, 200, 280, (0.0, 0.0))),
}


@pytest.fixture(scope="module")
def world() -> World:
    return corridor_loop(seed=1)


def _relation_error(m: Map, poses: FloatArray, h: Interpretation) -> tuple[float, float]:
    """(angle error in degrees, offset in metres) between lines refit to S_a and S_b."""
    world_pts = m.world_points(poses)
    pa = world_pts[m.offsets[h.s_a[:, 0]] + h.s_a[:, 1]]
    pb = world_pts[m.offsets[h.s_b[:, 0]] + h.s_b[:, 1]]
    phi_a, rho_a = fit_line(pa)
    phi_b, _ = fit_line(pb)
    e = phi_b - phi_a - (math.pi / 2 if h.mode is Mode.PERPENDICULAR else 0.0)
    e = e - math.pi * round(e / math.pi)
    offset = abs(math.cos(phi_a) * pb.mean(0)[0] + math.sin(phi_a) * pb.mean(0)[1] - rho_a)
    return abs(math.degrees(e)), offset


@pytest.mark.parametrize("mode", list(Mode))
def test_joint_solve_establishes_each_relation(world: World, mode: Mode) -> None:
    (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[mode]
    h = _interpretation(world, mode, _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb))
    before = _relation_error(world.map, world.map.poses, h)
    moved, _ = explicit_and_backpropagate(world.map, world.map.poses, h)
    poses, lines, report = solve_all(world.map, [h], DEFAULT, moved)
    assert report.converged
    angle, offset = _relation_error(world.map, poses, h)
    assert angle < 0.3, (before, angle)
    if mode in (Mode.COLOCATION, Mode.COLLINEAR):
        assert offset < 0.02, (before, offset)
    assert lines.shape == (2, 2)


def test_explicit_step_moves_nothing_along_the_null_space(world: World) -> None:
    m = world.map
    for mode in Mode:
        (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[mode]
        h = _interpretation(world, mode, _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb))
        t = _core.explicit_transform(mode.value, np.array(h.line_a), np.array(h.line_b))
        cb = np.mean(np.array(h.line_b), axis=0)
        c, s = math.cos(t[2]), math.sin(t[2])
        cb_new = np.array([c * cb[0] - s * cb[1] + t[0], s * cb[0] + c * cb[1] + t[1]])
        shift = cb_new - cb
        dir_a = np.subtract(h.line_a[1], h.line_a[0])
        dir_a /= np.linalg.norm(dir_a)
        if mode in (Mode.PARALLEL, Mode.PERPENDICULAR):
            assert np.linalg.norm(shift) < 1e-12  # translation is entirely null-space
        elif mode is Mode.COLLINEAR:
            assert abs(shift @ dir_a) < 1e-12  # no slide along the line
        moved, _ = explicit_and_backpropagate(m, m.poses, h)
        first, last_a = int(h.x_b.min()), int(h.x_a.max())
        np.testing.assert_array_equal(moved[: last_a + 1], m.poses[: last_a + 1])
        expected = compose(np.broadcast_to(t, (m.num_poses - first, 3)), m.poses[first:])
        np.testing.assert_allclose(moved[first:, :2], expected[:, :2], atol=1e-12)


def test_back_propagation_closes_the_gap_exactly(world: World) -> None:
    m = world.map
    (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[Mode.COLOCATION]
    h = _interpretation(
        world, Mode.COLOCATION, _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb)
    )
    moved, _ = explicit_and_backpropagate(m, m.poses, h)
    start, end = int(h.x_a.max()), int(h.x_b.min())
    assert end > start + 1
    # The gap closed: the chain's new relative transforms compose from the fixed pose onto the
    # moved block exactly, and each changed only by its share.
    p = moved[start : start + 1]
    for k in range(start, end):
        c, s = math.cos(moved[k, 2]), math.sin(moved[k, 2])
        d = moved[k + 1, :2] - moved[k, :2]
        z = np.array(
            [
                [
                    c * d[0] + s * d[1],
                    -s * d[0] + c * d[1],
                    wrap(np.array(moved[k + 1, 2] - moved[k, 2])),
                ]
            ]
        )
        p = compose(p, z)
    assert np.abs(p[0, :2] - moved[end, :2]).max() < 1e-9
    assert abs(wrap(np.array(p[0, 2] - moved[end, 2]))) < 1e-9
    rot, trans = chain_variances(m)
    assert np.all(rot > 0)
    assert np.all(trans > 0)
    assert np.abs(moved[start + 1 : end] - m.poses[start + 1 : end]).max() > 1e-3


def test_a_step_shown_off_its_measurement_takes_more_of_the_next_correction(world: World) -> None:
    """Back-propagation shares an error by how far each displayed step may be from the truth:
    a step whose displayed turn differs from its edge's measurement (re-measured by the odometry
    check, or bent by an earlier correction) has its rotational variance widened by the squared
    difference; steps shown as measured keep the edge's own variance."""
    m = world.map
    rot0, trans0 = chain_variances(m)
    assert np.allclose(chain_variances(m, m.poses)[0], rot0)
    k = m.num_poses // 3
    turned = m.poses.copy()
    turn = math.radians(7.0)
    # Rotate the poses after k about pose k's position: step k -> k+1 turns by `turn` more.
    c, s = math.cos(turn), math.sin(turn)
    d = turned[k + 1 :, :2] - turned[k, :2]
    turned[k + 1 :, 0] = turned[k, 0] + c * d[:, 0] - s * d[:, 1]
    turned[k + 1 :, 1] = turned[k, 1] + s * d[:, 0] + c * d[:, 1]
    turned[k + 1 :, 2] += turn
    # (Its translation in pose k's frame changes too; the rotational variance ignores that.)
    rot, trans = chain_variances(m, turned)
    assert rot[k] == pytest.approx(rot0[k] + turn**2, rel=1e-6)
    assert np.allclose(np.delete(rot, k), np.delete(rot0, k))
    assert np.array_equal(trans, trans0)


def test_newest_correction_changes_the_solution(world: World) -> None:
    """The released code rebuilt odometry from the current estimate, so a new correction barely
    moved anything. Here each correction must move the map, and the result must hold both."""
    (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[Mode.PARALLEL]
    first = _interpretation(
        world, Mode.PARALLEL, _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb)
    )
    poses1, _, _ = solve_all(
        world.map,
        [first],
        DEFAULT,
        explicit_and_backpropagate(world.map, world.map.poses, first)[0],
    )
    (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[Mode.COLOCATION]
    second = _interpretation(
        world, Mode.COLOCATION, _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb)
    )
    start2 = explicit_and_backpropagate(world.map, poses1, second)[0]
    poses2, _, report = solve_all(world.map, [first, second], DEFAULT, start2)
    assert np.abs(poses2[:, :2] - poses1[:, :2]).max() > 0.05
    assert _relation_error(world.map, poses2, second)[1] < 0.02
    assert _relation_error(world.map, poses2, first)[0] < 0.3
    assert report.converged


# --- the joint cost against SciPy on a small map -----------------------------------------------


def _small_map() -> tuple[Map, list[Interpretation]]:
    rng = np.random.default_rng(5)
    n = 24
    truth = np.zeros((n, 3))
    truth[:, 0] = np.arange(n) * 0.5
    truth[:, 2] = 0.02 * np.sin(np.arange(n))
    # Each pose sees a few points on the wall y = 2 and on the wall x = 13.
    scans = []
    for k in range(n):
        wx = truth[k, 0] + np.linspace(-1.0, 1.0, 10)
        wall1 = np.stack([wx, np.full(10, 2.0) + rng.normal(0, 0.01, 10)], 1)
        wall2 = np.stack([np.full(10, 13.0) + rng.normal(0, 0.01, 10), np.linspace(-1, 1, 10)], 1)
        world_pts = np.concatenate([wall1, wall2])
        c, s = math.cos(truth[k, 2]), math.sin(truth[k, 2])
        d = world_pts - truth[k, :2]
        scans.append(np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1))
    noisy = truth.copy()
    noisy[1:] += rng.normal(0, [0.03, 0.03, 0.01], (n - 1, 3))
    m = Map.from_poses_and_scans(noisy, scans)
    rows = lambda poses, pts: np.array([[p, q] for p in poses for q in pts], dtype=np.int64)  # noqa: E731
    hs = []
    for mode, (pa, qa), (pb, qb) in [
        (Mode.COLOCATION, (range(0, 4), range(0, 10)), (range(18, 22), range(0, 10))),
        (Mode.COLLINEAR, (range(4, 7), range(0, 10)), (range(14, 17), range(0, 10))),
        (Mode.PARALLEL, (range(7, 9), range(0, 10)), (range(20, 23), range(0, 10))),
        (Mode.PERPENDICULAR, (range(9, 11), range(0, 10)), (range(12, 14), range(10, 20))),
    ]:
        a, b = rows(pa, qa), rows(pb, qb)
        hs.append(_interpretation(World(m, truth, np.zeros(m.num_points, np.int64)), mode, a, b))
    return m, hs


def _joint_residuals(
    m: Map, hs: list[Interpretation], poses: FloatArray, lines: FloatArray
) -> FloatArray:
    """The docs/ALGORITHM.md §4.3 cost written independently: odometry, then per correction R_a,
    R_b, R_p."""
    from hitl_slam.graph import PoseGraph

    graph = PoseGraph(
        poses=poses, edges=m.edges, measurements=m.measurements, information=m.information
    )
    out = [whitened(graph, poses)]
    world = m.world_points(poses)
    for k, h in enumerate(hs):
        (pa, ra), (pb, rb) = lines[2 * k], lines[2 * k + 1]
        wa = world[m.offsets[h.s_a[:, 0]] + h.s_a[:, 1]]
        wb = world[m.offsets[h.s_b[:, 0]] + h.s_b[:, 1]]
        out.append((wa @ [math.cos(pa), math.sin(pa)] - ra) / DEFAULT.sigma_f)
        out.append((wb @ [math.cos(pb), math.sin(pb)] - rb) / DEFAULT.sigma_f)
        e = pb - pa - (math.pi / 2 if h.mode is Mode.PERPENDICULAR else 0.0)
        e = e - math.pi * round(e / math.pi)
        ca, cb = wa.mean(0), wb.mean(0)
        k1, k2 = math.sqrt(DEFAULT.k1), math.sqrt(DEFAULT.k2)
        if h.mode is Mode.COLOCATION:
            out.append(np.array([k1 * (cb - ca)[0], k1 * (cb - ca)[1], k2 * e]))
        elif h.mode is Mode.COLLINEAR:
            out.append(np.array([k1 * ((cb - ca) @ [math.cos(pa), math.sin(pa)]), k2 * e]))
        else:
            out.append(np.array([k2 * e]))
    return np.concatenate(out)


def test_joint_solve_matches_scipy_least_squares() -> None:
    m, hs = _small_map()
    start = m.poses.copy()
    # The §4.3 cost as written, every relation hard: from the uncorrected start the relations
    # are far from holding, and with their default kernel (docs/ALGORITHM.md §I.8) they would
    # yield instead.
    hard = DEFAULT.replace(relative_tolerance=1e-15, absolute_tolerance=1e-15, relation_dcs=0.0)
    ours, lines, report = solve_all(m, hs, hard, start)
    assert report.converged
    n = m.num_poses

    def fun(x: FloatArray) -> FloatArray:
        poses = start.copy()
        poses[1:] = compose(start[1:], exp(x[: 3 * (n - 1)].reshape(-1, 3)))
        return _joint_residuals(m, hs, poses, x[3 * (n - 1) :].reshape(-1, 2))

    x0 = np.concatenate([np.zeros(3 * (n - 1)), lines.ravel()])
    # Start SciPy from a perturbed point so that it does the work itself.
    x0[: 3 * (n - 1)] += 1e-3
    result = least_squares(fun, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=20000)
    theirs = start.copy()
    theirs[1:] = compose(start[1:], exp(result.x[: 3 * (n - 1)].reshape(-1, 3)))
    np.testing.assert_allclose(ours[:, :2], theirs[:, :2], atol=1e-6)
    np.testing.assert_allclose(wrap(ours[:, 2] - theirs[:, 2]), 0.0, atol=1e-6)
    np.testing.assert_allclose(lines, result.x[3 * (n - 1) :].reshape(-1, 2), atol=1e-6)
    assert float(fun(result.x) @ fun(result.x)) == pytest.approx(report.final_chi2, rel=1e-6)


@pytest.mark.parametrize("robust", ["odometry=cauchy:1", "human=huber", "odometry=dcs:10,loop=dcs"])
def test_joint_solve_takes_robust_kernels_per_edge_class(world: World, robust: str) -> None:
    (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[Mode.COLOCATION]
    rows_a, rows_b = _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb)
    h = _interpretation(world, Mode.COLOCATION, rows_a, rows_b)
    moved, _ = explicit_and_backpropagate(world.map, world.map.poses, h)
    config = DEFAULT.replace(robust=robust)
    poses, _, report = solve_all(world.map, [h], config, moved)
    assert report.converged
    assert report.weights.shape == (report.weights.size,)
    assert np.all((report.weights > 0) & (report.weights <= 1))
    if "human" not in robust:
        # Human factors keep full weight when only robot edges are robust.
        assert report.weights[-1] == 1.0
    angle, offset = _relation_error(world.map, poses, h)
    assert angle < 0.5
    assert offset < 0.05


def test_config_refuses_an_unknown_edge_class() -> None:
    with pytest.raises(InputError, match="unknown edge class"):
        DEFAULT.replace(robust="wheels=huber")


def test_threads_solving_on_one_map_take_turns(world: World) -> None:
    """The correction engine releases the GIL while it solves; a second thread entering the
    same map's engine got RuntimeError('Already borrowed'). Calls are serialized per map, and
    every thread gets the answer a lone call gives."""
    import threading

    (wa, la, ha, xa), (wb, lb, hb, xb) = CASES[Mode.COLLINEAR]
    h = _interpretation(
        world, Mode.COLLINEAR, _rows(world, wa, la, ha, xa), _rows(world, wb, lb, hb, xb)
    )
    moved, _ = explicit_and_backpropagate(world.map, world.map.poses, h)
    alone, _, _ = solve_all(world.map, [h], DEFAULT, moved)
    results: list[FloatArray] = []
    errors: list[BaseException] = []

    def run() -> None:
        for _ in range(4):
            try:
                results.append(solve_all(world.map, [h], DEFAULT, moved)[0])
            except BaseException as exc:  # the test reports whatever a thread met
                errors.append(exc)

    threads = [threading.Thread(target=run) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert len(results) == 12
    assert all(np.array_equal(r, alone) for r in results)
