"""One drawn correction through the whole pipeline (EM interpretation, explicit correction,
back-propagation, joint solve) on the generated corridor loop: each mode's relation holds between
the OBSERVATIONS afterwards, drawing direction does not matter, and bad drawings are rejected in a
real session without changing anything."""

from __future__ import annotations

import contextlib
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.errors import CorrectionRejected
from hitl_slam.geometry import fit_line
from hitl_slam.interpret import interpret
from hitl_slam.map import Map
from hitl_slam.pipeline import apply_correction
from hitl_slam.session import Session, apply_in_order
from hitl_slam.sim.corridor import (
    INNER_BOTTOM,
    OUTER_BOTTOM,
    OUTER_LEFT,
    World,
    corridor_loop,
    drawn_segment,
)
from reference import wrap

FloatArray = NDArray[np.float64]

# (wall a, poses seeing it), (wall b, poses seeing it), trimmed extents along each wall.
DRAWINGS = {
    Mode.COLOCATION: ((OUTER_BOTTOM, (0, 60), (0.3, 0.7)), (OUTER_BOTTOM, (265, 325), (0.3, 0.7))),
    Mode.COLLINEAR: ((OUTER_BOTTOM, (0, 60), (0.1, 0.45)), (OUTER_BOTTOM, (265, 325), (0.55, 0.9))),
    Mode.PARALLEL: ((OUTER_BOTTOM, (0, 60), (0.2, 0.8)), (INNER_BOTTOM, (265, 325), (0.2, 0.8))),
    Mode.PERPENDICULAR: ((OUTER_BOTTOM, (0, 60), (0.2, 0.8)), (OUTER_LEFT, (200, 280), (0.2, 0.8))),
}


@pytest.fixture(scope="module")
def world() -> World:
    return corridor_loop(seed=1)


def _draw(world: World, mode: Mode, seed: int = 0) -> Correction:
    rng = np.random.default_rng(seed)
    (wa, ra, ta), (wb, rb, tb) = DRAWINGS[mode]
    poses = world.map.poses
    a = drawn_segment(world, poses, wa, ra, rng, noise=0.05, along=ta)
    b = drawn_segment(world, poses, wb, rb, rng, noise=0.05, along=tb)
    return Correction.make(a, b, mode)


def relation_error(m: Map, poses: FloatArray, h: Interpretation) -> tuple[float, float]:
    """(angle error in degrees, offset of b's observations from a's line in metres), from lines
    refit to the observations S_a and S_b in ``poses``."""
    world_pts = m.world_points(poses)
    pa = world_pts[m.offsets[h.s_a[:, 0]] + h.s_a[:, 1]]
    pb = world_pts[m.offsets[h.s_b[:, 0]] + h.s_b[:, 1]]
    phi_a, rho_a = fit_line(pa)
    phi_b, _ = fit_line(pb)
    e = phi_b - phi_a - (math.pi / 2 if h.mode is Mode.PERPENDICULAR else 0.0)
    e -= math.pi * round(e / math.pi)
    centre_b = pb.mean(axis=0)
    offset = abs(math.cos(phi_a) * centre_b[0] + math.sin(phi_a) * centre_b[1] - rho_a)
    return abs(math.degrees(e)), offset


@pytest.mark.parametrize("mode", list(Mode))
def test_one_drawn_correction_establishes_its_relation(world: World, mode: Mode) -> None:
    m = world.map
    result = apply_correction(m, m.poses, _draw(world, mode), (), DEFAULT)
    h = result.interpretation
    angle_before, offset_before = relation_error(m, m.poses, h)
    angle, offset = relation_error(m, result.poses, h)
    assert angle_before > 2.0  # the heading fault is visible before
    assert angle < 0.3
    if mode in (Mode.COLOCATION, Mode.COLLINEAR):
        assert offset_before > 0.1
        assert offset < 0.02
    # Later poses moved, earlier ones (before the first pose of X_a's visit) hardly.
    assert (
        np.abs(result.poses[int(h.x_b.min()) :, :2] - m.poses[int(h.x_b.min()) :, :2]).max() > 0.1
    )


@pytest.mark.parametrize("mode", list(Mode))
def test_lines_are_undirected(world: World, mode: Mode) -> None:
    m = world.map
    drawn = _draw(world, mode, seed=3)
    base = apply_correction(m, m.poses, drawn, (), DEFAULT)
    flips = [
        Correction(mode, (drawn.a[1], drawn.a[0]), drawn.b),
        Correction(mode, drawn.a, (drawn.b[1], drawn.b[0])),
        Correction(mode, (drawn.a[1], drawn.a[0]), (drawn.b[1], drawn.b[0])),
    ]
    for flipped in flips:
        other = apply_correction(m, m.poses, flipped, (), DEFAULT)
        np.testing.assert_array_equal(other.interpretation.s_a, base.interpretation.s_a)
        np.testing.assert_array_equal(other.interpretation.s_b, base.interpretation.s_b)
        np.testing.assert_allclose(other.poses[:, :2], base.poses[:, :2], rtol=0, atol=1e-9)
        d = wrap(other.poses[:, 2] - base.poses[:, 2])
        assert np.abs(d).max() < 1e-9


def test_newest_of_two_drawn_corrections_changes_the_map(world: World) -> None:
    m = world.map
    first = apply_correction(m, m.poses, _draw(world, Mode.PARALLEL), (), DEFAULT)
    rng = np.random.default_rng(5)
    a = drawn_segment(world, first.poses, OUTER_BOTTOM, (0, 60), rng, along=(0.3, 0.7))
    b = drawn_segment(world, first.poses, OUTER_BOTTOM, (265, 325), rng, along=(0.3, 0.7))
    second = apply_correction(
        m, first.poses, Correction.make(a, b, Mode.COLOCATION), [first.interpretation], DEFAULT
    )
    assert np.abs(second.poses[:, :2] - first.poses[:, :2]).max() > 0.05
    assert relation_error(m, second.poses, second.interpretation)[1] < 0.02
    assert relation_error(m, second.poses, first.interpretation)[0] < 0.3


def _core_calls(fn: Callable[[], object]) -> list[str]:
    """The calls into the compiled core (``hitl_slam._core``'s functions and the methods of its
    objects) that ``fn`` makes, by name, seen by the interpreter's profiling hook."""
    calls: list[str] = []

    def hook(_frame: object, event: str, arg: object) -> None:
        if event != "c_call":
            return
        owner = getattr(arg, "__self__", None)
        if getattr(arg, "__module__", None) == "hitl_slam._core" or (
            owner is not None and type(owner).__module__ == "hitl_slam._core"
        ):
            calls.append(getattr(arg, "__qualname__", repr(arg)))

    sys.setprofile(hook)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return calls


def test_one_correction_crosses_into_the_core_once(world: World) -> None:
    """Issue 12: interpretation, explicit correction, back-propagation, the joint solve with
    every earlier correction, and both guards are one call into the core (after the map's
    one-time set-up: its scans, its engine and the odometry check, held by the workspace a
    session keeps)."""
    from hitl_slam.workspace import Workspace

    m = world.map
    held = Workspace(m)
    first = apply_correction(m, m.poses, _draw(world, Mode.PARALLEL), (), DEFAULT, workspace=held)
    rng = np.random.default_rng(5)
    a = drawn_segment(world, first.poses, OUTER_BOTTOM, (0, 60), rng, along=(0.3, 0.7))
    b = drawn_segment(world, first.poses, OUTER_BOTTOM, (265, 325), rng, along=(0.3, 0.7))
    drawn = Correction.make(a, b, Mode.COLOCATION)
    calls = _core_calls(
        lambda: apply_correction(
            m, first.poses, drawn, [first.interpretation], DEFAULT, workspace=held
        )
    )
    assert calls == ["CorrectionEngine.apply"], calls
    # A refused drawing too: one call, which refuses.
    far = Correction.make([[50.0, 50.0], [52.0, 50.0]], b, Mode.COLOCATION)

    def refused() -> None:
        with pytest.raises(CorrectionRejected):
            apply_correction(m, first.poses, far, [first.interpretation], DEFAULT, workspace=held)

    assert _core_calls(refused) == ["CorrectionEngine.apply"]
    # The hook sees calls into the core: the interpretation alone is one call of its own.
    scans = held.scans()
    assert _core_calls(lambda: interpret(m, first.poses, drawn, scans=scans)) == [
        "MapScans.interpret"
    ]


BAD_DRAWINGS = {
    "over empty space": ([[50.0, 50.0], [52.0, 50.0]], "real-b", "no observations under segment"),
    "zero length": ([[5.0, 0.0], [5.0, 0.0]], "real-b", "zero"),
    "same observations": ("real-a", "real-a", "same"),
}


@pytest.mark.parametrize("case", sorted(BAD_DRAWINGS))
def test_bad_drawings_change_nothing_in_a_real_session(
    world: World, tmp_path: Path, case: str
) -> None:
    good = _draw(world, Mode.COLOCATION)
    a, b, message = BAD_DRAWINGS[case]
    seg_a = good.a if a == "real-a" else a
    seg_b = good.b if b == "real-b" else (good.a if b == "real-a" else b)
    path = tmp_path / "s.hitl"
    with Session.new(world.map, path) as session:
        session.correct(good.a, good.b, "colocation")
        before = session.poses.copy()
        size = path.stat().st_size
        active = len(session.active)
        with pytest.raises(CorrectionRejected, match=message):
            session.correct(seg_a, seg_b, "collinear")
        np.testing.assert_array_equal(session.poses, before)
        assert len(session.active) == active
        assert session.can_undo
    with Session.open(path) as reopened:
        np.testing.assert_array_equal(reopened.poses, before)
        assert len(reopened.active) == active
    assert path.stat().st_size >= size  # only the rejection event was added


def test_nan_coordinates_are_refused(world: World) -> None:
    m = world.map
    with pytest.raises((CorrectionRejected, ValueError)):
        apply_correction(
            m,
            m.poses,
            Correction(Mode.PARALLEL, ((0.0, 0.0), (math.nan, 1.0)), ((1, 1), (2, 2))),
            (),
        )


# --- undo / redo with the real pipeline --------------------------------------------------------

_OPS = st.lists(
    st.one_of(st.sampled_from(["undo", "redo"]), st.integers(min_value=0, max_value=2)),
    min_size=1,
    max_size=8,
)


@settings(
    max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(ops=_OPS)
def test_any_sequence_equals_the_surviving_corrections_from_scratch(
    world: World, ops: list[object]
) -> None:
    """Corrections (drawn once on the input map), undos and redos in any order leave exactly the
    map that applying the surviving corrections from scratch gives, bit for bit."""
    drawings = [
        _draw(world, Mode.COLOCATION),
        _draw(world, Mode.PARALLEL),
        _draw(world, Mode.PERPENDICULAR),
    ]
    with Session.new(world.map) as session:
        for op in ops:
            if op == "undo":
                if session.can_undo:
                    session.undo()
            elif op == "redo":
                if session.can_redo:
                    session.redo()
            else:
                d = drawings[int(str(op))]
                with contextlib.suppress(CorrectionRejected):
                    session.correct(d.a, d.b, d.mode)
        surviving = list(session.corrections)
        poses = session.poses.copy()
    expected, _ = apply_in_order(world.map, surviving)
    np.testing.assert_array_equal(poses, expected)
    if not surviving:
        np.testing.assert_array_equal(poses, world.map.poses)
