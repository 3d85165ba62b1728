// Mouse, wheel and keyboard: turns input events into calls on the app (pan, zoom about the
// cursor, draw a segment, the single-key commands). Which drags draw and in which mode is
// decided here from the modifiers held at mousedown (correction.js has the bindings).

import { modeFromModifiers } from "./correction.js";

const MIN_SEGMENT_PX = 4; // shorter drags are clicks, not segments
const WHEEL_ZOOM = 0.0015; // zoom factor exp(-deltaY * WHEEL_ZOOM) per wheel pixel

export function attachInput(app, canvas) {
  let drag = null; // {kind: "pan" | "draw", mode, x, y, start: [wx, wy]}

  const local = (e) => {
    const rect = canvas.getBoundingClientRect();
    return [e.clientX - rect.left, e.clientY - rect.top];
  };

  canvas.addEventListener("pointerdown", (e) => {
    if (e.button !== 0) return;
    e.preventDefault();
    canvas.focus({ preventScroll: true });
    const [x, y] = local(e);
    const modified = modeFromModifiers(e);
    const mode = app.correcting ? modified || app.selectedMode : null;
    if (modified && !app.correcting) {
      app.hint("press p to enter correction mode, then draw the two segments");
    }
    canvas.setPointerCapture(e.pointerId);
    if (mode) {
      drag = { kind: "draw", mode, x, y, start: app.camera.toWorld(x, y) };
      canvas.classList.add("drawing");
    } else {
      drag = { kind: "pan", x, y };
      canvas.classList.add("panning");
    }
  });

  canvas.addEventListener("pointermove", (e) => {
    const [x, y] = local(e);
    app.setCursor(app.camera.toWorld(x, y));
    if (!drag) return;
    if (drag.kind === "pan") {
      app.camera.pan(x - drag.x, y - drag.y);
      drag.x = x;
      drag.y = y;
      app.requestRender();
    } else {
      app.setDraft(drag.mode, [drag.start, app.camera.toWorld(x, y)]);
    }
  });

  const finish = (e) => {
    if (!drag) return;
    const [x, y] = local(e);
    const d = drag;
    drag = null;
    canvas.classList.remove("drawing", "panning");
    if (d.kind !== "draw") {
      // A click (no drag) outside correction mode selects the loop closure under it.
      if (Math.hypot(x - d.x, y - d.y) < MIN_SEGMENT_PX && !app.correcting) app.click(x, y);
      return;
    }
    if (Math.hypot(x - d.x, y - d.y) < MIN_SEGMENT_PX) {
      app.setDraft(null, null);
      return;
    }
    app.addSegment(d.mode, [d.start, app.camera.toWorld(x, y)]);
  };
  canvas.addEventListener("pointerup", finish);
  canvas.addEventListener("pointercancel", finish);

  canvas.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      const pixels = e.deltaMode === 1 ? e.deltaY * 16 : e.deltaMode === 2 ? e.deltaY * 400 : e.deltaY;
      const [x, y] = local(e);
      app.camera.zoomAt(x, y, Math.exp(-pixels * WHEEL_ZOOM));
      app.requestRender();
    },
    { passive: false },
  );
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());

  window.addEventListener("keydown", (e) => {
    const target = e.target;
    if (target instanceof HTMLInputElement || target instanceof HTMLTextAreaElement) return;
    if (e.key === "Escape") {
      app.escape();
      return;
    }
    if (e.ctrlKey || e.metaKey || e.altKey || e.repeat) return; // leave browser shortcuts alone
    const command = {
      p: () => app.togglePOrApply(),
      u: () => app.undo(),
      U: () => app.redo(),
      A: () => app.align(),
      v: () => app.save(),
      l: () => app.journalStep(),
      c: () => app.toggleLoops(),
      n: () => app.stepLoop(1),
      N: () => app.stepLoop(-1),
      x: () => app.toggleSelectedLoop(),
      f: () => app.fit(),
      "?": () => app.toggleHelp(),
    }[e.key];
    if (command) {
      e.preventDefault();
      command();
    }
  });

  window.addEventListener("resize", () => app.resize());
}
