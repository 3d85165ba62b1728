"""What the browser tests and the web benchmark share: a real `hitl-slam serve` in a subprocess
(waiting for its "listening on" line), Chromium through Playwright, and helpers that act like a
person at the page (real mouse drags with modifier keys, key presses) or read its hooks
(``window.hitl``, documented in the front end's js/main.js).
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from numpy.typing import NDArray

REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "build" / "test-artifacts"

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser", "/usr/bin/google-chrome")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
VIEWPORT = {"width": 1280, "height": 800}

# What a front end that doubts its map says of it in the map's metadata (docs/FORMATS.md): the
# verdict, two stretches, and the comparison with a bag's own SLAM trajectory.
DOUBTFUL_STRETCHES = (
    {"first": 40, "last": 90, "reason": "match failed"},
    {"first": 300, "last": 330, "reason": "contradicts the loop closures"},
)
DOUBTFUL_FRONT_END = {
    "front_end_verdict": "doubtful",
    "front_end_doubtful": [dict(s) for s in DOUBTFUL_STRETCHES],
    "trajectory_comparison": {
        "trajectory": "slam (map -> base_link)",
        "bag_slam_m2": 12.5,
        "front_end_m2": 9.25,
    },
}
_LISTENING = re.compile(r"hitl-slam serve: listening on (\S+)")
_SERVE = "import sys; from hitl_slam.cli import main; sys.exit(main())"


# -- the browser ---------------------------------------------------------------------------------


def browser_required() -> bool:
    """CI (or HITL_REQUIRE_BROWSER=1) must run the browser tests: a missing browser fails."""
    return os.environ.get("CI") == "true" or os.environ.get("HITL_REQUIRE_BROWSER") == "1"


def no_browser(reason: str) -> None:
    """Skip (locally) or fail (CI) for want of a browser."""
    if browser_required():
        pytest.fail(f"{reason} (required: CI=true or HITL_REQUIRE_BROWSER=1)")
    pytest.skip(reason)


def find_chromium() -> str | None:
    """$HITL_CHROMIUM, else the first Chromium of the usual system paths."""
    explicit = os.environ.get("HITL_CHROMIUM")
    if explicit:
        return explicit if os.access(explicit, os.X_OK) else None
    return next((p for p in CHROMIUM_CANDIDATES if os.access(p, os.X_OK)), None)


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium (Playwright's sync API); skips or fails when there is none."""
    try:
        from playwright.sync_api import Error as PlaywrightError
        from playwright.sync_api import sync_playwright
    except ImportError:
        no_browser("playwright is not installed (pip install playwright)")
        raise  # unreachable: no_browser raises
    path = find_chromium()
    if path is None:
        explicit = os.environ.get("HITL_CHROMIUM")
        if explicit:
            no_browser(f"HITL_CHROMIUM={explicit} is not an executable")
        no_browser(f"no Chromium found (looked at {', '.join(CHROMIUM_CANDIDATES)})")
    with sync_playwright() as p:
        try:
            browser = p.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        except PlaywrightError as exc:
            no_browser(f"Chromium at {path} does not start: {str(exc).splitlines()[0]}")
            raise
        try:
            yield browser
        finally:
            browser.close()


# -- the server ----------------------------------------------------------------------------------


@dataclass
class Server:
    """A running `hitl-slam serve`: its page URL (with the token) and an HTTP client for /api."""

    process: subprocess.Popen[str]
    url: str
    cwd: Path
    output: list[str] = field(default_factory=list)

    @property
    def token(self) -> str:
        match = re.search(r"[?&]token=([^&]+)", self.url)
        assert match, self.url
        return match.group(1)

    @property
    def base(self) -> str:
        return self.url.split("/?", 1)[0]

    def api(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        headers = {"Authorization": f"Bearer {self.token}"}
        return httpx.request(method, self.base + path, headers=headers, timeout=60.0, **kwargs)

    def state(self) -> dict[str, Any]:
        r = self.api("GET", "/api/state")
        r.raise_for_status()
        result: dict[str, Any] = r.json()
        return result

    def poses_bytes(self) -> bytes:
        r = self.api("GET", "/api/map/poses")
        r.raise_for_status()
        return r.content

    def poses(self) -> NDArray[np.float32]:
        return np.frombuffer(self.poses_bytes(), dtype="<f4").reshape(-1, 3)

    def relations(self) -> list[dict[str, Any]]:
        r = self.api("GET", "/api/relations")
        r.raise_for_status()
        result: list[dict[str, Any]] = r.json()
        return result

    def stop(self) -> None:
        """Ctrl-C, as a person would; killed if it does not stop within 10 s."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)


@contextlib.contextmanager
def serve(
    cwd: Path, *args: str, timeout: float = 120.0, pythonpath: str | None = None
) -> Iterator[Server]:
    """`hitl-slam serve ARGS --port 0` in ``cwd``; yields once it listens, stops it after.
    ``pythonpath``: serve the hitl-slam found there (e.g. another checkout, for a comparison)."""
    command = [sys.executable, "-c", _SERVE, "serve", *args, "--port", "0"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    process = subprocess.Popen(
        command,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    output: list[str] = []
    listening = threading.Event()
    url: list[str] = []

    def read(stream: io.TextIOBase) -> None:
        for line in stream:
            output.append(line.rstrip("\n"))
            match = _LISTENING.search(line)
            if match and not url:
                url.append(match.group(1))
                listening.set()
        listening.set()  # the process ended

    assert process.stdout is not None
    threading.Thread(target=read, args=(process.stdout,), daemon=True).start()
    server = Server(process, "", cwd, output)
    try:
        listening.wait(timeout)
        if not url:
            raise RuntimeError(
                f"`hitl-slam serve {' '.join(args)}` did not start within {timeout:.0f} s "
                f"(exit code {process.poll()}):\n" + "\n".join(output)
            )
        server.url = url[0]
        yield server
    finally:
        server.stop()


# -- the page ------------------------------------------------------------------------------------


def open_page(
    browser: Any,
    url: str,
    *,
    timeout_ms: float = 60_000,
    init_script: str | None = None,
    viewport: dict[str, int] | None = None,
) -> Any:
    """A new page (own context, ``viewport`` or 1280 x 800, device pixel ratio 1) on ``url``,
    after its first frame with the map. Uncaught page errors are collected in ``page.errors``.
    ``init_script`` runs in the page before its own scripts."""
    context = browser.new_context(viewport=viewport or VIEWPORT, device_scale_factor=1)
    if init_script is not None:
        context.add_init_script(init_script)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.errors = errors
    page.goto(url)
    page.wait_for_function("window.hitl !== undefined", timeout=timeout_ms)
    page.evaluate("window.hitl.ready")
    return page


def to_client(page: Any, xy: Sequence[float]) -> tuple[float, float]:
    cx, cy = page.evaluate("([x, y]) => window.hitl.worldToClient(x, y)", [xy[0], xy[1]])
    return float(cx), float(cy)


def drag(page: Any, start: tuple[float, float], end: tuple[float, float], steps: int = 8) -> None:
    page.mouse.move(*start)
    page.mouse.down()
    page.mouse.move(*end, steps=steps)
    page.mouse.up()


def draw_segment(page: Any, segment: Sequence[Sequence[float]], modifiers: Sequence[str]) -> None:
    """A real mouse drag over the world segment, holding ``modifiers`` ("Shift", "Control",
    "Alt") from before the button goes down until after it comes up."""
    start, end = to_client(page, segment[0]), to_client(page, segment[1])
    for key in modifiers:
        page.keyboard.down(key)
    try:
        drag(page, start, end)
    finally:
        for key in reversed(modifiers):
            page.keyboard.up(key)


def wait_map_change(page: Any, version: int, timeout_ms: float = 30_000) -> int:
    """Wait until the page shows poses newer than ``version`` and is idle; its version now.

    Not merely a newer version: the version also rises when the background inconsistency of
    the current poses lands, which can happen just after ``version`` was read."""
    page.wait_for_function(
        f"window.hitl.state.map_version > {version} && !window.hitl.busy", timeout=timeout_ms
    )
    return int(page.evaluate("window.hitl.version"))


def zoom_to(page: Any, at: Sequence[float], pixels_per_metre: float) -> None:
    """Wheel-zoom about world point ``at`` until the view has at least ``pixels_per_metre``,
    then drag the map so ``at`` is in the middle of the canvas (a person zooming in on a spot)."""
    for _ in range(60):
        scale = page.evaluate(
            "([x, y]) => { const a = window.hitl.worldToClient(x, y);"
            " const b = window.hitl.worldToClient(x + 1, y); return b[0] - a[0]; }",
            [at[0], at[1]],
        )
        if scale >= pixels_per_metre:
            break
        page.mouse.move(*to_client(page, at))
        page.mouse.wheel(0, -120)
        page.wait_for_function("true")  # let the wheel event land
    box = page.locator("#map").bounding_box()
    centre = (box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    drag(page, to_client(page, at), centre)


def canvas_pixels(page: Any) -> NDArray[np.uint8]:
    """The map canvas as an (H, W, 3) array, from a real screenshot."""
    from PIL import Image

    png = page.locator("#map").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def changed_fraction(before: NDArray[np.uint8], after: NDArray[np.uint8]) -> float:
    """The fraction of pixels that differ by more than a little in any channel."""
    diff = np.abs(before.astype(np.int16) - after.astype(np.int16)).max(axis=2)
    return float(np.mean(diff > 24))


def save_artifact(page: Any, name: str) -> Path:
    """A full-page screenshot under build/test-artifacts/ (kept for people to look at)."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path))
    return path


def wait_until(predicate: Any, timeout: float = 10.0, interval: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())


def person_drawings(scenario: Any, seed: int, count: int) -> tuple[list[Any], NDArray[np.float64]]:
    """The simulated person's first ``count`` drawings on ``scenario``'s map (numpy seed
    ``seed``), each made on the map as the ones before left it, and the poses they lead to."""
    from hitl_slam.session import Session
    from hitl_slam.sim import SimulatedHuman

    human = SimulatedHuman(scenario, seed)
    out = []
    with Session.new(scenario.map) as session:
        for _ in range(count):
            drawn = human.next_correction(session.poses)
            assert drawn is not None
            session.apply(drawn)
            out.append(drawn)
        return out, session.poses.copy()
