"""Tests of the interpretation of drawn corrections (docs/ALGORITHM.md §3): EM accuracy and clutter
rejection on synthetic corridors, the grid index against brute force, drawing-direction invariance,
every pair rule and rejection, and the Rust kernels against numpy written from the formulas.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Correction, Interpretation, Mode, Segment
from hitl_slam.errors import CorrectionRejected, InputError
from hitl_slam.interpret import interpret
from hitl_slam.map import Map

FloatArray = NDArray[np.float64]

WALL_A: Segment = ((0.0, 0.0), (12.0, 0.0))  # corridor, right side going +x
WALL_B: Segment = ((0.0, 3.0), (12.0, 3.0))  # corridor, other side
WALL_C: Segment = ((28.0, 18.0), (42.0, 18.0))  # seen only on the excursion
SENSOR_RANGE = 4.0  # [m]
SPACING = 0.05  # [m] between wall points
NOISE = 0.015  # [m] across the wall
CLUTTER_PER_WALL = 12  # points per pose, uniform in a +-0.3 m strip around each visible wall
BAND = DEFAULT.candidate_band * DEFAULT.sigma_h


@dataclass
class World:
    map: Map
    true_world: FloatArray  # (P, 2) each point where it really is
    labels: NDArray[np.int64]  # (P,) wall index, or -1 for clutter
    error: tuple[float, float, float]  # (dx, dy, dtheta) applied to the poses from `first_wrong`
    first_wrong: int

    def displayed(self, p: tuple[float, float], pose_index: int) -> tuple[float, float]:
        """Where a true world point seen from `pose_index` shows up on the map."""
        if pose_index < self.first_wrong:
            return p
        q = _apply(self.error, np.array([p]))[0]
        return (float(q[0]), float(q[1]))

    def displayed_segment(self, seg: Segment, pose_index: int) -> Segment:
        return (self.displayed(seg[0], pose_index), self.displayed(seg[1], pose_index))


PIVOT = np.array([6.0, 1.5])


def _apply(error: tuple[float, float, float], pts: FloatArray) -> FloatArray:
    """The map error: a rotation by dtheta about PIVOT, then a shift."""
    dx, dy, dth = error
    c, s = math.cos(dth), math.sin(dth)
    q = pts - PIVOT
    return (
        np.stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]], axis=1) + PIVOT + [dx, dy]
    )


def _observe(
    pose: FloatArray, walls: list[Segment], rng: np.random.Generator
) -> tuple[FloatArray, NDArray[np.int64]]:
    """World points seen from `pose`: wall samples within range with noise, and clutter."""
    pts, labels = [], []
    for k, (p0, p1) in enumerate(walls):
        a, b = np.array(p0), np.array(p1)
        length = float(np.hypot(*(b - a)))
        d = (b - a) / length
        n = np.array([-d[1], d[0]])
        base = np.arange(0.0, length, SPACING)
        t = base + rng.uniform(0.0, SPACING, base.size)
        q = a + t[:, None] * d
        seen = np.hypot(*(q - pose[:2]).T) < SENSOR_RANGE
        if not seen.any():
            continue
        q = q[seen] + rng.normal(0.0, NOISE, (int(seen.sum()), 1)) * n
        pts.append(q)
        labels.append(np.full(len(q), k))
        ts = t[seen]
        tc = rng.uniform(ts.min(), ts.max(), CLUTTER_PER_WALL)
        across = rng.uniform(-0.3, 0.3, CLUTTER_PER_WALL)
        pts.append(a + tc[:, None] * d + across[:, None] * n)
        labels.append(np.full(CLUTTER_PER_WALL, -1))
    if not pts:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    return np.concatenate(pts), np.concatenate(labels).astype(np.int64)


def corridor(
    n1: int = 40,
    n_excursion: int = 30,
    n2: int = 40,
    error: tuple[float, float, float] = (0.2, 0.8, math.radians(2.0)),
    seed: int = 0,
) -> World:
    """A robot drives down a corridor (walls A and B, poses 0..n1-1), along wall C far away, then
    back up the corridor. The poses from the excursion on carry `error`, so the second pass shows
    the corridor's walls a second time, moved."""
    rng = np.random.default_rng(seed)
    visit1 = np.stack([np.linspace(1.0, 11.0, n1), np.full(n1, 1.5), np.zeros(n1)], axis=1)
    exc = np.stack(
        [np.linspace(30.0, 40.0, n_excursion), np.full(n_excursion, 19.5), np.zeros(n_excursion)],
        axis=1,
    )
    visit2 = np.stack([np.linspace(11.0, 1.0, n2), np.full(n2, 1.5), np.full(n2, math.pi)], axis=1)
    true = np.concatenate([visit1, exc, visit2])
    scans, truths, labels = [], [], []
    est = true.copy()
    first_wrong = n1
    est[first_wrong:, :2] = _apply(error, true[first_wrong:, :2])
    est[first_wrong:, 2] = true[first_wrong:, 2] + error[2]
    for pose in true:
        world, lab = _observe(pose, [WALL_A, WALL_B, WALL_C], rng)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        q = world - pose[:2]
        scans.append(np.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1]], axis=1))
        truths.append(world)
        labels.append(lab)
    m = Map.from_poses_and_scans(est, scans)
    return World(m, np.concatenate(truths), np.concatenate(labels), error, first_wrong)


@pytest.fixture(scope="module")
def world() -> World:
    return corridor()


def _run(
    w: World, a: Segment, b: Segment, mode: Mode = Mode.COLLINEAR, **config: float
) -> Interpretation:
    cfg = DEFAULT.replace(**config) if config else DEFAULT
    return interpret(w.map, w.map.poses, Correction.make(a, b, mode), cfg)


def _global(w: World, rows: NDArray[np.int64]) -> NDArray[np.int64]:
    return w.map.offsets[rows[:, 0]] + rows[:, 1]


def _line_angle(seg: Segment) -> float:
    (x0, y0), (x1, y1) = seg
    return math.atan2(y1 - y0, x1 - x0)


def _angle_mod_pi(a: float) -> float:
    r = a % math.pi
    return min(r, math.pi - r)


def _sloppy(seg: Segment, rng: np.random.Generator, deg: float, noise: float) -> Segment:
    """`seg` turned by `deg` about its middle, each end moved `noise` metres in some direction."""
    p = np.array(seg)
    mid = p.mean(axis=0)
    th = math.radians(deg)
    c, s = math.cos(th), math.sin(th)
    q = (p - mid) @ np.array([[c, s], [-s, c]]) + mid
    ang = rng.uniform(0, 2 * math.pi, 2)
    q += noise * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    return ((float(q[0, 0]), float(q[0, 1])), (float(q[1, 0]), float(q[1, 1])))


A_FIRST: Segment = ((3.0, 0.0), (7.0, 0.0))  # wall A as seen on the first pass


# --- EM accuracy and clutter ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_em_recovers_the_wall_from_a_sloppy_drawing(world: World, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    sign = 1 if seed % 2 else -1
    a = _sloppy(A_FIRST, rng, sign * 2.0, 0.05)
    b_true = world.displayed_segment(A_FIRST, world.first_wrong + 1)
    b = _sloppy(b_true, rng, -sign * 2.0, 0.05)
    h = _run(world, a, b)
    assert not h.swapped
    # Line a is the true wall y = 0: within 0.2 degree and 1 cm over its extent.
    assert _angle_mod_pi(_line_angle(h.line_a)) < math.radians(0.2)
    assert max(abs(h.line_a[0][1]), abs(h.line_a[1][1])) < 0.01
    # Line b is wall A as the second pass shows it.
    want = _line_angle(b_true)
    assert _angle_mod_pi(_line_angle(h.line_b) - want) < math.radians(0.2)
    n = np.array([-math.sin(want), math.cos(want)])
    for end in h.line_b:
        assert abs(float(n @ (np.array(end) - np.array(b_true[0])))) < 0.01
    # The extent spans the drawing (clipped to it plus the band).
    xs = sorted([h.line_a[0][0], h.line_a[1][0]])
    lo, hi = min(a[0][0], a[1][0]), max(a[0][0], a[1][0])
    assert lo - BAND - 1e-9 <= xs[0] < lo + 0.2
    assert hi - 0.2 < xs[1] <= hi + BAND + 1e-9
    assert h.iterations[0] >= 1
    assert all(math.isfinite(v) for v in h.log_likelihood)


def test_clutter_is_rejected_and_the_wall_is_kept(world: World) -> None:
    b = world.displayed_segment(A_FIRST, world.first_wrong + 1)
    h = _run(world, A_FIRST, b)
    idx = _global(world, h.s_a)
    true_y = world.true_world[idx, 1]
    # Nothing far from the wall; the clutter that was selected lies on it anyway.
    assert np.all(np.abs(true_y) < 0.1)
    clutter = world.labels == -1
    near_band = (
        clutter & (np.abs(world.true_world[:, 1]) > 0.12) & (np.abs(world.true_world[:, 1]) < 0.3)
    )
    assert near_band.sum() > 50  # the fixture really puts clutter in the band
    assert not np.isin(np.flatnonzero(near_band), idx).any()
    # Nearly every wall-A point of the first pass inside the drawing is selected.
    owner = world.map.pose_of_point()
    x = world.true_world[:, 0]
    wanted = (world.labels == 0) & np.isin(owner, h.x_a) & (x > 3.0) & (x < 7.0)
    assert np.isin(np.flatnonzero(wanted), idx).mean() > 0.97
    # Rows are (pose, index within that pose's scan).
    counts = np.diff(world.map.offsets)
    assert np.all(h.s_a[:, 1] < counts[h.s_a[:, 0]])
    assert np.all(h.s_a[:, 1] >= 0)
    assert np.array_equal(h.x_a, np.unique(h.s_a[:, 0]))
    assert np.array_equal(h.x_b, np.unique(h.s_b[:, 0]))
    assert h.s_a.dtype == np.int64
    assert h.x_a.dtype == np.int64


# --- the spatial index ---------------------------------------------------------------------------


def _brute_distance(points: FloatArray, seg: FloatArray) -> FloatArray:
    a, b = seg
    d = b - a
    t = np.clip(((points - a) @ d) / (d @ d), 0.0, 1.0)
    return np.asarray(np.hypot(*(points - (a + t[:, None] * d)).T))


coords = st.floats(-20.0, 20.0, allow_nan=False, width=64)
lattice = st.integers(-40, 40).map(lambda k: k * 0.5)


@settings(max_examples=300, deadline=None)
@given(
    pts=st.lists(st.tuples(st.one_of(coords, lattice), st.one_of(coords, lattice)), max_size=300),
    seg=st.tuples(coords, coords, st.one_of(coords, lattice), st.one_of(coords, lattice)),
    band=st.floats(0.01, 6.0),
)
def test_index_returns_exactly_the_brute_force_set(
    pts: list[tuple[float, float]], seg: tuple[float, float, float, float], band: float
) -> None:
    points = np.array(pts, dtype=np.float64).reshape(-1, 2)
    segment = np.array(seg, dtype=np.float64).reshape(2, 2)
    if np.hypot(*(segment[1] - segment[0])) < 1e-6:
        with pytest.raises(InputError):
            _core.segment_candidates(points, segment, band)
        return
    got = _core.segment_candidates(points, segment, band)
    assert np.array_equal(got, _core.segment_candidates(points, segment, band, use_index=False))
    # Against numpy's own distance: equal except within rounding of the band's edge.
    dist = _brute_distance(points, segment)
    sure = np.abs(dist - band) > 1e-9
    want = np.flatnonzero(dist <= band)
    assert np.array_equal(np.isin(np.flatnonzero(sure), got), np.isin(np.flatnonzero(sure), want))
    assert np.all(np.diff(got) > 0)


def test_index_on_a_large_random_map() -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform(-100, 100, (200_000, 2))
    for _ in range(20):
        seg = rng.uniform(-100, 100, (2, 2))
        got = _core.segment_candidates(points, seg, 0.3)
        want = np.flatnonzero(_brute_distance(points, seg) <= 0.3)
        assert np.array_equal(got, want)


# --- drawing direction ---------------------------------------------------------------------------


def test_result_does_not_depend_on_drawing_direction(world: World) -> None:
    rng = np.random.default_rng(8)
    a = _sloppy(A_FIRST, rng, 1.5, 0.04)
    b = _sloppy(world.displayed_segment(A_FIRST, world.first_wrong + 1), rng, -1.0, 0.04)
    ref = _run(world, a, b)

    def rev(s: Segment) -> Segment:
        return (s[1], s[0])

    for aa, bb in [(rev(a), b), (a, rev(b)), (rev(a), rev(b))]:
        h = _run(world, aa, bb)
        for key in ("s_a", "s_b", "x_a", "x_b"):
            assert np.array_equal(getattr(h, key), getattr(ref, key)), key
        for got, want in [(h.line_a, ref.line_a), (h.line_b, ref.line_b)]:
            g, r = np.array(got), np.array(want)
            assert min(np.abs(g - r).max(), np.abs(g[::-1] - r).max()) < 1e-9
        assert h.swapped == ref.swapped


# --- rejections ----------------------------------------------------------------------------------


def test_zero_length_segment_is_rejected(world: World) -> None:
    with pytest.raises(CorrectionRejected, match="segment a has zero length"):
        _run(world, ((3.0, 0.0), (3.0, 0.0)), A_FIRST)
    with pytest.raises(CorrectionRejected, match="segment b has zero length"):
        _run(world, A_FIRST, ((5.0, 0.0), (5.0 + 1e-8, 0.0)))


def test_nan_coordinates_are_rejected(world: World) -> None:
    bad = Correction(Mode.COLOCATION, ((math.nan, 0.0), (7.0, 0.0)), A_FIRST)
    with pytest.raises(CorrectionRejected, match="segment a has a non-finite coordinate"):
        interpret(world.map, world.map.poses, bad)
    bad = Correction(Mode.COLOCATION, A_FIRST, ((3.0, 0.0), (math.inf, 0.0)))
    with pytest.raises(CorrectionRejected, match="segment b has a non-finite coordinate"):
        interpret(world.map, world.map.poses, bad)


def test_empty_segment_is_rejected(world: World) -> None:
    nowhere: Segment = ((3.0, 10.0), (7.0, 10.0))
    with pytest.raises(
        CorrectionRejected, match="no observations under segment b; draw along a wall"
    ):
        _run(world, A_FIRST, nowhere)
    with pytest.raises(CorrectionRejected, match="no observations under segment a;"):
        _run(world, nowhere, A_FIRST)
    with pytest.raises(CorrectionRejected, match="segments a and b; draw along a wall"):
        _run(world, nowhere, ((20.0, 10.0), (25.0, 10.0)))


def test_same_observations_are_rejected(world: World) -> None:
    with pytest.raises(CorrectionRejected, match="select the same observations"):
        _run(world, A_FIRST, A_FIRST)
    with pytest.raises(CorrectionRejected, match="select the same observations"):
        _run(world, A_FIRST, (A_FIRST[1], A_FIRST[0]))


def test_same_visit_is_rejected() -> None:
    # One pass only: walls A and B are seen from exactly the same poses.
    w = corridor(n1=30, n_excursion=0, n2=0, error=(0.0, 0.0, 0.0))
    with pytest.raises(CorrectionRejected, match="seen from the same visit"):
        _run(w, A_FIRST, ((3.0, 3.0), (7.0, 3.0)), Mode.PARALLEL)


def _alternating(n: int = 40) -> Map:
    """Even poses see only wall A, odd poses only wall B: the two sets interleave in time."""
    rng = np.random.default_rng(3)
    poses = np.stack([np.linspace(1.0, 11.0, n), np.full(n, 1.5), np.zeros(n)], axis=1)
    scans = []
    for i, pose in enumerate(poses):
        world, _ = _observe(pose, [WALL_A if i % 2 == 0 else WALL_B], rng)
        scans.append(world - pose[:2])
    return Map.from_poses_and_scans(poses, scans)


def test_interleaved_sets_are_rejected_naming_both_ranges() -> None:
    m = _alternating()
    drawn = Correction.make(A_FIRST, ((3.0, 3.0), (7.0, 3.0)), Mode.PARALLEL)
    with pytest.raises(CorrectionRejected, match="interleave") as info:
        interpret(m, m.poses, drawn)
    msg = str(info.value)
    # Both ranges are named: even poses for a, odd poses for b, all within the 40 poses.
    ranges = [(int(lo), int(hi)) for lo, hi in re.findall(r"poses (\d+)-(\d+)", msg)]
    assert "segment a is seen from poses" in msg
    assert len(ranges) == 2
    (a0, a1), (b0, b1) = ranges
    assert (a0 % 2, a1 % 2, b0 % 2, b1 % 2) == (0, 0, 1, 1)
    assert a0 < b1 <= 39
    assert b0 < a1


def test_bad_poses_and_config_are_input_errors(world: World) -> None:
    drawn = Correction.make(A_FIRST, A_FIRST, Mode.COLLINEAR)
    with pytest.raises(InputError, match="shape"):
        interpret(world.map, world.map.poses[:-1], drawn)
    poses = world.map.poses.copy()
    poses[3, 0] = math.nan
    with pytest.raises(InputError, match="non-finite"):
        interpret(world.map, poses, drawn)
    with pytest.raises(InputError):
        interpret(world.map, world.map.poses, drawn, DEFAULT.replace(candidate_band=0.0))


# --- the pair rules ------------------------------------------------------------------------------


def test_swap_rule(world: World) -> None:
    later = world.displayed_segment(A_FIRST, world.first_wrong + 1)
    kept = _run(world, A_FIRST, later)
    swapped = _run(world, later, A_FIRST)
    assert not kept.swapped
    assert swapped.swapped
    assert kept.x_a.max() < kept.x_b.min()
    assert swapped.x_a.max() < swapped.x_b.min()
    # Swapping renames a and b, nothing else.
    assert np.array_equal(kept.s_a, swapped.s_a)
    assert np.array_equal(kept.s_b, swapped.s_b)
    assert kept.line_a == swapped.line_a
    assert kept.line_b == swapped.line_b
    assert swapped.iterations == kept.iterations
    assert any("swapped" in n for n in swapped.notes)
    # a is the first pass, b the second.
    assert kept.x_a.max() < world.first_wrong <= kept.x_b.min()


@pytest.mark.parametrize(("n1", "n2"), [(60, 30), (30, 60)])
def test_one_visit_per_segment(n1: int, n2: int) -> None:
    # No map error: both passes show wall A in the same place, and one drawing covers both.
    w = corridor(n1=n1, n_excursion=30, n2=n2, error=(0.0, 0.0, 0.0), seed=5)
    wall_c: Segment = ((32.0, 18.0), (38.0, 18.0))
    h = _run(w, A_FIRST, wall_c)
    first = np.arange(n1)
    second = np.arange(n1 + 30, n1 + 30 + n2)
    denser, other = (first, second) if n1 > n2 else (second, first)
    wall_side = h.x_a if not h.swapped else h.x_b
    rows = h.s_a if not h.swapped else h.s_b
    assert np.all(np.isin(wall_side, denser))
    assert not np.isin(rows[:, 0], other).any()
    assert h.swapped == (n2 > n1)  # the kept visit of wall A comes after wall C
    note = next(n for n in h.notes if "visits" in n)
    assert f"kept poses {wall_side[0]}-{wall_side[-1]}" in note
    assert "dropped poses" in note


def test_poses_below_the_threshold_are_dropped(world: World) -> None:
    b = world.displayed_segment(A_FIRST, world.first_wrong + 1)
    everything = _run(world, A_FIRST, b, min_points_per_pose=1)
    owners, counts = np.unique(everything.s_a[:, 0], return_counts=True)
    t_p = int(np.median(counts))
    assert counts.min() < t_p  # some poses fall below it
    h = _run(world, A_FIRST, b, min_points_per_pose=t_p)
    assert np.array_equal(h.x_a, owners[counts >= t_p])
    assert np.all(np.isin(h.s_a[:, 0], h.x_a))
    # S is exactly the unfiltered S restricted to the surviving poses.
    keep = np.isin(everything.s_a[:, 0], h.x_a)
    assert np.array_equal(h.s_a, everything.s_a[keep])
    # The default T_p drops the poses that see only the end of the drawing.
    default = _run(world, A_FIRST, b)
    assert default.x_a.size <= everything.x_a.size


# --- the Rust kernels against numpy --------------------------------------------------------------


def _responsibilities(d: FloatArray, pi: float, sigma: float, band: float) -> FloatArray:
    g = np.exp(-0.5 * (d / sigma) ** 2) / (math.sqrt(2 * math.pi) * sigma)
    return np.asarray(pi * g / (pi * g + (1 - pi) / (2 * band)))


def _weighted_pca(points: FloatArray, w: FloatArray) -> tuple[FloatArray, float]:
    c = (w[:, None] * points).sum(axis=0) / w.sum()
    q = points - c
    scatter = (w[:, None, None] * q[:, :, None] * q[:, None, :]).sum(axis=0)
    _, vecs = np.linalg.eigh(scatter)
    n = vecs[:, 0]  # smallest eigenvalue: the normal
    if n[0] < 0 or (n[0] == 0 and n[1] < 0):
        n = -n
    return n, float(n @ c)


def _random_scene(rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    phi = rng.uniform(-math.pi, math.pi)
    d = np.array([math.cos(phi), math.sin(phi)])
    n = np.array([-d[1], d[0]])
    origin = rng.uniform(-30, 30, 2)
    t = rng.uniform(0, 5, 400)
    wall = origin + t[:, None] * d + rng.normal(0, 0.02, (400, 1)) * n
    clutter = origin + rng.uniform(-1, 6, (150, 1)) * d + rng.uniform(-0.5, 0.5, (150, 1)) * n
    seg = np.array([origin + 0.5 * d, origin + 4.5 * d]) + rng.normal(0, 0.05, (2, 2))
    return np.concatenate([wall, clutter]), seg


EM_ARGS = {
    "band": 0.3,
    "sigma_em": 0.03,
    "pi0": 0.5,
    "tol_m": 1e-4,
    "tol_rad": 1e-4,
    "tol_pi": 1e-4,
}


@pytest.mark.parametrize("seed", range(8))
def test_rust_kernels_match_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    points, seg = _random_scene(rng)
    # Zero iterations: the candidates and the E-step at the drawn line.
    (zero,) = _core.em_fit(points, seg[None], max_iterations=0, **EM_ARGS)
    assert np.array_equal(zero.candidates, np.flatnonzero(_brute_distance(points, seg) <= 0.3))
    d = seg[1] - seg[0]
    n = np.array([-d[1], d[0]]) / np.hypot(*d)
    dist = (points[zero.candidates] - seg.mean(axis=0)) @ n
    w0 = _responsibilities(dist, 0.5, 0.03, 0.3)
    np.testing.assert_allclose(zero.weights, w0, rtol=1e-12, atol=1e-14)
    ll = np.log(
        0.5 * np.exp(-0.5 * (dist / 0.03) ** 2) / (math.sqrt(2 * math.pi) * 0.03) + 0.5 / 0.6
    )
    assert zero.log_likelihood == pytest.approx(ll.sum(), rel=1e-12)
    # line_fit is the weighted PCA.
    cand = points[zero.candidates]
    phi, rho, _ = _core.line_fit(cand, w0, seg, 0.3)
    n_ref, rho_ref = _weighted_pca(cand, w0)
    assert math.cos(phi) == pytest.approx(n_ref[0], abs=1e-10)
    assert math.sin(phi) == pytest.approx(n_ref[1], abs=1e-10)
    assert rho == pytest.approx(rho_ref, abs=1e-9)
    # One iteration: M-step from w0, then the E-step at the new line with pi = mean(w0).
    (one,) = _core.em_fit(points, seg[None], max_iterations=1, **EM_ARGS)
    assert one.iterations == 1
    assert one.phi == pytest.approx(phi, abs=1e-12)
    assert one.rho == pytest.approx(rho, abs=1e-9)
    assert one.mixing == pytest.approx(w0.mean(), rel=1e-12)
    w1 = _responsibilities(cand @ n_ref - rho_ref, float(w0.mean()), 0.03, 0.3)
    np.testing.assert_allclose(one.weights, w1, rtol=1e-8, atol=1e-12)
    # The full run agrees with a numpy EM written from the same formulas.
    (full,) = _core.em_fit(points, seg[None], max_iterations=50, **EM_ARGS)
    nv, r, pi = n, float(n @ seg.mean(axis=0)), 0.5
    for _ in range(full.iterations):
        w = _responsibilities(cand @ nv - r, pi, 0.03, 0.3)
        nv_new, r = _weighted_pca(cand, w)
        nv = nv_new
        pi = float(np.clip(w.mean(), 1e-3, 1 - 1e-3))
    assert math.cos(full.phi) == pytest.approx(nv[0], abs=1e-9)
    assert full.rho == pytest.approx(r, abs=1e-9)
    assert full.converged
    assert full.num_inliers == int((full.weights > 0.5).sum())


def test_em_fit_scans_matches_em_fit_on_world_points(world: World) -> None:
    segs = np.array([A_FIRST, world.displayed_segment(A_FIRST, world.first_wrong + 1)])
    args = {**EM_ARGS, "max_iterations": 50}
    by_scans = _core.em_fit_scans(
        world.map.poses, world.map.points, world.map.offsets, segs, **args
    )
    by_world = _core.em_fit(world.map.world_points(), segs, **args)
    for f, g in zip(by_scans, by_world, strict=True):
        assert np.array_equal(f.candidates, g.candidates)
        np.testing.assert_allclose(f.weights, g.weights, atol=1e-9)
        assert f.phi == pytest.approx(g.phi, abs=1e-9)
        assert f.rho == pytest.approx(g.rho, abs=1e-9)
        assert f.extent.shape == (2, 2)


def test_core_rejects_bad_arrays_with_input_errors() -> None:
    pts = np.zeros((5, 2))
    seg = np.array([[0.0, 0.0], [1.0, 0.0]])
    args = {**EM_ARGS, "max_iterations": 5}
    with pytest.raises(InputError, match=r"shape \(n, 2\)"):
        _core.em_fit(np.zeros((5, 3)), seg[None], **args)
    with pytest.raises(InputError, match=r"\(S, 2, 2\)"):
        _core.em_fit(pts, np.zeros((1, 3, 2)), **args)
    with pytest.raises(InputError, match="not finite"):
        _core.em_fit(np.array([[0.0, math.nan]]), seg[None], **args)
    with pytest.raises(InputError, match="mixing"):
        _core.em_fit(pts, seg[None], **{**args, "pi0": 1.0})
    with pytest.raises(InputError, match="offsets"):
        _core.em_fit_scans(np.zeros((2, 3)), pts, np.array([0, 2]), seg[None], **args)
    with pytest.raises(InputError, match="weights"):
        _core.line_fit(pts, np.ones(4), seg, 0.3)
    # A non-contiguous view is read correctly (copied, not misread).
    big = np.zeros((5, 4))
    big[:, 2] = np.linspace(0, 1, 5)
    got = _core.segment_candidates(big[:, 2:], seg, 0.1)
    assert np.array_equal(got, np.arange(5))


@pytest.mark.parametrize("sigma_h", [1e6, 1e200])
def test_an_absurd_drawing_uncertainty_is_an_input_error_not_a_crash(
    world: World, sigma_h: float
) -> None:
    """A sigma_h of kilometres made snapping ask for an offset histogram of 1e201 bins, and the
    core's allocation failed ('capacity overflow', an internal error); it is a plain
    InputError, and the map is untouched."""
    rng = np.random.default_rng(3)
    a = _sloppy(A_FIRST, rng, 1.5, 0.04)
    b = _sloppy(world.displayed_segment(A_FIRST, world.first_wrong + 1), rng, -1.0, 0.04)
    before = world.map.poses.copy()
    drawn = Correction.make(a, b, Mode.COLLINEAR, sigma_h=sigma_h)
    with pytest.raises((InputError, CorrectionRejected), match=r"too wide|sigma_h"):
        interpret(world.map, world.map.poses, drawn, DEFAULT)
    assert np.array_equal(world.map.poses, before)
