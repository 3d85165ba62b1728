"""hitl_slam.geometry, the package's one plane geometry, against the tests' reference
(tests/reference.py) and the Rust core's conventions: angles in (-pi, pi], lines with rho >= 0."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from hitl_slam import _core
from hitl_slam.geometry import (
    between,
    chain_steps,
    compose,
    compose_rows,
    fit_line,
    integrate,
    invert,
    line_angle,
    rotate,
    to_robot,
    to_world,
    transform,
    wrap,
)
from reference import between as ref_between
from reference import compose as ref_compose
from reference import fit_line as ref_fit_line
from reference import inverse as ref_inverse
from reference import transform_points as ref_transform
from reference import wrap as ref_wrap

FloatArray = NDArray[np.float64]
PI = math.pi


def poses(rng: np.random.Generator, k: int, spread: float = 10.0) -> FloatArray:
    p = rng.uniform(-spread, spread, (k, 3))
    p[:, 2] = rng.uniform(-PI, PI, k)
    return p


def in_range(theta: FloatArray) -> bool:
    return bool(np.all((theta > -PI) & (theta <= PI)))


def same_heading(a: FloatArray, b: FloatArray, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(np.abs(ref_wrap(np.asarray(a) - np.asarray(b))), 0.0, atol=atol)


# --- wrap -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("angle", "expected"),
    [
        (PI, PI),
        (-PI, PI),
        (3 * PI, PI),
        (-3 * PI, PI),
        (0.0, 0.0),
        (2 * PI, 0.0),
        (-2 * PI, 0.0),
        (PI / 2, PI / 2),
        (-PI / 2, -PI / 2),
        (1.5 * PI, -0.5 * PI),
        (-1.5 * PI, 0.5 * PI),
    ],
)
def test_wrap_is_half_open_minus_pi_exclusive_pi_inclusive(angle: float, expected: float) -> None:
    for value in (wrap(angle), float(wrap(np.array([angle]))[0])):
        assert isinstance(value, float)
        assert value == pytest.approx(expected, abs=1e-15)
        assert -PI < value <= PI
    assert wrap(angle) == _core.wrap_angle(angle)  # the Rust core's, to the bit


def test_wrap_keeps_angles_in_range_bit_for_bit_and_the_sign_of_zero() -> None:
    inside = np.array([PI, -PI + 1e-15, 1e-300, -1e-300, 0.1, -3.0, 2.5])
    np.testing.assert_array_equal(wrap(inside), inside)
    assert math.copysign(1.0, wrap(-0.0)) == -1.0
    assert math.copysign(1.0, float(wrap(np.array([-0.0]))[0])) == -1.0


@pytest.mark.parametrize("huge", [1e6, -1e6, 1e12, -1e15, 1e100, -1e300, 1.7e308])
def test_wrap_of_huge_angles_agrees_with_the_rust_core(huge: float) -> None:
    value = wrap(huge)
    assert -PI < value <= PI
    assert value == _core.wrap_angle(huge)
    assert float(wrap(np.array([huge]))[0]) == value


def test_wrap_is_vectorised_and_matches_the_reference_and_the_core() -> None:
    rng = np.random.default_rng(3)
    angles = np.concatenate(
        [
            rng.uniform(-50.0, 50.0, 2000),
            rng.uniform(-1e9, 1e9, 200),
            np.arange(-9, 10) * PI,
            np.arange(-9, 10) * PI / 2,
        ]
    )
    got = wrap(angles)
    assert got.shape == angles.shape
    assert got.dtype == np.float64
    assert in_range(got)
    np.testing.assert_array_equal(got, [_core.wrap_angle(a) for a in angles.tolist()])
    np.testing.assert_array_equal(got, [wrap(a) for a in angles.tolist()])  # scalar path
    # The reference's own formula agrees up to rounding (the same heading).
    same_heading(got, ref_wrap(angles), atol=1e-6)
    np.testing.assert_allclose(got[:2000], ref_wrap(angles[:2000]), atol=1e-13)
    # Any shape; the input is not modified.
    grid = angles[:2000].reshape(40, 50)
    before = grid.copy()
    assert wrap(grid).shape == (40, 50)
    np.testing.assert_array_equal(grid, before)
    assert isinstance(wrap(np.float64(7.0)), float)
    assert isinstance(wrap(np.array(7.0)), float)


def test_wrap_of_non_finite_angles_is_nan() -> None:
    assert math.isnan(wrap(math.inf))
    assert math.isnan(wrap(-math.inf))
    assert math.isnan(wrap(math.nan))
    assert np.isnan(wrap(np.array([math.inf, -math.inf, math.nan]))).all()


# --- SE(2) ------------------------------------------------------------------------------------


def test_compose_between_invert_match_the_reference() -> None:
    rng = np.random.default_rng(11)
    a, b = poses(rng, 500), poses(rng, 500)
    np.testing.assert_allclose(compose(a, b), ref_compose(a, b), atol=1e-12)
    np.testing.assert_allclose(compose_rows(a, b), ref_compose(a, b), atol=1e-12)
    np.testing.assert_allclose(between(a, b), ref_between(a, b), atol=1e-12)
    np.testing.assert_allclose(invert(a), ref_inverse(a), atol=1e-12)
    for out in (compose(a, b), between(a, b), invert(a)):
        assert in_range(out[:, 2])
    # One pose against many rows, either way round, and one against one.
    np.testing.assert_allclose(compose(a[0], b), ref_compose(a[0], b), atol=1e-12)
    np.testing.assert_allclose(compose(a, b[0]), ref_compose(a, b[0]), atol=1e-12)
    np.testing.assert_allclose(between(a[0], b), ref_between(a[0], b), atol=1e-12)
    assert compose(a[0], b[0]).shape == (3,)
    np.testing.assert_allclose(compose(a[0], b[0]), ref_compose(a[0], b[0])[0], atol=1e-12)
    np.testing.assert_allclose(invert(a[0]), ref_inverse(a[0])[0], atol=1e-12)


def test_round_trips() -> None:
    rng = np.random.default_rng(12)
    a, b = poses(rng, 400), poses(rng, 400)
    identity = np.zeros_like(a)
    np.testing.assert_allclose(compose(a, between(a, b))[:, :2], b[:, :2], atol=1e-12)
    same_heading(compose(a, between(a, b))[:, 2], b[:, 2])
    np.testing.assert_allclose(compose(a, invert(a)), identity, atol=1e-12)
    np.testing.assert_allclose(compose(invert(a), a), identity, atol=1e-12)
    np.testing.assert_allclose(invert(invert(a)), a, atol=1e-12)
    np.testing.assert_allclose(between(a, b), compose(invert(a), b), atol=1e-12)
    np.testing.assert_allclose(invert(between(a, b)), between(b, a), atol=1e-12)
    # Chained steps integrate back to the poses.
    chain = poses(rng, 300, spread=2.0)
    steps = chain_steps(chain)
    np.testing.assert_allclose(steps, ref_between(chain[:-1], chain[1:]), atol=1e-12)
    back = integrate(chain[0], steps)
    np.testing.assert_allclose(back[:, :2], chain[:, :2], atol=1e-9)
    same_heading(back[:, 2], chain[:, 2], atol=1e-9)
    assert in_range(back[:, 2])
    assert in_range(steps[:, 2])


def test_integrate_is_the_sequential_composition() -> None:
    rng = np.random.default_rng(13)
    start = np.array([1.0, -2.0, 3.0])
    steps = np.column_stack(
        [rng.uniform(0, 1, 50), rng.uniform(-0.2, 0.2, 50), rng.normal(0, 1, 50)]
    )
    expected = [start]
    for z in steps:
        expected.append(ref_compose(expected[-1], z)[0])
    np.testing.assert_allclose(integrate(start, steps), np.array(expected), atol=1e-12)
    np.testing.assert_array_equal(integrate(start, np.zeros((0, 3))), [start])


def test_headings_at_the_seam_stay_in_half_open_range() -> None:
    a = np.array([[0.0, 0.0, PI], [0.0, 0.0, -PI + 1e-16], [1.0, 2.0, PI / 2]])
    b = np.array([[0.0, 0.0, PI], [0.0, 0.0, -PI], [0.0, 0.0, PI / 2]])
    assert compose(a, b)[0, 2] == 0.0 or abs(compose(a, b)[0, 2]) < 1e-15
    assert compose(a, b)[2, 2] == PI
    assert invert(np.array([0.0, 0.0, PI]))[2] == PI  # -pi wraps to pi
    assert between(np.zeros(3), np.array([0.0, 0.0, -PI]))[2] == PI
    for out in (compose(a, b), invert(a), between(a, b), between(b, a)):
        assert in_range(out[..., 2])


def test_points_between_frames() -> None:
    rng = np.random.default_rng(14)
    pose = poses(rng, 40)
    pts = rng.uniform(-5, 5, (40, 2))
    expected = np.array([ref_transform(p, q[None, :])[0] for p, q in zip(pose, pts, strict=True)])
    np.testing.assert_allclose(transform(pose, pts), expected, atol=1e-12)
    np.testing.assert_allclose(transform(pose[3], pts), ref_transform(pose[3], pts), atol=1e-12)
    np.testing.assert_allclose(to_robot(pose, transform(pose, pts)), pts, atol=1e-12)
    owners = rng.integers(0, 40, 300)
    many = rng.uniform(-5, 5, (300, 2))
    np.testing.assert_allclose(
        to_world(pose, owners, many), transform(pose[owners], many), atol=1e-12
    )
    # rotate: the rotation part alone; a pose's composition moves points like transform.
    np.testing.assert_allclose(
        rotate(pose[:, 2], pts) + pose[:, :2], transform(pose, pts), atol=1e-12
    )
    np.testing.assert_allclose(rotate(-pose[:, 2], rotate(pose[:, 2], pts)), pts, atol=1e-12)
    as_pose = np.column_stack([pts, np.zeros(40)])
    np.testing.assert_allclose(compose(pose, as_pose)[:, :2], transform(pose, pts), atol=1e-12)


def test_bad_pose_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="rows"):
        compose(np.zeros((4, 2)), np.zeros((4, 3)))


# --- lines ------------------------------------------------------------------------------------


def line_points(phi: float, rho: float, rng: np.random.Generator, k: int = 60) -> FloatArray:
    n = np.array([math.cos(phi), math.sin(phi)])
    t = np.array([-n[1], n[0]])
    along = rng.uniform(-3, 3, k)
    off = rng.normal(0, 1e-3, k)
    return np.asarray(rho * n + along[:, None] * t + off[:, None] * n)


def test_fit_line_has_rho_non_negative_and_matches_the_reference() -> None:
    rng = np.random.default_rng(21)
    for _ in range(200):
        phi, rho = rng.uniform(-PI, PI), rng.uniform(0.01, 20.0)
        pts = line_points(phi, rho, rng)
        got_phi, got_rho = fit_line(pts)
        assert got_rho >= 0
        assert -PI < got_phi <= PI
        ref_phi, ref_rho = ref_fit_line(pts)
        assert got_rho == pytest.approx(ref_rho, abs=1e-9)
        assert abs(ref_wrap(np.array([got_phi - ref_phi]))[0]) < 1e-9
        # The same line as the one the points were drawn on (rho > 0: the normal is unique).
        assert got_rho == pytest.approx(rho, abs=5e-3)
        assert abs(ref_wrap(np.array([got_phi - phi]))[0]) < 5e-3
        # n . p = rho on the line.
        n = np.array([math.cos(got_phi), math.sin(got_phi)])
        assert np.abs(pts @ n - got_rho).max() < 1e-2


def test_fit_line_flips_a_normal_that_would_give_a_negative_rho() -> None:
    # y = -2: the principal normal (0, 1) gives rho = -2; the line is (phi = -pi/2, rho = 2).
    pts = np.column_stack([np.linspace(-1, 1, 9), np.full(9, -2.0)])
    phi, rho = fit_line(pts)
    assert rho == pytest.approx(2.0)
    assert phi == pytest.approx(-PI / 2)
    # x = -3 (normal (1, 0) first): phi = pi, rho = 3.
    phi, rho = fit_line(np.column_stack([np.full(9, -3.0), np.linspace(-1, 1, 9)]))
    assert (phi, rho) == (pytest.approx(PI), pytest.approx(3.0))


def test_fit_line_through_the_origin_keeps_the_normal_towards_plus_x() -> None:
    t = np.arange(-5.0, 6.0)  # the centroid exactly 0
    # As the Rust core: the normal oriented like (1, 0) (kept when perpendicular to it).
    phi, rho = fit_line(np.column_stack([t, t]))  # y = x: normal (1, -1)/sqrt 2
    assert rho == pytest.approx(0.0, abs=1e-15)
    assert phi == pytest.approx(-PI / 4)
    phi, rho = fit_line(np.column_stack([t, np.zeros(11)]))  # the x axis: normal (0, 1)
    assert rho == 0.0
    assert phi == pytest.approx(PI / 2)
    phi, rho = fit_line(np.column_stack([np.zeros(11), t]))  # the y axis: normal (1, 0)
    assert rho == 0.0
    assert phi == pytest.approx(0.0)


def test_fit_line_without_a_principal_direction_and_bad_input() -> None:
    assert fit_line(np.array([[3.0, 4.0]])) == (0.0, 3.0)  # as the Rust core's test
    assert fit_line(np.array([[-3.0, 4.0]])) == (PI, 3.0)
    square = np.array([[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]])
    assert fit_line(square) == (0.0, 1.5)
    with pytest.raises(ValueError, match="at least one point"):
        fit_line(np.zeros((0, 2)))
    with pytest.raises(ValueError, match="at least one point"):
        fit_line(np.array([[math.nan, 0.0], [1.0, 1.0]]))


def test_the_angle_between_two_lines_is_undirected_and_in_zero_to_ninety_degrees() -> None:
    """line_angle against the smallest turn that brings one line onto the other (a line turned
    by pi is the same line), for scalars and arrays alike."""
    rng = np.random.default_rng(4)
    a = rng.uniform(-4 * math.pi, 4 * math.pi, 400)
    b = rng.uniform(-4 * math.pi, 4 * math.pi, 400)
    by_search = np.array(
        [min(abs(x - y - k * math.pi) for k in range(-10, 11)) for x, y in zip(a, b, strict=True)]
    )
    scalars = np.array([line_angle(float(x), float(y)) for x, y in zip(a, b, strict=True)])
    np.testing.assert_allclose(scalars, by_search, atol=1e-12)
    np.testing.assert_allclose(line_angle(a, b), scalars, atol=1e-12)
    assert np.all((scalars >= 0.0) & (scalars <= math.pi / 2))
    assert line_angle(0.1, 0.1 + math.pi) == pytest.approx(0.0, abs=1e-15)  # the same line
    assert line_angle(0.0, math.pi / 2) == pytest.approx(math.pi / 2)  # perpendicular
    assert line_angle(0.3, -0.2) == line_angle(-0.2, 0.3)
