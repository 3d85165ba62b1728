"""Aligning with the scans in a real browser: `hitl-slam serve` on a session of the generated room
(a second's alignment), the "Align with scans" button busy and disabled while the server aligns,
the map redrawn after with "aligned with scans" in the status bar, u back to the map before,
Shift+A again from the keyboard; on the room with loop closures, the map's loop closures faded and
their Reject / Reinstate button disabled (saying why) while aligned, until undo; and on a session
whose guard refuses, the reason shown as a refused correction's is, the map unchanged. Skipped
without a browser, except on CI.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.config import DEFAULT, Config
from hitl_slam.map import Map
from hitl_slam.session import Session
from hitl_slam.sim import SimulatedHuman, lost_poses_room
from loop_support import map_with_loops
from web_support import (
    Server,
    chromium,
    open_page,
    save_artifact,
    serve,
    wait_until,
)

# The room's simulated scans contradict a quarter of its odometry steps once matched again: the
# default guard refuses that, a guard allowing every step lets it through.
PERMISSIVE = DEFAULT.replace(
    align_max_contradicted=1.0,
    align_min_loop_closures=0,
    align_consistency_guard=False,
    align_max_overruled=1.0,
)
BUTTON = "#btn-align"
INDICATOR = "#st-aligned"
LOOP_BUTTON = "#btn-loop-toggle"
ALIGNED_TIP = (
    "the map is aligned with its scans; undo the alignment to reject or reinstate loop closures"
)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


def _room_server(folder: Path, config: Config, m: Map | None = None) -> Any:
    path = folder / "room.hitl"
    Session.new(lost_poses_room(0).map if m is None else m, path, config=config).close()
    return serve(folder, path.name)


@pytest.fixture
def aligning(tmp_path: Path) -> Iterator[Server]:
    with _room_server(tmp_path, PERMISSIVE) as server:
        yield server


@pytest.fixture
def aligning_loops(tmp_path: Path) -> Iterator[Server]:
    with _room_server(tmp_path, PERMISSIVE, map_with_loops()) as server:
        yield server


@pytest.fixture
def refusing(tmp_path: Path) -> Iterator[Server]:
    with _room_server(tmp_path, DEFAULT) as server:
        yield server


def settle(page: Any, effect: str, timeout_ms: float = 60_000) -> None:
    """Wait until the page shows ``effect`` (a JavaScript condition) and is no longer busy."""
    page.wait_for_function(f"({effect}) && !window.hitl.busy", timeout=timeout_ms)


def test_align_button_aligns_then_undo_and_shift_a(browser: Any, aligning: Server) -> None:
    page = open_page(browser, aligning.url)
    button = page.locator(BUTTON)
    assert button.is_enabled()
    assert "undo returns to the map before" in (button.get_attribute("title") or "")
    before = aligning.poses_bytes()
    assert page.evaluate("window.hitl.state.aligned") is False
    assert page.locator(INDICATOR).is_hidden()

    button.click()
    # Busy while the server aligns: disabled, saying so.
    page.wait_for_function(
        f"document.querySelector('{BUTTON}').disabled && window.hitl.busy"
        " && window.hitl.message.kind === 'busy'"
    )
    assert button.text_content() == "Aligning\u2026"
    assert button.get_attribute("aria-busy") == "true"
    settle(page, "window.hitl.state.aligned === true")
    assert button.is_enabled()
    assert button.text_content() == "Align with scans"
    message = page.evaluate("window.hitl.message")
    assert message["kind"] == "ok", message
    assert message["text"].startswith("aligned with the scans"), message
    # The figures: the inconsistency before and after; no statement to yield or hold (none was
    # drawn), so the message names none.
    assert "inconsistency" in message["text"], message
    assert " m\u00b2" in message["text"], message
    assert "your statements" not in message["text"], message
    state = page.evaluate("window.hitl.state")
    assert state["last"]["kind"] == "align"
    assert aligning.poses_bytes() != before
    assert "align" in page.locator("#st-solve").text_content()
    assert state["aligned"] is True
    indicator = page.locator(INDICATOR)
    assert indicator.is_visible()
    assert indicator.text_content() == "aligned with scans"
    save_artifact(page, "align-after.png")

    # The version also rises when the background inconsistency lands, so each step waits for
    # its own effect, not for any newer version.
    page.keyboard.press("u")
    settle(page, "window.hitl.state.aligned === false")
    assert aligning.poses_bytes() == before
    assert indicator.is_hidden()

    page.keyboard.press("Shift+A")
    settle(page, "window.hitl.state.aligned === true")
    assert page.evaluate("window.hitl.state.last.kind") == "align"
    assert aligning.poses_bytes() != before
    assert indicator.is_visible()
    assert page.errors == []


def test_while_aligned_the_maps_loop_closures_are_faded_and_cannot_be_toggled(
    browser: Any, aligning_loops: Server
) -> None:
    page = open_page(browser, aligning_loops.url)
    loops = page.evaluate("window.hitl.loopClosures()")
    assert len(loops) == aligning_loops.state()["loop_closures"]["count"] > 0
    assert not any(c["dimmed"] for c in loops)
    toggle = page.locator(LOOP_BUTTON)
    default_title = toggle.get_attribute("title") or ""
    assert "Reject the selected loop closure" in default_title
    page.keyboard.press("n")  # selects loop closure 0
    assert page.evaluate("window.hitl.selectedLoop") == 0
    assert toggle.is_enabled()

    page.keyboard.press("Shift+A")
    settle(page, "window.hitl.state.aligned === true")
    assert page.locator(INDICATOR).is_visible()
    assert all(c["dimmed"] for c in page.evaluate("window.hitl.loopClosures()"))
    assert page.evaluate("window.hitl.selectedLoop") == 0
    assert toggle.is_disabled()
    assert toggle.get_attribute("title") == ALIGNED_TIP
    assert "replaced (aligned)" in page.evaluate("window.hitl.loopStatus()")
    save_artifact(page, "align-loops.png")

    # x says why instead of asking the server (which would refuse): nothing changes.
    aligned = aligning_loops.poses_bytes()
    page.keyboard.press("x")
    page.wait_for_function(f"window.hitl.message.text === {ALIGNED_TIP!r}")
    assert not page.evaluate("window.hitl.busy")
    state = aligning_loops.state()  # its version may have risen with the inconsistency
    assert state["last"]["kind"] == "align"
    assert state["aligned"] is True
    assert state["loop_closures"]["rejected"] == page.evaluate(
        "window.hitl.state.loop_closures.rejected"
    )
    assert aligning_loops.poses_bytes() == aligned

    # Undo the alignment: everything is as before.
    page.keyboard.press("u")
    settle(page, "window.hitl.state.aligned === false")
    assert page.locator(INDICATOR).is_hidden()
    assert not any(c["dimmed"] for c in page.evaluate("window.hitl.loopClosures()"))
    assert toggle.is_enabled()
    assert toggle.get_attribute("title") == default_title
    assert "in the solve" in page.evaluate("window.hitl.loopStatus()")
    page.keyboard.press("x")
    settle(page, "window.hitl.state.loop_closures.rejected.includes(0)")
    assert 0 in aligning_loops.state()["loop_closures"]["rejected"]
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
    assert page.evaluate("window.hitl.state.aligned") is False
    assert page.locator(INDICATOR).is_hidden()
    save_artifact(page, "align-refused.png")
    assert page.errors == []


def test_the_message_says_which_way_the_statements_went(browser: Any, tmp_path: Path) -> None:
    """With a correction in effect the alignment solves twice (the statements yielding to the
    scans, or firm) and keeps the more consistent map; its message says which."""
    scenario = lost_poses_room(0)
    path = tmp_path / "room.hitl"
    with Session.new(scenario.map, path, config=PERMISSIVE) as session:
        drawn = SimulatedHuman(scenario, 0).next_correction(np.array(session.poses))
        assert drawn is not None
        session.apply(drawn)
    with serve(tmp_path, path.name) as server:
        page = open_page(browser, server.url)
        page.keyboard.press("Shift+A")
        settle(page, "window.hitl.state.aligned === true")
        statements = server.state()["last"]["alignment"]["statements"]
        assert statements in ("yield", "firm")
        text = page.evaluate("window.hitl.message.text")
        wanted = "yield to the scans" if statements == "yield" else "held firm"
        assert f"your statements {wanted}, the more consistent way" in text, text
        assert page.errors == []
