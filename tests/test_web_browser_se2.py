"""The page's one plane geometry, js/se2.js, in a real browser against hitl_slam.geometry: the same
conventions (headings in (-pi, pi]) and, for wrap, the same arithmetic to the bit. Skipped without
a browser, except on CI (see web_support)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.geometry import compose, to_world, wrap
from web_support import chromium, open_page, serve

PI = math.pi


@pytest.fixture(scope="module")
def page(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    with chromium() as browser, serve(tmp_path_factory.mktemp("se2"), "--demo") as server:
        page = open_page(browser, server.url)
        yield page
        assert page.errors == []
        page.context.close()


def se2(page: Any, body: str, arg: Any) -> Any:
    """Runs ``body`` (an async function of ``(se2, arg)``) with the page's se2.js module."""
    return page.evaluate(
        f"async (arg) => {{ const se2 = await import('./static/js/se2.js'); "
        f"return await (async (se2, arg) => {{ {body} }})(se2, arg); }}",
        arg,
    )


def test_wrap_matches_the_python_and_rust_wrap_to_the_bit(page: Any) -> None:
    rng = np.random.default_rng(5)
    angles = [PI, -PI, 3 * PI, -3 * PI, 0.0, 2 * PI, -2 * PI, 1e6, -1e12, 1e300, -1.7e308]
    angles += rng.uniform(-40, 40, 200).tolist() + (np.arange(-8, 9) * PI / 2).tolist()
    got = se2(page, "return arg.map(se2.wrap);", angles)
    assert got == [wrap(a) for a in angles]
    assert all(-PI < v <= PI for v in got)
    assert got[:4] == [PI, PI, PI, PI]


def test_compose_and_robot_to_world_match_the_python_geometry(page: Any) -> None:
    rng = np.random.default_rng(6)
    a = rng.uniform(-5, 5, (20, 3))
    b = rng.uniform(-5, 5, (20, 3))
    a[:, 2] = rng.uniform(-PI, PI, 20)
    b[:, 2] = rng.uniform(-PI, PI, 20)
    a[0, 2], b[0, 2] = PI, PI  # the seam: pi + pi is 0, not 2 pi
    got = se2(
        page,
        "return arg.a.map((p, k) => se2.compose(p, arg.b[k]));",
        {"a": a.tolist(), "b": b.tolist()},
    )
    np.testing.assert_allclose(got, compose(a, b), rtol=0, atol=1e-12)
    assert all(-PI < row[2] <= PI for row in got)

    # Scans placed by their poses (float32 out), whole and by index.
    counts = [3, 0, 5, 2]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    points = rng.uniform(-4, 4, (int(offsets[-1]), 2))
    poses = a[: len(counts)]
    owner = np.repeat(np.arange(len(counts)), counts)
    expected = to_world(poses, owner, points).astype(np.float32)
    arg = {
        "points": points.ravel().tolist(),
        "offsets": offsets.tolist(),
        "poses": poses.ravel().tolist(),
        "owner": owner.tolist(),
        "indices": [7, 0, 99, 3],
    }
    placed = se2(
        page,
        "return Array.from(se2.placePoints(new Float32Array(arg.points), arg.offsets, arg.poses));",
        arg,
    )
    f32 = points.astype(np.float32).astype(np.float64)  # the page holds points as float32
    np.testing.assert_allclose(
        np.reshape(placed, (-1, 2)), to_world(poses, owner, f32).astype(np.float32), atol=1e-6
    )
    np.testing.assert_allclose(np.reshape(placed, (-1, 2)), expected, atol=1e-5)
    picked = se2(
        page,
        "return Array.from(se2.placeIndexed(new Float32Array(arg.points), arg.owner, "
        "arg.poses, arg.indices));",
        arg,
    )
    np.testing.assert_allclose(np.reshape(picked, (-1, 2)), np.reshape(placed, (-1, 2))[[7, 0, 3]])
    one = se2(
        page,
        "return se2.toWorld(arg.pose, arg.p[0], arg.p[1]);",
        {"pose": a[1].tolist(), "p": [1.0, 2.0]},
    )
    np.testing.assert_allclose(
        one, to_world(a[1:2], np.zeros(1, dtype=np.int64), np.array([[1.0, 2.0]]))[0], atol=1e-12
    )


def test_the_page_imports_se2_for_every_robot_to_world_transform() -> None:
    js = Path(__file__).resolve().parents[1] / "python" / "hitl_slam" / "web" / "static" / "js"
    for name in ("main.js", "view.js", "splat.js"):
        assert 'from "./se2.js"' in (js / name).read_text(encoding="utf-8"), name
    for path in js.glob("*.js"):
        if path.name != "se2.js":
            text = path.read_text(encoding="utf-8")
            assert "Math.cos(" not in text, path.name
            assert "Math.sin(" not in text, path.name
