"""A page of another origin, in a real browser, cannot change a session served by `hitl-slam
serve` (issue 13, finding 8): Chromium opens the hitl-slam page (which sets the token cookie),
then a page served by a second HTTP server on another port of the same machine (the same site, so
the SameSite=Strict cookie goes along) tries undo, redo, save, export and a correction by every
means a page has without a CORS preflight (body-less and text/plain fetches, form posts) and with
one. The session must not change: history, poses, files, journal. Skipped without a browser,
except on CI (CI=true or HITL_REQUIRE_BROWSER=1), where that fails.
"""

from __future__ import annotations

import contextlib
import http.server
import json
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from hitl_slam.sim import SimulatedHuman, lost_poses_room
from web_support import chromium, open_page, serve, wait_map_change, wait_until

# What the other origin's page does; TARGET is the hitl-slam server, DRAWN a correction it would
# accept. Each attempt's outcome lands in window.outcome, the forms' in window.formsLoaded.
ATTACK = """<!doctype html><meta charset="utf-8"><title>another site</title>
<iframe name="sink"></iframe>
<script>
const TARGET = %(target)s;
const DRAWN = %(drawn)s;
window.outcome = {};
window.formsLoaded = 0;
async function attempt(name, path, init) {
  try {
    const r = await fetch(TARGET + path, { method: "POST", credentials: "include", ...init });
    window.outcome[name] = `${r.type}:${r.status}`;
  } catch (err) {
    window.outcome[name] = `refused:${err.message}`;
  }
}
function postForm(path, fields, enctype) {
  const form = document.createElement("form");
  form.method = "POST";
  form.action = TARGET + path;
  form.enctype = enctype;
  form.target = "sink";
  for (const [name, value] of Object.entries(fields)) {
    const input = document.createElement("input");
    input.name = name;
    input.value = value;
    form.appendChild(input);
  }
  document.body.appendChild(form);
  form.submit();
}
window.attack = async () => {
  const text = (body) => ({ mode: "no-cors", headers: { "Content-Type": "text/plain" },
                            body: JSON.stringify(body) });
  for (const path of ["/api/undo", "/api/redo", "/api/save", "/api/journal/step"]) {
    await attempt(`bodyless ${path}`, path, { mode: "no-cors" });
  }
  await attempt("text save", "/api/save", text({ name: "stolen" }));
  await attempt("text export", "/api/export", text({ path: "stolen.g2o" }));
  await attempt("text correction", "/api/corrections", text(DRAWN));
  // With a JSON type the browser asks first (a preflight); the server never says yes.
  for (const [path, body] of [["/api/undo", undefined], ["/api/corrections", DRAWN]]) {
    await attempt(`json ${path}`, path, {
      mode: "cors", headers: { "Content-Type": "application/json", "X-Hitl-Slam": "1" },
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  }
  document.querySelector("iframe").addEventListener("load", () => { window.formsLoaded += 1; });
  postForm("/api/undo", { x: "1" }, "application/x-www-form-urlencoded");
};
window.moreForms = () => {
  postForm("/api/save", { '{"name": "stolen", "x": "': '"}' }, "text/plain");
};
window.lastForm = () => {
  postForm("/api/redo", {}, "multipart/form-data");
};
</script>
"""

PAGE_HEADERS = {"X-Hitl-Slam": "1", "Content-Type": "application/json"}


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


@contextlib.contextmanager
def other_origin(page_html: str) -> Iterator[str]:
    """A second HTTP server on another port of 127.0.0.1 serving ``page_html`` at /; its URL."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = page_html.encode("utf-8")
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


def journal_length(session_file: Path) -> int:
    connection = sqlite3.connect(f"{session_file.resolve().as_uri()}?mode=ro", uri=True, timeout=5)
    try:
        return int(connection.execute("SELECT count(*) FROM events").fetchone()[0])
    finally:
        connection.close()


@pytest.mark.parametrize("mode", ["token", "no-token"])
def test_a_page_of_another_origin_cannot_undo_redo_save_or_correct(
    mode: str, browser: Any, tmp_path: Path
) -> None:
    scenario = lost_poses_room(0)
    human = SimulatedHuman(scenario, 0)
    args = ["--demo"] + (["--no-token"] if mode == "no-token" else [])
    with serve(tmp_path, *args) as server:
        base = server.url.split("?", 1)[0].rstrip("/")
        auth = {"Authorization": f"Bearer {server.token}"} if mode == "token" else {}

        def api(method: str, path: str, **kwargs: Any) -> httpx.Response:
            headers = {**PAGE_HEADERS, **auth}
            return httpx.request(method, base + path, headers=headers, timeout=60, **kwargs)

        # Two corrections applied, one undone: undo, redo, save and correct all could change it.
        drawings = []
        for _ in range(2):
            poses = api("GET", "/api/map/poses").content
            current = np.frombuffer(poses, dtype="<f4").reshape(-1, 3).astype(np.float64)
            drawn = human.next_correction(current)
            assert drawn is not None
            r = api("POST", "/api/corrections", json=drawn.to_json())
            assert r.json()["accepted"] is True, r.text
            drawings.append(drawn.to_json())
        assert api("POST", "/api/undo").status_code == 200
        session_file = tmp_path / "hitl-demo" / "lost-poses.hitl"
        folder = session_file.parent

        def fingerprint() -> tuple[Any, ...]:
            state = api("GET", "/api/state").json()
            return (
                [(h["index"], h["status"]) for h in state["history"]],
                state["can_undo"],
                state["can_redo"],
                api("GET", "/api/map/poses").content,
                sorted(p.name for p in folder.iterdir()),
                journal_length(session_file),
            )

        before = fingerprint()
        assert before[1], "nothing to undo"
        assert before[2], "nothing to redo"

        # The person has the hitl-slam page open in this browser (so the cookie is set).
        own = open_page(browser, server.url)
        context = own.context
        html = ATTACK % {"target": json.dumps(base), "drawn": json.dumps(drawings[0])}
        with other_origin(html) as evil_url:
            evil = context.new_page()
            evil.goto(evil_url)
            evil.evaluate("window.attack()")
            outcome = evil.evaluate("window.outcome")
            assert len(outcome) == 9, outcome
            # Sent without a preflight (opaque answers), or stopped by it.
            for name, result in outcome.items():
                if name.startswith("json"):
                    assert result.startswith("refused:"), (name, result)
                else:
                    assert result == "opaque:0", (name, result)
            for step, expected in (("moreForms", 2), ("lastForm", 3)):
                evil.wait_for_function(f"window.formsLoaded >= {expected - 1}")
                evil.evaluate(f"window.{step}()")
            # Each form's answer loaded in the frame (an error page there: the server's answers
            # may not be framed).
            evil.wait_for_function("window.formsLoaded >= 3")
        assert fingerprint() == before
        assert not [p for p in folder.iterdir() if "stolen" in p.name or "corrected" in p.name]

        # The page's own requests still go through: undo and redo from its keys, save with v.
        version = int(own.evaluate("window.hitl.version"))
        own.keyboard.press("u")
        wait_map_change(own, version)
        assert api("GET", "/api/state").json()["can_undo"] is False
        own.keyboard.press("v")
        assert wait_until(lambda: len(list(folder.glob("lost-poses-corrected.*"))) == 4)
        assert own.errors == []
