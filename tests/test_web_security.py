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

from hitl_slam.errors import InputError
from hitl_slam.session import Session
from hitl_slam.sim import SimulatedHuman, campus, lost_poses_room
from hitl_slam.web import SessionHost, create_app, run_server
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
    ("POST", "/api/interpret"),
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
        r = c.post("/api/undo", **credentials)
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
