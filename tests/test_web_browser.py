"""The web UI in a real browser: `hitl-slam serve --demo` in a subprocess, headless Chromium
through Playwright, and a person's actions (key presses, mouse drags holding Ctrl / Shift / Alt)
with the drawing taken from the simulated human of ``hitl_slam.sim``. Skipped without a browser,
except on CI (CI=true or HITL_REQUIRE_BROWSER=1), where that fails.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.corrections import Correction, Mode
from hitl_slam.corrections_file import write_corrections
from hitl_slam.session import Session
from hitl_slam.sim import SimulatedHuman, lost_poses_room
from web_support import (
    DOUBTFUL_FRONT_END,
    DOUBTFUL_STRETCHES,
    Server,
    canvas_pixels,
    changed_fraction,
    chromium,
    draw_segment,
    open_page,
    person_drawings,
    save_artifact,
    serve,
    to_client,
    wait_map_change,
    wait_until,
    zoom_to,
)

POINTING_PX = 4.0  # the front end's sigma_h = POINTING_PX / (pixels per metre), js/correction.js


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


@pytest.fixture
def demo(tmp_path: Path) -> Iterator[Server]:
    with serve(tmp_path, "--demo") as server:
        yield server


@pytest.fixture(scope="module")
def first_correction() -> Correction:
    """What the simulated human draws first on the damaged demo room: two passes along the
    south wall, 26 degrees apart, collinear."""
    scenario = lost_poses_room(0)
    drawn = SimulatedHuman(scenario, 0).next_correction(scenario.map.poses)
    assert drawn is not None
    assert drawn.mode is Mode.COLLINEAR, drawn
    return drawn


def world(drawn: Correction) -> tuple[list[list[float]], list[list[float]]]:
    return [list(p) for p in drawn.a], [list(p) for p in drawn.b]


def focus_on(page: Any, drawn: Correction) -> None:
    """Zoom in on the drawing as far as the human's accuracy asks (sigma_h -> pixels)."""
    a, b = world(drawn)
    centre = np.mean(np.array(a + b), axis=0)
    sigma = drawn.sigma_h if drawn.sigma_h is not None else 0.1
    zoom_to(page, centre, POINTING_PX / sigma * 1.0001)
    assert page.evaluate("window.hitl.sigmaH()") <= sigma + 1e-9


def draw_pair(page: Any, drawn: Correction, modifiers: list[str]) -> None:
    a, b = world(drawn)
    draw_segment(page, a, modifiers)
    draw_segment(page, b, modifiers)


def apply_through_page(page: Any, drawn: Correction) -> int:
    """Zoom in, p, Shift-drag both segments, wait for the preview, p; the new version."""
    focus_on(page, drawn)
    page.keyboard.press("p")
    draw_pair(page, drawn, ["Shift"])
    page.wait_for_function("window.hitl.highlighted().a > 0 && window.hitl.highlighted().b > 0")
    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("p")
    return wait_map_change(page, version)


def test_collinear_correction_from_the_simulated_human(
    browser: Any, demo: Server, first_correction: Correction
) -> None:
    page = open_page(browser, demo.url)
    scenario = lost_poses_room(0)
    # The page serves the very map the human looked at.
    np.testing.assert_allclose(demo.poses(), scenario.map.poses, atol=1e-4)
    before_path = save_artifact(page, "demo-before.png")

    focus_on(page, first_correction)
    before = canvas_pixels(page)
    page.keyboard.press("p")
    assert page.evaluate("window.hitl.correcting")
    a, b = world(first_correction)
    draw_segment(page, a, ["Shift"])
    assert page.evaluate("window.hitl.mode") == "collinear"
    assert page.evaluate("window.hitl.pending") == 1
    draw_segment(page, b, ["Shift"])
    page.wait_for_function("window.hitl.highlighted().a > 0 && window.hitl.highlighted().b > 0")
    shown = page.evaluate("window.hitl.highlighted()")
    preview = page.evaluate("window.hitl.preview")
    assert preview["accepted"], preview
    assert shown["a"] > 50, shown
    assert shown["b"] > 50, shown
    save_artifact(page, "demo-preview.png")

    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("p")
    wait_map_change(page, version)
    page.wait_for_function("window.hitl.lastRedrawMs !== null")
    assert page.evaluate("window.hitl.message.kind") == "ok"
    assert not page.evaluate("window.hitl.correcting")

    relations = demo.relations()
    assert len(relations) == 1, relations
    (relation,) = relations
    assert relation["mode"] == "collinear"
    assert relation["angle_deg"] < 0.3, relation
    assert relation["offset_m"] is not None
    assert relation["offset_m"] < 0.02, relation
    assert demo.state()["applied"] == 1

    after = canvas_pixels(page)
    moved = changed_fraction(before, after)
    assert moved > 0.01, f"only {moved:.2%} of the canvas changed after the correction"

    page.keyboard.press("f")
    page.wait_for_timeout(150)
    corrected_path = save_artifact(page, "corrected-demo.png")
    assert before_path.stat().st_size > 10_000
    assert corrected_path.stat().st_size > 10_000
    status = page.locator("#statusbar").inner_text()
    assert "1 correction" in status, status
    assert "apply" in status, status
    assert page.errors == []


def test_undo_restores_the_map_exactly_and_redo_brings_it_back(
    browser: Any, demo: Server, first_correction: Correction
) -> None:
    page = open_page(browser, demo.url)
    original = demo.poses_bytes()
    apply_through_page(page, first_correction)
    corrected = demo.poses_bytes()
    assert corrected != original

    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("u")
    version = wait_map_change(page, version)
    assert demo.poses_bytes() == original
    assert demo.state()["applied"] == 0
    # The page shows the restored map: what it holds is what the server serves.
    assert page.evaluate("window.hitl.state.can_redo")

    page.keyboard.press("Shift+U")
    wait_map_change(page, version)
    assert demo.poses_bytes() == corrected
    assert demo.state()["applied"] == 1
    assert page.errors == []


SLOW_CORRECTIONS = """
(() => {
  const real = window.fetch.bind(window);
  window.fetch = async (input, init) => {
    const answer = await real(input, init);
    if (String(input).endsWith("api/corrections") && init && init.method === "POST") {
      await new Promise((resolve) => setTimeout(resolve, 1500));
    }
    return answer;
  };
})();
"""
"""The page's fetch holding each correction's answer 1.5 s: a long solve, as on a big map."""


def test_a_key_pressed_during_a_long_correction_waits_says_so_and_runs_after_it(
    browser: Any, demo: Server, first_correction: Correction
) -> None:
    """Issue 40: u pressed while a correction solves is not dropped. It is queued, the page says
    so, and it undoes the correction once that is in."""
    page = open_page(browser, demo.url, init_script=SLOW_CORRECTIONS)
    original = demo.poses_bytes()
    focus_on(page, first_correction)
    page.keyboard.press("p")
    draw_pair(page, first_correction, ["Shift"])
    page.wait_for_function("window.hitl.highlighted().a > 0 && window.hitl.highlighted().b > 0")
    page.keyboard.press("p")
    page.wait_for_function("window.hitl.busy")
    page.keyboard.press("u")
    assert page.evaluate("window.hitl.queued") == ["undo"]
    assert page.evaluate("window.hitl.message.text") == "queued: undo (after the correction)"
    page.wait_for_function(
        "!window.hitl.busy && window.hitl.queued.length === 0"
        " && window.hitl.message.text === 'undone'",
        timeout=60_000,
    )
    assert demo.poses_bytes() == original
    state = demo.state()
    assert state["applied"] == 0
    assert state["can_redo"]
    assert page.errors == []


def test_a_drawing_over_empty_space_is_rejected_and_changes_nothing(
    browser: Any, demo: Server
) -> None:
    page = open_page(browser, demo.url)
    x0, y0, x1, y1 = demo.state()["bounds"]
    # Zoom out about the map's middle until there is room beside it.
    middle = to_client(page, ((x0 + x1) / 2, (y0 + y1) / 2))
    page.mouse.move(*middle)
    for _ in range(4):
        page.mouse.wheel(0, 240)
    page.wait_for_timeout(100)
    width = x1 - x0
    a = [[x1 + 0.4 * width, y0], [x1 + 0.4 * width, y1]]
    b = [[x0 - 0.4 * width, y0], [x0 - 0.4 * width, y1]]
    box = page.locator("#map").bounding_box()
    for point in a + b:
        cx, cy = to_client(page, point)
        assert box["x"] < cx < box["x"] + box["width"]
        assert box["y"] < cy < box["y"] + box["height"]
    poses, applied = demo.poses_bytes(), demo.state()["applied"]

    page.keyboard.press("p")
    draw_segment(page, a, ["Shift"])
    draw_segment(page, b, ["Shift"])
    message = page.locator("#message.rejected")
    message.wait_for(state="visible")
    assert "rejected" in message.inner_text()
    assert len(message.inner_text()) > 20
    assert page.evaluate("window.hitl.highlighted()") == {"a": 0, "b": 0}
    page.keyboard.press("p")  # trying to apply it anyway
    page.wait_for_timeout(300)
    assert page.locator("#message.rejected").is_visible()
    assert demo.poses_bytes() == poses
    assert demo.state()["applied"] == applied
    assert page.errors == []


@pytest.mark.parametrize(
    ("modifiers", "mode"),
    [
        (["Control"], "colocation"),
        (["Shift"], "collinear"),
        (["Shift", "Alt"], "perpendicular"),
        (["Shift", "Control"], "parallel"),
    ],
)
def test_modifier_keys_pick_the_mode(
    browser: Any,
    shared_demo: Server,
    first_correction: Correction,
    modifiers: list[str],
    mode: str,
) -> None:
    page = open_page(browser, shared_demo.url)
    a, b = world(first_correction)
    page.keyboard.press("p")
    draw_segment(page, a, modifiers)
    assert page.evaluate("window.hitl.mode") == mode
    with page.expect_request(
        lambda r: r.url.endswith("/api/interpret") and r.method == "POST"
    ) as request:
        draw_segment(page, b, modifiers)
    body = json.loads(request.value.post_data)
    assert body["mode"] == mode
    np.testing.assert_allclose(body["a"], a, atol=0.03)
    np.testing.assert_allclose(body["b"], b, atol=0.03)
    assert 0 < body["sigma_h"] <= 0.1
    page.context.close()


@pytest.fixture(scope="module")
def shared_demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One server for the tests that only preview (nothing they do changes the map)."""
    with serve(tmp_path_factory.mktemp("shared"), "--demo") as server:
        yield server


def test_escape_help_buttons_errors_and_two_tabs(
    browser: Any, demo: Server, first_correction: Correction
) -> None:
    page = open_page(browser, demo.url)
    # The second tab is a second window: Chromium throttles a tab in the background, as it would
    # for a person looking at the other one, and that is not what this test is about.
    other = open_page(browser, demo.url)
    posted: list[str] = []
    page.on("request", lambda r: posted.append(r.url) if r.method == "POST" else None)

    # Esc drops the pending pair and its preview; p then leaves correction mode, sending nothing.
    page.keyboard.press("p")
    draw_pair(page, first_correction, ["Shift"])
    page.wait_for_function("window.hitl.highlighted().a > 0")
    page.keyboard.press("Escape")
    assert page.evaluate("window.hitl.highlighted()") == {"a": 0, "b": 0}
    assert page.evaluate("window.hitl.mode") is None
    assert page.evaluate("window.hitl.pending") == 0
    page.keyboard.press("p")
    assert not page.evaluate("window.hitl.correcting")
    assert not [u for u in posted if u.endswith("/api/corrections")]

    # ? shows and hides the help, as does its button.
    help_panel = page.locator("#help")
    assert help_panel.is_hidden()
    page.keyboard.press("?")
    assert help_panel.is_visible()
    assert "Shift" in help_panel.inner_text()
    page.keyboard.press("?")
    assert help_panel.is_hidden()
    page.click("#btn-help")
    assert help_panel.is_visible()
    page.click("#btn-help")
    assert help_panel.is_hidden()
    page.keyboard.press("?")
    page.keyboard.press("Escape")
    assert help_panel.is_hidden()

    # Server errors are shown: 409 from the server, a 403 and a dropped connection (simulated).
    page.keyboard.press("u")
    page.locator("#message.error").wait_for(state="visible")
    assert "nothing to undo" in page.locator("#message").inner_text()
    page.route(
        "**/api/redo",
        lambda route: route.fulfill(status=403, body='{"detail": "wrong or missing token"}'),
    )
    page.keyboard.press("Shift+U")
    page.wait_for_function("window.hitl.message.text.includes('access denied')")
    page.unroute("**/api/redo")
    page.route("**/api/redo", lambda route: route.abort("connectionrefused"))
    page.keyboard.press("Shift+U")
    page.wait_for_function("window.hitl.message.text.includes('cannot reach')")
    page.unroute("**/api/redo")

    # Mode button + plain drags + Apply, no modifier keys; the other tab follows.
    focus_on(page, first_correction)
    page.click("button.mode[data-mode=collinear]")
    assert page.evaluate("window.hitl.correcting")
    draw_pair(page, first_correction, [])
    page.wait_for_function("window.hitl.highlighted().b > 0")
    assert page.evaluate("window.hitl.mode") == "collinear"
    version = int(page.evaluate("window.hitl.version"))
    page.click("#btn-apply")
    version = wait_map_change(page, version)
    assert demo.state()["applied"] == 1
    other.wait_for_function(f"window.hitl.version >= {version}", timeout=5_000)
    assert other.evaluate("window.hitl.state.applied") == 1
    assert "1 correction" in other.locator("#st-applied").inner_text()

    # ... and the other way round: undo in the second tab, the first one follows.
    other.keyboard.press("u")
    page.wait_for_function(f"window.hitl.version > {version}", timeout=5_000)
    page.wait_for_function("window.hitl.state.applied === 0", timeout=5_000)
    assert page.errors == []
    assert other.errors == []


def test_wheel_zooms_about_the_cursor_and_drag_pans(browser: Any, shared_demo: Server) -> None:
    page = open_page(browser, shared_demo.url)
    box = page.locator("#map").bounding_box()
    spot = (box["x"] + 0.3 * box["width"], box["y"] + 0.7 * box["height"])
    under = page.evaluate("([x, y]) => window.hitl.clientToWorld(x, y)", list(spot))
    page.mouse.move(*spot)
    page.mouse.wheel(0, -300)
    page.wait_for_timeout(100)
    np.testing.assert_allclose(to_client(page, under), spot, atol=0.5)
    scale = page.evaluate("window.hitl.worldToClient(1, 0)[0] - window.hitl.worldToClient(0, 0)[0]")
    page.mouse.move(*spot)
    page.mouse.down()
    page.mouse.move(spot[0] + 100, spot[1] - 50, steps=5)
    page.mouse.up()
    np.testing.assert_allclose(to_client(page, under), (spot[0] + 100, spot[1] - 50), atol=0.5)
    assert page.evaluate(
        "window.hitl.worldToClient(1, 0)[0] - window.hitl.worldToClient(0, 0)[0]"
    ) == pytest.approx(scale)
    page.context.close()


def test_save_and_journal_step(tmp_path: Path, browser: Any) -> None:
    # A corrections file of the human's first two drawings, and where they lead.
    steps, expected = person_drawings(lost_poses_room(0), 0, 2)
    journal = tmp_path / "fixes.jsonl"
    write_corrections(journal, steps)

    with serve(tmp_path, "--demo", "--journal", str(journal)) as server:
        page = open_page(browser, server.url)
        assert page.locator("#st-journal").inner_text() == "journal 0/2"
        for k in (1, 2):
            version = int(page.evaluate("window.hitl.version"))
            page.keyboard.press("l")
            wait_map_change(page, version)
            state = server.state()
            assert state["journal"]["next"] == k
            assert state["applied"] == k
            assert page.locator("#st-journal").inner_text() == f"journal {k}/2"
        np.testing.assert_allclose(server.poses(), expected, atol=1e-4)
        page.keyboard.press("l")  # nothing left: the server says so (409), the page shows it
        page.locator("#message.error").wait_for(state="visible")

        folder = tmp_path / "hitl-demo"
        assert not list(folder.glob("*-corrected.*"))
        page.keyboard.press("v")
        page.locator("#message.ok").wait_for(state="visible")
        assert wait_until(lambda: len(list(folder.glob("lost-poses-corrected.*"))) == 4)
        names = sorted(p.name for p in folder.glob("lost-poses-corrected.*"))
        assert names == [f"lost-poses-corrected.{e}" for e in ("g2o", "pgm", "txt", "yaml")]
        assert "saved" in page.locator("#message").inner_text()
        assert page.errors == []


def drawn_lines(page: Any) -> dict[str, Any]:
    """Where the page draws the applied corrections' lines: world segments, their ends on the
    screen, and the "1a"/"1b" labels as laid out in the page."""
    lines = page.evaluate("window.hitl.appliedLines()")
    ends = [[to_client(page, p) for p in (c[side])] for c in lines for side in ("a", "b")]
    labels = page.evaluate(
        """() => [...document.querySelectorAll("#labels span")].map(
            (s) => [s.textContent, s.getBoundingClientRect().x, s.getBoundingClientRect().y])"""
    )
    return {"lines": lines, "ends": ends, "labels": labels}


def test_a_reload_shows_every_segment_where_the_live_page_did(
    browser: Any, demo: Server, first_correction: Correction
) -> None:
    """A colocation of the two passes of the south wall: live, both solved lines sit on the wall;
    after a reload they are drawn exactly where they were (the server's lines, not a guess)."""
    page = open_page(browser, demo.url)
    assert page.evaluate("window.hitl.hintVisible()")
    hint = page.locator("#hint").inner_text()
    assert "press p" in hint, hint
    assert "Ctrl" in hint, hint

    drawn = Correction.make(
        first_correction.a, first_correction.b, "colocation", first_correction.sigma_h
    )
    focus_on(page, drawn)
    page.keyboard.press("p")
    draw_pair(page, drawn, ["Control"])
    assert page.evaluate("window.hitl.mode") == "colocation"
    page.wait_for_function("window.hitl.highlighted().a > 0 && window.hitl.highlighted().b > 0")
    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("p")
    wait_map_change(page, version)
    page.wait_for_function("window.hitl.appliedLines().length === 1")
    assert not page.evaluate("window.hitl.hintVisible()")  # the first correction is made

    centre = np.mean(np.array(world(drawn)[0] + world(drawn)[1]), axis=0)
    view = [float(centre[0]), float(centre[1]), 150.0]
    page.evaluate("([x, y, s]) => window.hitl.lookAt(x, y, s)", view)
    page.wait_for_timeout(100)
    live = drawn_lines(page)
    (line,) = live["lines"]
    # Live, segment b lies on the wall with segment a (one line), not where it was drawn.
    a, b = np.array(line["a"]), np.array(line["b"])
    direction = (a[1] - a[0]) / np.linalg.norm(a[1] - a[0])
    normal = np.array([-direction[1], direction[0]])
    assert np.abs((b - a[0]) @ normal).max() < 0.02, line
    drawn_b = np.array(drawn.b)
    assert np.abs((drawn_b - a[0]) @ normal).max() > 0.3  # it was drawn well off the wall
    assert [text for text, _, _ in live["labels"]] == ["1a", "1b"]
    save_artifact(page, "colocation-live.png")

    page.reload()
    page.wait_for_function("window.hitl !== undefined")
    page.evaluate("window.hitl.ready")
    page.wait_for_function("window.hitl.appliedLines().length === 1")
    page.evaluate("([x, y, s]) => window.hitl.lookAt(x, y, s)", view)
    page.wait_for_timeout(100)
    reloaded = drawn_lines(page)
    save_artifact(page, "colocation-reloaded.png")
    assert reloaded == live
    assert not page.evaluate("window.hitl.hintVisible()")
    assert page.errors == []


@pytest.mark.parametrize("points", ["gpu", "cpu"])
def test_both_point_paths_place_the_scans_by_the_poses(
    browser: Any, demo: Server, first_correction: Correction, points: str
) -> None:
    """The points drawn by the vertex shader (a pose texture) and by the CPU splat land on the
    same pixels, before and after a correction moves them."""
    pages = {}
    for path in ("gpu", "cpu"):
        pages[path] = open_page(browser, f"{demo.url}&points={path}")
        assert pages[path].evaluate("window.hitl.pointsPath") == path
    assert pages["gpu"].evaluate("window.hitl.placedBy") in ("shader", "cpu")
    page = pages[points]
    apply_through_page(page, first_correction)
    state = demo.state()
    for p in pages.values():
        p.wait_for_function(f"window.hitl.version >= {state['version']}")
        p.evaluate("() => { window.hitl.lookAt(3.2, 2.0, 90); }")
        p.wait_for_timeout(150)
    # Only the laser points: orange pixels, in both renderings of the same view.
    shots = {k: canvas_pixels(p) for k, p in pages.items()}
    orange = {
        k: (s[:, :, 0].astype(int) - s[:, :, 2].astype(int) > 60) & (s[:, :, 1] > 100)
        for k, s in shots.items()
    }
    assert orange["gpu"].sum() > 1000
    assert orange["cpu"].sum() > 1000
    overlap = (orange["gpu"] & orange["cpu"]).sum() / max(orange["cpu"].sum(), 1)
    assert overlap > 0.8, overlap
    for p in pages.values():
        assert p.errors == []


def test_the_front_ends_doubtful_stretches_are_drawn_and_said(tmp_path: Path, browser: Any) -> None:
    """A front-end map whose metadata names doubtful stretches (issue 39, point 6): the page draws
    a purple band along the poses of each, and its status bar gives the verdict and the
    comparison with a bag's own SLAM trajectory."""
    import dataclasses

    room = lost_poses_room(0).map
    stretches = DOUBTFUL_STRETCHES
    m = dataclasses.replace(
        room,
        name="room (hitl-slam front end)",
        metadata={**room.metadata, "front_end": "hitl-slam", **DOUBTFUL_FRONT_END},
    )
    path = tmp_path / "room.hitl"
    Session.new(m, str(path)).close()
    with serve(tmp_path, str(path)) as server:
        page = open_page(browser, server.url)
        drawn = page.evaluate("window.hitl.doubtful()")
        assert [(s["first"], s["last"], s["reason"]) for s in drawn] == [
            (s["first"], s["last"], s["reason"]) for s in stretches
        ]
        poses = server.poses()
        for s, placed in zip(stretches, drawn, strict=True):
            path_xy = np.array(placed["path"])
            assert len(path_xy) == s["last"] - s["first"] + 1
            np.testing.assert_allclose(path_xy, poses[s["first"] : s["last"] + 1, :2], atol=1e-5)
        assert page.evaluate("window.hitl.verdictStatus()") == (
            "front end: doubtful map: 2 stretches, scans 40-90, 300-330"
        )
        assert page.evaluate("window.hitl.compareStatus()") == (
            "at start: bag's SLAM 12.50 \u00b7 front end 9.25 m\u00b2 (front end lower)"
        )
        tooltip = page.locator("#st-verdict").get_attribute("title")
        assert tooltip.endswith(
            "scans 40-90: match failed\nscans 300-330: contradicts the loop closures"
        ), tooltip
        assert page.locator("#legend-doubtful").is_visible()
        assert page.locator("#st-verdict").is_visible()
        # The band is on the screen, along each stretch: purple pixels around its middle pose.
        pixels = canvas_pixels(page).astype(np.int16)
        purple = (pixels[..., 0] > pixels[..., 1] + 25) & (pixels[..., 2] > pixels[..., 1] + 25)
        box = page.locator("#map").bounding_box()
        for s in stretches:
            middle = poses[(s["first"] + s["last"]) // 2, :2]
            x, y = to_client(page, [float(v) for v in middle])
            col, row = int(x - box["x"]), int(y - box["y"])
            assert purple[row - 10 : row + 11, col - 10 : col + 11].sum() > 5, s
        save_artifact(page, "doubtful-stretches.png")
        assert page.errors == []
        page.context.close()


def test_a_map_without_a_verdict_says_nothing_of_one(browser: Any, shared_demo: Server) -> None:
    page = open_page(browser, shared_demo.url)
    assert page.evaluate("window.hitl.doubtful()") == []
    assert page.evaluate("window.hitl.mapInfo.poses") == "as_input"
    assert not page.locator("#st-verdict").is_visible()
    assert not page.locator("#st-compare").is_visible()
    assert not page.locator("#legend-doubtful").is_visible()
    page.context.close()
