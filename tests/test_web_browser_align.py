"""Aligning with the scans in a real browser: `hitl-slam serve` on a session of the generated room
(a second's alignment), the "Align with scans" button busy and disabled while the server aligns,
the map redrawn after, u back to the map before, Shift+A again from the keyboard; and on a session
whose guard refuses, the reason shown as a refused correction's is, the map unchanged. Skipped
without a browser, except on CI.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hitl_slam.config import DEFAULT, Config
from hitl_slam.session import Session
from hitl_slam.sim import lost_poses_room
from web_support import (
    Server,
    chromium,
    open_page,
    save_artifact,
    serve,
    wait_until,
    wait_version_above,
)

# The room's simulated scans contradict a quarter of its odometry steps once matched again: the
# default guard refuses that, a guard allowing every step lets it through.
PERMISSIVE = DEFAULT.replace(align_max_contradicted=1.0)
BUTTON = "#btn-align"


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


def _room_server(folder: Path, config: Config) -> Any:
    path = folder / "room.hitl"
    Session.new(lost_poses_room(0).map, path, config=config).close()
    return serve(folder, path.name)


@pytest.fixture
def aligning(tmp_path: Path) -> Iterator[Server]:
    with _room_server(tmp_path, PERMISSIVE) as server:
        yield server


@pytest.fixture
def refusing(tmp_path: Path) -> Iterator[Server]:
    with _room_server(tmp_path, DEFAULT) as server:
        yield server


def test_align_button_aligns_then_undo_and_shift_a(browser: Any, aligning: Server) -> None:
    page = open_page(browser, aligning.url)
    button = page.locator(BUTTON)
    assert button.is_enabled()
    assert "undo returns to the map before" in (button.get_attribute("title") or "")
    before = aligning.poses_bytes()
    version = int(page.evaluate("window.hitl.version"))

    button.click()
    # Busy while the server aligns: disabled, saying so.
    page.wait_for_function(
        f"document.querySelector('{BUTTON}').disabled && window.hitl.busy"
        " && window.hitl.message.kind === 'busy'"
    )
    assert button.text_content() == "Aligning\u2026"
    assert button.get_attribute("aria-busy") == "true"
    version = wait_version_above(page, version)
    page.wait_for_function("!window.hitl.busy")
    assert button.is_enabled()
    assert button.text_content() == "Align with scans"
    message = page.evaluate("window.hitl.message")
    assert message["kind"] == "ok", message
    assert message["text"].startswith("aligned with the scans"), message
    state = page.evaluate("window.hitl.state")
    assert state["last"]["kind"] == "align"
    assert aligning.poses_bytes() != before
    assert "align" in page.locator("#st-solve").text_content()
    save_artifact(page, "align-after.png")

    page.keyboard.press("u")
    version = wait_version_above(page, version)
    assert aligning.poses_bytes() == before

    page.keyboard.press("Shift+A")
    version = wait_version_above(page, version)
    page.wait_for_function("!window.hitl.busy")
    assert page.evaluate("window.hitl.state.last.kind") == "align"
    assert aligning.poses_bytes() != before
    assert page.errors == []


def test_a_refused_alignment_shows_its_reason_and_changes_nothing(
    browser: Any, refusing: Server
) -> None:
    page = open_page(browser, refusing.url)
    before = refusing.poses_bytes()
    version = int(page.evaluate("window.hitl.version"))
    page.locator(BUTTON).click()
    page.wait_for_function("window.hitl.message.kind === 'rejected'", timeout=60_000)
    message = page.evaluate("window.hitl.message")
    assert message["text"].startswith("alignment refused: the scans disagree with the odometry")
    assert "the map was not changed" in message["text"]
    assert page.locator("#message").is_visible()
    assert wait_until(lambda: not page.evaluate("window.hitl.busy"))
    assert page.locator(BUTTON).is_enabled()
    assert int(page.evaluate("window.hitl.version")) == version
    assert refusing.state()["version"] == version
    assert refusing.poses_bytes() == before
    save_artifact(page, "align-refused.png")
    assert page.errors == []
