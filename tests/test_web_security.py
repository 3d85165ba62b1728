"""Who can reach `hitl-slam serve` and what bad requests do: no unauthenticated server off
loopback, the token on every route (query, bearer, cookie), the Host check against DNS
rebinding, save/export paths kept inside the session folder, body-size limits, malformed JSON, and
a SIGKILL during a correction losing nothing acknowledged (real server processes)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import select
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from hitl_slam.corrections import Correction
from hitl_slam.errors import InputError
from hitl_slam.session import Session
from hitl_slam.sim import SimulatedHuman, campus, lost_poses_room
from hitl_slam.web import SessionHost, create_app, run_server
from hitl_slam.web.schemas import Drawn
from hitl_slam.web.security import BodyLimit, is_loopback

with warnings.catch_warnings():
    # starlette 1.x asks for httpx2 behind its TestClient; httpx (installed) serves the same.
    warnings.simplefilter("ignore", UserWarning)
    from starlette.testclient import TestClient

TOKEN = "test-token-0123456789"
BASE = "http://127.0.0.1:8765"
REFUSED_NO_TOKEN = "refusing to serve on 0.0.0.0 without an access token; drop --no-token"
# The simulated person's first drawing on the lost-poses room (seed 0): the server accepts it.
DRAWN: dict[str, Any] = {
    "mode": "collinear",
    "a": [[4.211911960548843, 0.0006517842233591813], [4.748997309998837, 0.006803661175207041]],
    "b": [[4.247261434931527, 0.04460687181064192], [5.726351430444526, 0.7704815930762334]],
    "sigma_h": 0.02,
}


# -- fixtures ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def room_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A session file of the lost-poses room, copied for each test that changes it."""
    path = tmp_path_factory.mktemp("room") / "room.hitl"
    Session.new(lost_poses_room(0).map, path).close()
    return path


@dataclass
class Site:
    """A session folder, a folder beside it that must stay untouched, and the static files."""

    folder: Path
    outside: Path
    static: Path
    host: SessionHost


@pytest.fixture
def site(room_session: Path, tmp_path: Path) -> Iterator[Site]:
    folder, outside, static = tmp_path / "session", tmp_path / "outside", tmp_path / "static"
    for d in (folder, outside, static):
        d.mkdir()
    (folder / "room.hitl").write_bytes(room_session.read_bytes())
    (outside / "keep.g2o").write_text("precious\n")
    (static / "index.html").write_text("<!doctype html><title>hitl-slam test page</title>")
    (static / "probe.txt").write_text("static ok")
    host = SessionHost(Session.open(folder / "room.hitl"), metrics=False)
    yield Site(folder, outside, static, host)
    host.close()


def app_client(site: Site, token: str | None = TOKEN, **kwargs: Any) -> TestClient:
    app = create_app(site.host, token=token, static_dir=site.static, **kwargs)
    return TestClient(app, base_url=BASE, raise_server_exceptions=False)


@pytest.fixture
def client(site: Site) -> Iterator[TestClient]:
    with app_client(site) as c:
        c.headers["Authorization"] = f"Bearer {TOKEN}"
        yield c


def snapshot_tree(path: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes()
        for p in sorted(path.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


# -- no token off loopback ------------------------------------------------------------------------


def test_loopback_detection() -> None:
    for host in ("127.0.0.1", "127.0.0.2", "::1", "[::1]", "localhost"):
        assert is_loopback(host), host
    for host in ("0.0.0.0", "::", "", "192.168.1.10", "10.0.0.1", "8.8.8.8"):
        assert not is_loopback(host), host


@pytest.mark.parametrize("bind", ["0.0.0.0", "::", "192.168.1.10"])
def test_the_library_refuses_a_tokenless_server_off_loopback(
    bind: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, site: Site
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=f"refusing to serve on {re.escape(bind)} without"):
        run_server(demo="lost-poses", host=bind, port=0, no_token=True)
    assert not (tmp_path / "hitl-demo").exists()  # refused before anything was created
    with pytest.raises(InputError, match="without an access token"):
        create_app(site.host, token=None, bind=bind)
    # With a token the same bind is allowed (and the Host header is not restricted).
    with TestClient(
        create_app(site.host, token=TOKEN, bind=bind), base_url="http://lan-name.example:8765"
    ) as c:
        assert c.get("/api/state", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200


def test_the_command_refuses_a_tokenless_server_off_loopback(tmp_path: Path) -> None:
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "hitl_slam.cli",
            "serve",
            "--demo",
            "--host",
            "0.0.0.0",
            "--no-token",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2
    assert run.stderr.strip().splitlines() == [f"hitl-slam: error: {REFUSED_NO_TOKEN}"]
    assert run.stdout == ""
    assert not (tmp_path / "hitl-demo").exists()


def test_token_and_no_token_together_are_refused(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "hitl_slam.cli", "serve", "--demo", "--token", TOKEN, "--no-token"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2
    assert "not allowed with argument" in run.stderr


# -- the token ------------------------------------------------------------------------------------

ROUTES = [
    ("GET", "/"),
    ("GET", "/static/probe.txt"),
    ("GET", "/static/missing.js"),
    ("GET", "/api/state"),
    ("GET", "/api/state?after=1"),
    ("GET", "/api/map/points"),
    ("GET", "/api/map/poses"),
    ("GET", "/api/map/offsets"),
    ("GET", "/api/relations"),
    ("GET", "/api/loop_closures"),
    ("POST", "/api/interpret"),
    ("POST", "/api/loop_closures"),
    ("POST", "/api/corrections"),
    ("POST", "/api/undo"),
    ("POST", "/api/redo"),
    ("POST", "/api/save"),
    ("POST", "/api/export"),
    ("POST", "/api/journal/step"),
]
WRONG = [
    {},
    {"params": {"token": "wrong-token-0123456789"}},
    {"params": {"token": ""}},
    {"headers": {"Authorization": "Bearer wrong-token-0123456789"}},
    {"headers": {"Authorization": f"Basic {TOKEN}"}},
    {"headers": {"Cookie": "hitl_token=wrong-token-0123456789"}},
    {"params": {"token": TOKEN[:-1]}},
    {"params": {"token": TOKEN + "x"}},
    {"params": {"token": "é" * 20}},
]


@pytest.mark.parametrize(("method", "path"), ROUTES)
def test_every_route_needs_the_token(method: str, path: str, site: Site) -> None:
    with app_client(site) as c:
        for credentials in WRONG:
            r = c.request(method, path, json=DRAWN if method == "POST" else None, **credentials)
            assert r.status_code == 403, (path, credentials)
            if path == "/":  # a person at a browser gets a page saying how to get in
                assert r.headers["content-type"] == "text/html; charset=utf-8"
                assert "?token=" in r.text
            else:
                assert "token" in r.json()["detail"]
            assert "set-cookie" not in r.headers
            assert r.headers["cache-control"] == "no-store"
            assert r.headers["x-content-type-options"] == "nosniff"
    # Nothing was changed by any of those requests.
    assert site.host.session.history == []
    assert snapshot_tree(site.folder).keys() == {"room.hitl"}


@pytest.mark.parametrize(
    "credentials",
    [
        {"params": {"token": TOKEN}},
        {"headers": {"Authorization": f"Bearer {TOKEN}"}},
        {"headers": {"Authorization": f"bearer  {TOKEN} "}},
        {"headers": {"Cookie": f"hitl_token={TOKEN}"}},
        {"headers": {"Cookie": f"other=1; hitl_token_8765={TOKEN}"}},
    ],
)
def test_the_right_token_works_by_query_bearer_and_cookie(
    credentials: dict[str, Any], site: Site
) -> None:
    with app_client(site) as c:
        page = c.get("/", **credentials)
        assert page.status_code == 200
        assert "hitl-slam test page" in page.text
        c.cookies.clear()  # the page's cookie must not stand in for the credentials under test
        assert c.get("/static/probe.txt", **credentials).text == "static ok"
        assert c.get("/static/missing.js", **credentials).status_code == 404
        assert c.get("/api/state", **credentials).json()["num_poses"] == 499
        headers = {"X-Hitl-Slam": "1", **credentials.get("headers", {})}
        r = c.post("/api/undo", params=credentials.get("params"), headers=headers)
        assert r.status_code == 409  # authenticated; nothing to undo


def test_the_page_sets_the_cookie_and_the_cookie_alone_then_works(site: Site) -> None:
    with app_client(site) as c:
        page = c.get("/", params={"token": TOKEN})
        cookies = page.headers.get_list("set-cookie")
        assert f"hitl_token={TOKEN}; HttpOnly; SameSite=Strict; Path=/" in cookies
        assert f"hitl_token_8765={TOKEN}; HttpOnly; SameSite=Strict; Path=/" in cookies
        # An API answer sets no cookie.
        assert "set-cookie" not in c.get("/api/state", params={"token": TOKEN}).headers
    with app_client(site) as fresh:
        assert fresh.get("/api/state").status_code == 403
        header = {"Cookie": f"hitl_token={TOKEN}"}
        assert fresh.get("/api/map/poses", headers=header).status_code == 200


def test_no_token_server_on_loopback_needs_none(site: Site) -> None:
    with app_client(site, token=None) as c:
        assert c.get("/api/state").status_code == 200
        assert c.get("/").status_code == 200


@pytest.mark.parametrize("token", ["short", "has space in it", "semi;colon;token", "é" * 10])
def test_unusable_tokens_are_refused(token: str, site: Site) -> None:
    with pytest.raises(InputError, match="access token must be"):
        create_app(site.host, token=token)


def test_a_missing_front_end_is_a_404_not_a_crash(site: Site, tmp_path: Path) -> None:
    app = create_app(site.host, token=None, static_dir=tmp_path / "nothing-here")
    with TestClient(app, base_url=BASE, raise_server_exceptions=False) as c:
        page = c.get("/")
        assert page.status_code == 404
        assert "not installed" in page.text
        assert c.get("/static/js/main.js").status_code == 404
        assert c.get("/api/state").status_code == 200


# -- the Host header --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "host",
    ["evil.example", "evil.example:8765", "127.0.0.1.evil.example", "localhost.evil.example:80"],
)
def test_another_sites_host_header_is_refused_on_loopback(host: str, site: Site) -> None:
    with app_client(site) as c:
        headers = {"Host": host, "Authorization": f"Bearer {TOKEN}"}
        for path in ("/", "/api/state", "/static/probe.txt"):
            r = c.get(path, headers=headers)
            assert r.status_code == 403
            assert "Host" in r.json()["detail"]


@pytest.mark.parametrize(
    "host", ["127.0.0.1", "127.0.0.1:8765", "localhost:1234", "LOCALHOST", "[::1]:8765", "[::1]"]
)
def test_loopback_host_headers_are_served(host: str, site: Site) -> None:
    with app_client(site) as c:
        r = c.get("/api/state", headers={"Host": host, "Authorization": f"Bearer {TOKEN}"})
        assert r.status_code == 200


# -- save and export stay inside the session folder -----------------------------------------------


def test_export_paths_cannot_leave_the_session_folder(client: TestClient, site: Site) -> None:
    outside = site.outside
    (site.folder / "link.g2o").symlink_to(outside / "keep.g2o")
    (site.folder / "linked-dir").symlink_to(outside, target_is_directory=True)
    (site.folder / "sub").mkdir()
    (site.folder / "sub" / "up").symlink_to(site.folder.parent, target_is_directory=True)
    before = snapshot_tree(outside)
    refused = {
        "../x.g2o": 403,
        "../outside/x.g2o": 403,
        "a/../../x.g2o": 403,
        "sub/../../outside/x.g2o": 403,
        "..\\x.g2o": 403,
        str(outside / "x.g2o"): 403,
        "/etc/passwd.g2o": 403,
        "~/x.g2o": 403,
        "link.g2o": 403,
        "linked-dir/x.g2o": 403,
        "linked-dir/x.pgm": 403,
        "sub/up/outside/x.g2o": 403,
        "x\x00.g2o": 400,
        "x.g2o\x00.txt": 400,
        "": 403,
        ".": 403,
        "x.exe": 400,
    }
    for path, status in refused.items():
        r = client.post("/api/export", json={"path": path})
        assert r.status_code == status, (path, r.text)
        assert "detail" in r.json()
    assert snapshot_tree(outside) == before
    assert (outside / "keep.g2o").read_text() == "precious\n"
    assert not (site.folder.parent / "x.g2o").exists()
    # Inside is fine, also through a link that stays inside.
    (site.folder / "inner").mkdir()
    (site.folder / "inner-link").symlink_to(site.folder / "inner", target_is_directory=True)
    r = client.post("/api/export", json={"path": "inner-link/fine.g2o"})
    assert r.status_code == 200
    assert r.json()["files"] == ["inner/fine.g2o"]
    # The server still works after all that.
    assert client.get("/api/state").status_code == 200


@pytest.mark.parametrize(
    "name",
    ["../x", "a/b", "a\\b", ".hidden", "..", "x..y", "x" * 101, "a b", "", "nul\x00", "é", "/abs"],
)
def test_save_names_must_be_plain_file_stems(name: str, client: TestClient, site: Site) -> None:
    before = snapshot_tree(site.outside)
    r = client.post("/api/save", json={"name": name})
    assert r.status_code == 400
    assert "plain file name" in r.json()["detail"]
    assert snapshot_tree(site.folder).keys() == {"room.hitl"}
    assert snapshot_tree(site.outside) == before


def test_save_refuses_a_link_out_of_the_folder(client: TestClient, site: Site) -> None:
    (site.folder / "out.g2o").symlink_to(site.outside / "keep.g2o")
    r = client.post("/api/save", json={"name": "out"})
    assert r.status_code == 403
    assert (site.outside / "keep.g2o").read_text() == "precious\n"
    assert client.post("/api/save", json={"name": "fine-name_1.2"}).status_code == 200


def test_wrong_body_types_for_save_and_export(client: TestClient) -> None:
    for path, body in (
        ("/api/save", {"name": 3}),
        ("/api/save", {"name": None, "extra": 1}),
        ("/api/export", {}),
        ("/api/export", {"path": ["x.g2o"]}),
        ("/api/export", {"path": None}),
    ):
        assert client.post(path, json=body).status_code == 422, (path, body)


# -- body size ------------------------------------------------------------------------------------


def test_oversized_bodies_are_refused_with_413(site: Site) -> None:
    with app_client(site, max_body=4096) as c:
        c.headers["Authorization"] = f"Bearer {TOKEN}"
        big = json.dumps({**DRAWN, "pad": "x" * 5000}).encode()
        r = c.post("/api/corrections", content=big, headers={"Content-Type": "application/json"})
        assert r.status_code == 413
        assert "4096" in r.json()["detail"]

        def chunks() -> Iterator[bytes]:
            for _ in range(10):
                yield b" " * 1000

        # No Content-Length (chunked): counted while reading.
        r = c.post("/api/interpret", content=chunks(), headers={"Content-Type": "application/json"})
        assert "content-length" not in r.request.headers
        assert r.status_code == 413
        # A body of exactly the limit is read (and is then bad JSON: 422), then things work.
        r = c.post(
            "/api/corrections", content=b" " * 4096, headers={"Content-Type": "application/json"}
        )
        assert r.status_code == 422
        assert c.post("/api/interpret", json=DRAWN).status_code == 200
    assert site.host.session.history == []


def test_the_body_limit_stops_reading_a_stream_early() -> None:
    """At the ASGI level: an endless chunked body is cut off just past the limit, and the app
    behind the guard never runs."""
    consumed = 0
    sent: list[dict[str, Any]] = []
    reached = False

    async def endless() -> dict[str, Any]:
        nonlocal consumed
        consumed += 1
        return {"type": "http.request", "body": b"x" * 1000, "more_body": True}

    async def send(message: Any) -> None:
        sent.append(message)

    async def app(scope: Any, receive: Any, send: Any) -> None:
        nonlocal reached
        reached = True

    scope = {"type": "http", "method": "POST", "path": "/api/corrections", "headers": []}
    asyncio.run(BodyLimit(app, max_body=10_000)(scope, endless, send))
    assert not reached
    assert consumed == 11
    assert sent[0]["status"] == 413


# -- malformed input --------------------------------------------------------------------------

MALFORMED = [
    b"{",
    b"not json",
    b'{"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]]',
    b"[]",
    b'"collinear"',
    b"null",
    b"{}",
    b'{"mode": "diagonal", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, 0], [1, 0]]}',
    b'{"mode": "collinear", "a": [[0, 0], [1, 0], [2, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, "0"], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, true], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, NaN], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, Infinity], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, 1e999], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]], "sigma_h": 0}',
    b'{"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]], "sigma_h": -1}',
    b'{"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]], "sigma_h": "x"}',
    b'{"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]], "typo": 1}',
    b'{"mode": ["collinear"], "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, 1]]}',
    b'{"mode": "collinear", "a": {"x": 1}, "b": [[0, 1], [1, 1]]}',
    b"\xff\xfe\x00garbage",
    b"[" * 50_000 + b"]" * 50_000,
]


@pytest.mark.parametrize("path", ["/api/interpret", "/api/corrections"])
def test_malformed_json_is_a_client_error_and_the_server_keeps_working(
    path: str, client: TestClient, site: Site
) -> None:
    for body in MALFORMED:
        r = client.post(path, content=body, headers={"Content-Type": "application/json"})
        assert r.status_code in (400, 422), (body[:80], r.status_code, r.text[:200])
        assert "detail" in r.json()
    r = client.get("/api/state", params={"after": "not-a-number"})
    assert r.status_code == 422
    assert site.host.session.history == []
    # Still serving, and still correcting.
    assert client.get("/api/state").status_code == 200
    preview = client.post("/api/interpret", json=DRAWN)
    assert preview.status_code == 200
    assert preview.json()["accepted"] is True


# -- real server processes ------------------------------------------------------------------------

_LISTENING = re.compile(r"hitl-slam serve: listening on (\S+)")


@dataclass
class Served:
    process: subprocess.Popen[str]
    url: str
    lines: list[str]  # everything it printed so far (appended to by a reader thread)

    @property
    def base(self) -> str:
        return self.url.split("/?", 1)[0]

    def api(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        headers = {"Authorization": f"Bearer {TOKEN}", **kwargs.pop("headers", {})}
        return httpx.request(method, self.base + path, headers=headers, timeout=120, **kwargs)


@contextlib.contextmanager
def serve(args: list[str], cwd: Path, timeout: float = 180.0) -> Iterator[Served]:
    """`python -m hitl_slam.cli serve ARGS --port 0 --token TOKEN` until its "listening" line."""
    process = subprocess.Popen(
        [sys.executable, "-m", "hitl_slam.cli", "serve", *args, "--port", "0", "--token", TOKEN],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    listening = threading.Event()

    def pump() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            lines.append(line)
            if _LISTENING.search(line):
                listening.set()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        if not listening.wait(timeout):
            raise AssertionError(f"no 'listening' line; output: {lines}")
        match = next(m for m in map(_LISTENING.search, list(lines)) if m)
        yield Served(process, match.group(1), lines)
    finally:
        if process.poll() is None:
            process.kill()
        process.wait(timeout=30)
        reader.join(timeout=10)


def test_real_server_guards_host_and_token_and_chunked_bodies(tmp_path: Path) -> None:
    with serve(["--demo"], tmp_path) as server:
        assert f"?token={TOKEN}" in server.url
        assert server.api("GET", "/api/state").status_code == 200
        assert httpx.get(server.base + "/api/state").status_code == 403
        evil = server.api("GET", "/api/state", headers={"Host": "evil.example"})
        assert evil.status_code == 403
        assert server.api("GET", "/api/state", headers={"Host": "localhost"}).status_code == 200

        # A chunked body with no Content-Length, sent until the server answers.
        port = int(server.base.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=30) as conn:
            conn.sendall(
                b"POST /api/corrections HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                + f"Authorization: Bearer {TOKEN}\r\n".encode()
                + b"Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
            )
            chunk = b" " * 65536
            sent = 0
            with contextlib.suppress(OSError):
                while sent < 64 << 20:
                    readable, _, _ = select.select([conn], [], [], 0)
                    if readable:
                        break
                    conn.sendall(b"%x\r\n%s\r\n" % (len(chunk), chunk))
                    sent += len(chunk)
            answer = b""
            with contextlib.suppress(OSError):
                while b"\r\n\r\n" not in answer:
                    data = conn.recv(65536)
                    if not data:
                        break
                    answer += data
        assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
        assert sent < 48 << 20  # answered while the body was still coming
        # ... and the server is still there.
        assert server.api("GET", "/api/state").status_code == 200


def _last_event(session_file: Path) -> tuple[int, str]:
    connection = sqlite3.connect(f"{session_file.resolve().as_uri()}?mode=ro", uri=True, timeout=5)
    try:
        row = connection.execute(
            "SELECT seq, kind FROM events ORDER BY seq DESC LIMIT 1"
        ).fetchone()
    finally:
        connection.close()
    return int(row[0]), str(row[1])


def test_sigkill_during_a_correction_loses_nothing_acknowledged(tmp_path: Path) -> None:
    # The campus (3,380 poses, 440k points): a correction computes for tens of milliseconds, a
    # window in which to kill the server once its request is journaled (polled every 2 ms).
    scenario = campus(0)
    human = SimulatedHuman(scenario, 0)
    session_file = tmp_path / "hitl-demo" / "campus.hitl"

    def draw(server: Served) -> dict[str, Any]:
        """The person's next drawing on the map as served, one the server can interpret."""
        poses = np.frombuffer(server.api("GET", "/api/map/poses").content, dtype="<f4")
        for _ in range(10):
            drawn = human.next_correction(poses.reshape(-1, 3).astype(np.float64))
            assert drawn is not None
            if server.api("POST", "/api/interpret", json=drawn.to_json()).json()["accepted"]:
                return drawn.to_json()
            human.rejected(drawn)
        raise AssertionError("no drawing the server accepts")

    with serve(["--demo", "--demo-world", "campus"], tmp_path) as server:
        assert "created the demo session" in "".join(server.lines)
        answer = server.api("POST", "/api/corrections", json=draw(server)).json()
        assert answer["accepted"] is True  # acknowledged
        # The second one, acknowledged too. (That other requests are answered while a
        # correction computes is tested deterministically in test_web_api.py.)
        answer = server.api("POST", "/api/corrections", json=draw(server)).json()
        assert answer["accepted"] is True
        state_2 = server.api("GET", "/api/state").json()
        poses_2 = server.api("GET", "/api/map/poses").content
        seq_2, kind_2 = _last_event(session_file)
        assert kind_2 == "correction"

        third = draw(server)
        failures: list[BaseException] = []

        def send_third() -> None:
            try:
                server.api("POST", "/api/corrections", json=third)
            except httpx.HTTPError as exc:  # the server dies under it: expected
                failures.append(exc)

        sender = threading.Thread(target=send_third, daemon=True)
        sender.start()
        deadline = time.monotonic() + 60
        seq, kind = seq_2, kind_2
        while seq == seq_2 and time.monotonic() < deadline:
            with contextlib.suppress(sqlite3.OperationalError):
                seq, kind = _last_event(session_file)
            time.sleep(0.002)
        server.process.kill()  # SIGKILL: no clean-up of any kind
        server.process.wait(timeout=30)
        sender.join(timeout=30)
        assert seq > seq_2, "the third correction was never journaled"

    with serve([str(session_file)], tmp_path) as server:
        assert "reopened the session" in "".join(server.lines)
        state = server.api("GET", "/api/state").json()
        history = state["history"]
        assert [e["status"] for e in history[:2]] == ["applied", "applied"]
        assert history[:2] == state_2["history"]
        assert history[2]["drawn"] == third
        if history[2]["status"] == "applied":
            # The solve beat the kill (a very fast machine): then undo it to check the rest.
            assert kind == "correction"
            state = server.api("POST", "/api/undo").json()
        else:
            assert kind == "request"
            assert history[2]["status"] == "interrupted"
            assert "ended" in history[2]["reason"]
            assert failures  # never acknowledged
        assert state["applied"] == 2
        assert server.api("GET", "/api/map/poses").content == poses_2
        assert [r["index"] for r in server.api("GET", "/api/relations").json()] == [0, 1]
        # The interrupted session goes on: a new correction applies.
        assert server.api("POST", "/api/corrections", json=draw(server)).status_code == 200


def test_ctrl_c_stops_the_server_cleanly(tmp_path: Path) -> None:
    with serve(["--demo"], tmp_path) as server:
        state = server.api("GET", "/api/state").json()
        while state["inconsistency_m2"] is None:  # its arrival is a new version; let it pass
            state = server.api("GET", "/api/state", params={"after": state["version"]}).json()
        polled: list[float] = []

        def poll() -> None:
            t0 = time.monotonic()
            r = server.api("GET", "/api/state", params={"after": state["version"]})
            assert r.status_code == 200
            polled.append(time.monotonic() - t0)

        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        time.sleep(0.5)
        assert not polled  # waiting for a change
        t0 = time.monotonic()
        server.process.send_signal(signal.SIGINT)  # as Ctrl-C
        assert server.process.wait(timeout=30) == 0
        assert time.monotonic() - t0 < 10
        poller.join(timeout=10)
        assert polled  # the long-poll was answered, not cut off
        assert polled[0] < 10
    assert any("stopped; every acknowledged change" in line for line in server.lines)
    assert (tmp_path / "hitl-demo" / "lost-poses.hitl").is_file()


# -- cross-origin requests (issue 13, finding 8) ------------------------------------------------

# Every state-changing route, with a body it accepts (None: body-less).
CHANGING: list[tuple[str, dict[str, Any] | None]] = [
    ("/api/undo", None),
    ("/api/redo", None),
    ("/api/save", None),
    ("/api/save", {"name": "stolen"}),
    ("/api/export", {"path": "stolen.g2o"}),
    ("/api/corrections", DRAWN),
    ("/api/journal/step", None),
    ("/api/interpret", DRAWN),
    ("/api/loop_closures", {"index": 0, "rejected": True}),
]
FOREIGN = [
    {"Origin": "http://evil.example"},
    {"Origin": "http://127.0.0.1:9999"},  # another server on this machine: same site, cookie sent
    {"Origin": "https://127.0.0.1:8765"},
    {"Origin": "http://127.0.0.1.evil.example:8765"},
    {"Origin": "null"},
    {"Origin": "garbage"},
    {"Sec-Fetch-Site": "cross-site"},
    {"Sec-Fetch-Site": "same-site"},
    {"Origin": "http://127.0.0.1:8765", "Sec-Fetch-Site": "cross-site"},
]


def journal_events(session_file: Path) -> list[tuple[str, dict[str, Any]]]:
    connection = sqlite3.connect(f"{session_file.resolve().as_uri()}?mode=ro", uri=True, timeout=5)
    try:
        rows = connection.execute("SELECT kind, payload FROM events ORDER BY seq").fetchall()
    finally:
        connection.close()
    return [(str(kind), json.loads(payload)) for kind, payload in rows]


def undoable_and_redoable(site: Site) -> None:
    """Two corrections applied and one undone: undo, redo, save and correct would all change
    something."""
    site.host.apply(drawn_correction(DRAWN))
    site.host.apply(drawn_correction(DRAWN))
    site.host.undo()
    state = site.host.state()
    assert state["can_undo"], state["history"]
    assert state["can_redo"], state["history"]


def drawn_correction(body: dict[str, Any]) -> Correction:
    return Drawn.model_validate(body).to_correction()


def session_fingerprint(site: Site) -> tuple[Any, ...]:
    host = site.host
    return (
        host.version,
        [(e.index, e.status.value) for e in host.session.history],
        host.session.poses.tobytes(),
        snapshot_tree(site.folder).keys(),
        len(journal_events(site.folder / "room.hitl")),
    )


@pytest.mark.parametrize(
    ("mode", "token", "bind", "base"),
    [
        ("no token", None, "127.0.0.1", BASE),
        ("token in the cookie", TOKEN, "127.0.0.1", BASE),
        ("token, any interface", TOKEN, "0.0.0.0", "http://lan-name.example:8765"),
    ],
)
def test_cross_origin_requests_change_nothing_in_every_mode(
    mode: str, token: str | None, bind: str, base: str, site: Site
) -> None:
    undoable_and_redoable(site)
    before = session_fingerprint(site)
    cookie = {} if token is None else {"Cookie": f"hitl_token={token}"}
    app = create_app(site.host, token=token, bind=bind, static_dir=site.static)
    with TestClient(app, base_url=base, raise_server_exceptions=False) as c:
        for path, body in CHANGING:
            for foreign in FOREIGN:
                # As a browser sends it: JSON (after a preflight nobody grants) or not at all.
                for kind in ({"Content-Type": "application/json"}, {}):
                    headers = {**cookie, **foreign, **kind}
                    content = None if body is None else json.dumps(body)
                    r = c.post(path, content=content, headers=headers)
                    assert r.status_code == 403, (mode, path, foreign, r.text)
                    assert "cross-origin request refused" in r.json()["detail"]
        assert session_fingerprint(site) == before
        # The page's own origin (and a client that sends none, e.g. curl) is served.
        own = {**cookie, "Origin": base, "Content-Type": "application/json"}
        assert c.post("/api/undo", headers=own).status_code == 200
        same = {**own, "Sec-Fetch-Site": "same-origin"}
        assert c.post("/api/redo", headers=same).status_code == 200
        assert c.post("/api/undo", headers={**cookie, "X-Hitl-Slam": "1"}).status_code == 200
        assert session_fingerprint(site) != before


@pytest.mark.parametrize(
    "headers",
    [
        {},
        {"Content-Type": "text/plain"},
        {"Content-Type": "application/x-www-form-urlencoded"},
        {"Content-Type": "multipart/form-data; boundary=x"},
        {"Content-Type": "text/plain; charset=utf-8"},
    ],
)
def test_a_simple_request_cannot_change_anything(headers: dict[str, str], site: Site) -> None:
    """What a page of another origin can send without a preflight (a form, a body-less or
    text/plain fetch), even where no Origin arrives: 415, nothing changed."""
    undoable_and_redoable(site)
    before = session_fingerprint(site)
    with app_client(site, token=None) as c:
        for path, body in CHANGING:
            for content in (None, b"name=stolen", json.dumps(body).encode()):
                r = c.post(path, content=content, headers=headers)
                assert r.status_code == 415, (path, headers, content, r.text)
                assert "Content-Type" in r.json()["detail"]
    assert session_fingerprint(site) == before
    # With the header the page sends, or a JSON type, or a bearer token, it works.
    with app_client(site, token=None) as c:
        assert c.post("/api/undo", headers={"X-Hitl-Slam": "1"}).status_code == 200
        assert c.post("/api/redo", headers={"Content-Type": "application/json"}).status_code == 200
    with app_client(site) as c:
        assert c.post("/api/undo", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200


def test_same_origin_compares_scheme_host_and_port() -> None:
    from hitl_slam.web.security import same_origin

    for origin, host in (
        ("http://127.0.0.1:8765", "127.0.0.1:8765"),
        ("HTTP://LOCALHOST:8765", "localhost:8765"),
        ("http://[::1]:8765", "[::1]:8765"),
        ("http://example.org", "example.org:80"),
        ("http://example.org:80", "example.org"),
    ):
        assert same_origin(origin, host), (origin, host)
    for origin, host in (
        ("http://127.0.0.1:8766", "127.0.0.1:8765"),
        ("https://127.0.0.1:8765", "127.0.0.1:8765"),
        ("http://localhost:8765", "127.0.0.1:8765"),
        ("null", "127.0.0.1:8765"),
        ("", "127.0.0.1:8765"),
        ("http://127.0.0.1:99999", "127.0.0.1:8765"),
        ("http://127.0.0.1:8765/path", "127.0.0.1:8765"),
        ("http://user@127.0.0.1:8765", "127.0.0.1:8765"),
        ("http://127.0.0.1:8765", None),
    ):
        assert not same_origin(origin, host), (origin, host)


def test_the_real_no_token_server_refuses_a_foreign_origin(tmp_path: Path) -> None:
    """The finding as probed: `serve --no-token`, a body-less POST from another page."""
    process = subprocess.Popen(
        [sys.executable, "-m", "hitl_slam.cli", "serve", "--demo", "--no-token", "--port", "0"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert process.stdout is not None
        base = ""
        for line in process.stdout:
            match = _LISTENING.search(line)
            if match:
                base = match.group(1).rstrip("/")
                break
        assert base, "no 'listening' line"
        session_file = tmp_path / "hitl-demo" / "lost-poses.hitl"
        events = len(journal_events(session_file))
        for path in ("/api/undo", "/api/redo", "/api/save"):
            r = httpx.post(base + path, headers={"Origin": "http://evil.example"}, timeout=60)
            assert r.status_code == 403, (path, r.text)
            r = httpx.post(base + path, headers={"Content-Type": "text/plain"}, timeout=60)
            assert r.status_code == 415, (path, r.text)
        assert len(journal_events(session_file)) == events
        assert not list((tmp_path / "hitl-demo").glob("*-corrected.*"))
        saved = httpx.post(base + "/api/save", headers={"X-Hitl-Slam": "1"}, timeout=60)
        assert saved.status_code == 200
        assert len(journal_events(session_file)) == events + 4
    finally:
        process.kill()
        process.wait(timeout=30)


# -- what is wrong with a body ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("content", "content_type", "status", "says"),
    [
        (b'{"mode": ' + b"1" * 10_000 + b"}", "application/json", 400, "number of 10000"),
        (b"[" * 100_000 + b"]" * 100_000, "application/json", 400, "levels deep"),
        (b'{"mode": "collinear", "a": [[1e' + b"0" * 200 + b", 0]]}", None, 400, "number of"),
        (b'{"mode": "\xff"}', "application/json", 400, "not UTF-8 (byte 0xff at offset 10"),
        (b"\xef\xbb", "application/json", 400, "not UTF-8"),
        (json.dumps(DRAWN).encode("utf-16"), "application/json; charset=utf-16", 415, "utf-16"),
        (json.dumps(DRAWN).encode("latin-1"), "application/json; charset=latin-1", 415, "latin-1"),
        (json.dumps(DRAWN).encode("utf-16-le"), "application/json", 422, "JSON decode error"),
        (json.dumps(DRAWN).encode(), "text/plain", 415, "Content-Type"),
        (b'{"mode": "collinear"', "application/json", 422, "JSON decode error"),
    ],
)
@pytest.mark.parametrize("path", ["/api/interpret", "/api/corrections"])
def test_body_errors_say_what_is_wrong(
    path: str, content: bytes, content_type: str | None, status: int, says: str, site: Site
) -> None:
    with app_client(site, token=None) as c:
        headers = {"X-Hitl-Slam": "1"}
        headers["Content-Type"] = content_type or "application/json"
        r = c.post(path, content=content, headers=headers)
        assert r.status_code == status, r.text[:300]
        assert says in r.text
        assert "There was an error parsing the body" not in r.text
    assert site.host.session.history == []


def test_a_body_declared_utf8_or_undeclared_is_applied(site: Site) -> None:
    with app_client(site, token=None) as c:
        for content_type in ("application/json; charset=UTF-8", "application/json"):
            r = c.post(
                "/api/interpret", content=json.dumps(DRAWN), headers={"Content-Type": content_type}
            )
            assert r.status_code == 200
            assert r.json()["accepted"] is True


@pytest.mark.parametrize(
    "body",
    [
        {"mode": "collinear", "a": [[1e308, 1e308], [-1e308, -1e308]], "b": [[0, 1], [1, 1]]},
        {"mode": "collinear", "a": [[0, 0], [1, 0]], "b": [[0, 1], [1, -1.5e9]]},
        {**DRAWN, "sigma_h": 1e200},
        {**DRAWN, "sigma_h": 1e308},
    ],
)
def test_coordinates_that_overflow_are_refused_without_a_warning(
    body: dict[str, Any], site: Site
) -> None:
    with app_client(site, token=None) as c, warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        for path in ("/api/interpret", "/api/corrections"):
            r = c.post(path, json=body)
            assert r.status_code == 422, r.text
            assert "out of range" in r.text or "less than or equal to 1000" in r.text
    assert [str(w.message) for w in seen if issubclass(w.category, RuntimeWarning)] == []
    assert site.host.session.history == []


def test_coordinates_up_to_the_limit_are_served(site: Site) -> None:
    far = {"mode": "collinear", "a": [[1e9, 1e9], [1e9 - 1, 1e9]], "b": [[-1e9, 0], [-1e9, 1]]}
    with app_client(site, token=None) as c:
        r = c.post("/api/interpret", json=far)
        assert r.status_code == 200
        assert r.json()["accepted"] is False  # nothing drawn there
        assert c.post("/api/interpret", json={**DRAWN, "sigma_h": 1e3}).status_code == 200


# -- every file written is journaled ----------------------------------------------------------


def test_every_save_and_export_is_journaled(client: TestClient, site: Site) -> None:
    session_file = site.folder / "room.hitl"
    written: list[str] = []
    r = client.post("/api/save", json={"name": "all"})
    assert r.status_code == 200
    written += r.json()["files"]
    for name in ("x.g2o", "x.txt", "x.covars", "grid.pgm", "fixes.jsonl"):
        r = client.post("/api/export", json={"path": name})
        assert r.status_code == 200, r.text
        written += r.json()["files"]
    assert [w for w in written if w.endswith((".yaml", ".jsonl"))] == [
        "all.yaml",
        "grid.yaml",
        "fixes.jsonl",
    ]
    saves = [payload for kind, payload in journal_events(session_file) if kind == "save"]
    assert [s["path"] for s in saves] == [str(site.folder.resolve() / w) for w in written]
    assert [s["format"] for s in saves] == [Path(w).suffix for w in written]
    # The session still opens (save events are no history) and serves on.
    assert client.get("/api/state").json()["history"] == []


# -- the page without the token ---------------------------------------------------------------


def test_the_page_without_the_token_says_how_to_get_in(site: Site) -> None:
    with app_client(site) as c:
        for params in ({}, {"token": "wrong-token-0123456789"}):
            r = c.get("/", params=params)
            assert r.status_code == 403
            assert r.headers["content-type"] == "text/html; charset=utf-8"
            assert "hitl-slam serve" in r.text
            assert "?token=" in r.text
            assert "wrong-token" not in r.text
            assert "set-cookie" not in r.headers
        # The API stays JSON for programs.
        api = c.get("/api/state")
        assert api.status_code == 403
        assert "token" in api.json()["detail"]
