"""Map quality metrics: the inconsistency metric (counter form == pairwise form exactly, an
independent numpy reference, a perfect map near zero, rigid-motion invariance), ATE, the
relations error, the Table 1 feature errors, and `hitl-slam metrics`."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from hitl_slam.cli import main
from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError
from hitl_slam.io.relations import read_relations
from hitl_slam.map import Map
from hitl_slam.metrics import (
    FeaturePair,
    PairKind,
    ate,
    feature_pair_errors,
    inconsistency,
    relations_error,
    table1,
)
from hitl_slam.sim.corridor import World, corridor_loop
from reference import wrap

FloatArray = NDArray[np.float64]

NO_RULES = DEFAULT.replace(metric_surface_cells=0.0, metric_min_stop=0.0, metric_grazing_deg=0.0)


def random_map(rng: np.random.Generator, scans: int) -> Map:
    poses = np.column_stack(
        [rng.uniform(-1, 1, scans), rng.uniform(-1, 1, scans), rng.uniform(-np.pi, np.pi, scans)]
    )
    points = []
    for _ in range(scans):
        beams = int(rng.integers(0, 20))
        angle = rng.uniform(-np.pi, np.pi) + 0.2 * np.arange(beams)
        r = rng.uniform(0.05, 2.5, beams)
        points.append(np.column_stack([r * np.cos(angle), r * np.sin(angle)]))
    return Map.from_poses_and_scans(poses, points)


def moved(poses: FloatArray, a: tuple[float, float, float]) -> FloatArray:
    """Every pose moved by the rigid transform ``a`` (the whole world moves with it)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.column_stack(
        [
            c * poses[:, 0] - s * poses[:, 1] + a[0],
            s * poses[:, 0] + c * poses[:, 1] + a[1],
            poses[:, 2] + a[2],
        ]
    )


# --- an independent reference of docs/ALGORITHM.md §6.1, written from the definition -------------


def _cells_crossed(a: FloatArray, b: FloatArray, width: int, height: int) -> set[tuple[int, int]]:
    """Cells (grid coordinates) whose closed square meets the segment a-b, by clipping the
    segment against each cell of its bounding box (no traversal)."""
    out = set()
    lo = np.floor(np.minimum(a, b)).astype(int)
    hi = np.floor(np.maximum(a, b)).astype(int)
    d = b - a
    for ix in range(max(lo[0], 0), min(hi[0], width - 1) + 1):
        for iy in range(max(lo[1], 0), min(hi[1], height - 1) + 1):
            t0, t1 = 0.0, 1.0
            for p, q in ((-d[0], a[0] - ix), (d[0], ix + 1 - a[0]), (-d[1], a[1] - iy)):
                t0, t1 = _clip(p, q, t0, t1)
            t0, t1 = _clip(d[1], iy + 1 - a[1], t0, t1)
            if t0 <= t1:
                out.add((ix, iy))
    return out


def _clip(p: float, q: float, t0: float, t1: float) -> tuple[float, float]:
    if p == 0:
        return (t0, t1) if q >= 0 else (1.0, 0.0)
    r = q / p
    return (max(t0, r), t1) if p < 0 else (t0, min(t1, r))


def reference_inconsistency(
    m: Map, origin: FloatArray, shape: tuple[int, int], config: Config
) -> float:
    res = config.grid_resolution
    height, width = shape
    world = m.world_points()
    free_sets, hit_sets = [], []
    for i in range(m.num_poses):
        pts = world[m.offsets[i] : m.offsets[i + 1]]
        o = m.poses[i, :2]
        cells = np.floor((pts - origin) / res).astype(int)
        hits = {(x, y) for x, y in cells.tolist() if 0 <= x < width and 0 <= y < height}
        free: set[tuple[int, int]] = set()
        for k, h in enumerate(pts):
            v = h - o
            r = math.hypot(*v)
            near = [pts[j] - h for j in (k - 1, k + 1) if 0 <= j < len(pts)]
            near = [t for t in near if t @ t > 0]
            if near:
                t = min(near, key=lambda t: float(t @ t))  # the first on a tie, as the core
                sin_inc = abs(v[0] * t[1] - v[1] * t[0]) / (r * math.hypot(*t))
            else:
                sin_inc = 1.0
            if sin_inc <= 0 or sin_inc < math.sin(math.radians(config.metric_grazing_deg)):
                continue
            stop = max(config.metric_surface_cells * res / sin_inc, config.metric_min_stop)
            if r - stop <= 0:
                continue
            end = o + v * (r - stop) / r
            free |= _cells_crossed((o - origin) / res, (end - origin) / res, width, height)
        free_sets.append(free)
        hit_sets.append(hits)
    pairs = sum(
        len(f & h) for i, f in enumerate(free_sets) for j, h in enumerate(hit_sets) if i != j
    )
    return pairs * res * res


# --- inconsistency ---------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    scans=st.integers(1, 7),
    resolution=st.sampled_from([0.05, 0.1, 0.3]),
    rules=st.sampled_from([DEFAULT, NO_RULES, DEFAULT.replace(metric_grazing_deg=40.0)]),
)
def test_counter_form_equals_pairwise_form_exactly(
    seed: int, scans: int, resolution: float, rules: Config
) -> None:
    m = random_map(np.random.default_rng(seed), scans)
    config = rules.replace(grid_resolution=resolution)
    counter = inconsistency(m, config=config)
    pairwise = inconsistency(m, config=config, pairwise=True)
    assert counter.total_m2 == pairwise.total_m2
    np.testing.assert_array_equal(counter.heat, pairwise.heat)
    np.testing.assert_array_equal(counter.origin, pairwise.origin)
    assert counter.total_m2 == pytest.approx(resolution**2 * counter.heat.sum(), rel=1e-12)
    # One thread or many: the same integers.
    assert inconsistency(m, config=config, threads=1).total_m2 == counter.total_m2
    assert inconsistency(m, config=config, threads=3).total_m2 == counter.total_m2


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    scans=st.integers(2, 5),
    rules=st.sampled_from([DEFAULT, NO_RULES, DEFAULT.replace(metric_grazing_deg=40.0)]),
)
def test_matches_an_independent_reference(seed: int, scans: int, rules: Config) -> None:
    m = random_map(np.random.default_rng(seed), scans)
    config = rules.replace(grid_resolution=0.1)
    got = inconsistency(m, config=config)
    expected = reference_inconsistency(m, got.origin, got.heat.shape, config)
    assert got.total_m2 == pytest.approx(expected, rel=1e-12, abs=1e-12)


@pytest.fixture(scope="module")
def perfect() -> World:
    return corridor_loop(range_noise=0.0, odom_xy=0.0, odom_theta=0.0, fault_at=None)


@pytest.fixture(scope="module")
def damaged() -> World:
    return corridor_loop(range_noise=0.0, odom_xy=0.0, odom_theta=0.0)


def test_a_perfect_map_scores_near_zero_and_a_damaged_one_does_not(
    perfect: World, damaged: World
) -> None:
    good = inconsistency(perfect.map).total_m2
    bad = inconsistency(damaged.map).total_m2
    # docs/ALGORITHM.md §6.2: a ground-truth corridor map scores under 3% of its damaged version.
    assert bad > 200.0
    assert good < 0.03 * bad
    # The damaged map's own scans at their true poses are the perfect map again.
    assert inconsistency(damaged.map, damaged.truth).total_m2 == pytest.approx(good)
    # Without the robustness rules the perfect map looks far worse.
    assert inconsistency(perfect.map, config=NO_RULES).total_m2 > 10 * good


@pytest.mark.parametrize(
    "transform", [(0.013, -0.021, 0.0), (31.7, -12.2, 0.7), (-40.0, 8.0, -2.6), (0.0, 0.0, np.pi)]
)
def test_rigid_motion_changes_only_grid_effects(
    perfect: World, damaged: World, transform: tuple[float, float, float]
) -> None:
    # Moving the whole map moves walls off cell boundaries: the value changes by quantization
    # only, measured at under 4% on this map (5% allowed), and the perfect map stays near zero.
    base = inconsistency(damaged.map).total_m2
    after = inconsistency(damaged.map, moved(damaged.map.poses, transform)).total_m2
    assert after == pytest.approx(base, rel=0.05)
    still_good = inconsistency(perfect.map, moved(perfect.map.poses, transform)).total_m2
    assert still_good < 0.03 * base


def test_like_reuses_the_grid_and_ignores_data_outside_it(damaged: World) -> None:
    before = inconsistency(damaged.map)
    after = inconsistency(damaged.map, damaged.truth, like=before)
    assert after.heat.shape == before.heat.shape
    np.testing.assert_array_equal(after.origin, before.origin)
    assert after.total_m2 < 0.1 * before.total_m2
    left, right, bottom, top = before.extent
    world = damaged.map.world_points()
    assert left <= world[:, 0].min()
    assert right >= world[:, 0].max()
    assert bottom <= world[:, 1].min()
    assert top >= world[:, 1].max()
    far = inconsistency(damaged.map, moved(damaged.map.poses, (500.0, 0.0, 0.0)), like=before)
    assert far.total_m2 == 0.0


def test_heat_is_only_on_cells_some_scan_hit(damaged: World) -> None:
    result = inconsistency(damaged.map)
    cells = np.floor((damaged.map.world_points() - result.origin) / result.resolution).astype(int)
    hit = np.zeros(result.heat.shape, dtype=bool)
    hit[cells[:, 1], cells[:, 0]] = True  # row = y, column = x
    assert np.count_nonzero(result.heat) > 100
    assert not np.any((result.heat > 0) & ~hit)


def test_bad_input_is_an_input_error(perfect: World) -> None:
    m = perfect.map
    with pytest.raises(InputError, match=r"shape \(325, 3\)"):
        inconsistency(m, m.poses[:-1])
    bad = m.poses.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        inconsistency(m, bad)
    with pytest.raises(InputError, match="too large"):
        inconsistency(m, config=DEFAULT.replace(grid_resolution=1e-4))
    with pytest.raises(InputError, match="grazing_deg"):
        inconsistency(m, config=DEFAULT.replace(metric_grazing_deg=120.0))
    with pytest.raises(InputError, match="threads"):
        inconsistency(m, threads=-1)
    with pytest.raises(InputError, match="small maps"):
        inconsistency(Map.from_poses_and_scans(np.zeros((2001, 3)), [[]] * 2001), pairwise=True)


# --- ATE -------------------------------------------------------------------------------------


def test_ate_hand_computed() -> None:
    truth = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, -1.0]])
    estimate = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 1.0]])
    # Unaligned: one point 2 m off among three.
    assert ate(estimate, truth, align=False) == pytest.approx(math.sqrt(4 / 3))
    # Aligned: centroids (1, 1/3) and (1, -1/3), best rotation 0, residuals -2/3, -2/3, 4/3.
    assert ate(estimate, truth) == pytest.approx(math.sqrt(8) / 3)
    shifted = np.array([[0.0, 1.0, 0.3], [1.0, 1.0, 0.1]])
    assert ate(shifted, np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), align=False) == 1.0


def test_ate_removes_exactly_a_rigid_motion() -> None:
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(50, 3))
    estimate = moved(truth, (4.0, -2.0, 2.5))
    assert ate(estimate, truth) == pytest.approx(0.0, abs=1e-12)
    assert ate(estimate, truth, align=False) > 1.0
    noisy = estimate + rng.normal(scale=0.1, size=estimate.shape)
    # Against an SVD (Kabsch) alignment written out in full.
    p, q = noisy[:, :2] - noisy[:, :2].mean(0), truth[:, :2] - truth[:, :2].mean(0)
    u, _, vt = np.linalg.svd(p.T @ q)
    r = (u @ vt).T
    expected = math.sqrt(np.mean(np.sum((p @ r.T - q) ** 2, axis=1)))
    assert ate(noisy, truth) == pytest.approx(expected, rel=1e-9)
    with pytest.raises(InputError, match="differ in length"):
        ate(truth[:3], truth)


# --- relations -------------------------------------------------------------------------------


def relations_map() -> Map:
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi / 2], [1.0, 1.0, np.pi - 0.05]])
    scans = [np.array([[1.0, 0.0], [1.0, 0.1]])] * 3
    return Map.from_poses_and_scans(poses, scans, timestamps=np.array([10.0, 11.0, 12.0]))


def test_relations_error_hand_computed(tmp_path: Path) -> None:
    path = tmp_path / "r.relations"
    # x_1^-1 x_2 = (1, 0, pi/2): exact. x_2^-1 x_3 = (1, 0, pi/2 - 0.05): given with 0.1 m and
    # 0.1 rad off. x_1^-1 x_3 = (1, 1, pi - 0.05): given yaw -pi + 0.05 (0.1 rad off across
    # the wrap) and 0.3, 0.4 m off.
    path.write_text(
        f"10.0 11.0 1.0 0.0 0 0 0 {np.pi / 2!r}\n"
        f"11.0 12.0 1.0 0.1 0 0 0 {np.pi / 2 + 0.05!r}\n"
        f"10.0 12.0 1.3 1.4 0 0 0 {-np.pi + 0.05!r}\n"
    )
    err = relations_error(relations_map(), None, read_relations(path))
    np.testing.assert_allclose(err.translation, [0.0, 0.1, 0.5], atol=1e-12)
    np.testing.assert_allclose(err.rotation_deg, np.degrees([0.0, 0.1, 0.1]), atol=1e-9)
    np.testing.assert_array_equal(err.pairs, [[0, 1], [1, 2], [0, 2]])
    assert err.count == 3
    assert err.translation_mean == pytest.approx(0.2)
    assert err.translation_std == pytest.approx(np.std([0.0, 0.1, 0.5]))
    assert err.translation_max == pytest.approx(0.5)
    assert err.rotation_mean_deg == pytest.approx(np.degrees(0.2 / 3))
    assert err.rotation_max_deg == pytest.approx(np.degrees(0.1))
    # Other poses: all three scans moved together changes nothing.
    same = relations_error(
        relations_map(), moved(relations_map().poses, (3, 4, 1)), read_relations(path)
    )
    np.testing.assert_allclose(same.translation, err.translation, atol=1e-12)


def timed_walk(rng: np.random.Generator, n: int) -> tuple[Map, FloatArray, Path]:
    """A map of ``n`` scans 0.2 s apart (jittered) whose poses are a noisy copy of a random walk,
    and relations between random pairs of scans made from the walk (the truth)."""
    truth = np.cumsum(rng.normal(0, [0.3, 0.3, 0.2], (n, 3)), axis=0)
    truth[:, 2] = wrap(truth[:, 2])
    poses = truth + rng.normal(0, [0.02, 0.02, 0.01], (n, 3))
    stamps = 1000.0 + 0.2 * np.arange(n) + rng.uniform(-0.01, 0.01, n)
    scans = [np.array([[1.0, 0.0]])] * n
    return Map.from_poses_and_scans(poses, scans, timestamps=stamps), truth, stamps


def relations_of(
    path: Path, truth: FloatArray, stamps: FloatArray, pairs: NDArray[np.int64]
) -> Path:
    lines = []
    for i, j in pairs.tolist():
        a, b = truth[i].tolist(), truth[j].tolist()
        ti, tj = float(stamps[i]), float(stamps[j])
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        yaw = math.remainder(b[2] - a[2], 2 * math.pi)
        lines.append(f"{ti!r} {tj!r} {c * dx + s * dy!r} {-s * dx + c * dy!r} 0 0 0 {yaw!r}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relations_of_a_cut_log_are_matched_or_skipped(tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 200
    full, truth, stamps = timed_walk(rng, n)
    pairs = rng.integers(0, n, (150, 2))
    relations = read_relations(relations_of(tmp_path / "r.relations", truth, stamps, pairs))
    whole = relations_error(full, None, relations)
    assert (whole.matched, whole.skipped) == (150, 0)
    np.testing.assert_array_equal(whole.pairs, pairs)
    # The log cut: its first and last 20% of scans dropped.
    keep = np.arange(n // 5, n - n // 5)
    cut = Map.from_poses_and_scans(
        full.poses[keep], [np.array([[1.0, 0.0]])] * len(keep), timestamps=stamps[keep]
    )
    inside = np.all((pairs >= keep[0]) & (pairs <= keep[-1]), axis=1)
    assert 0 < inside.sum() < 150
    err = relations_error(cut, None, relations)
    assert (err.matched, err.skipped) == (inside.sum(), 150 - inside.sum())
    assert err.rows is not None
    np.testing.assert_array_equal(err.rows, np.flatnonzero(inside))
    np.testing.assert_array_equal(keep[err.pairs], pairs[inside])
    np.testing.assert_allclose(err.translation, whole.translation[inside], rtol=1e-12)
    np.testing.assert_allclose(err.rotation_deg, whole.rotation_deg[inside], rtol=1e-12)


@pytest.mark.parametrize("seed", [3, 4])
def test_a_restamped_log_scores_with_a_larger_tolerance(tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    full, truth, stamps = timed_walk(rng, 120)
    pairs = rng.integers(0, 120, (80, 2))
    relations = read_relations(relations_of(tmp_path / "r.relations", truth, stamps, pairs))
    whole = relations_error(full, None, relations)
    assert full.timestamps is not None
    late = Map.from_poses_and_scans(
        full.poses, [np.array([[1.0, 0.0]])] * 120, timestamps=full.timestamps + 0.02
    )
    # The default tolerance (1 ms) stays: nothing of a log 20 ms late matches, and it says so.
    with pytest.raises(InputError, match=r"no scan within 0\.001 s of t1 .* larger tolerance"):
        relations_error(late, None, relations)
    err = relations_error(late, None, relations, tolerance=0.05)
    assert (err.matched, err.skipped, err.tolerance) == (80, 0, 0.05)
    np.testing.assert_array_equal(err.pairs, whole.pairs)
    np.testing.assert_array_equal(err.translation, whole.translation)
    # Nearest, not first within the tolerance: 0.15 s reaches two scans, the right one is nearer.
    wide = relations_error(late, None, relations, tolerance=0.15)
    np.testing.assert_array_equal(wide.pairs, whole.pairs)


def test_the_default_tolerance_is_one_millisecond(tmp_path: Path) -> None:
    import inspect

    from hitl_slam.io.relations import match_relations, nearest_scans

    for function in (relations_error, match_relations, nearest_scans):
        assert inspect.signature(function).parameters["tolerance"].default == 1e-3
    m = relations_map()
    path = tmp_path / "r.relations"
    path.write_text("10.0009 11.0 1.0 0.0 0 0 0 0\n10.0011 12.0 1.0 0.0 0 0 0 0\n")
    err = relations_error(m, None, read_relations(path))
    assert (err.matched, err.skipped) == (1, 1)
    with pytest.raises(InputError, match=r"relation 2: no scan within 0\.001 s"):
        match_relations(read_relations(path), m.timestamps)


def test_relations_need_timestamps(tmp_path: Path) -> None:
    path = tmp_path / "r.relations"
    path.write_text("10.0 11.0 1.0 0.0 0 0 0 0\n")
    m = relations_map()
    untimed = Map.from_poses_and_scans(m.poses, [m.points[:2]] * 3)
    with pytest.raises(InputError, match="timestamps"):
        relations_error(untimed, None, read_relations(path))
    path.write_text("10.0 13.5 1.0 0.0 0 0 0 0\n")
    with pytest.raises(InputError, match="no scan within"):
        relations_error(m, None, read_relations(path))


# --- Table 1 feature errors ------------------------------------------------------------------


def walls_map() -> tuple[Map, FloatArray, NDArray[np.int64]]:
    """Three labelled walls seen by two poses: wall 0 on y = 0, wall 1 through (2, 3) at 2
    degrees, wall 2 on x = 5; plus unlabelled clutter. Returns the map, the poses the points
    were generated under, and the labels."""
    xs = np.linspace(0.0, 4.0, 9)
    tilt = math.radians(2.0)
    world = {
        0: np.column_stack([xs, np.zeros_like(xs)]),
        1: np.column_stack([2.0 + (xs - 2.0) * math.cos(tilt), 3.0 + (xs - 2.0) * math.sin(tilt)]),
        2: np.column_stack([np.full(5, 5.0), np.linspace(0.5, 2.5, 5)]),
        -1: np.array([[2.5, 1.5]]),
    }
    poses = np.array([[1.0, 1.0, 0.3], [3.0, 2.0, -1.2]])
    scans, labels = [], []
    for i, pose in enumerate(poses):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rows = [(w, p) for w, pts in world.items() for p in pts if (w + i) % 2 == 0 or w == 0]
        local = [
            [
                c * (p[0] - pose[0]) + s * (p[1] - pose[1]),
                -s * (p[0] - pose[0]) + c * (p[1] - pose[1]),
            ]
            for _, p in rows
        ]
        scans.append(np.array(local))
        labels.extend(w for w, _ in rows)
    # The map's own poses are the true ones moved rigidly: every relation between walls holds.
    m = Map.from_poses_and_scans(moved(poses, (0.5, -0.2, 0.1)), scans)
    return m, poses, np.array(labels, dtype=np.int64)


def test_feature_pair_errors_hand_computed() -> None:
    m, poses, labels = walls_map()
    pairs = [
        FeaturePair(0, 1, PairKind.PARALLEL, 0.0),
        (0, 2, "perpendicular", 90.0),
        (1, 0, "spacing", 3.0),
    ]
    errors = feature_pair_errors(m, poses, labels, pairs)
    assert [e.pair.kind for e in errors] == [
        PairKind.PARALLEL,
        PairKind.PERPENDICULAR,
        PairKind.SPACING,
    ]
    assert errors[0].measured == pytest.approx(2.0)
    assert errors[0].error == pytest.approx(2.0)
    assert errors[1].measured == pytest.approx(90.0)
    assert errors[1].error == pytest.approx(0.0, abs=1e-9)
    # Centroid of wall 1 is 3 m from line 0; centroid of wall 0, (2, 0), is 3 cos(2 deg) from
    # line 1.
    spacing = 0.5 * (3.0 + 3.0 * math.cos(math.radians(2.0)))
    assert errors[2].measured == pytest.approx(spacing)
    assert errors[2].error == pytest.approx(3.0 - spacing)
    # Under the map's own (rigidly offset) poses the walls are still 2 degrees apart.
    own = feature_pair_errors(m, None, labels, pairs[:1])
    assert own[0].error == pytest.approx(2.0)


def test_feature_pair_errors_reject_bad_input() -> None:
    m, poses, labels = walls_map()
    with pytest.raises(InputError, match="kind one of"):
        feature_pair_errors(m, poses, labels, [(0, 1, "diagonal", 0.0)])
    with pytest.raises(InputError, match="wall 7 has 0"):
        feature_pair_errors(m, poses, labels, [(0, 7, "parallel", 0.0)])
    with pytest.raises(InputError, match="integer labels"):
        feature_pair_errors(m, poses, labels[:-1], [(0, 1, "parallel", 0.0)])


def test_table1_markdown() -> None:
    m, poses, labels = walls_map()
    pairs = [(0, 1, "parallel", 0.0), (0, 2, "perpendicular", 90.0), (0, 1, "spacing", 3.2)]
    before = feature_pair_errors(m, poses, labels, pairs)
    after = feature_pair_errors(m, poses, labels, [(0, 1, "parallel", 2.0), *pairs[1:]])
    with pytest.raises(InputError, match="same pairs"):
        table1(before, after)
    text = table1(before, before, name="walls")
    header, rule, row = text.splitlines()
    assert header.startswith("| Map | Samples A | Samples T | Input A (deg)")
    assert rule.startswith("|---|")
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:3] == ["walls", "2", "1"]
    assert float(cells[3]) == pytest.approx((before[0].error + before[1].error) / 2, abs=0.005)
    assert float(cells[4]) == pytest.approx(before[2].error, abs=0.0005)
    only_angles = table1(before[:2], before[:2])
    assert only_angles.splitlines()[2].split("|")[5].strip() == "-"


# --- CLI -------------------------------------------------------------------------------------


def write_carmen(path: Path) -> None:
    """A three-scan FLASER log in a 4 x 4 m box (180 beams over 180 degrees, exact ranges)."""
    poses = [(1.0, 1.0, 0.0), (2.0, 1.0, math.pi / 2), (2.0, 2.0, math.pi)]
    lines = []
    for k, (x, y, th) in enumerate(poses):
        angles = th + np.radians(-90.0 + np.arange(180))
        d = np.column_stack([np.cos(angles), np.sin(angles)])
        with np.errstate(divide="ignore"):
            tx = np.where(d[:, 0] > 0, (4.0 - x) / d[:, 0], -x / d[:, 0])
            ty = np.where(d[:, 1] > 0, (4.0 - y) / d[:, 1], -y / d[:, 1])
        r = np.minimum(np.abs(tx), np.abs(ty))
        ranges = " ".join(f"{v:.4f}" for v in r)
        t = 100.0 + k
        lines.append(f"FLASER 180 {ranges} {x} {y} {th} {x} {y} {th} {t} host {t}\n")
    path.write_text("".join(lines))


def test_cli_metrics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "box.log"
    write_carmen(log)
    rel = tmp_path / "box.relations"
    rel.write_text(f"100.0 101.0 1.1 0.0 0 0 0 {np.pi / 2!r}\n101.0 102.0 1.0 0.0 0 0 0 1.5707\n")
    heat = tmp_path / "heat.png"
    assert main(["metrics", str(log), "--relations", str(rel), "--heat-map", str(heat), "-q"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"{log}: 3 poses, 540 points"
    assert out[1].startswith("inconsistency: ")
    assert "cells of 0.05 m" in out[1]
    assert out[2].startswith(
        "relations: 2 matched, 0 skipped (no scan within 0.001 s), translation 0.0500 +- 0.0500 m "
        "(max 0.1000), rotation"
    )
    assert out[3] == f"wrote {heat}"
    assert heat.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_metrics_matches_the_library(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "box.log"
    write_carmen(log)
    from hitl_slam.io.carmen import read_carmen

    expected = inconsistency(read_carmen(log), config=DEFAULT.replace(grid_resolution=0.1))
    assert main(["metrics", str(log), "--resolution", "0.1"]) == 0
    assert f"inconsistency: {expected.total_m2:.3f} m^2" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--heat-map", "heat.jpg"], "PNG"),
        (["--resolution", "0"], "--resolution"),
        (["--relations", "missing.relations"], "missing.relations"),
    ],
)
def test_cli_metrics_bad_input_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    log = tmp_path / "box.log"
    write_carmen(log)
    extra = [str(tmp_path / e) if e.endswith((".jpg", ".relations")) else e for e in extra]
    assert main(["metrics", str(log), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert message in err


def test_cli_metrics_relations_that_do_not_fit_fail_before_any_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "box.log"
    write_carmen(log)
    rel = tmp_path / "other.relations"
    rel.write_text("500.0 501.0 1.0 0.0 0 0 0 0\n")
    assert main(["metrics", str(log), "--relations", str(rel)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "no scan within" in captured.err


def test_matplotlib_is_imported_only_for_the_heat_map(tmp_path: Path) -> None:
    log = tmp_path / "box.log"
    write_carmen(log)
    code = (
        "import sys\n"
        "from hitl_slam.cli import main\n"
        f"assert main(['metrics', {str(log)!r}, '-q']) == 0\n"
        "assert 'matplotlib' not in sys.modules, 'matplotlib imported without --heat-map'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert "inconsistency:" in done.stdout


LASER = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "laser"


@pytest.mark.skipif(not LASER.is_dir(), reason=f"public laser datasets not found at {LASER}")
def test_cli_metrics_scores_a_cut_and_a_restamped_freiburg_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Freiburg 079 (Kuemmerle et al. 2009, via Radish; CC-BY) with its relations: cut to its
    middle 60%, and re-stamped 20 ms late."""
    import bz2

    from hitl_slam.io.carmen import read_carmen

    with bz2.open(LASER / "fr079.clf.bz2", "rt") as f:
        lines = f.read().splitlines(keepends=True)
    lasers = [k for k, line in enumerate(lines) if line.startswith("FLASER ")]
    first, last = lasers[len(lasers) // 5], lasers[len(lasers) - len(lasers) // 5 - 1]
    cut = tmp_path / "cut.clf"
    cut.write_text(
        "".join(line for k, line in enumerate(lines) if k < lasers[0] or first <= k <= last)
    )
    late = tmp_path / "late.clf"
    shifted = []
    for line in lines:
        tokens = line.split(" ")
        if tokens[0] == "FLASER":
            n = int(tokens[1])
            tokens[8 + n] = repr(float(tokens[8 + n]) + 0.02)
        shifted.append(" ".join(tokens))
    late.write_text("".join(shifted))
    relations_path = LASER / "fr079.relations"
    relations = read_relations(relations_path)
    whole = relations_error(read_carmen(LASER / "fr079.clf.bz2"), None, relations)
    assert (whole.matched, whole.skipped) == (len(relations), 0)

    def score(log: Path, *extra: str) -> tuple[int, str]:
        code = main(["metrics", str(log), "--relations", str(relations_path), "-q", *extra])
        captured = capsys.readouterr()
        return code, (captured.out.splitlines() or [captured.err])[-1]

    # Cut: the relations with both scans kept are scored as on the whole log, the rest skipped.
    stamps = read_carmen(cut).timestamps
    assert stamps is not None
    inside = (np.minimum(relations.t1, relations.t2) >= stamps.min() - 1e-3) & (
        np.maximum(relations.t1, relations.t2) <= stamps.max() + 1e-3
    )
    assert 0.3 < inside.mean() < 0.9
    code, line = score(cut, "--resolution", "0.5")
    assert code == 0
    mean = np.mean(whole.translation[inside])
    assert line.startswith(
        f"relations: {inside.sum()} matched, {len(relations) - inside.sum()} skipped (no scan "
        f"within 0.001 s), translation {mean:.4f} +- "
    ), line
    # Re-stamped 20 ms late: refused at the default tolerance, scored as the original with 50 ms.
    code, line = score(late, "--resolution", "0.5")
    assert code == 2
    assert "no scan within 0.001 s" in line
    assert "--tolerance" in line
    code, line = score(late, "--resolution", "0.5", "--tolerance", "0.05")
    assert code == 0
    assert line.startswith(
        f"relations: {len(relations)} matched, 0 skipped (no scan within 0.05 s), translation "
        f"{whole.translation_mean:.4f} +- {whole.translation_std:.4f} m"
    ), line


def test_cli_metrics_tolerance_goes_with_relations(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "box.log"
    write_carmen(log)
    assert main(["metrics", str(log), "--tolerance", "0.01"]) == 2
    assert "--tolerance goes with --relations" in capsys.readouterr().err
    rel = tmp_path / "box.relations"
    rel.write_text("100.0 101.0 1.1 0.0 0 0 0 0\n")
    assert main(["metrics", str(log), "--relations", str(rel), "--tolerance", "-1"]) == 2
    assert "--tolerance must be a number of seconds >= 0" in capsys.readouterr().err
