#!/usr/bin/env python
"""Web UI latency, in headless Chromium against a real `hitl-slam serve`.

Two questions: (1) how long from pressing Apply to the first frame that shows the corrected map,
on the 3,380-pose generated campus (target: a median under 300 ms), and (2) how long a frame
takes while panning and zooming a map of more than 500,000 laser points (target: under 20 ms).

    python benches/web_latency.py                          # prints the tables
    python benches/web_latency.py --write benches/README.md
    python benches/web_latency.py --only apply --baseline /tmp/base/python   # side by side

(1) The simulated human (hitl_slam.sim) draws its first correction on the campus; the script
draws it in the page with real Shift-drags, waits for the preview, presses p and reads the
page's own measurement (window.hitl.lastRedraw: from sending the request to the end of the first
frame with the new map, GPU finished), then presses u to undo, so every repeat starts from the
same map. The bytes the page receives for one correction are summed from the page's resource
timings: every response from pressing p to that first frame, and the long poll that reported it.
With --baseline DIR, a second server runs the hitl-slam found in DIR (another checkout, its
PYTHONPATH) with its own front end, and the first correction is timed on both in turns.
(2) The campus toured in finer steps (549,552 points) and Freiburg 079 (1.7 M points, from
../shared/datasets/laser/) are panned with a mouse drag and zoomed with the wheel; frame
time is measured by the page from the start of the draw to a 1-pixel readPixels (which waits for
the GPU), and the interval between animation frames while an in-page driver pans or zooms every
frame.
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import statistics
import sys
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO / "tests"))  # web_support: the browser tests' server and Chromium

import web_support  # noqa: E402

APPLY_TARGET_MS = 300.0
FRAME_TARGET_MS = 20.0
FR079 = REPO.parent / "shared" / "datasets" / "laser" / "fr079.clf.bz2"


@dataclass(frozen=True)
class ApplyRun:
    label: str
    total_ms: list[float]
    solve_ms: list[float]
    request_ms: list[float]
    fetch_ms: list[float]
    upload_ms: list[float]
    draw_ms: list[float]
    megabytes: float
    kilobytes_received: float  # everything the page received per correction (median)
    poses: int
    points: int


@dataclass(frozen=True)
class FrameRun:
    map: str
    points: int
    path: str
    frame_ms: list[float]
    splat_ms: list[float]
    raf_ms: list[float]


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values)) if values else float("nan")


def p95(values: Sequence[float]) -> float:
    return float(np.percentile(values, 95)) if values else float("nan")


@contextlib.contextmanager
def browser_or_exit() -> Iterator[Any]:
    if web_support.find_chromium() is None:
        raise SystemExit("no Chromium found: install chromium or set HITL_CHROMIUM")
    with web_support.chromium() as browser:
        yield browser


MODIFIERS = {
    "colocation": ["Control"],
    "collinear": ["Shift"],
    "perpendicular": ["Shift", "Alt"],
    "parallel": ["Shift", "Control"],
}


def look_at(page: Any, segment: Sequence[Sequence[float]], sigma_h: float | None) -> None:
    """Centre the view on a segment, zoomed in as far as the human's accuracy asks (4 pixels a
    sigma_h, as the page counts it) while the whole segment still shows."""
    pts = np.array(segment, dtype=float)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    box = page.locator("#map").bounding_box()
    span = np.maximum(hi - lo, 1e-3)
    fits = min((box["width"] - 200) / span[0], (box["height"] - 200) / span[1])
    scale = min(fits, 4.0 / (sigma_h if sigma_h is not None else 0.1))
    centre = (lo + hi) / 2
    page.evaluate("([x, y, s]) => window.hitl.lookAt(x, y, s)", [centre[0], centre[1], scale])


# The bytes received for one correction: every response that ended after p was pressed and
# started before the first frame with the new map (the apply request's start plus totalMs).
_RECEIVED = """
([pressed, totalMs]) => {
  const entries = performance.getEntriesByType("resource");
  const apply = entries.find((e) => e.name.includes("api/corrections") && e.startTime >= pressed);
  if (!apply) return null;
  const frame = apply.startTime + totalMs;
  return entries
    .filter((e) => e.responseEnd >= pressed && e.startTime <= frame)
    .reduce((sum, e) => sum + e.encodedBodySize, 0);
}
"""


def draw_and_apply(page: Any, drawn: Any) -> dict[str, Any] | None:
    """Draws ``drawn`` in the page as a person would (centring on each segment in turn), waits
    for the preview and presses p; the page's lastRedraw (with ``received``: the bytes the page
    received for it), or None if the preview was rejected."""
    page.keyboard.press("p")
    for segment in (drawn.a, drawn.b):
        look_at(page, segment, drawn.sigma_h)
        web_support.draw_segment(page, [list(p) for p in segment], MODIFIERS[drawn.mode.value])
    page.wait_for_function("window.hitl.preview !== null", timeout=60_000)
    if not page.evaluate("window.hitl.preview.accepted"):
        page.keyboard.press("Escape")
        page.keyboard.press("p")
        return None
    version = int(page.evaluate("window.hitl.version"))
    pressed = float(
        page.evaluate(
            "performance.clearResourceTimings(); performance.setResourceTimingBufferSize(2000);"
            " performance.now()"
        )
    )
    page.keyboard.press("p")
    page.wait_for_function(
        f"window.hitl.lastRedraw !== null && window.hitl.lastRedraw.version > {version}",
        timeout=60_000,
    )
    redraw: dict[str, Any] = page.evaluate("window.hitl.lastRedraw")
    page.wait_for_timeout(300)  # the long poll's answer, if it is still on its way
    redraw["received"] = page.evaluate(_RECEIVED, [pressed, float(redraw["totalMs"])])
    return redraw


def undo(page: Any) -> None:
    version = int(page.evaluate("window.hitl.version"))
    page.keyboard.press("u")
    web_support.wait_version_above(page, version, timeout_ms=60_000)


def apply_run(runs: Sequence[dict[str, Any]], label: str, state: dict[str, Any]) -> ApplyRun:
    def column(name: str) -> list[float]:
        return [float(r[name]) for r in runs if r.get(name) is not None]

    return ApplyRun(
        label=label,
        total_ms=column("totalMs"),
        solve_ms=column("solveMs"),
        request_ms=column("requestMs"),
        fetch_ms=column("fetchMs"),
        upload_ms=column("uploadMs"),
        draw_ms=column("drawMs"),
        megabytes=median(column("bytes")) / 1e6,
        kilobytes_received=median(column("received")) / 1e3,
        poses=int(state["num_poses"]),
        points=int(state["num_points"]),
    )


def measure_apply(
    browser: Any, repeats: int, trees: Sequence[tuple[str, str | None]]
) -> list[ApplyRun]:
    """For each (name, PYTHONPATH or None for this tree): a server on the campus. The human's
    first correction is timed ``repeats`` times on each server in turns (undone after each,
    after one warm-up each), then its next ``repeats`` corrections in a row on each."""
    from hitl_slam.sim import SimulatedHuman, campus

    with contextlib.ExitStack() as stack:
        servers = []
        for name, path in trees:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory()))
            server = stack.enter_context(
                web_support.serve(folder, "--demo", "--demo-world", "campus", pythonpath=path)
            )
            servers.append((name, server, web_support.open_page(browser, server.url)))
        state = servers[0][1].state()
        human = SimulatedHuman(campus(0), 0)
        first = human.next_correction(servers[0][1].poses().astype(np.float64))
        assert first is not None, "the simulated human sees nothing to correct on the campus"
        same: dict[str, list[dict[str, Any]]] = {name: [] for name, _, _ in servers}
        for k in range(repeats + 1):
            for name, _, page in servers:
                redraw = draw_and_apply(page, first)
                assert redraw is not None, f"{name}: the first correction was rejected"
                if k > 0:
                    same[name].append(redraw)
                undo(page)
        runs = []
        for name, server, page in servers:
            page.wait_for_function("window.hitl.state.applied === 0")
            human = SimulatedHuman(campus(0), 0)
            successive: list[dict[str, Any]] = []
            for _ in range(4 * repeats):  # a rejected drawing is not counted; the human tries again
                if len(successive) == repeats:
                    break
                drawn = human.next_correction(server.poses().astype(np.float64))
                if drawn is None:
                    break
                redraw = draw_and_apply(page, drawn)
                if redraw is None:
                    human.rejected(drawn)
                else:
                    successive.append(redraw)
            page.context.close()
            prefix = f"{name}: " if len(servers) > 1 else ""
            runs += [
                apply_run(same[name], f"{prefix}first correction, undone after each", state),
                apply_run(
                    successive, f"{prefix}corrections 1 to {len(successive)} in a row", state
                ),
            ]
    return runs


# An in-page driver: every animation frame, a wheel event at the canvas centre (zooming in, then
# out) or a pan of the view, so frames come as fast as the page can draw them.
_DRIVE = """
async (frames) => {
  const canvas = document.getElementById("map");
  const r = canvas.getBoundingClientRect();
  const cx = r.left + r.width / 2, cy = r.top + r.height / 2;
  const start = window.hitl.clientToWorld(cx, cy);
  const stamps = [];
  for (let i = 0; i < frames; i++) {
    stamps.push(await new Promise((done) => requestAnimationFrame(done)));
    const phase = Math.floor((4 * i) / frames);
    if (phase < 2) {
      const dy = phase === 0 ? -40 : 40;
      canvas.dispatchEvent(new WheelEvent("wheel", {deltaY: dy, clientX: cx, clientY: cy,
                                                    bubbles: true, cancelable: true}));
    } else {
      const [x, y] = window.hitl.clientToWorld(cx + 6, cy + (phase === 2 ? 3 : -3));
      window.hitl.lookAt(x, y);
    }
  }
  stamps.push(await new Promise((done) => requestAnimationFrame(done)));
  window.hitl.lookAt(start[0], start[1]);
  return stamps.slice(2).map((t, k) => t - stamps[k + 1]);  // the first frames settle in
}
"""


def measure_frames(browser: Any, url: str, name: str, path: str, moves: int) -> FrameRun:
    page = web_support.open_page(browser, f"{url}&points={path}")
    assert page.evaluate("window.hitl.pointsPath") == path
    points = int(page.evaluate("window.hitl.numPoints"))
    box = page.locator("#map").bounding_box()
    centre = (box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.wait_for_timeout(300)
    before = len(page.evaluate("window.hitl.frameTimes()"))
    splats_before = len(page.evaluate("window.hitl.splatTimes()"))
    # Real input: a drag (pan) and wheel notches (zoom about the cursor), each answered by a frame.
    page.mouse.move(*centre)
    page.mouse.down()
    for i in range(moves):
        page.mouse.move(centre[0] + 4 * (i + 1), centre[1] + 2 * (i + 1))
        page.evaluate("new Promise((done) => requestAnimationFrame(() => done()))")
    page.mouse.up()
    for i in range(moves):
        page.mouse.wheel(0, -60 if i < moves // 2 else 60)
        page.evaluate("new Promise((done) => requestAnimationFrame(() => done()))")
    frames = page.evaluate("window.hitl.frameTimes()")[before:]
    splats = page.evaluate("window.hitl.splatTimes()")[splats_before:]
    raf = page.evaluate(_DRIVE, 2 * moves)
    page.context.close()
    return FrameRun(
        name,
        points,
        path,
        [float(f) for f in frames],
        [float(s) for s in splats],
        [float(r) for r in raf],
    )


def dense_campus(folder: Path) -> Path:
    """The generated campus toured in steps of 0.24 m: 4,225 scans, 549,552 points."""
    from hitl_slam.io.covars import write_covars
    from hitl_slam.sim import campus

    scenario = campus(0, step=0.24)
    path = folder / "campus-dense.covars"
    write_covars(scenario.map, scenario.map.poses, path)
    return path


def run_frames(browser: Any, moves: int, gpu_moves: int, skip_fr079: bool) -> list[FrameRun]:
    runs: list[FrameRun] = []
    with tempfile.TemporaryDirectory() as folder:
        dense = dense_campus(Path(folder))
        with web_support.serve(Path(folder), str(dense)) as server:
            name = "generated campus, 0.24 m steps"
            runs.append(measure_frames(browser, server.url, name, "cpu", moves))
        if skip_fr079 or not FR079.exists():
            return runs
        copy = Path(folder) / FR079.name  # the session is created beside the map file
        shutil.copyfile(FR079, copy)
        with web_support.serve(Path(folder), str(copy)) as server:
            runs.append(measure_frames(browser, server.url, "Freiburg 079", "cpu", moves))
            runs.append(measure_frames(browser, server.url, "Freiburg 079", "gpu", gpu_moves))
    return runs


def renderer_and_version(browser: Any) -> tuple[str, str]:
    page = browser.new_page()
    renderer = page.evaluate(
        """() => { const gl = document.createElement("canvas").getContext("webgl");
        const d = gl.getExtension("WEBGL_debug_renderer_info");
        return String(gl.getParameter(d ? d.UNMASKED_RENDERER_WEBGL : gl.RENDERER)); }"""
    )
    page.close()
    return str(renderer), str(browser.version)


def tables(apply: Sequence[ApplyRun], frames: Sequence[FrameRun]) -> str:
    out: list[str] = []
    if apply:
        run = apply[0]
        out += [
            f"Apply to redraw on the generated campus ({run.poses} poses, {run.points} points), "
            "drawn by the simulated human with real mouse drags:",
            "",
            "| corrections | n | apply to first frame, median (ms) | median / target "
            "| min - max (ms) | solve on the server (ms) | request round trip (ms) "
            "| fetch arrays (ms) | upload (ms) | draw (ms) | arrays (MB) "
            "| received per correction (kB) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in apply:
            if not r.total_ms:
                continue
            total = median(r.total_ms)
            out.append(
                f"| {r.label} | {len(r.total_ms)} | {total:.0f} | {total / APPLY_TARGET_MS:.2f} "
                f"| {min(r.total_ms):.0f} - {max(r.total_ms):.0f} "
                f"| {median(r.solve_ms):.0f} | {median(r.request_ms):.0f} "
                f"| {median(r.fetch_ms):.0f} | {median(r.upload_ms):.1f} "
                f"| {median(r.draw_ms):.1f} | {r.megabytes:.3f} | {r.kilobytes_received:.0f} |"
            )
        out.append("")
        baseline = [r for r in apply if r.label.startswith("baseline: first")]
        ours = [r for r in apply if r.label.startswith("this tree: first")]
        if baseline and ours and baseline[0].total_ms and ours[0].total_ms:
            b, o = median(baseline[0].total_ms), median(ours[0].total_ms)
            out += [
                f"Side by side, first correction: this tree {o:.0f} ms, baseline {b:.0f} ms: "
                f"**{o / b:.2f}x**; received per correction {ours[0].kilobytes_received:.0f} kB "
                f"against {baseline[0].kilobytes_received:.0f} kB.",
                "",
            ]
        shares = [
            f"{r.label}: {median(r.solve_ms):.0f} ms solving, "
            f"{median(r.request_ms) - median(r.solve_ms):.0f} ms more until the answer arrives, "
            f"{median(r.total_ms) - median(r.request_ms):.0f} ms after it"
            for r in apply
            if r.total_ms
        ]
        out += [
            "Where the time goes (medians): " + "; ".join(shares) + ". The first two are the "
            "server's; what comes after the answer is the front end's (fetching the new arrays, "
            "started when the long poll reports the new version, uploading, drawing).",
            "",
        ]
    if frames:
        out += [
            "Pan and zoom (1280 x 800 window, device pixel ratio 1):",
            "",
            "| map | points | points drawn by | frames | frame time median (ms) | p95 (ms) "
            "| median / target | of which CPU splat (ms) | rAF interval median (ms) | p95 (ms) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for f in frames:
            how = "CPU splat (default here)" if f.path == "cpu" else "GL_POINTS"
            splat = f"{median(f.splat_ms):.1f}" if f.splat_ms else "-"
            out.append(
                f"| {f.map} | {f.points} | {how} | {len(f.frame_ms)} | {median(f.frame_ms):.1f} "
                f"| {p95(f.frame_ms):.1f} | {median(f.frame_ms) / FRAME_TARGET_MS:.2f} | {splat} "
                f"| {median(f.raf_ms):.1f} | {p95(f.raf_ms):.1f} |"
            )
        out.append("")
    return "\n".join(out)


def section(body: str, renderer: str, version: str) -> str:
    import compare_gtsam as shared

    notes = (
        f"Chromium {version}, headless, `--disable-gpu`: WebGL through {renderer}. Targets: "
        f"apply to redraw {APPLY_TARGET_MS:.0f} ms, frame {FRAME_TARGET_MS:.0f} ms. Frame time is "
        "the page's draw up to a 1-pixel readPixels (the GPU is done); the rAF interval is the "
        "time between animation frames while an in-page driver pans or zooms every frame "
        "(Chromium paces frames at 60 Hz, so 16.7 ms is the floor). On a software WebGL the page "
        "splats the points on the CPU (js/splat.js): GL_POINTS costs SwiftShader about 0.6 us a "
        "point; the GL_POINTS row shows what that path costs here."
    )
    credit = (
        "Freiburg 079 data: the Freiburg SLAM benchmark (Kuemmerle et al. 2009), via Radish; "
        "thanks to its authors."
    )
    tail = ["", credit] if "Freiburg" in body else []
    return "\n".join([*shared.provenance(), "", notes, "", body.strip(), *tail])


HEADING = "## 6. Web UI latency (`web_latency.py`)"
INTRO = """How long from pressing Apply to seeing the corrected map, and how long does a frame take
while panning and zooming a big map, in the browser UI of `hitl-slam serve`? Targets: under
300 ms on the 3,380-pose generated campus; under 20 ms a frame with more than 500,000 points.

```sh
python benches/web_latency.py --write benches/README.md
```
"""


def write(path: Path, body: str) -> None:
    import compare_gtsam as shared

    text = path.read_text()
    if "<!-- web_latency:begin -->" not in text:
        block = f"{HEADING}\n\n{INTRO}\n<!-- web_latency:begin -->\n<!-- web_latency:end -->\n\n"
        text = text.replace("## Data", block + "## Data", 1) if "## Data" in text else text + block
        path.write_text(text)
    shared.replace_section(path, "web_latency", body)


def parse_arguments(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed corrections (default 7)")
    parser.add_argument("--moves", type=int, default=40, help="drag and wheel steps (default 40)")
    parser.add_argument(
        "--gpu-moves", type=int, default=6, help="steps for the slow GL_POINTS path (default 6)"
    )
    parser.add_argument("--only", choices=("apply", "frames"), help="run one of the two")
    parser.add_argument("--no-fr079", action="store_true", help="skip Freiburg 079")
    parser.add_argument("--write", type=Path, help="update this README's web_latency section")
    parser.add_argument(
        "--baseline",
        metavar="DIR",
        help="also serve the hitl-slam found in DIR (its PYTHONPATH, e.g. another checkout's "
        "python/ folder with its _core built) and time the first correction on both in turns",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    sys.path.insert(0, str(HERE))  # compare_gtsam, for provenance() and replace_section()
    args = parse_arguments(argv)
    with browser_or_exit() as browser:
        renderer, version = renderer_and_version(browser)
        trees: list[tuple[str, str | None]] = [("this tree", None)]
        if args.baseline is not None:
            here = str(REPO / "python")
            trees = [("baseline", args.baseline), ("this tree", here)]
        apply = measure_apply(browser, args.repeats, trees) if args.only != "frames" else []
        frames = (
            run_frames(browser, args.moves, args.gpu_moves, args.no_fr079)
            if args.only != "apply"
            else []
        )
    body = tables(apply, frames)
    print(f"Chromium {version}; WebGL: {renderer}\n")
    print(body)
    if args.write is not None:
        write(args.write, section(body, renderer, version))
        print(f"wrote the web_latency section of {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
