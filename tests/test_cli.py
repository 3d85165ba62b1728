"""The command line: exit codes, messages, outputs (run in-process and as a real subprocess)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hitl_slam
from hitl_slam.cli import main


def test_generate_then_solve(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    graph_path = tmp_path / "m.g2o"
    assert main(["generate", str(graph_path), "--poses", "300", "--seed", "2"]) == 0
    assert graph_path.with_suffix(".truth.txt").is_file()
    out = tmp_path / "m-opt.g2o"
    assert main(["solve", str(graph_path), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "iter" in text
    assert "converged" in text
    solved = hitl_slam.load_graph(out)
    graph = hitl_slam.load_graph(graph_path)
    assert hitl_slam.chi2(graph, solved.poses) < 0.01 * hitl_slam.chi2(graph)


def test_solve_gauss_newton_to_toro_quietly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph_path = tmp_path / "m.g2o"
    main(["generate", str(graph_path), "--poses", "100"])
    capsys.readouterr()
    out = tmp_path / "m.graph"
    assert main(["solve", str(graph_path), "-o", str(out), "--method", "gn", "--quiet"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("gauss-newton: chi2")
    assert hitl_slam.load_graph(out).num_poses == 100


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("", "empty"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 nan\n", ":2:"),
        ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 5 1 0 0 1 0 0 1 0 1\n", ":2:"),
    ],
)
def test_bad_input_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, message: str
) -> None:
    bad = tmp_path / "bad.g2o"
    bad.write_text(content)
    out = tmp_path / "out.g2o"
    assert main(["solve", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("hitl-slam: error: ")
    assert message in err
    assert not out.exists()


def test_unsupported_output_and_missing_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["solve", str(tmp_path / "nope.g2o"), "-o", str(tmp_path / "o.g2o")]) == 2
    assert "no such file" in capsys.readouterr().err
    graph_path = tmp_path / "m.g2o"
    main(["generate", str(graph_path), "--poses", "20"])
    assert main(["solve", str(graph_path), "-o", str(tmp_path / "o.csv")]) == 2
    assert "use .g2o or .graph" in capsys.readouterr().err


def test_existing_output_survives_a_failed_run(tmp_path: Path) -> None:
    out = tmp_path / "o.g2o"
    out.write_text("precious")
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0\n")
    assert main(["solve", str(bad), "-o", str(out)]) == 2
    assert out.read_text() == "precious"


def test_console_script_help_and_exit_code(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "hitl_slam.cli", "solve", "--help"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0
    assert "examples:" in run.stdout
    assert "--max-iterations" in run.stdout
    run = subprocess.run(
        [sys.executable, "-m", "hitl_slam.cli", "solve", str(tmp_path / "x.g2o"), "-o", "y.g2o"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 2
    assert "Traceback" not in run.stderr
    assert np.char.count(run.stderr, "\n") == 1
