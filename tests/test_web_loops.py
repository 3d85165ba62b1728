"""Loop closures through the web API (issue 14, part 4): the page reads them once, the state says
which are rejected, POST /api/loop_closures rejects or reinstates one and the map re-solves; undo
and redo cross it like a correction, and a restarted server on the same session file shows it
still rejected. On the generated room with planted loop closures (tests/loop_support.py)."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from hitl_slam.map import Map
from hitl_slam.session import Session
from hitl_slam.web import SessionHost, create_app
from loop_support import FALSE_LOOP, TRUE_PAIRS, map_with_loops, room

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from starlette.testclient import TestClient

BASE = "http://127.0.0.1:8765"
PAGE_HEADERS = {"X-Hitl-Slam": "1"}


@pytest.fixture(scope="module")
def loops_map() -> Map:
    return map_with_loops()


def _client(path: Path) -> tuple[SessionHost, TestClient]:
    host = SessionHost(Session.open(path), metrics=False)
    client = TestClient(create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS)
    return host, client


@pytest.fixture
def session_path(loops_map: Map, tmp_path: Path) -> Path:
    path = tmp_path / "loops.hitl"
    Session.new(loops_map, path).close()
    return path


@pytest.fixture
def client(session_path: Path) -> Iterator[TestClient]:
    host, c = _client(session_path)
    with c:
        yield c
    host.close()


def _poses(client: TestClient) -> bytes:
    r = client.get("/api/map/poses")
    assert r.status_code == 200
    return r.content


def test_the_page_reads_the_loop_closures_once_and_the_state_names_the_rejected(
    client: TestClient,
) -> None:
    loops = client.get("/api/loop_closures").json()
    assert loops["pairs"][: len(TRUE_PAIRS)] == [list(p) for p in TRUE_PAIRS]
    assert loops["pairs"][FALSE_LOOP] == [60, 420]
    assert loops["weight"] == pytest.approx([1.0, 1.0, 0.7, 1.0, 1.0, 0.01])
    assert loops["auto_rejected"] == [False] * FALSE_LOOP + [True]
    assert len(loops["score"]) == FALSE_LOOP + 1
    state = client.get("/api/state").json()
    assert state["loop_closures"] == {"count": FALSE_LOOP + 1, "rejected": [FALSE_LOOP]}


def test_reject_undo_redo_and_restart_keep_it_rejected(session_path: Path) -> None:
    host, client = _client(session_path)
    with client:
        before = _poses(client)
        version = client.get("/api/state").json()["version"]
        r = client.post("/api/loop_closures", json={"index": 1, "rejected": True})
        assert r.status_code == 200, r.text
        state = r.json()
        assert state["loop_closures"]["rejected"] == [1, FALSE_LOOP]
        assert state["map_version"] > version
        assert state["last"]["kind"] == "loop_closure"
        assert state["last"]["iterations"] >= 1
        assert state["can_undo"]
        assert not state["can_redo"]
        after = _poses(client)
        assert after != before
        # The same request again changes nothing: a conflict.
        again = client.post("/api/loop_closures", json={"index": 1, "rejected": True})
        assert again.status_code == 409
        assert "already rejected" in again.json()["detail"]
        # Undo reinstates it with the poses exactly as before; redo rejects it again.
        state = client.post("/api/undo").json()
        assert state["loop_closures"]["rejected"] == [FALSE_LOOP]
        assert _poses(client) == before
        state = client.post("/api/redo").json()
        assert state["loop_closures"]["rejected"] == [1, FALSE_LOOP]
        assert _poses(client) == after
        # Reinstating the false one moves the map; undone, it is rejected again.
        state = client.post("/api/loop_closures", json={"index": FALSE_LOOP, "rejected": False})
        assert state.json()["loop_closures"]["rejected"] == [1]
        assert _poses(client) != after
        client.post("/api/undo")
    host.close()
    # A restarted server on the same file: still rejected, same poses, redo still there.
    host, client = _client(session_path)
    with client:
        state = client.get("/api/state").json()
        assert state["loop_closures"]["rejected"] == [1, FALSE_LOOP]
        assert _poses(client) == after
        assert state["can_undo"]
        assert state["can_redo"]
        state = client.post("/api/redo").json()
        assert state["loop_closures"]["rejected"] == [1]
    host.close()


@pytest.mark.parametrize(
    ("body", "status"),
    [
        ({"index": 99, "rejected": True}, 400),
        ({"index": -1, "rejected": True}, 422),
        ({"index": "1", "rejected": True}, 422),
        ({"index": 1, "rejected": 1}, 422),
        ({"index": 1}, 422),
        ({"index": 1, "rejected": True, "why": "x"}, 422),
    ],
)
def test_bad_requests_change_nothing(client: TestClient, body: object, status: int) -> None:
    before = client.get("/api/state").json()
    r = client.post("/api/loop_closures", json=body)
    assert r.status_code == status, r.text
    after = client.get("/api/state").json()
    assert after["version"] == before["version"]
    assert after["loop_closures"] == before["loop_closures"]


def test_a_map_without_loop_closures_has_none_to_reject(tmp_path: Path) -> None:
    path = tmp_path / "room.hitl"
    Session.new(room().map, path).close()
    host, client = _client(path)
    with client:
        assert client.get("/api/loop_closures").json() == {
            "pairs": [],
            "weight": [],
            "score": [],
            "auto_rejected": [],
        }
        assert client.get("/api/state").json()["loop_closures"] == {"count": 0, "rejected": []}
        r = client.post("/api/loop_closures", json={"index": 0, "rejected": True})
        assert r.status_code == 400
        assert "no loop closures" in r.json()["detail"]
    host.close()


def test_undo_crosses_corrections_and_loop_closure_steps(
    session_path: Path, loops_map: Map
) -> None:
    from hitl_slam.sim import SimulatedHuman

    host, client = _client(session_path)
    human = SimulatedHuman(room(), 0)
    with client:
        start = _poses(client)
        client.post("/api/loop_closures", json={"index": 0, "rejected": True})
        rejected = _poses(client)
        drawn = human.next_correction(np.frombuffer(rejected, "<f4").reshape(-1, 3).astype(float))
        assert drawn is not None
        applied = client.post("/api/corrections", json=drawn.to_json()).json()
        assert applied["accepted"], applied
        assert applied["state"]["applied"] == 1
        assert applied["state"]["loop_closures"]["rejected"] == [0, FALSE_LOOP]
        assert len(applied["state"]["lines"]) == 1
        state = client.post("/api/undo").json()  # the correction
        assert state["applied"] == 0
        assert state["loop_closures"]["rejected"] == [0, FALSE_LOOP]
        assert _poses(client) == rejected
        state = client.post("/api/undo").json()  # the rejection
        assert state["loop_closures"]["rejected"] == [FALSE_LOOP]
        assert _poses(client) == start
        assert not state["can_undo"]
    host.close()
