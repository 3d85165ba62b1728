// The test and benchmark hooks on window.hitl: read-only views of the app's state plus a few
// helpers to convert coordinates and move the view. Installed by main.js; nothing here acts on
// the server.
//
// window.hitl:
//   ready            Promise, resolved after the first frame with the map is drawn
//   version          state version of the map on screen (rises with every change)
//   state            the latest State from the server (see the API's GET /api/state)
//   mode             mode of the pending correction ("collinear", ...) or null
//   correcting       whether correction mode (key p) is on
//   pending          how many segments of the pending pair are drawn (0, 1 or 2)
//   message          {text, kind} of #message; kind "rejected", "error", "ok", "info", "busy"
//                    (an alignment running) or ""
//   busy             whether a command (apply, undo, redo, align, ...) is in flight
//   worldToClient(x, y) -> [clientX, clientY]   world metres to page (viewport) pixels
//   clientToWorld(cx, cy) -> [x, y]
//   lookAt(x, y, pixelsPerMetre)                centre the view (pixelsPerMetre optional)
//   sigmaH()         the pointing accuracy [m] a drag would be sent with at this zoom
//   highlighted()    {a, b}: how many S_a / S_b points of the preview are highlighted
//   preview          the last /api/interpret answer for the pending pair, or null
//   lastRedrawMs     time from sending an apply request to the first frame drawn with its map
//   lastRedraw       its split: {version, totalMs, requestMs, solveMs, fetchMs, uploadMs, drawMs,
//                    bytes}; fetch and upload are of the new poses (the scans stay on the page),
//                    draw of that first frame
//   appliedLines()   the applied corrections' lines as drawn: [{index, mode, a, b}], a and b
//                    each [[x0, y0], [x1, y1]] in world metres (the server's State.lines)
//   hintVisible()    whether the first-use hint (how to start a correction) shows
//   loopClosures()   the loop closures as drawn: [{index, pair, weight, rejected, style, dimmed,
//                    p0, p1}] (style "trusted", "down-weighted", "untrusted" or "rejected";
//                    dimmed while the map is aligned with its scans (State.aligned); p0, p1 the
//                    world positions of the two poses on screen); [] for a map without any
//   selectedLoop     index of the selected loop closure, or null
//   loopsVisible     whether the loop closures are drawn (key c)
//   loopStatus()     the status bar's loop closure text
//   mapInfo          what the served map is (GET /api/map/info), or null before it arrived
//   doubtful()       the front end's doubtful stretches as drawn: [{first, last, reason, path}]
//                    (path: the world positions of their poses on screen); [] for none
//   verdictStatus()  the status bar's text on the front end's verdict ("" when none)
//   compareStatus()  the status bar's comparison with a bag's own SLAM trajectory ("" when none)
//   frameTimes()     recent frame durations [ms], each up to a 1-pixel readPixels (GPU done)
//   rafIntervals()   recent intervals between consecutive animation frames [ms]
//   splatTimes()     of the frame times, the part spent counting points on the CPU ("cpu" path)
//   renderer         the WebGL renderer string; numPoints: laser points shown
//   pointsPath       "gpu" (GL_POINTS) or "cpu" (splatted, on a software WebGL); see view.js
//   placedBy         for "gpu": "shader" (points placed by a pose texture) or "cpu"

/** Defines window.hitl over `app` (the App of main.js). */
export function installHooks(app) {
  window.hitl = {
    ready: app.ready,
    get version() {
      return app.version;
    },
    get state() {
      return app.state;
    },
    get mode() {
      return app.draft ? app.draft.mode : app.pending.mode;
    },
    get correcting() {
      return app.correcting;
    },
    get pending() {
      return app.pending.segments.length;
    },
    get message() {
      return { ...app.ui.message };
    },
    get busy() {
      return app.busy;
    },
    get queued() {
      return app.queue.map((q) => q.what);
    },
    get preview() {
      return app.preview;
    },
    get lastRedrawMs() {
      return app.lastRedraw ? app.lastRedraw.totalMs : null;
    },
    get lastRedraw() {
      return app.lastRedraw ? { ...app.lastRedraw } : null;
    },
    get renderer() {
      return app.view.renderer;
    },
    get numPoints() {
      return app.view.numPoints;
    },
    get pointsPath() {
      return app.view.pointsPath;
    },
    get placedBy() {
      return app.view.placedBy;
    },
    appliedLines: () =>
      app.applied.map((c) => ({ index: c.index, mode: c.mode, a: c.a.segment, b: c.b.segment })),
    hintVisible: () => app.ui.hintVisible(),
    loopClosures: () => app.placedLoops.map((c) => ({ ...c })),
    get selectedLoop() {
      return app.selectedLoop;
    },
    get loopsVisible() {
      return app.loopsVisible;
    },
    loopStatus: () => document.getElementById("st-loops").textContent,
    get mapInfo() {
      return app.info;
    },
    doubtful: () => app.placedDoubtful.map((s) => ({ ...s, path: s.path.map((p) => [...p]) })),
    verdictStatus: () => document.getElementById("st-verdict").textContent,
    compareStatus: () => document.getElementById("st-compare").textContent,
    worldToClient(x, y) {
      const rect = app.canvas.getBoundingClientRect();
      const [sx, sy] = app.camera.toScreen(x, y);
      return [rect.left + sx, rect.top + sy];
    },
    clientToWorld(cx, cy) {
      const rect = app.canvas.getBoundingClientRect();
      return app.camera.toWorld(cx - rect.left, cy - rect.top);
    },
    lookAt(x, y, pixelsPerMetre) {
      app.camera.cx = x;
      app.camera.cy = y;
      if (pixelsPerMetre) app.camera.scale = pixelsPerMetre;
      app.refreshIndicator();
      app.requestRender();
    },
    sigmaH: () => app.sigmaH(),
    highlighted: () => ({ ...app.highlights }),
    frameTimes: () => app.view.frames.slice(),
    rafIntervals: () => app.rafs.slice(),
    splatTimes: () => app.view.splats.slice(),
  };
}
