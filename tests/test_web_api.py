"""The web UI's HTTP API (`hitl-slam serve`) through starlette's TestClient on the generated
lost-poses room: the state document, the binary arrays, interpret / apply / reject / undo / redo,
relation residuals, the long-poll, several clients, journal step-through, save, export, the
inconsistency published after a change, restarting on the same session file, and the command."""

from __future__ import annotations

import base64
import json
import math
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from hitl_slam.cli import main
from hitl_slam.config import DEFAULT
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.corrections_file import read_corrections
from hitl_slam.errors import InputError
from hitl_slam.geometry import fit_line
from hitl_slam.io.covars import write_covars
from hitl_slam.map import Map
from hitl_slam.metrics import inconsistency
from hitl_slam.session import Session
from hitl_slam.sim import Scenario, lost_poses_room
from hitl_slam.web import SessionHost, create_app
from hitl_slam.web.host import NothingToDo
from hitl_slam.web.server import open_session, session_path_for
from web_support import person_drawings

with warnings.catch_warnings():
    # starlette 1.x asks for httpx2 behind its TestClient; httpx (installed) serves the same.
    warnings.simplefilter("ignore", UserWarning)
    from starlette.testclient import TestClient

BASE = "http://127.0.0.1:8765"
# What the page's own POSTs carry (js/api.js): a body-less POST without either header is refused
# (415), as a page of another origin could send it without a preflight.
PAGE_HEADERS = {"X-Hitl-Slam": "1"}
EMPTY_SPACE = {"mode": "collinear", "a": [[50.0, 50.0], [52.0, 50.0]], "b": [[60, 60], [62, 60]]}


@pytest.fixture(scope="module")
def room() -> Scenario:
    return lost_poses_room(0)


@pytest.fixture(scope="module")
def drawings(room: Scenario) -> list[Correction]:
    """Three drawings the simulated person makes, each on the map as the previous left it."""
    return person_drawings(room, 0, 3)[0]


def as_json(drawn: Correction) -> dict[str, Any]:
    return drawn.to_json()


def session_file(room: Scenario, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "room.hitl"
    Session.new(room.map, path).close()
    return path


@pytest.fixture
def host(room: Scenario, tmp_path: Path) -> Iterator[SessionHost]:
    h = SessionHost(Session.open(session_file(room, tmp_path / "s")), poll_timeout=5.0)
    yield h
    h.close()


@pytest.fixture
def client(host: SessionHost) -> Iterator[TestClient]:
    with TestClient(create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS) as c:
        yield c


def f32(data: bytes, width: int) -> NDArray[np.float32]:
    return np.frombuffer(data, dtype="<f4").reshape(-1, width)


def poses_bytes(client: TestClient) -> bytes:
    r = client.get("/api/map/poses")
    assert r.status_code == 200
    return r.content


def wait_for_metric(client: TestClient, timeout: float = 30.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = client.get("/api/state").json()
        if state["inconsistency_m2"] is not None:
            return state
        time.sleep(0.02)
    raise AssertionError("the inconsistency never arrived")


# -- reading ----------------------------------------------------------------------------------


def test_state_document(client: TestClient, room: Scenario) -> None:
    state = client.get("/api/state").json()
    assert set(state) == {
        "version",
        "map_version",
        "name",
        "session",
        "num_poses",
        "num_points",
        "bounds",
        "applied",
        "can_undo",
        "can_redo",
        "last",
        "inconsistency_m2",
        "history",
        "lines",
        "loop_closures",
        "aligned",
        "journal",
    }
    assert state["lines"] == []
    assert state["loop_closures"] == {"count": 0, "rejected": []}
    assert state["aligned"] is False
    assert state["session"] == "room.hitl"
    assert state["name"] == room.map.name
    assert (state["num_poses"], state["num_points"]) == (499, room.map.num_points)
    assert (state["applied"], state["can_undo"], state["can_redo"]) == (0, False, False)
    assert state["last"] is None
    assert state["history"] == []
    assert state["journal"] == {"loaded": 0, "next": 0, "source": None}
    world = room.map.world_points()
    xy = np.concatenate([world, room.map.poses[:, :2]])
    assert state["bounds"] == pytest.approx([*xy.min(axis=0), *xy.max(axis=0)])


def test_binary_arrays_are_the_map_in_float32(client: TestClient, room: Scenario) -> None:
    m = room.map
    version = client.get("/api/state").json()["version"]
    points = client.get("/api/map/points")
    poses = client.get("/api/map/poses")
    offsets = client.get("/api/map/offsets")
    for r in (points, poses, offsets):
        assert r.status_code == 200
        assert r.headers["content-type"] == "application/octet-stream"
    assert len(points.content) == m.num_points * 2 * 4
    assert len(poses.content) == m.num_poses * 3 * 4
    assert len(offsets.content) == (m.num_poses + 1) * 4
    assert int(points.headers["X-Map-Version"]) >= version
    assert np.array_equal(f32(points.content, 2), m.world_points().astype(np.float32))
    assert np.array_equal(f32(poses.content, 3), m.poses.astype(np.float32))
    assert np.array_equal(np.frombuffer(offsets.content, dtype="<i4"), m.offsets)
    # The page's own array: each scan's points once, in the robot frame.
    scans = client.get("/api/map/scans")
    assert scans.headers["content-type"] == "application/octet-stream"
    assert np.array_equal(f32(scans.content, 2), m.points.astype(np.float32))


# -- interpret, apply, reject -------------------------------------------------------------------


def test_interpret_previews_and_changes_nothing(
    client: TestClient, room: Scenario, drawings: list[Correction]
) -> None:
    before = wait_for_metric(client)  # so that no version can come from the metric meanwhile
    poses = poses_bytes(client)
    preview = client.post("/api/interpret", json=as_json(drawings[0])).json()
    assert preview["accepted"] is True
    assert preview["mode"] == "collinear"
    assert len(preview["line_a"]) == 2
    assert preview["notes"]
    offsets = room.map.offsets
    for s, x in (("s_a", "x_a"), ("s_b", "x_b")):
        index = np.frombuffer(base64.b64decode(preview[s]), dtype="<u4")
        assert index.size > 10
        # Each global point index belongs to a pose of the matching pose set.
        owners = np.searchsorted(offsets, index, side="right") - 1
        assert set(owners.tolist()) <= set(preview[x])
    after = client.get("/api/state").json()
    assert after == before
    assert poses_bytes(client) == poses


def test_apply_moves_the_map_and_the_relation_holds(
    client: TestClient, room: Scenario, drawings: list[Correction]
) -> None:
    before = poses_bytes(client)
    version = client.get("/api/state").json()["version"]
    r = client.post("/api/corrections", json=as_json(drawings[0]))
    assert r.status_code == 200
    applied = r.json()
    assert applied["accepted"] is True
    assert applied["solve_ms"] > 0
    assert applied["preview"]["accepted"] is True
    state = applied["state"]
    assert state["version"] > version
    assert state["map_version"] == state["version"]
    assert (state["applied"], state["can_undo"], state["can_redo"]) == (1, True, False)
    assert state["last"]["kind"] == "apply"
    assert state["last"]["iterations"] >= 1
    assert state["last"]["cost"] <= state["last"]["initial_cost"]
    entry = state["history"][0]
    assert entry["status"] == "applied"
    assert entry["drawn"] == as_json(drawings[0])
    assert entry["line_a"] is not None
    assert entry["x_a"]
    assert entry["x_b"]
    after = poses_bytes(client)
    assert after != before
    moved = f32(after, 3)
    assert not np.array_equal(moved, f32(before, 3))
    points = client.get("/api/map/points")
    assert int(points.headers["X-Map-Version"]) >= state["version"]
    (relation,) = client.get("/api/relations").json()
    assert relation["index"] == 0
    assert relation["mode"] == "collinear"
    assert relation["angle_deg"] < 0.3
    assert relation["offset_m"] < 0.02


def residual(m: Map, poses: NDArray[np.float64], h: Interpretation) -> tuple[float, float]:
    """(angle between the lines refit to S_a and S_b [deg], offset of S_b's centroid from
    line a [m]) for a collinear correction, computed here independently of the server."""
    world = m.world_points(poses)
    pa = world[m.offsets[h.s_a[:, 0]] + h.s_a[:, 1]]
    pb = world[m.offsets[h.s_b[:, 0]] + h.s_b[:, 1]]
    phi_a, rho_a = fit_line(pa)
    phi_b, _ = fit_line(pb)
    e = phi_b - phi_a
    e -= math.pi * round(e / math.pi)
    centre = pb.mean(axis=0)
    return abs(math.degrees(e)), abs(
        math.cos(phi_a) * centre[0] + math.sin(phi_a) * centre[1] - rho_a
    )


def test_relations_are_measured_on_the_current_poses(
    client: TestClient, host: SessionHost, room: Scenario, drawings: list[Correction]
) -> None:
    assert client.get("/api/relations").json() == []
    client.post("/api/corrections", json=as_json(drawings[0]))
    client.post("/api/corrections", json=as_json(drawings[1]))
    relations = client.get("/api/relations").json()
    assert [r["index"] for r in relations] == [0, 1]
    for relation, h in zip(relations, host.session.active, strict=True):
        angle, offset = residual(room.map, host.session.poses, h)
        assert relation["angle_deg"] == pytest.approx(angle, abs=1e-9)
        assert relation["offset_m"] == pytest.approx(offset, abs=1e-9)
        # The same observations on the damaged input poses: the relation was broken.
        angle0, offset0 = residual(room.map, room.map.poses, h)
        assert angle0 > 1.0 or offset0 > 0.05
    client.post("/api/undo")
    assert [r["index"] for r in client.get("/api/relations").json()] == [0]


def test_drawing_over_empty_space_is_rejected_and_changes_nothing(client: TestClient) -> None:
    poses = poses_bytes(client)
    points = client.get("/api/map/points").content
    before = client.get("/api/state").json()
    r = client.post("/api/corrections", json=EMPTY_SPACE)
    assert r.status_code == 200
    rejected = r.json()
    assert rejected["accepted"] is False
    assert "no observations" in rejected["reason"]
    state = rejected["state"]
    assert state["applied"] == 0
    assert not state["can_undo"]
    assert state["last"]["kind"] == "reject"
    assert state["last"]["reason"] == rejected["reason"]
    assert state["map_version"] == before["map_version"]
    assert [e["status"] for e in state["history"]] == ["rejected"]
    assert poses_bytes(client) == poses
    assert client.get("/api/map/points").content == points
    preview = client.post("/api/interpret", json=EMPTY_SPACE).json()
    assert preview["accepted"] is False
    assert "no observations" in preview["reason"]


def test_undo_restores_the_poses_exactly_and_redo_reapplies(
    client: TestClient, drawings: list[Correction]
) -> None:
    r = client.post("/api/undo")
    assert r.status_code == 409
    assert r.json() == {"detail": "nothing to undo"}
    assert client.post("/api/redo").status_code == 409
    initial = poses_bytes(client)
    client.post("/api/corrections", json=as_json(drawings[0]))
    first = poses_bytes(client)
    client.post("/api/corrections", json=as_json(drawings[1]))
    second = poses_bytes(client)
    assert len({initial, first, second}) == 3

    state = client.post("/api/undo").json()
    assert (state["applied"], state["can_undo"], state["can_redo"]) == (1, True, True)
    assert state["last"]["kind"] == "undo"
    assert [e["status"] for e in state["history"]] == ["applied", "undone"]
    assert poses_bytes(client) == first
    client.post("/api/undo")
    assert poses_bytes(client) == initial
    assert client.post("/api/undo").status_code == 409

    state = client.post("/api/redo").json()
    assert state["last"]["kind"] == "redo"
    assert poses_bytes(client) == first
    client.post("/api/redo")
    assert poses_bytes(client) == second
    assert client.post("/api/redo").status_code == 409
    assert len(client.get("/api/relations").json()) == 2


def test_a_new_correction_discards_the_redo_stack(
    client: TestClient, drawings: list[Correction]
) -> None:
    client.post("/api/corrections", json=as_json(drawings[0]))
    client.post("/api/undo")
    state = client.post("/api/corrections", json=as_json(drawings[0]))
    assert [e["status"] for e in state.json()["state"]["history"]] == ["discarded", "applied"]
    assert client.post("/api/redo").status_code == 409


# -- notification ---------------------------------------------------------------------------------


def test_long_poll_returns_promptly_on_a_change_from_another_thread(
    room: Scenario, tmp_path: Path, drawings: list[Correction]
) -> None:
    host = SessionHost(Session.open(session_file(room, tmp_path)), poll_timeout=10.0, metrics=False)
    try:
        with TestClient(
            create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS
        ) as client:
            version = client.get("/api/state").json()["version"]
            changer = threading.Timer(0.3, host.apply, args=(drawings[0],))
            changer.start()
            t0 = time.monotonic()
            state = client.get(f"/api/state?after={version}").json()
            elapsed = time.monotonic() - t0
            changer.join()
            assert state["version"] > version
            assert state["applied"] == 1
            assert 0.25 < elapsed < 5.0
            # Already behind: answered at once.
            t0 = time.monotonic()
            assert client.get(f"/api/state?after={version}").json()["version"] > version
            assert time.monotonic() - t0 < 2.0
    finally:
        host.close()


def test_long_poll_times_out_with_the_unchanged_state(room: Scenario, tmp_path: Path) -> None:
    host = SessionHost(Session.open(session_file(room, tmp_path)), poll_timeout=0.4, metrics=False)
    try:
        with TestClient(
            create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS
        ) as client:
            state = client.get("/api/state").json()
            t0 = time.monotonic()
            again = client.get(f"/api/state?after={state['version']}").json()
            elapsed = time.monotonic() - t0
            assert again == state
            assert 0.35 < elapsed < 3.0
        # The same wait without HTTP.
        t0 = time.monotonic()
        assert host.wait_for_change(state["version"], timeout=0.2)["version"] == state["version"]
        assert time.monotonic() - t0 >= 0.15
    finally:
        host.close()


def test_host_wait_wakes_on_change_and_on_close(
    host: SessionHost, drawings: list[Correction]
) -> None:
    version = host.version
    threading.Timer(0.2, host.apply, args=(drawings[0],)).start()
    t0 = time.monotonic()
    # The inconsistency of the initial map may arrive first (also a new version); wait past it.
    state = host.wait_for_change(version, timeout=10.0)
    while state["applied"] == 0 and time.monotonic() - t0 < 10.0:
        state = host.wait_for_change(state["version"], timeout=10.0)
    assert state["applied"] == 1
    assert time.monotonic() - t0 < 5.0
    while state["inconsistency_m2"] is None:  # let the metric's own new version pass
        state = host.wait_for_change(state["version"], timeout=10.0)
    current = host.version
    threading.Timer(0.2, host.wake_all).start()
    t0 = time.monotonic()
    host.wait_for_change(current, timeout=10.0)
    assert time.monotonic() - t0 < 5.0
    assert host.closing


def test_inconsistency_arrives_after_each_change(
    client: TestClient, host: SessionHost, room: Scenario, drawings: list[Correction]
) -> None:
    initial = wait_for_metric(client)
    expected = inconsistency(room.map, room.map.poses, DEFAULT).total_m2
    assert initial["inconsistency_m2"] == pytest.approx(expected)
    applied = client.post("/api/corrections", json=as_json(drawings[0])).json()["state"]
    # Not waited for by the request; then published under a newer version.
    if applied["inconsistency_m2"] is None:
        later = client.get(f"/api/state?after={applied['version']}").json()
        assert later["version"] > applied["version"]
    later = wait_for_metric(client)
    poses = host.session.poses
    assert later["inconsistency_m2"] == pytest.approx(
        inconsistency(room.map, poses, DEFAULT).total_m2
    )
    assert later["inconsistency_m2"] < initial["inconsistency_m2"]
    # Undo returns to a map whose value is known: shown at once.
    undone = client.post("/api/undo").json()
    assert undone["inconsistency_m2"] == initial["inconsistency_m2"]


def test_two_clients_stay_consistent(host: SessionHost, drawings: list[Correction]) -> None:
    app = create_app(host, token=None)
    with (
        TestClient(app, base_url=BASE, headers=PAGE_HEADERS) as a,
        TestClient(app, base_url=BASE, headers=PAGE_HEADERS) as b,
    ):
        version = b.get("/api/state").json()["version"]
        seen: dict[str, Any] = {}

        def watch() -> None:
            state = b.get(f"/api/state?after={version}").json()
            while state["applied"] == 0:
                state = b.get(f"/api/state?after={state['version']}").json()
            seen["state"] = state
            seen["poses"] = b.get("/api/map/poses").content

        watcher = threading.Thread(target=watch)
        watcher.start()
        applied = a.post("/api/corrections", json=as_json(drawings[0])).json()
        watcher.join(timeout=30)
        assert not watcher.is_alive()
        assert seen["state"]["history"] == applied["state"]["history"]
        assert seen["poses"] == a.get("/api/map/poses").content

        # Two corrections sent at once from both clients are applied one after the other.
        results: list[dict[str, Any]] = []
        sends = [
            threading.Thread(
                target=lambda c=c, d=d: results.append(
                    c.post("/api/corrections", json=as_json(d)).json()
                )
            )
            for c, d in ((a, drawings[1]), (b, drawings[2]))
        ]
        for t in sends:
            t.start()
        for t in sends:
            t.join(timeout=60)
        assert len(results) == 2
        final_a, final_b = a.get("/api/state").json(), b.get("/api/state").json()
        # The inconsistency of the new map may arrive (a new version) between the two reads.
        metric = ("version", "inconsistency_m2")
        assert {k: v for k, v in final_a.items() if k not in metric} == {
            k: v for k, v in final_b.items() if k not in metric
        }
        accepted = sum(r["accepted"] for r in results)
        assert final_a["applied"] == 1 + accepted
        assert len(final_a["history"]) == 3
        versions = sorted(r["state"]["version"] for r in results)
        assert versions[0] < versions[1]


# -- journal step-through, save, export ---------------------------------------------------------


def test_journal_step_applies_the_corrections_file_in_order(
    room: Scenario, tmp_path: Path, drawings: list[Correction]
) -> None:
    corrections = tmp_path / "fixes.jsonl"
    corrections.write_text(
        "\n".join(
            [
                json.dumps(as_json(drawings[0])),
                json.dumps(as_json(drawings[1])),
                '{"action": "undo"}',
                json.dumps(EMPTY_SPACE),
            ]
        )
        + "\n"
    )
    steps = read_corrections(corrections)
    host = SessionHost(
        Session.open(session_file(room, tmp_path / "s")),
        journal=steps,
        journal_source=corrections.name,
    )
    try:
        with TestClient(
            create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS
        ) as client:
            state = client.get("/api/state").json()
            assert state["journal"] == {"loaded": 4, "next": 0, "source": "fixes.jsonl"}
            first = client.post("/api/journal/step").json()
            assert first["accepted"] is True
            assert first["preview"]["accepted"] is True
            assert first["state"]["journal"]["next"] == 1
            after_first = poses_bytes(client)
            second = client.post("/api/journal/step").json()
            assert second["state"]["applied"] == 2
            undo = client.post("/api/journal/step").json()
            assert undo["accepted"] is True
            assert undo["preview"] is None
            assert undo["state"]["applied"] == 1
            assert undo["state"]["last"]["kind"] == "undo"
            assert poses_bytes(client) == after_first
            rejected = client.post("/api/journal/step").json()
            assert rejected["accepted"] is False
            assert rejected["reason"].startswith("journal line 4: no observations")
            assert rejected["state"]["journal"]["next"] == 4
            r = client.post("/api/journal/step")
            assert r.status_code == 409
            assert "all 4 steps" in r.json()["detail"]
    finally:
        host.close()


def test_journal_step_without_a_journal_is_a_conflict(client: TestClient) -> None:
    r = client.post("/api/journal/step")
    assert r.status_code == 409
    assert "--journal" in r.json()["detail"]


def test_save_writes_the_four_files_beside_the_session(
    client: TestClient, host: SessionHost, room: Scenario, drawings: list[Correction]
) -> None:
    client.post("/api/corrections", json=as_json(drawings[0]))
    folder = Path(host.folder)
    r = client.post("/api/save", json={})
    assert r.status_code == 200
    files = r.json()["files"]
    assert files == [f"room-corrected{ext}" for ext in (".txt", ".g2o", ".pgm", ".yaml")]
    for name in files:
        assert (folder / name).is_file()
        assert (folder / name).stat().st_size > 0
    tum = np.loadtxt(folder / "room-corrected.txt")
    assert tum.shape == (room.map.num_poses, 8)
    assert np.allclose(tum[:, 1:3], host.session.poses[:, :2])
    named = client.post("/api/save", json={"name": "fixed_v2"}).json()["files"]
    assert named[0] == "fixed_v2.txt"
    assert (folder / "fixed_v2.yaml").is_file()
    # Without a body at all, the default name again.
    assert client.post("/api/save").json()["files"][0] == "room-corrected.txt"
    assert sorted(p.name for p in folder.iterdir() if p.name.startswith(".")) == []


def test_export_formats(client: TestClient, host: SessionHost, drawings: list[Correction]) -> None:
    client.post("/api/corrections", json=as_json(drawings[0]))
    folder = Path(host.folder)
    for name, expected in (
        ("out.g2o", ["out.g2o"]),
        ("out.txt", ["out.txt"]),
        ("out.covars", ["out.covars"]),
        ("grid.pgm", ["grid.pgm", "grid.yaml"]),
        ("fixes.jsonl", ["fixes.jsonl"]),
    ):
        r = client.post("/api/export", json={"path": name})
        assert r.status_code == 200, r.text
        assert r.json()["files"] == expected
        for f in expected:
            assert (folder / f).is_file()
    assert "VERTEX_SE2" in (folder / "out.g2o").read_text()
    steps = read_corrections(folder / "fixes.jsonl")
    assert [s.drawn for s in steps] == [drawings[0]]  # type: ignore[union-attr]
    (folder / "sub").mkdir()
    assert client.post("/api/export", json={"path": "sub/x.g2o"}).json()["files"] == ["sub/x.g2o"]
    r = client.post("/api/export", json={"path": "x.bmp"})
    assert r.status_code == 400
    assert ".g2o" in r.json()["detail"]
    assert client.post("/api/export", json={"path": "missing/x.g2o"}).status_code == 400


# -- the session across restarts ------------------------------------------------------------------


def test_reopening_the_session_gives_the_same_state(
    room: Scenario, tmp_path: Path, drawings: list[Correction]
) -> None:
    path = session_file(room, tmp_path)
    host = SessionHost(Session.open(path), metrics=False)
    with TestClient(create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS) as client:
        for d in drawings:
            client.post("/api/corrections", json=as_json(d))
        client.post("/api/corrections", json=EMPTY_SPACE)
        client.post("/api/undo")
        before = client.get("/api/state").json()
        arrays = [client.get(f"/api/map/{a}").content for a in ("points", "poses", "offsets")]
        relations = client.get("/api/relations").json()
    host.close()

    host = SessionHost(Session.open(path), metrics=False)
    try:
        with TestClient(
            create_app(host, token=None), base_url=BASE, headers=PAGE_HEADERS
        ) as client:
            after = client.get("/api/state").json()
            assert [client.get(f"/api/map/{a}").content for a in ("points", "poses")] == arrays[:2]
            assert client.get("/api/map/offsets").content == arrays[2]
            assert client.get("/api/relations").json() == relations
            for key in ("version", "map_version", "last", "inconsistency_m2"):
                before.pop(key)
                after.pop(key)
            assert after == before
            assert [e["status"] for e in after["history"]] == [
                "applied",
                "applied",
                "undone",
                "rejected",
            ]
            # ... and it continues where it was left: redo the undone correction.
            assert client.post("/api/redo").json()["applied"] == 3
    finally:
        host.close()


def test_host_refuses_output_for_an_in_memory_session(room: Scenario) -> None:
    host = SessionHost(Session.new(room.map), metrics=False)
    try:
        with pytest.raises(InputError, match="in memory"):
            host.save()
        with pytest.raises(NothingToDo):
            host.undo()
    finally:
        host.close()


# -- opening sessions and the command -----------------------------------------------------------


def test_open_session_creates_then_reopens_beside_the_map(room: Scenario, tmp_path: Path) -> None:
    covars = tmp_path / "lab.covars"
    write_covars(room.map, room.map.poses, covars)
    session, how = open_session(covars)
    session.close()
    assert how.startswith("created the session")
    assert (tmp_path / "lab.hitl").is_file()
    session, how = open_session(covars)
    session.close()
    assert how.startswith("reopened the session")
    session, how = open_session(tmp_path / "lab.hitl")
    session.close()
    assert how.startswith("reopened")
    assert session_path_for("logs/run.clf.gz") == Path("logs/run.hitl")
    assert session_path_for("a.b.log") == Path("a.b.hitl")
    with pytest.raises(InputError, match="no such"):
        open_session(tmp_path / "nope.hitl")
    with pytest.raises(InputError, match="exactly one"):
        open_session(None)
    with pytest.raises(InputError, match="exactly one"):
        open_session(covars, demo="lost-poses")


def test_open_session_demo_lives_under_the_current_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    session, how = open_session(demo="lost-poses")
    session.close()
    assert (tmp_path / "hitl-demo" / "lost-poses.hitl").is_file()
    assert "created the demo session" in how
    session, how = open_session(demo="lost-poses")
    session.close()
    assert "reopened the demo session" in how
    with pytest.raises(InputError, match="unknown demo world"):
        open_session(demo="mars")


def test_serve_help_teaches_by_example(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["serve", "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "hitl-slam serve --demo" in out
    assert "--no-token" in out
    assert "--journal" in out
    assert "Shift" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["serve"], "exactly one"),
        (["serve", "x.hitl", "--demo"], "not both"),
        (["serve", "--demo-world", "campus"], "--demo-world goes with --demo"),
        (["serve", "nowhere.hitl"], "no such session file"),
        (["serve", "--demo", "--port", "70000"], "--port"),
        (["serve", "--demo", "--journal", "missing.jsonl"], "no such file"),
        (["serve", "--demo", "--token", "a b c d e f g h"], "token"),
    ],
)
def test_serve_bad_arguments_exit_2_with_one_line(
    argv: list[str],
    message: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert message in err[0]


def test_demo_points_to_the_serve_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "d"
    assert main(["demo", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"hitl-slam serve {out / 'lost-poses.hitl'}\n" in text
    assert "not part of this version" not in text


def test_other_requests_are_answered_while_a_correction_computes(
    room: Scenario, drawings: list[Correction], tmp_path: Path
) -> None:
    # An applier that takes a second (without the GIL, like the Rust solve): meanwhile the state,
    # the arrays and the long-poll answer at once, with the map from before the correction.
    from hitl_slam.pipeline import apply_correction

    started = threading.Event()

    def slow(*args: Any) -> Any:
        started.set()
        time.sleep(1.0)
        return apply_correction(*args)

    session = Session.new(room.map, tmp_path / "slow.hitl", applier=slow)
    h = SessionHost(session, poll_timeout=5.0, metrics=False)
    try:
        with TestClient(create_app(h, token=None), base_url=BASE, headers=PAGE_HEADERS) as c:
            before = c.get("/api/map/poses").content
            done: dict[str, Any] = {}

            def send() -> None:
                done["answer"] = c.post("/api/corrections", json=as_json(drawings[0])).json()
                done["at"] = time.monotonic()

            sender = threading.Thread(target=send)
            sender.start()
            assert started.wait(10)
            t0 = time.monotonic()
            state = c.get("/api/state").json()
            poses = c.get("/api/map/poses").content
            answered = time.monotonic()
            sender.join(30)
            assert answered - t0 < 0.5  # not queued behind the solve
            assert answered < done["at"]
            assert state["applied"] == 0
            assert poses == before
            assert done["answer"]["accepted"] is True
            assert c.get("/api/state").json()["applied"] == 1
    finally:
        h.close()


# -- what the page draws: solved lines and robot-frame scans -------------------------------------


def test_state_serves_the_solved_lines(
    host: SessionHost, client: TestClient, room: Scenario, drawings: list[Correction]
) -> None:
    """Each correction in effect comes with its solved lines (the session's, not a refit), each
    as the stretch of that line its observations cover; undo brings the earlier ones back."""
    states = []
    for d in drawings[:2]:
        r = client.post("/api/corrections", json=as_json(d)).json()
        assert r["accepted"], r
        states.append(r["state"])
    session = host.session
    lines = session.lines
    state = states[-1]
    assert [c["index"] for c in state["lines"]] == [0, 1]
    poses = session.poses
    for k, (c, h) in enumerate(zip(state["lines"], session.active, strict=True)):
        assert c["mode"] == h.mode.value
        for side, rows, row in (("a", h.s_a, 2 * k), ("b", h.s_b, 2 * k + 1)):
            line = c[side]
            assert (line["phi"], line["rho"]) == (lines[row, 0], lines[row, 1])
            normal = np.array([math.cos(line["phi"]), math.sin(line["phi"])])
            ends = np.array(line["segment"])
            np.testing.assert_allclose(ends @ normal, line["rho"], atol=1e-9)
            # It covers its observations: their projections along the line fall within it.
            along = np.array([-normal[1], normal[0]])
            t = room.map.observed_points(rows, poses) @ along
            np.testing.assert_allclose(sorted(ends @ along), [t.min(), t.max()], atol=1e-9)
    undone = client.post("/api/undo").json()
    assert undone["lines"] == states[0]["lines"]
    assert client.post("/api/redo").json()["lines"] == state["lines"]


def test_a_correction_costs_the_page_only_its_poses(
    client: TestClient, room: Scenario, drawings: list[Correction]
) -> None:
    """The scans are fetched once in the robot frame; a new map is the poses (N * 12 bytes)."""
    scans = client.get("/api/map/scans").content
    r = client.post("/api/corrections", json=as_json(drawings[0])).json()
    assert r["accepted"]
    assert client.get("/api/map/scans").content == scans
    poses = client.get("/api/map/poses")
    assert len(poses.content) == room.map.num_poses * 12
    assert int(poses.headers["X-Map-Version"]) == r["state"]["version"]
    # Placed as the page places them, the scans are the world points of the new map.
    p = f32(poses.content, 3).astype(np.float64)
    local = f32(scans, 2).astype(np.float64)
    owner = room.map.pose_of_point()
    c, s = np.cos(p[owner, 2]), np.sin(p[owner, 2])
    world = np.stack(
        [
            p[owner, 0] + c * local[:, 0] - s * local[:, 1],
            p[owner, 1] + s * local[:, 0] + c * local[:, 1],
        ],
        axis=1,
    )
    np.testing.assert_allclose(world, f32(client.get("/api/map/points").content, 2), atol=2e-4)


def test_bounds_are_exact_without_placing_every_point(room: Scenario) -> None:
    from hitl_slam.web.drawing import MapDrawing

    drawing = MapDrawing(room.map)
    rng = np.random.default_rng(3)
    for scale in (0.0, 0.3, 5.0):
        poses = room.map.poses + scale * rng.normal(size=room.map.poses.shape)
        xy = np.concatenate([room.map.world_points(poses), poses[:, :2]])
        assert drawing.bounds(poses) == (*xy.min(axis=0), *xy.max(axis=0))


def test_bounds_stay_exact_for_degenerate_scans_and_any_move() -> None:
    """The bounds place only each scan's hull vertices, then whole only the scans near an
    extreme: scans of no, one, two, repeated or collinear points, a wall of points a hair off
    its line, and poses moved far beyond where the map was (as a correction may move them) give
    exactly the extremes of every point, bit for bit, before and after the move."""
    from hitl_slam.web.drawing import MapDrawing

    rng = np.random.default_rng(7)
    wall = np.stack([np.linspace(-3.0, 3.0, 61), 2.0 + 1e-12 * rng.normal(size=61)], axis=1)
    scans = [
        np.empty((0, 2)),
        np.array([[1.0, 2.0]]),
        np.array([[1.0, 2.0], [-3.0, 0.5]]),
        np.array([[1.5, 1.5]] * 5),
        np.stack([np.linspace(0.0, 4.0, 9), np.linspace(1.0, 3.0, 9)], axis=1),
        wall,
        *(rng.normal(scale=5.0, size=(int(rng.integers(3, 40)), 2)) for _ in range(40)),
    ]
    n = len(scans)
    poses = np.stack([rng.normal(size=n), rng.normal(size=n), rng.uniform(-4, 4, n)], axis=1)
    map = Map.from_poses_and_scans(poses, scans, name="odd")
    drawing = MapDrawing(map)
    for shift in (0.0, 1.0, 1e3, 1e6):
        for _ in range(20):
            moved = poses.copy()
            moved[:, :2] += shift * rng.normal(size=(n, 2))
            moved[:, 2] = rng.uniform(-4, 4, n)
            xy = np.concatenate([map.world_points(moved), moved[:, :2]])
            assert drawing.bounds(moved) == (*xy.min(axis=0), *xy.max(axis=0))


def test_bounds_are_exact_where_a_wall_is_the_extreme() -> None:
    """A straight wall (a scan's hull edge) turned square to an axis: in exact arithmetic its
    points tie, as placed they differ in the last bits, and a point inside the edge (no hull
    vertex) can be the extreme; the bounds are still those of every point, bit for bit."""
    from hitl_slam.web.drawing import MapDrawing

    rng = np.random.default_rng(11)
    t = np.linspace(-4.0, 4.0, 200)
    inner = 0
    for beta in rng.uniform(-np.pi, np.pi, 8):
        wall = np.stack([3.0 + t * np.cos(beta), -1.0 + t * np.sin(beta)], axis=1)
        behind = [3.0 + 2.0 * np.sin(beta), -1.0 - 2.0 * np.cos(beta)]
        map = Map.from_poses_and_scans(np.zeros((1, 3)), [np.vstack([wall, [behind]])])
        drawing = MapDrawing(map)
        for trial in range(24):
            # The wall's outward normal along +x, +y, -x or -y in the world.
            theta = np.pi / 2 * (trial % 4) - beta - np.pi / 2 + rng.normal(scale=1e-13)
            pose = np.array([[*rng.normal(scale=0.01, size=2), theta]])
            world = map.world_points(pose)
            xy = np.concatenate([world, pose[:, :2]])
            expected = (*xy.min(axis=0), *xy.max(axis=0))
            assert drawing.bounds(pose) == expected
            axis, value = trial % 2, expected[(trial + 2) % 4]
            at = np.flatnonzero(world[:, axis] == value)
            inner += int(np.all((at > 0) & (at < t.size - 1)))
    assert inner > 0  # the case this test is about did occur
