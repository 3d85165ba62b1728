"""`hitl-slam evaluate` machinery on the quick scenarios (the lost-poses room and the corridors),
and the real-log scenario builder on the small Intel log when the shared datasets are present."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hitl_slam.cli import main
from hitl_slam.evaluation import LASER, real_log_scenario, run_evaluation, table
from hitl_slam.sim import Scenario
from hitl_slam.sim.odometry import HeadingJump


def test_quick_evaluation_repairs_and_reports(tmp_path: Path) -> None:
    results, report = run_evaluation(tmp_path, quick=True)
    assert [r.name for r in results] == ["lost-poses-room", "parallel-corridors"]
    for r in results:
        assert r.angle_after < r.angle_before
        assert r.angle_after < 1.0
        assert r.spacing_after < 0.05
        assert r.inconsistency_reduction > 0.5
        assert r.ate_after < r.ate_before
        assert r.figure is not None
        assert r.figure.stat().st_size > 0
    text = report.read_text()
    assert "| lost-poses-room |" in text
    assert "**mean**" in table(results)


def test_evaluate_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", "--quick", "-q", "-o", str(tmp_path)]) == 0
    assert "report:" in capsys.readouterr().out
    assert (tmp_path / "report.md").is_file()


@pytest.mark.skipif(
    not (LASER / "intel-corrected.log.gz").is_file(),
    reason=f"public laser logs not found at {LASER} (the ../shared folder beside the repo)",
)
def test_real_log_scenario_has_labelled_walls_and_known_pairs() -> None:
    s = real_log_scenario(
        LASER / "intel-corrected.log.gz",
        name="intel",
        faults=lambda n: [HeadingJump(n // 2, math.radians(10.0))],
    )
    assert isinstance(s, Scenario)
    assert s.map.num_poses == s.truth.shape[0]
    labelled = s.wall_of_point >= 0
    assert labelled.mean() > 0.2
    # The truth scores (near) zero against its own pairs; the damage is visible.
    assert s.errors(s.truth).mean_angular < 1e-6
    assert s.errors(s.map.poses).mean_angular > 1.0
    assert np.all(np.isfinite(s.map.poses))
