"""The solved lines are part of a session's state: kept per step, journaled with each correction,
restored by undo and redo and by reopening, bit for bit; a journal written before they were kept
still opens (its lines refit). And `Session.run_step`, the one place a corrections-file step is
replayed (the CLI and the web host go through it)."""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.corrections_file import Apply, Redo, Undo
from hitl_slam.errors import CorrectionRejected, InputError, SolverError
from hitl_slam.map import Map
from hitl_slam.session import Session, StepRefused, refit_lines
from test_session import REJECTED, drawing, fake_applier, reseal, same, tiny_map


@dataclass(frozen=True)
class LinesResult:
    poses: NDArray[np.float64]
    interpretation: Interpretation
    lines: NDArray[np.float64]
    iterations: int
    initial_chi2: float
    final_chi2: float
    time_s: float


def lines_applier(
    map: Map,
    poses: NDArray[np.float64],
    drawn: Correction,
    active: Sequence[Interpretation],
    config: Config,
) -> LinesResult:
    """The fake pipeline plus solved lines: every active correction's two lines, values that
    depend on the step (so a restored step is told apart from its neighbours)."""
    r = fake_applier(map, poses, drawn, active, config)
    k = len(active) + 1
    phi = np.sin(np.arange(2 * k) + 0.1 * k + drawn.a[0][0])
    rho = np.cos(np.arange(2 * k) * 0.7 + drawn.b[0][1]) * 3.0 + 1.0 / 3.0
    lines = np.stack([phi, rho], axis=1)
    return LinesResult(
        r.poses, r.interpretation, lines, r.iterations, r.initial_chi2, r.final_chi2, r.time_s
    )


def test_lines_follow_every_step_and_survive_reopening(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    seen: list[NDArray[np.float64]] = []
    with Session.new(tiny_map(), path, applier=lines_applier) as s:
        assert s.lines.shape == (0, 2)
        for seed in (0.5, 1.5, 2.5):
            outcome = s.apply(drawing(seed))
            assert same(s.lines, np.asarray(outcome.lines, dtype=np.float64))  # type: ignore[attr-defined]
            seen.append(s.lines)
        assert s.lines.shape == (6, 2)
        s.undo()
        assert same(s.lines, seen[1])
        s.undo()
        assert same(s.lines, seen[0])
        s.redo()
        assert same(s.lines, seen[1])
        with pytest.raises(ValueError, match="read-only"):
            s.lines[0, 0] = 1.0  # read-only, as the poses
    with Session.open(path) as reopened:
        assert same(reopened.lines, seen[1])
        reopened.undo()
        assert same(reopened.lines, seen[0])
        reopened.redo()
        reopened.redo()
        assert same(reopened.lines, seen[2])
    # Journaled with the correction, as JSON numbers (exact round trip).
    connection = sqlite3.connect(path)
    payloads = [
        json.loads(p)
        for (p,) in connection.execute("SELECT payload FROM events WHERE kind = 'correction'")
    ]
    connection.close()
    assert [len(p["lines"]) for p in payloads] == [2, 4, 6]
    assert np.array(payloads[2]["lines"]).tobytes() == seen[2].tobytes()


def test_a_journal_without_lines_opens_and_refits_them(tmp_path: Path) -> None:
    """Sessions written before lines were journaled (or by an applier without lines): the
    lines are refit by total least squares to S_a and S_b under the step's poses."""
    path = tmp_path / "old.hitl"
    with Session.new(tiny_map(), path, applier=fake_applier) as s:
        s.apply(drawing(0.5))
        s.apply(drawing(1.5))
        live = s.lines
    connection = sqlite3.connect(path)
    assert all(
        "lines" not in json.loads(p)
        for (p,) in connection.execute("SELECT payload FROM events WHERE kind = 'correction'")
    )
    connection.close()
    with Session.open(path) as s:
        assert same(s.lines, live)
        assert same(s.lines, refit_lines(s.input_map, s.poses, s.active))
        s.undo()
        assert s.lines.shape == (2, 2)


def test_damaged_or_bad_lines_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.hitl"
    with Session.new(tiny_map(), path, applier=lines_applier) as s:
        s.apply(drawing(0.5))
    connection = sqlite3.connect(path)
    (payload,) = connection.execute(
        "SELECT payload FROM events WHERE kind = 'correction'"
    ).fetchone()
    data = json.loads(payload)
    data["lines"] = data["lines"][:1]
    connection.execute(
        "UPDATE events SET payload = ? WHERE kind = 'correction'", (json.dumps(data),)
    )
    connection.commit()
    connection.close()
    reseal(path)  # the checksum would give the change away first
    with pytest.raises(InputError, match=r"damaged.*lines must be 2"):
        Session.open(path)

    def wrong_lines(*args: object) -> LinesResult:
        r = lines_applier(*args)  # type: ignore[arg-type]
        return LinesResult(r.poses, r.interpretation, r.lines[:, :1], 1, 1.0, 1.0, 0.0)

    def nan_lines(*args: object) -> LinesResult:
        r = lines_applier(*args)  # type: ignore[arg-type]
        return LinesResult(r.poses, r.interpretation, r.lines * math.nan, 1, 1.0, 1.0, 0.0)

    for applier, message in ((wrong_lines, "lines of shape"), (nan_lines, "non-finite lines")):
        with Session.new(tiny_map(), applier=applier) as s:  # type: ignore[arg-type]
            before = s.poses
            with pytest.raises(SolverError, match=message):
                s.apply(drawing(0.5))
            assert s.poses is before
            assert s.lines.shape == (0, 2)
            assert s.history[-1].status.value == "interrupted"


def test_run_step_does_each_kind_of_step(tmp_path: Path) -> None:
    with Session.new(tiny_map(), tmp_path / "s.hitl", applier=lines_applier) as s:
        done = s.run_step(Apply(drawing(0.5), line=3))
        assert done.action == "apply"
        assert done.outcome is not None
        assert done.entry.status.value == "applied"
        assert done.entry.index == 0
        assert same(s.poses, np.asarray(done.outcome.poses))
        applied = s.poses
        done = s.run_step(Undo())
        assert (done.action, done.outcome, done.entry.status.value) == ("undo", None, "undone")
        assert same(s.poses, s.input_map.poses)
        with pytest.raises(StepRefused, match="nothing to undo"):
            s.run_step(Undo())
        done = s.run_step(Redo())
        assert done.action == "redo"
        assert same(s.poses, applied)
        with pytest.raises(StepRefused, match="nothing to redo"):
            s.run_step(Redo())
        with pytest.raises(CorrectionRejected):
            s.run_step(Apply(REJECTED))
        assert same(s.poses, applied)
        assert isinstance(StepRefused("x"), InputError)  # callers catching InputError still do
