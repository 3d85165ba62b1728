"""Aligning the map with its scans through the web API: POST /api/align re-runs the scan matching
from the current poses, keeps every correction and answers the new State (``last.kind`` "align"
with the alignment's figures); undo returns exactly to the map before, a refusal answers 409 with
the reason and changes nothing, and while the alignment is in effect the map's own loop closures
cannot be rejected or reinstated. On the generated room with planted loop closures
(tests/loop_support.py), where a real alignment takes a second or two, and once on the corrected
Orebro log when ../shared is beside the repository."""

from __future__ import annotations

import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.alignment import AlignmentRefused
from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import InputError, SolverError
from hitl_slam.map import Map
from hitl_slam.session import Session
from hitl_slam.web import SessionHost, create_app
from loop_support import FALSE_LOOP, map_with_loops, room

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from starlette.testclient import TestClient

BASE = "http://127.0.0.1:8765"
PAGE_HEADERS = {"X-Hitl-Slam": "1"}
LASER = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "laser"
OREBRO = LASER / "orebro-corrected.log.gz"

# The room's scans are few and simulated: matched again they contradict a quarter of its odometry
# steps, which the default guard refuses, and the aligned room can hold the statement off (the
# guard of docs/ALGORITHM.md §I.16). Allowing every step and statement lets the alignment
# through: these tests are about the endpoint, not the guards.
PERMISSIVE = DEFAULT.replace(
    align_max_contradicted=1.0,
    align_min_loop_closures=0,
    align_consistency_guard=False,
    align_max_overruled=1.0,
)

needs_logs = pytest.mark.skipif(
    not OREBRO.is_file(), reason="../shared/datasets/laser is not beside the repository"
)


@pytest.fixture(scope="module")
def loops_map() -> Map:
    return map_with_loops()


def _session_file(m: Map, path: Path, config: Config = DEFAULT) -> Path:
    Session.new(m, path, config=config).close()
    return path


def _client(path: Path) -> tuple[SessionHost, TestClient]:
    host = SessionHost(Session.open(path), metrics=False)
    client = TestClient(create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS)
    return host, client


@pytest.fixture
def served(loops_map: Map, tmp_path: Path) -> Iterator[tuple[SessionHost, TestClient]]:
    """The room with loop closures, default configuration."""
    host, client = _client(_session_file(loops_map, tmp_path / "room.hitl"))
    with client:
        yield host, client
    host.close()


def _poses(client: TestClient) -> bytes:
    r = client.get("/api/map/poses")
    assert r.status_code == 200
    content: bytes = r.content
    return content


def _state(client: TestClient) -> dict[str, Any]:
    r = client.get("/api/state")
    assert r.status_code == 200
    result: dict[str, Any] = r.json()
    return result


def _correct(client: TestClient) -> None:
    """One correction the simulated human draws on the map as it stands."""
    from hitl_slam.sim import SimulatedHuman

    poses = np.frombuffer(_poses(client), "<f4").reshape(-1, 3).astype(float)
    drawn = SimulatedHuman(room(), 0).next_correction(poses)
    assert drawn is not None
    applied = client.post("/api/corrections", json=drawn.to_json()).json()
    assert applied["accepted"], applied


def test_align_keeps_the_corrections_and_undo_returns_to_the_map_before(
    loops_map: Map, tmp_path: Path
) -> None:
    path = _session_file(loops_map, tmp_path / "room.hitl", PERMISSIVE)
    host, client = _client(path)
    with client:
        _correct(client)
        corrected = _poses(client)
        before = _state(client)
        assert before["aligned"] is False

        r = client.post("/api/align")
        assert r.status_code == 200, r.text
        state = r.json()
        aligned = _poses(client)
        assert aligned != corrected
        assert state["version"] > before["version"]
        assert state["map_version"] == state["version"]
        last = state["last"]
        assert last["kind"] == "align"
        assert last["iterations"] >= 1
        assert np.isfinite([last["cost"], last["initial_cost"], last["time_ms"]]).all()
        assert last["reason"] is None
        figures = last["alignment"]
        assert figures["steps"] == loops_map.num_poses - 1
        assert 0 <= figures["contradicted"] <= figures["steps"]
        assert figures["loop_closures"] >= 0
        assert figures["loop_closures_rejected"] >= 0
        assert figures["poses_moved"] > 0
        assert figures["max_move_m"] > 0
        assert figures["relation_dcs"] in (DEFAULT.align_relation_dcs, DEFAULT.relation_dcs)
        firm = figures["relation_dcs"] == DEFAULT.relation_dcs
        assert figures["statements"] == ("firm" if firm else "yield")
        # Every correction is kept: still in effect, with its solved lines.
        assert state["applied"] == 1
        assert [h["status"] for h in state["history"]] == ["applied"]
        assert [c["index"] for c in state["lines"]] == [0]
        assert (state["can_undo"], state["can_redo"]) == (True, False)
        assert state["loop_closures"] == before["loop_closures"]
        assert state["aligned"] is True
        assert _state(client)["aligned"] is True

        # The alignment's own loop closures replaced the map's: toggling one is refused, clearly.
        r = client.post("/api/loop_closures", json={"index": 0, "rejected": True})
        assert r.status_code == 409
        assert "aligned with its scans" in r.json()["detail"]
        assert "undo the alignment" in r.json()["detail"]
        assert _state(client)["version"] == state["version"]
        assert _state(client)["aligned"] is True
        assert _poses(client) == aligned

        # Undo: exactly the map before, the correction still in effect; redo: the aligned map.
        undone = client.post("/api/undo").json()
        assert undone["last"]["kind"] == "undo"
        assert undone["last"]["alignment"] is None
        assert _poses(client) == corrected
        assert undone["applied"] == 1
        assert undone["can_redo"]
        assert undone["lines"] == before["lines"]
        assert undone["aligned"] is False
        redone = client.post("/api/redo").json()
        assert redone["last"]["kind"] == "redo"
        assert _poses(client) == aligned
        assert redone["lines"] == state["lines"]
        assert redone["aligned"] is True
    host.close()

    # Journaled: a restarted server on the same file shows the aligned map, and after undo the
    # map's loop closures can be rejected again.
    host, client = _client(path)
    with client:
        assert _poses(client) == aligned
        restarted = _state(client)
        assert restarted["can_undo"]
        assert restarted["aligned"] is True
        assert client.post("/api/undo").json()["aligned"] is False
        assert _poses(client) == corrected
        r = client.post("/api/loop_closures", json={"index": 0, "rejected": True})
        assert r.status_code == 200, r.text
        assert r.json()["loop_closures"]["rejected"] == [0, FALSE_LOOP]
    host.close()


def test_a_refused_alignment_answers_409_with_the_reason_and_changes_nothing(
    served: tuple[SessionHost, TestClient],
) -> None:
    # The real guard: on the room's sparse simulated scans the aligned map contradicts too many
    # odometry steps.
    _, client = served
    before, poses = _state(client), _poses(client)
    assert before["aligned"] is False
    r = client.post("/api/align")
    assert r.status_code == 409, r.text
    detail = r.json()["detail"]
    assert "contradicts" in detail
    assert "odometry steps" in detail
    assert "the map was not changed" in detail
    assert _state(client) == before
    assert _state(client)["aligned"] is False
    assert _poses(client) == poses
    assert client.post("/api/undo").status_code == 409  # nothing was put on the stack


@pytest.mark.parametrize(
    ("error", "status"),
    [
        (AlignmentRefused("the scans disagree with the odometry; the map was not changed"), 409),
        (InputError("room: 0 laser points over 499 poses; a pose graph without scans"), 400),
        (SolverError("the aligned solve diverged"), 500),
    ],
)
def test_every_failure_answers_its_reason_and_leaves_the_state_as_it_was(
    served: tuple[SessionHost, TestClient],
    monkeypatch: pytest.MonkeyPatch,
    error: Exception,
    status: int,
) -> None:
    _, client = served

    def fail(self: Session, progress: Any = None) -> Any:
        raise error

    monkeypatch.setattr(Session, "align", fail)
    before, poses = _state(client), _poses(client)
    r = client.post("/api/align")
    assert r.status_code == status
    assert r.json() == {"detail": str(error)}
    assert _state(client) == before
    assert _poses(client) == poses


def test_other_requests_are_answered_while_an_alignment_runs(
    loops_map: Map, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The alignment runs in the threadpool: the state and the arrays answer at once with the map
    # from before, and a change asked for meanwhile waits for it.
    original = Session.align
    started, release = threading.Event(), threading.Event()

    def held(self: Session, progress: Any = None) -> Any:
        started.set()
        assert release.wait(30)
        return original(self, progress)

    monkeypatch.setattr(Session, "align", held)
    host, client = _client(_session_file(loops_map, tmp_path / "room.hitl", PERMISSIVE))
    with client:
        before = _state(client)
        poses = _poses(client)
        done: dict[str, Any] = {}

        def send(what: str) -> None:
            done[what] = client.post(f"/api/{what}")

        aligning = threading.Thread(target=send, args=("align",))
        aligning.start()
        assert started.wait(10)
        undoing = threading.Thread(target=send, args=("undo",))
        undoing.start()
        t0 = time.monotonic()
        assert _state(client)["version"] == before["version"]
        assert _poses(client) == poses
        assert time.monotonic() - t0 < 1.0
        assert "undo" not in done  # queued behind the alignment
        release.set()
        aligning.join(60)
        undoing.join(60)
        assert done["align"].status_code == 200, done["align"].text
        assert done["align"].json()["last"]["kind"] == "align"
        assert done["align"].json()["aligned"] is True
        # The undo ran after it: it undid the alignment.
        assert done["undo"].status_code == 200, done["undo"].text
        assert done["undo"].json()["version"] > done["align"].json()["version"]
        assert done["undo"].json()["aligned"] is False
        assert _poses(client) == poses
    host.close()


@needs_logs
def test_align_a_bent_orebro_log(tmp_path: Path) -> None:
    """The corrected Orebro log under slow heading drift (the corrected log itself is refused:
    aligning it makes it no more consistent)."""
    import numpy as np

    from hitl_slam.full_evaluation import _base_scenario
    from hitl_slam.sim.fault_models import damaged, drift

    base = _base_scenario("Orebro", 1)
    m = damaged(base, drift(base.truth, np.random.default_rng(1)), 1).map  # type: ignore[attr-defined]
    host, client = _client(_session_file(m, tmp_path / "orebro.hitl"))
    with client:
        before = _poses(client)
        r = client.post("/api/align")
        assert r.status_code == 200, r.text
        last = r.json()["last"]
        assert last["kind"] == "align"
        figures = last["alignment"]
        assert figures["steps"] == m.num_poses - 1
        assert figures["inconsistency"][1] < figures["inconsistency"][0]
        assert figures["contradicted"] <= DEFAULT.align_max_contradicted * figures["steps"]
        assert figures["loop_closures"] >= 1
        assert _poses(client) != before
        client.post("/api/undo")
        assert _poses(client) == before
    host.close()
