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


def _jittered_chain_file(path: Path, num_poses: int = 400, seed: int = 0) -> None:
    """A g2o odometry chain with exact measurements and vertices off by 1 m / 1 rad."""
    rng = np.random.default_rng(seed)
    lines = []
    for i in range(num_poses):
        x, y, t = (0.0, 0.0, 0.0) if i == 0 else (*rng.normal(0, 1.0, 2), rng.normal(0, 1.0))
        lines.append(f"VERTEX_SE2 {i} {x} {y} {t}")
    for i in range(num_poses - 1):
        lines.append(f"EDGE_SE2 {i} {i + 1} 1 0 {rng.normal(0, 0.2)} 100 0 0 100 0 1000")
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("init", ["tree", "chordal"])
def test_solve_from_a_computed_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], init: str
) -> None:
    graph_path = tmp_path / "chain.g2o"
    _jittered_chain_file(graph_path)
    out = tmp_path / "out.g2o"
    assert main(["solve", str(graph_path), "-o", str(out), "--init", init, "--quiet"]) == 0
    line = capsys.readouterr().out.strip()
    assert "converged (function_tolerance:" in line
    graph = hitl_slam.load_graph(graph_path)
    assert hitl_slam.chi2(graph, hitl_slam.load_graph(out).poses) < 1e-9


def test_not_converged_exits_3_and_still_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph_path = tmp_path / "chain.g2o"
    _jittered_chain_file(graph_path)
    out = tmp_path / "out.g2o"
    code = main(["solve", str(graph_path), "-o", str(out), "--max-iterations", "1", "--quiet"])
    assert code == 3
    assert "NOT converged (max_iterations:" in capsys.readouterr().out
    assert out.is_file()


def test_robust_solve_lists_the_down_weighted_edges(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph_path = tmp_path / "m.g2o"
    main(["generate", str(graph_path), "--poses", "300", "--seed", "4"])
    bad = "EDGE_SE2 10 250 7 -3 2.5 44.7 0 0 44.7 0 44.7\n"
    graph_path.write_text(graph_path.read_text() + bad)
    capsys.readouterr()
    out = tmp_path / "out.g2o"
    args = ["solve", str(graph_path), "-o", str(out), "--robust", "dcs:10", "--quiet"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "robust (loop=dcs:10)" in text
    assert "10->250 (w " in text
    # The edge class is chosen with CLASS=; an unknown class is bad input.
    args = ["solve", str(graph_path), "-o", str(out), "--robust", "wheel=dcs"]
    assert main(args) == 2
    assert "unknown edge class" in capsys.readouterr().err


def test_solve_help_teaches_init_robust_and_exit_codes(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit):
        main(["solve", "--help"])
    text = capsys.readouterr().out
    for needle in ["--init", "chordal", "--robust", "dcs", "dogleg", "3 not converged"]:
        assert needle in text


def test_metrics_reads_a_silent_log_as_the_sensor_saw_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from test_map_io import _room_log

    log = tmp_path / "silent.clf"
    log.write_text(_room_log(50.0))
    assert main(["metrics", str(log), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "maximum laser range inferred: 600 readings piled at 49.980 m" in captured.err
    assert "40 poses, 6600 points" in captured.out
    assert main(["metrics", str(log), "--quiet", "--max-range", "2.5"]) == 0
    captured = capsys.readouterr()
    assert "inferred" not in captured.err
    assert "6600 points" not in captured.out
    # A session made from the log carries the note; commands on it do not repeat it.
    session = tmp_path / "silent.hitl"
    from hitl_slam import Session, load_map

    Session.new(load_map(log), session).close()
    capsys.readouterr()
    for command in (["metrics", str(session)], ["export", str(session), "-o", "x.g2o"]):
        if command[0] == "export":
            command[-1] = str(tmp_path / "x.g2o")
        assert main([*command, "--quiet"]) == 0
        assert "maximum laser range" not in capsys.readouterr().err
