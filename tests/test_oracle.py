"""The oracle applier of `hitl-slam evaluate --full --applier oracle` (docs/ALGORITHM.md
§I.14): it must select exactly the observations the careful person meant, put each fault's
variance on the steps it hit, and run inside the full evaluation in place of the pipeline."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest

from hitl_slam.full_evaluation import evaluate_run
from hitl_slam.session import Session
from hitl_slam.sim import parallel_corridors
from hitl_slam.sim.careful import CarefulPerson
from hitl_slam.sim.fault_models import damaged, drift, jump
from hitl_slam.sim.odometry import HeadingDrift, HeadingJump
from hitl_slam.sim.oracle import oracle_applier, true_information


def _scenario(seed: int, fault=jump):  # type: ignore[no-untyped-def]
    base = parallel_corridors(seed, heading_jump_deg=0.0)
    return damaged(base, fault(base.truth, np.random.default_rng(seed)), seed + 100)


@pytest.mark.parametrize("seed", [0, 3])
def test_the_oracle_selects_the_labelled_points_of_the_passes_drawn_on(seed: int) -> None:
    scenario = _scenario(seed)
    person = CarefulPerson(scenario, seed, endpoint_noise=0.15)
    session = Session.new(scenario.map, applier=oracle_applier(scenario, person))
    m = scenario.map
    checked = 0
    try:
        for _ in range(3):
            drawn = person.next_correction(np.array(session.poses))
            if drawn is None:
                break
            issue = person.last
            assert issue is not None
            session.apply(drawn)
            h = session.active[-1]
            earlier, later = sorted((issue.a, issue.b), key=lambda v: v.first)
            for rows, visit in ((h.s_a, earlier), (h.s_b, later)):
                global_idx = m.offsets[rows[:, 0]] + rows[:, 1]
                assert np.all(scenario.wall_of_point[global_idx] == visit.wall)
                assert rows[:, 0].min() >= visit.first
                assert rows[:, 0].max() <= visit.last
                lo, hi = m.offsets[visit.first], m.offsets[visit.last + 1]
                assert rows.shape[0] == np.count_nonzero(
                    scenario.wall_of_point[lo:hi] == visit.wall
                )
            checked += 1
    finally:
        session.close()
    assert checked >= 1


def test_the_error_model_puts_each_fault_on_the_steps_it_hit() -> None:
    scenario = _scenario(1)
    (fault,) = scenario.faults
    assert isinstance(fault, HeadingJump)
    info = true_information(scenario)
    e = scenario.map.edges
    var = 1.0 / info[:, 2, 2]
    at = np.flatnonzero((e[:, 1] == fault.pose) & (e[:, 0] == fault.pose - 1))
    assert at.size == 1
    assert var[at[0]] >= fault.angle**2
    others = np.delete(var, at)
    assert others.max() < 0.01 * fault.angle**2

    drifted = _scenario(2, fault=drift)
    (d,) = drifted.faults
    assert isinstance(d, HeadingDrift)
    var_d = 1.0 / true_information(drifted)[:, 2, 2]
    plain = 1.0 / true_information(_scenario(2, fault=lambda truth, rng: []))[:, 2, 2]
    e = drifted.map.edges
    inside = (e[:, 0] >= d.start) & (e[:, 0] < d.stop - 1)
    moved = np.hypot(*drifted.map.measurements[:, :2].T) > 0.05
    assert np.all(var_d[inside & moved] > plain[inside & moved])
    assert np.allclose(var_d[~inside], plain[~inside], rtol=0.5)


@pytest.mark.parametrize("error_model", [False, True])
def test_the_full_evaluation_runs_with_the_oracle_and_accepts_every_drawing(
    error_model: bool,
) -> None:
    run = evaluate_run(
        "parallel corridors",
        "jump",
        0.15,
        seed=2,
        max_corrections=4,
        align=False,
        applier=functools.partial(oracle_applier, error_model=error_model),
    )
    assert run.drawings
    assert all(d.accepted for d in run.drawings)
    assert all(d.meant is True for d in run.drawings)
    assert math.isfinite(run.ate[1])
    assert run.angle[1] < run.angle[0]


def test_the_full_evaluation_command_takes_the_oracle_as_its_applier(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """`hitl-slam evaluate --full --applier oracle-model` hands run_full the oracle with the
    odometry's true noise; --applier without --full is refused."""
    import hitl_slam.full_evaluation as full
    from hitl_slam.cli import main

    class Stop(Exception):
        pass

    seen: list[object] = []

    def fake_run_full(**kwargs: object) -> None:
        seen.append(kwargs["applier"])
        raise Stop

    monkeypatch.setattr(full, "run_full", fake_run_full)
    with pytest.raises(Stop):
        main(["evaluate", "--full", "--applier", "oracle-model", "-o", str(tmp_path), "-q"])
    (applier,) = seen
    assert isinstance(applier, functools.partial)
    assert applier.func is oracle_applier
    assert applier.keywords == {"error_model": True}
    assert main(["evaluate", "--applier", "oracle", "-o", str(tmp_path)]) == 2
