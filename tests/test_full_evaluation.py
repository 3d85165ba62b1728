"""The full evaluation of issue 11 (hitl-slam evaluate --full): fault models, the careful person,
the per-drawing record and the report."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from hitl_slam.errors import InputError
from hitl_slam.full_evaluation import LASER, Drawing, Run, evaluate_run, full_report, summary
from hitl_slam.sim import parallel_corridors
from hitl_slam.sim.careful import CarefulPerson, DrawingStyle
from hitl_slam.sim.fault_models import (
    FAULT_MODELS,
    FULL_FAULTS,
    bend,
    damaged,
    drift,
    jump,
    laps,
    scale,
    slip,
)
from hitl_slam.sim.odometry import (
    NO_NOISE,
    HeadingDrift,
    HeadingJump,
    ScaleError,
    Slip,
    odometry,
    relative_motions,
)

needs_logs = pytest.mark.skipif(
    not (LASER / "orebro-corrected.log.gz").is_file(),
    reason="../shared/datasets/laser is not beside the repository",
)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fault_models_put_their_faults_where_they_say(seed: int) -> None:
    truth = parallel_corridors(seed, heading_jump_deg=0.0).truth
    n = truth.shape[0]
    rng = np.random.default_rng(seed)
    (j,) = jump(truth, rng)
    assert isinstance(j, HeadingJump)
    assert 0.3 * n <= j.pose < 0.7 * n
    assert math.isclose(abs(j.angle), math.radians(30.0))
    (d,) = drift(truth, rng)
    assert isinstance(d, HeadingDrift)
    travel = float(np.hypot(*np.diff(truth[:, :2], axis=0).T).sum())
    assert math.isclose(abs(d.rate) * travel, math.radians(15.0), rel_tol=1e-9)
    (b,) = bend(truth, rng)
    assert isinstance(b, HeadingDrift)
    heading = np.unwrap(truth[b.start : b.stop, 2])
    assert np.max(np.abs(heading - heading[0])) <= math.radians(10.0) + 1e-9
    two = laps(truth, rng)
    assert len(two) == 2
    assert all(isinstance(f, HeadingJump) for f in two)
    assert two[0].pose < two[1].pose  # type: ignore[union-attr]
    signs = {math.copysign(1.0, jump(truth, np.random.default_rng(s))[0].angle) for s in range(12)}
    assert signs == {-1.0, 1.0}
    # The two outside the issue's four: one step off by 0.5-1.5 m (in the robot's frame), or
    # every distance 3-6% off; the headings are left alone by both.
    (s,) = slip(truth, rng)
    assert isinstance(s, Slip)
    assert 0.3 * n <= s.pose < 0.7 * n
    assert 0.5 <= math.hypot(s.dx, s.dy) <= 1.5
    (k,) = scale(truth, rng)
    assert isinstance(k, ScaleError)
    assert (k.start, k.stop) == (0, n)
    assert 0.03 <= abs(k.factor - 1.0) <= 0.06
    true_steps = relative_motions(truth)
    slipped = relative_motions(odometry(truth, rng, NO_NOISE, [s]))
    off = slipped - true_steps
    assert np.allclose(off[s.pose - 1], [s.dx, s.dy, 0.0], atol=1e-9)
    assert np.allclose(np.delete(off, s.pose - 1, axis=0), 0.0, atol=1e-9)
    scaled = relative_motions(odometry(truth, rng, NO_NOISE, [k]))
    assert np.allclose(scaled[:, :2], k.factor * true_steps[:, :2], atol=1e-9)
    assert np.allclose(scaled[:, 2], true_steps[:, 2], atol=1e-9)
    with pytest.raises(InputError, match="slip at pose"):
        odometry(truth, rng, NO_NOISE, [Slip(n, 1.0, 0.0)])
    with pytest.raises(InputError, match="scale error"):
        odometry(truth, rng, NO_NOISE, [ScaleError(0, n, 0.0)])


def test_the_careful_person_draws_true_statements_in_both_directions() -> None:
    scenario = damaged(
        parallel_corridors(3, heading_jump_deg=0.0),
        jump(parallel_corridors(3, heading_jump_deg=0.0).truth, np.random.default_rng(3)),
        5,
    )
    person = CarefulPerson(scenario, 4, endpoint_noise=0.15)
    poses = scenario.map.poses
    directions, count = set(), 0
    for issue in person.inconsistencies(poses)[:12]:
        drawn = person._draw_pair(poses, issue)
        if drawn is None:
            continue
        count += 1
        for seg, visit in ((drawn.a, issue.a), (drawn.b, issue.b)):
            p0, p1 = np.asarray(seg)
            # Drawn along the pass meant: its points lie near the stroke's line.
            pts = person._points(poses, visit)
            d = (p1 - p0) / np.hypot(*(p1 - p0))
            off = np.abs((pts - p0) @ np.array([-d[1], d[0]]))
            assert np.median(off) < 0.5
            assert np.hypot(*(p1 - p0)) >= 8 * 0.15 - 1e-9
            directions.add(bool(d @ np.array([1.0, 0.0]) > 0))
    assert count >= 4
    assert directions == {True, False}


@needs_logs
def test_a_run_records_every_drawing_and_the_report_shows_the_targets() -> None:
    run = evaluate_run("Orebro", "jump", 0.05, seed=1, max_corrections=6)
    assert isinstance(run, Run)
    assert run.drawings
    assert run.accepted <= 6
    for d in run.drawings:
        assert isinstance(d, Drawing)
        assert d.accepted or d.reason
        if not d.accepted:
            assert d.ate[0] == d.ate[1]
    # Each accepted drawing starts where the previous one ended.
    accepted = [d for d in run.drawings if d.accepted]
    for x, y in itertools.pairwise(accepted):
        assert x.ate[1] == y.ate[0]
    assert run.ate[1] < run.ate[0]  # a 30-degree jump repaired at least in part
    text = full_report([run], "provenance line")
    for needle in ("drawings accepted >= 95%", "## Refusals by reason", "### Orebro, jump, 5 cm"):
        assert needle in text
    # The last step, the alignment with the scans, says which of its two solves it kept.
    assert run.alignment.startswith(("applied (Phi 100)", "applied (Phi 1000)", "refused: "))
    assert "## Alignment with the scans" in text
    if run.alignment.startswith("applied"):
        firm = int(run.alignment == "applied (Phi 1000)")
        assert f"it kept the firm one, the more consistent there, in {firm}." in text
    s = summary([run])
    assert s["drawings"] == len(run.drawings)


@needs_logs
def test_cli_full_writes_the_report_and_says_whether_targets_are_met(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from hitl_slam.cli import main

    code = main(
        ["evaluate", "--full", "--maps", "Orebro", "--faults", "bend", "-o", str(tmp_path), "-q"]
    )
    assert code in (0, 1)
    text = (tmp_path / "full.md").read_text()
    assert "| Orebro | bend | 5 |" in text
    assert "| Orebro | bend | 15 |" in text
    assert "| guard | accepted, changed by it | refused by it |" in text
    assert main(["evaluate", "--full", "--faults", "quake", "-o", str(tmp_path)]) == 2


def test_a_guard_is_named_by_the_note_it_leaves() -> None:
    """The notes and refusals the core writes (rust/src/correction/apply.rs, and the pipeline's
    robust-odometry note) name the guard that acted, by its section of docs/ALGORITHM.md; other
    notes name none."""
    from hitl_slam.full_evaluation import _guards

    assert _guards(
        [
            "applied as collinear: the two passes' positions along the wall contradict the "
            "odometry (chi2 of the map's measurements 12.0 as colocation, 3.0 as collinear)"
        ]
    ) == ("colocation guard (chi2, §I.3)",)
    assert _guards(
        [
            "applied as collinear: the map is more consistent with the two passes on one line "
            "than at one place (10.0 -> 9.0 m^2)",
            "3 chain steps between the passes (first 12) could not be checked by the scans; ...",
        ]
    ) == (
        "colocation consistency (scans, §I.13)",
        "unchecked steps: robust odometry solve kept (§I.12)",
    )
    assert _guards(["segment a covers 2 visits; kept poses 3-9 (40 points), dropped 20-30"]) == ()
    assert _guards(["applying it would contradict the robot's own measurements: ..."]) == (
        "consistency guard: refused (§I.6)",
    )


def test_unknown_fault_model_is_an_input_error() -> None:
    from hitl_slam.errors import InputError

    assert FULL_FAULTS == ("jump", "drift", "bend", "laps")
    assert list(FAULT_MODELS)[: len(FULL_FAULTS)] == list(FULL_FAULTS)  # the seeds depend on it
    with pytest.raises(InputError, match="unknown fault model"):
        evaluate_run("Orebro", "quake", 0.05)


@pytest.mark.parametrize("seed", [1, 6])
def test_a_person_drawing_past_the_ends_and_beside_the_wall_is_still_understood(seed: int) -> None:
    """Another drawing style (sim.careful.DrawingStyle): strokes run on past the ends of the
    copy by up to 0.4 m and drawn up to 0.2 m beside it, with 10 cm endpoint noise. On a
    generated world the person's drawings are still interpreted and make the map better."""
    style = DrawingStyle(overshoot=0.4, side=0.2)
    run = evaluate_run(
        "parallel corridors",
        "laps",
        0.10,
        seed=seed,
        max_corrections=8,
        align=False,
        person_style=style,
    )
    assert len(run.drawings) >= 4
    assert run.accepted >= 0.75 * len(run.drawings), [d.reason for d in run.drawings]
    assert run.angle[1] < run.angle[0]
    assert run.ate[1] < run.ate[0]
    with pytest.raises(InputError, match="overshoot and side"):
        DrawingStyle(side=-0.1)
