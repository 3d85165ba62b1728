"""Issue 11's application failure classes: true statements that made maps worse.

- A loop with one 12-degree heading jump, repaired one drawing at a time by a person who says
  "same wall" (colocation) over the copies they see: the passes saw different stretches of the
  walls, so the centres of their observations are not one place, and forcing them together bent
  the room into a spiral (ATE 0.2 -> 1-2 m, wall angles 35-53 deg, before the guard).
- A long colocation of two diverging copies of a wall (5 degrees apart) seen over different
  stretches: it must end with the copies on one line and the rest of the map straight.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest
from numpy.typing import NDArray

from copies_world import WALL_A, CopiesWorld, careful_drawing, copies_world
from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Correction, Interpretation, Mode
from hitl_slam.errors import CorrectionRejected
from hitl_slam.evaluation import _ate
from hitl_slam.pipeline import apply_correction
from hitl_slam.session import Session
from hitl_slam.sim.human import SimulatedHuman
from hitl_slam.sim.scenario import single_room
from reference import wrap


@pytest.mark.parametrize("seed", range(4))
def test_heading_jump_loop_repaired_by_colocations_never_gets_worse(seed: int) -> None:
    sc = single_room(seed, heading_jump_deg=12.0, laps=2.0)
    person = SimulatedHuman(
        sc,
        seed,
        check_selection=False,
        same_wall_mode=Mode.COLOCATION,
        min_sigma_h=0.1,
        endpoint_noise=0.05,
    )
    ate = [_ate(sc.map.poses, sc.truth)]
    angle = [sc.errors(sc.map.poses).mean_angular]
    with Session.new(sc.map) as session:
        for _ in range(6):
            drawn = person.next_correction(session.poses)
            if drawn is None:
                break
            try:
                session.apply(drawn)
            except CorrectionRejected:
                person.rejected(drawn)
                continue
            ate.append(_ate(session.poses, sc.truth))
            angle.append(sc.errors(session.poses).mean_angular)
    # At least one correction (with seed 2 the first one repairs the loop: ATE 0.006 m, and the
    # person sees nothing more to draw); every one of them is checked below.
    assert len(ate) >= 2, "the person found nothing to correct"
    # Each step: never much worse (a few cm / tenths of a degree of slack for noise-level maps).
    for k in range(1, len(ate)):
        assert ate[k] <= 1.05 * ate[k - 1] + 0.02, ate
        assert angle[k] <= 1.05 * angle[k - 1] + 0.3, angle
    assert ate[-1] < 0.5 * ate[0], ate
    assert angle[-1] < 0.5, angle


def _long_colocation(seed: int) -> tuple[CopiesWorld, Correction]:
    """Lap 1 turned 5 degrees: the copies diverge from ~0 to ~0.6 m over the 14 m wall; the
    person draws "same wall" over the first 20-75% of copy a and the 35-95% of copy b."""
    rng = np.random.default_rng(500 + seed)
    w = copies_world([(0.0, 0.0, 0.0), (0.0, 0.1, math.radians(5.0))], seed)
    c0, c1 = w.copy_of(WALL_A, 0), w.copy_of(WALL_A, 1)
    a = careful_drawing(c0, rng, offset=(0.0, 0.05), span=(0.1, 0.6))
    b = careful_drawing(c1, rng, offset=(0.0, 0.05), span=(0.35, 0.95))
    return w, Correction.make(a, b, Mode.COLOCATION)


@pytest.mark.parametrize("seed", range(3))
def test_long_colocation_of_diverging_copies_ends_on_one_line(seed: int) -> None:
    w, drawn = _long_colocation(seed)
    result = apply_correction(w.map, w.map.poses, drawn, (), DEFAULT)
    assert any("applied as collinear" in n for n in result.interpretation.notes)
    # Each lap's corridor pass was driven straight and stays nearly so. (Not yet exactly: the
    # Gaussian odometry spreads the 5 degrees over every edge between the passes, up to 1 deg
    # within a pass here; putting it on the edges where it happened is issue 11's open point 3.)
    for lap in w.laps:
        before = w.map.poses[lap]
        after = result.poses[lap]
        turn = wrap(after[:, 2] - before[:, 2])
        assert np.ptp(turn) < math.radians(1.2)
    # The copies end on one line: lap 1's wall direction within 0.3 deg of lap 0's.
    lap1 = w.laps[1]
    d = wrap(result.poses[lap1, 2] - w.map.poses[lap1, 2] + math.radians(5.0))
    assert np.abs(d).max() < math.radians(0.3)


@pytest.mark.parametrize("seed", range(3))
def test_different_stretches_are_left_to_the_solves_not_to_their_lengths(seed: int) -> None:
    # The same long colocation over different stretches. The stretches' lengths alone do not
    # make it collinear (docs/ALGORITHM.md §I.3): both readings are solved, and the
    # along-the-wall part is dropped because it contradicts the odometry, with both figures in
    # the note.
    w, drawn = _long_colocation(seed)
    result = apply_correction(w.map, w.map.poses, drawn, (), DEFAULT)
    notes = " ".join(result.interpretation.notes)
    assert result.interpretation.mode is Mode.COLLINEAR
    assert "positions along the wall contradict the odometry" in notes, notes


def _segment_over(points: np.ndarray) -> list[list[float]]:
    """A segment through ``points`` along their line, 10th to 90th percentile."""
    centre = points.mean(axis=0)
    _, vecs = np.linalg.eigh((points - centre).T @ (points - centre))
    d = vecs[:, 1]
    t = np.quantile((points - centre) @ d, [0.1, 0.9])
    return [list(centre + t[0] * d), list(centre + t[1] * d)]


def chi2_limit(dof: int, probability: float) -> float:
    """The reference: the ``probability`` quantile of chi2 with ``dof`` degrees of freedom by
    Wilson-Hilferty (the core's ``correction::chi2_limit``)."""
    z = NormalDist().inv_cdf(probability)
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3


@pytest.mark.parametrize("seed", [1, 2])
def test_a_result_beyond_the_odometry_noise_is_tried_again_or_refused(seed: int) -> None:
    """The consistency guard's decision, on a real log (Seattle, Radish) damaged by odometry
    noise: a solved result that breaks the chain by 40 degrees at one step (far beyond the
    odometry's noise) is not applied as is. With the visit choice the drawing allows it is
    solved again (a note gives both chi2 figures) when that is within the limit, and refused
    with the figures when no alternative exists; a result within the noise passes untouched."""
    import dataclasses

    from hitl_slam.full_evaluation import LASER, _base_scenario
    from hitl_slam.interpret import checked_drawing, from_core, interpret
    from hitl_slam.pipeline import correction_engine, explicit_and_backpropagate, solve_all
    from hitl_slam.sim.fault_models import damaged
    from hitl_slam.workspace import Workspace

    if not (LASER / "seattle-corrected.log.gz").is_file():
        pytest.skip("../shared/datasets/laser is not beside the repository")
    scenario = damaged(_base_scenario("Seattle", 0), [], seed)
    m, poses = scenario.map, scenario.map.poses
    n = m.num_poses
    rng = np.random.default_rng(seed)
    pairs = [p for p in scenario.feature_pairs if p.kind == "perpendicular"]
    drawn = None
    for k in rng.permutation(len(pairs)):
        pa = scenario.wall_points(poses, pairs[k].i, (0, n // 3))
        pb = scenario.wall_points(poses, pairs[k].j, (2 * n // 3, n))
        if len(pa) >= 150 and len(pb) >= 150:
            drawn = Correction.make(_segment_over(pa), _segment_over(pb), Mode.PERPENDICULAR)
            break
    assert drawn is not None
    h = interpret(m, poses, drawn)
    held = Workspace(m)
    engine, _ = correction_engine(m, held)
    seg_a, seg_b, sigma_h = checked_drawing(drawn, DEFAULT)

    def guard(h: Interpretation, new_poses: NDArray[np.float64]) -> object:
        """The core's guard on ``h`` solved to ``new_poses``: None (apply as is), or the
        alternative (interpretation, poses); CorrectionRejected with the figures."""
        return engine._consistency_guard(
            held.scans(),
            poses,
            seg_a,
            seg_b,
            drawn.mode.value,
            (
                h.mode.value,
                np.asarray(h.line_a),
                np.asarray(h.line_b),
                h.s_a,
                h.s_b,
                h.x_a,
                h.x_b,
            ),
            new_poses,
            [],
            DEFAULT,
            sigma_h=sigma_h,
            consistency_z=NormalDist().inv_cdf(DEFAULT.consistency_guard),
        )

    moved, _ = explicit_and_backpropagate(m, poses, h, workspace=held)
    good, _, _ = solve_all(m, [h], DEFAULT, moved, workspace=held)
    limit = chi2_limit(3 * m.edges.shape[0], DEFAULT.consistency_guard)
    assert engine.base_chi2(good) < limit
    assert guard(h, good) is None  # within the noise: untouched
    broken = good.copy()
    step = n // 2
    turn = np.array([0.0, 0.0, math.radians(40.0)])
    c, s_ = math.cos(turn[2]), math.sin(turn[2])
    rel = broken[step:, :2] - broken[step - 1, :2]
    broken[step:, :2] = broken[step - 1, :2] + rel @ np.array([[c, s_], [-s_, c]])
    broken[step:, 2] += turn[2]
    assert engine.base_chi2(broken) > limit
    # A drawing whose nearest passes are the ones kept (the guard's own retry, interpreted
    # with the nearest visits, selects the same observations): nothing else to try, refused.
    nearest = interpret(m, poses, drawn, nearest_visits=True)
    with pytest.raises(CorrectionRejected, match=r"chi2 would go from \d+ to \d+, beyond"):
        guard(nearest, broken)
    # A first interpretation that kept other passes: the nearest ones are solved and applied.
    other = dataclasses.replace(h, s_a=h.s_a[: max(1, len(h.s_a) // 2)])
    out = guard(other, broken)
    assert isinstance(out, tuple)
    h2, new = from_core(out[0]), out[1]
    assert "nearest the drawings" in h2.notes[-1]
    assert engine.base_chi2(new) < limit


@pytest.mark.parametrize("value", [1.0, 1.5, 99.0])
def test_consistency_guard_must_be_a_probability(value: float) -> None:
    from hitl_slam.errors import InputError

    with pytest.raises(InputError, match="consistency_guard is a probability"):
        DEFAULT.replace(consistency_guard=value)
    assert DEFAULT.replace(consistency_guard=0.0).consistency_guard == 0.0
