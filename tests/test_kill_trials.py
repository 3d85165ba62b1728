"""The kill -9 trials (tests/kill_trials.py): a short run (the long one is `make kill-trials`),
and the checker itself, shown to catch a lost acknowledged step, a damaged session file and a
half-written output."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

import kill_trials
from hitl_slam.session import Session
from test_session import fake_applier, tiny_map


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_a_few_kill_trials(capsys: pytest.CaptureFixture[str]) -> None:
    assert kill_trials.main(["--trials", "2", "--seed", "7", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "2 trials, 0 lost acknowledged steps, 0 partial outputs" in out


def written(directory: Path, seed: int, steps: int) -> Path:
    """The session file a child would leave after ``steps`` steps of its plan."""
    path = directory / "s.hitl"
    with Session.new(tiny_map(), path, applier=fake_applier) as session:
        for step in kill_trials.plan(seed)[:steps]:
            kill_trials.run_step(session, step, path)
    return path


def check(directory: Path, seed: int, acked: int) -> kill_trials.Tally:
    tally = kill_trials.Tally()
    kill_trials.check_trial(directory, seed, acked, kill_trials.reference(seed), tally)
    return tally


def test_the_checker_accepts_the_acknowledged_steps_and_one_in_flight(tmp_path: Path) -> None:
    # (A check applies one more correction to the file, to see it still takes one.)
    for acked in (4, 3):
        directory = tmp_path / str(acked)
        directory.mkdir()
        written(directory, 5, 4)
        tally = check(directory, 5, acked)
        assert tally.failures == []
        assert tally.in_flight_committed == (acked == 3)


def test_the_checker_finds_a_lost_step(tmp_path: Path) -> None:
    written(tmp_path, 5, 3)
    tally = check(tmp_path, 5, 5)
    assert tally.lost == 1
    assert "5 steps acknowledged, the file holds another state" in tally.failures[0]


def test_the_checker_finds_a_damaged_session_and_a_half_written_output(tmp_path: Path) -> None:
    seed = next(s for s in range(100) if kill_trials.plan(s)[0][0] == "save")
    path = written(tmp_path, seed, 2)
    output = kill_trials.output_path(path, 0)
    output.write_bytes(output.read_bytes()[: output.stat().st_size // 2])
    tally = check(tmp_path, seed, 2)
    assert tally.partial == 1
    assert output.name in " ".join(tally.failures)
    output.unlink()
    with path.open("r+b") as f:
        f.truncate(path.stat().st_size - 1000)
    tally = check(tmp_path, seed, 2)
    assert tally.partial == 1
    assert "the session file does not open" in tally.failures[0]
