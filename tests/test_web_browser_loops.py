"""Loop closures in a real browser (issue 14, part 4): `hitl-slam serve` on a raw CARMEN log
(the corrected Orebro log, Radish, copied to a temporary folder) runs the front end, and the
page draws its loop closures by trust; a click selects one, x rejects it (the map re-solves), u
brings it back, c hides them all. Skipped without a browser, except on CI.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from web_support import (
    Server,
    canvas_pixels,
    changed_fraction,
    chromium,
    open_page,
    save_artifact,
    serve,
    to_client,
    wait_until,
)

LASER = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "laser"


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


@pytest.fixture
def orebro(tmp_path: Path) -> Iterator[Server]:
    source = LASER / "orebro-corrected.log.gz"
    if not source.is_file():
        pytest.skip("../shared/datasets/laser is not beside the repository")
    shutil.copyfile(source, tmp_path / "orebro.log.gz")
    with serve(tmp_path, "orebro.log.gz", timeout=300) as server:
        yield server


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = b - a
    t = 0.0 if not d.any() else float(np.clip(np.dot(p - a, d) / np.dot(d, d), 0, 1))
    return float(np.hypot(*(a + t * d - p)))


def _loneliest(loops: list[dict[str, Any]]) -> tuple[int, np.ndarray]:
    """The loop closure in the solve whose midpoint is farthest from every other loop closure's
    line, and that midpoint (world), so a click there means that one."""
    best, where, margin = -1, np.zeros(2), -1.0
    for c in loops:
        if c["rejected"]:
            continue
        mid = (np.array(c["p0"]) + np.array(c["p1"])) / 2
        gap = min(
            (
                _segment_distance(mid, np.array(o["p0"]), np.array(o["p1"]))
                for o in loops
                if o["index"] != c["index"]
            ),
            default=np.inf,
        )
        if gap > margin:
            best, where, margin = c["index"], mid, gap
    return best, where


def test_serve_a_raw_log_draws_and_rejects_loop_closures(browser: Any, orebro: Server) -> None:
    assert any("ran the front end over orebro.log.gz" in line for line in orebro.output)
    state = orebro.state()
    count = state["loop_closures"]["count"]
    assert count >= 2, state["loop_closures"]
    auto = state["loop_closures"]["rejected"]

    page = open_page(browser, orebro.url)
    page.wait_for_function(f"window.hitl.loopClosures().length === {count}")
    drawn = page.evaluate("window.hitl.loopClosures()")
    assert [c["index"] for c in drawn if c["style"] == "rejected"] == auto
    assert all(c["style"] != "rejected" for c in drawn if c["index"] not in auto)
    assert page.evaluate("window.hitl.loopsVisible")
    assert page.locator("#st-loops").is_visible()
    assert f"{count - len(auto)}/{count} in the solve" in page.evaluate("window.hitl.loopStatus()")
    # Each is drawn between the poses it joins, as the server has them.
    poses = orebro.poses()
    for c in drawn:
        i, j = c["pair"]
        np.testing.assert_allclose(c["p0"], poses[i, :2], atol=1e-4)
        np.testing.assert_allclose(c["p1"], poses[j, :2], atol=1e-4)
    save_artifact(page, "loops-orebro.png")

    # A click on one selects it; x rejects it and the map re-solves.
    k, mid = _loneliest(drawn)
    page.mouse.click(*to_client(page, mid))
    page.wait_for_function(f"window.hitl.selectedLoop === {k}")
    assert f"loop closure {k}:" in page.evaluate("window.hitl.loopStatus()")
    assert page.locator("#btn-loop-toggle").inner_text() == "Reject"
    before = canvas_pixels(page)
    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("x")
    page.wait_for_function(
        f"window.hitl.version > {version} && window.hitl.loopClosures()[{k}].style === 'rejected'"
    )
    assert wait_until(lambda: k in orebro.state()["loop_closures"]["rejected"])
    assert page.evaluate("window.hitl.message.kind") == "ok"
    assert "rejected" in page.evaluate("window.hitl.message.text")
    assert page.locator("#btn-loop-toggle").inner_text() == "Reinstate"
    assert "rejected" in page.evaluate("window.hitl.loopStatus()")
    after = canvas_pixels(page)
    assert changed_fraction(before, after) > 0.0005
    save_artifact(page, "loops-orebro-rejected.png")

    # u undoes it: in the solve again.
    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("u")
    page.wait_for_function(
        f"window.hitl.version > {version} && window.hitl.loopClosures()[{k}].style !== 'rejected'"
    )
    assert orebro.state()["loop_closures"]["rejected"] == auto

    # c hides them (the canvas changes), c again shows them.
    shown = canvas_pixels(page)
    page.keyboard.press("c")
    page.wait_for_function("!window.hitl.loopsVisible")
    page.wait_for_timeout(150)
    assert changed_fraction(shown, canvas_pixels(page)) > 0.0005
    page.keyboard.press("c")
    page.wait_for_function("window.hitl.loopsVisible")
    assert page.errors == []
