"""`hitl-slam demo`: the lost-poses room is repaired to the paper's accuracy, and the files it
promises are written."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from hitl_slam.cli import main
from hitl_slam.demo import TRUE_WIDTH, run_demo


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def test_demo_repairs_the_room(tmp_path: Path) -> None:
    result = run_demo(tmp_path / "out")
    assert abs(result.width_after - TRUE_WIDTH) <= 0.02
    assert result.angle_after <= 0.5
    assert abs(result.width_before - TRUE_WIDTH) > 0.1  # the input is visibly wrong
    assert result.angle_before > 2.0
    assert result.inconsistency_after < 0.2 * result.inconsistency_before
    assert 1 <= result.corrections <= 15
    for f in result.files:
        assert f.is_file()
        assert f.stat().st_size > 0
    assert _png_size(tmp_path / "out" / "before_after.png") == (1800, 900)


def test_demo_command_prints_the_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "-o", str(tmp_path / "d"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| room width (m) | 5.97 | 6.31 | 6.33 |" in out
    assert (tmp_path / "d" / "lost-poses.hitl").is_file()
