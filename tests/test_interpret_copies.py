"""Issue 11's interpretation failure classes, reproduced on generated laps: a careful person's
drawing 10-20 cm beside a copy of a wall with other copies and clutter near it, two segments
on near copies, three laps. Each drawing is a true statement; each must be accepted with the
copy it was drawn on."""

from __future__ import annotations

import math

import numpy as np
import pytest

from copies_world import WALL_A, WALL_B, CopiesWorld, careful_drawing, copies_world
from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.interpret import interpret

SEEDS = range(int(__import__("os").environ.get("COPIES_SEEDS", "6")))


def _interpret(w: CopiesWorld, a: object, b: object, mode: Mode = Mode.COLLINEAR) -> Interpretation:
    return interpret(w.map, w.map.poses, Correction.make(a, b, mode), DEFAULT)  # type: ignore[arg-type]


def _laps_of(w: CopiesWorld, h: Interpretation) -> tuple[set[int], set[int]]:
    return set(w.lap_of(h.x_a).tolist()), set(w.lap_of(h.x_b).tolist())


def _distance_to(copy: np.ndarray, line: tuple[tuple[float, float], tuple[float, float]]) -> float:
    """Largest distance of the line's ends from the infinite line through `copy`."""
    p0, p1 = copy
    d = (p1 - p0) / float(np.hypot(*(p1 - p0)))
    n = np.array([-d[1], d[0]])
    return max(abs(float((np.array(q) - p0) @ n)) for q in line)


@pytest.mark.parametrize("noise", [0.05, 0.15])
@pytest.mark.parametrize("seed", SEEDS)
def test_doubled_wall_drawn_beside_its_copies_is_accepted(seed: int, noise: float) -> None:
    # Copies 0.5-0.7 m apart, slightly turned; the drawings 10-20 cm off with 5 or 15 cm end
    # noise.
    rng = np.random.default_rng(100 + seed)
    gap = rng.uniform(0.5, 0.7) * rng.choice([-1, 1])
    w = copies_world([(0.0, 0.0, 0.0), (0.0, gap, math.radians(rng.uniform(-1.0, 1.0)))], seed)
    c0, c1 = w.copy_of(WALL_A, 0), w.copy_of(WALL_A, 1)
    a = careful_drawing(c0, rng, endpoint_noise=noise, others=(c1,))
    b = careful_drawing(c1, rng, endpoint_noise=noise, others=(c0,))
    h = _interpret(w, a, b)
    assert _laps_of(w, h) == ({0}, {1})
    assert _distance_to(w.copy_of(WALL_A, 0), h.line_a) < 0.03
    assert _distance_to(w.copy_of(WALL_A, 1), h.line_b) < 0.03
    assert any("moved" in note for note in h.notes)


@pytest.mark.parametrize("seed", SEEDS)
def test_near_copies_get_distinct_visits(seed: int) -> None:
    # Copies 3-10 cm apart: both inside each segment's band and in one EM line.
    rng = np.random.default_rng(200 + seed)
    gap = rng.uniform(0.03, 0.10) * rng.choice([-1, 1])
    w = copies_world([(0.0, 0.0, 0.0), (0.0, gap, 0.0)], seed)
    a = careful_drawing(w.copy_of(WALL_A, 0), rng, offset=(0.0, 0.05))
    b = careful_drawing(w.copy_of(WALL_A, 1), rng, offset=(0.0, 0.05))
    h = _interpret(w, a, b)
    laps = _laps_of(w, h)
    assert laps in (({0}, {1}), ({1}, {0})), laps


@pytest.mark.parametrize("seed", SEEDS)
def test_three_laps_each_segment_keeps_its_own_copy(seed: int) -> None:
    rng = np.random.default_rng(300 + seed)
    step = rng.uniform(0.35, 0.5)
    w = copies_world([(0.0, 0.0, 0.0), (0.0, step, 0.0), (0.0, 2 * step, 0.0)], seed)
    first, second = (0, 2) if seed % 2 == 0 else (1, 2)
    copies = [w.copy_of(WALL_A, k) for k in range(3)]

    def draw(k: int) -> object:
        others = tuple(c for j, c in enumerate(copies) if j != k)
        return careful_drawing(copies[k], rng, others=others)

    a, b = draw(first), draw(second)
    h = _interpret(w, a, b)
    assert _laps_of(w, h) == ({first}, {second})
    # Not a mixture: each line lies on its own copy.
    assert _distance_to(w.copy_of(WALL_A, first), h.line_a) < 0.03
    assert _distance_to(w.copy_of(WALL_A, second), h.line_b) < 0.03


@pytest.mark.parametrize("seed", SEEDS)
def test_parallel_walls_of_two_laps(seed: int) -> None:
    # "These are parallel": wall A on lap 0, wall B on lap 1 (turned 3 degrees).
    rng = np.random.default_rng(400 + seed)
    w = copies_world([(0.0, 0.0, 0.0), (0.1, 0.3, math.radians(3.0))], seed)
    a = careful_drawing(w.copy_of(WALL_A, 0), rng)
    b = careful_drawing(w.copy_of(WALL_B, 1), rng)
    h = _interpret(w, a, b, Mode.PARALLEL)
    assert _laps_of(w, h) == ({0}, {1})


def test_search_off_is_the_papers_em_from_the_drawing() -> None:
    # With search_band 0 a drawing 18 cm off a wall whose copy is in the band is refused
    # (issue 11's report); with the search it is accepted.
    rng = np.random.default_rng(7)
    w = copies_world([(0.0, 0.0, 0.0), (0.0, 0.55, 0.0)], 3)
    a = careful_drawing(w.copy_of(WALL_A, 0), rng, offset=(0.18, 0.18), endpoint_noise=0.0)
    b = careful_drawing(w.copy_of(WALL_A, 1), rng, offset=(0.18, 0.18), endpoint_noise=0.0)
    drawn = Correction.make(a, b, Mode.COLLINEAR)
    h = interpret(w.map, w.map.poses, drawn, DEFAULT)
    assert _laps_of(w, h) == ({0}, {1})
    off = DEFAULT.replace(search_band=0.0)
    try:
        h_off = interpret(w.map, w.map.poses, drawn, off)
    except Exception:
        return
    # Without the search it may still pass when the drawing happens to be on the copy's side.
    assert not any("moved" in note for note in h_off.notes)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_sparse_copy_among_dense_ones_is_selected(seed: int) -> None:
    # A lap driven four times faster than the others leaves a copy with a fifth of their points;
    # the other laps' copies lie 0.35-0.45 m beside it, turned 2.5-4 degrees, so that each
    # enters its candidate band towards one end. The search finds the sparse line, but on some
    # layouts EM on the whole band held none of its points ("N points near segment a, none of
    # them on one line", seen on the Intel log in the full evaluation); on the narrow band
    # around the line it keeps them.
    rng = np.random.default_rng(500 + seed)
    errors = [(0.0, 0.0, 0.0)]
    for _ in range(3):
        side = float(rng.choice([-1.0, 1.0]))
        turn = math.radians(rng.uniform(2.5, 4.0))
        errors.append((0.0, side * rng.uniform(0.35, 0.45), -side * turn))
    w = copies_world(errors, seed, n=[12, 50, 50, 50])
    copies = [w.copy_of(WALL_A, k) for k in range(4)]
    other = int(rng.integers(1, 4))
    a = careful_drawing(
        copies[0], rng, offset=(0.0, 0.05), endpoint_noise=0.05, others=tuple(copies[1:])
    )
    # "Parallel to the far wall" as another lap shows it, drawn on that copy.
    walls_b = [w.copy_of(WALL_B, k) for k in range(4)]
    b = careful_drawing(
        walls_b[other],
        rng,
        offset=(0.0, 0.02),
        endpoint_noise=0.02,
        others=tuple(c for k, c in enumerate(walls_b) if k != other),
    )
    h = _interpret(w, a, b, Mode.PARALLEL)
    assert _laps_of(w, h)[0] == {0}
    assert _distance_to(copies[0], h.line_a) < 0.03


@pytest.mark.parametrize("noise", [0.05, 0.15])
@pytest.mark.parametrize("seed", SEEDS)
def test_a_sparse_copy_beside_a_dense_one_is_not_refused(seed: int, noise: float) -> None:
    # A lap driven four times faster leaves a copy with a fifth of the points, 6-15 cm from a
    # dense one. The segment drawn on the sparse copy snaps to the dense line next to it, both
    # segments select the dense lap, and the pair rules refused ("seen from the same visit",
    # the full evaluation on the Seattle log). Interpreted again without the dense lap's points,
    # the sparse segment finds its own copy, nearer its drawing than the dense one.
    rng = np.random.default_rng(600 + seed)
    gap = rng.uniform(0.06, 0.15) * rng.choice([-1, 1])
    n = [50, 12] if seed % 2 == 0 else [12, 50]  # which lap is the sparse one
    w = copies_world([(0.0, 0.0, 0.0), (0.0, gap, math.radians(rng.uniform(-0.5, 0.5)))], seed, n=n)
    copies = [w.copy_of(WALL_A, k) for k in range(2)]
    # Each drawn within a few cm of its copy, to either side.
    a, b = (
        careful_drawing(
            copies[k], rng, offset=(0.0, 0.04), endpoint_noise=noise, others=(copies[1 - k],)
        )
        for k in (0, 1)
    )
    h = _interpret(w, a, b, Mode.COLOCATION)
    assert _laps_of(w, h) == ({0}, {1})
    # The lines are not asserted within a few cm of their copies: where EM's line held both
    # copies, the kept visit's points near that mixed line include clutter, and on some layouts
    # (6 of 40 at COPIES_SEEDS=20) the line leans up to 0.13 m off at one end (docs/ALGORITHM.md
    # §I.10: refitting the kept visit alone was tried and not kept).
