// The app: holds the server's state and the map on screen, reacts to input (interaction.js),
// talks to the server (api.js), keeps in step with other tabs through a long poll on
// /api/state?after=V, and schedules frames (view.js). The page's hooks for tests and
// benchmarks (window.hitl) are in hooks.js.

import * as api from "./api.js";
import { Camera } from "./camera.js";
import { PendingPair, sigmaForScale } from "./correction.js";
import { comparisonText, placeStretches, stretchLines, stretchList, verdictText } from "./doubtful.js";
import { installHooks } from "./hooks.js";
import { attachInput } from "./interaction.js";
import { ALIGNED_LOOPS, frameLoop, loopLines, pickLoop, placeLoops } from "./loops.js";
import { overlay } from "./overlay.js";
import { placeIndexed } from "./se2.js";
import { Ui } from "./ui.js";
import { MapView } from "./view.js";

class App {
  constructor() {
    this.canvas = document.getElementById("map");
    this.ui = new Ui();
    this.camera = new Camera();
    this.view = new MapView(this.canvas);
    this.state = null; // latest State
    this.version = -1; // state version whose map is on screen
    this.scans = null; // {points: robot-frame Float32Array (P*2), offsets: Int32Array (N+1)}, once
    this.owner = null; // Int32Array (P): each point's pose
    this.poses = null; // Float32Array (N*3) of the map on screen
    this.applied = []; // State.lines shown: the corrections in effect with their solved lines
    this.correcting = false;
    this.selectedMode = null; // mode button for plain drags
    this.pending = new PendingPair();
    this.draft = null; // {mode, segment} while dragging
    this.preview = null; // answer of /api/interpret for the pending pair
    this.previewSeq = 0;
    this.highlights = { a: 0, b: 0 };
    this.busy = false; // a command (apply, undo, redo, step, loop closure, align, save) in flight
    this.queue = []; // commands asked for while one was in flight, to run in order after it
    this.loading = null; // the running map fetch (one at a time)
    this.wanted = -1; // newest state version whose map should be fetched
    this.measure = null; // {t0, t1, solveMs, version} of the apply awaiting its first frame
    this.lastLoad = null; // {version, fetchMs, uploadMs, bytes} of the latest poses fetched
    this.labels = []; // "1a"/"1b" labels of the applied corrections
    this.loops = null; // the map's loop closures (GET /api/loop_closures), fetched once
    this.loopsVisible = true; // key c
    this.selectedLoop = null; // index of the selected loop closure
    this.placedLoops = []; // the loop closures as drawn now (loops.js placeLoops)
    this.info = null; // what the served map is (GET /api/map/info), fetched once
    this.placedDoubtful = []; // the front end's doubtful stretches as drawn now (doubtful.js)
    this.lastRedraw = null;
    this.frameScheduled = false;
    this.lastFrameTs = null;
    this.rafs = [];
    this.fitted = false;
    let resolveReady;
    this.ready = new Promise((resolve) => {
      resolveReady = resolve;
    });
    this.resolveReady = resolveReady;
  }

  async start() {
    this.resize();
    attachInput(this, this.canvas);
    this.bindButtons();
    const [state, scans, info] = await Promise.all([api.getState(), api.getScans(), api.getMapInfo()]);
    this.info = info;
    this.ui.setMapInfo(info.description, verdictText(info), comparisonText(info), stretchList(info));
    this.scans = scans;
    const owner = new Int32Array(scans.points.length >>> 1);
    for (let p = 0; p + 1 < scans.offsets.length; p++) owner.fill(p, scans.offsets[p], scans.offsets[p + 1]);
    this.owner = owner;
    this.view.setScans(scans.points, scans.offsets);
    if (state.loop_closures && state.loop_closures.count > 0) this.loops = await api.getLoopClosures();
    this.ui.setName(state.name, state.session);
    this.setState(state);
    await this.ensureMap(state.version);
    this.syncLoop();
  }

  bindButtons() {
    const on = (id, f) => document.getElementById(id).addEventListener("click", f);
    on("btn-apply", () => this.apply());
    on("btn-undo", () => this.undo());
    on("btn-redo", () => this.redo());
    on("btn-align", () => this.align());
    on("btn-fit", () => this.fit());
    on("btn-save", () => this.save());
    on("btn-journal", () => this.journalStep());
    on("btn-loops", () => this.toggleLoops());
    on("btn-loop-toggle", () => this.toggleSelectedLoop());
    on("btn-help", () => this.toggleHelp());
    for (const b of document.querySelectorAll("button.mode")) {
      b.addEventListener("click", () => {
        const mode = this.selectedMode === b.dataset.mode ? null : b.dataset.mode;
        this.selectedMode = mode;
        if (mode) this.correcting = true;
        this.ui.setSelectedMode(mode);
        this.refreshIndicator();
      });
    }
  }

  // -- server state and map ------------------------------------------------------------------

  setState(s) {
    if (this.state && s.version < this.state.version) return; // an older answer, arrived late
    this.state = s;
    this.ui.setState(s);
    const n = s.num_poses;
    const flags = new Uint8Array(n);
    for (const h of s.history) {
      if (h.status !== "applied") continue;
      for (const i of h.x_a || []) if (i < n) flags[i] = 1;
      for (const i of h.x_b || []) if (i < n) flags[i] = 1;
    }
    this.view.setConstrained(flags);
    this.constrained = flags;
    this.ui.setHint(s);
    this.refreshLoops();
    this.followState();
    if (s.version > this.version) {
      // Not every change moves the map (a rejection, the inconsistency arriving): the server's
      // map_version says when the poses last changed; without it, a lone rejection is known
      // not to move them. Then the arrays on screen stay and nothing is fetched.
      const unmoved =
        typeof s.map_version === "number"
          ? s.map_version <= this.version
          : s.version === this.version + 1 && s.last && s.last.kind === "reject";
      if (unmoved && !this.loading) {
        this.version = s.version;
        this.followState();
      } else {
        this.ensureMap(s.version).catch((e) => this.error(e));
      }
    }
  }

  /**
   * Shows the latest state's solved lines once the poses on screen are those they were solved
   * with (the state's map_version), so lines and points always move together.
   */
  followState() {
    const s = this.state;
    if (!s || !this.poses) return;
    const mapVersion = typeof s.map_version === "number" ? s.map_version : s.version;
    if (mapVersion <= this.version && this.applied !== s.lines) {
      this.applied = s.lines || [];
      this.refreshLines();
    } else {
      this.requestRender();
    }
  }

  /**
   * Fetches the poses until the map on screen is at least `version`: the scans are on the page
   * already (robot frame), so a new map is N*3 floats, and the view places the points.
   */
  ensureMap(version) {
    this.wanted = Math.max(this.wanted, version);
    if (this.loading) return this.loading;
    this.loading = (async () => {
      try {
        while (this.version < this.wanted) {
          const t0 = performance.now();
          const fetched = await api.getPoses();
          const t1 = performance.now();
          this.poses = fetched.poses;
          this.view.setPoses(fetched.poses, this.constrained || new Uint8Array(0));
          this.refreshLoops();
          this.refreshDoubtful();
          const t2 = performance.now();
          this.version = Math.max(this.version, fetched.version);
          this.wanted = Math.max(this.wanted, fetched.version);
          this.lastLoad = {
            version: fetched.version,
            fetchMs: t1 - t0,
            uploadMs: t2 - t1,
            bytes: fetched.poses.byteLength,
          };
          if (!this.fitted) {
            this.fit();
            this.fitted = true;
          }
          this.followState();
          // A preview shown over the old map would be stale: ask again on the new one.
          if (this.pending.complete && this.preview) this.requestPreview();
          else this.refreshHighlights();
        }
      } finally {
        this.loading = null;
      }
    })();
    return this.loading;
  }

  /** Keeps this tab in step with the server (and other tabs): long poll on the version. */
  async syncLoop() {
    let backoff = 500;
    let failed = false;
    for (;;) {
      try {
        const s = await api.getState(this.state ? this.state.version : null);
        if (failed) this.ui.show("connected to the server again", "ok");
        backoff = 500;
        failed = false;
        if (!this.state || s.version !== this.state.version) this.setState(s);
      } catch (e) {
        failed = true;
        this.error(e);
        await new Promise((r) => setTimeout(r, backoff));
        backoff = Math.min(backoff * 2, 10000);
      }
    }
  }

  // -- drawing a correction ------------------------------------------------------------------

  refreshIndicator() {
    if (!this.correcting) {
      this.ui.setIndicator(false, "view");
    } else {
      const mode = this.draft ? this.draft.mode : this.pending.mode || this.selectedMode;
      const n = this.pending.segments.length;
      const what = mode ? `${mode} ${n}/2` : "Ctrl / Shift + drag";
      const sigma = `\u03c3h ${(100 * this.sigmaH()).toFixed(1)} cm`;
      this.ui.setIndicator(true, `correcting \u00b7 ${what} \u00b7 ${sigma}`);
    }
    this.ui.setApplyReady(this.pending.complete && (!this.preview || this.preview.accepted));
  }

  sigmaH() {
    return sigmaForScale(this.camera.scale);
  }

  setDraft(mode, segment) {
    this.draft = mode ? { mode, segment } : null;
    this.refreshLines();
    this.refreshIndicator();
  }

  addSegment(mode, segment) {
    this.draft = null;
    if (this.pending.complete || (this.pending.mode && this.pending.mode !== mode)) {
      this.clearPreview();
    }
    this.pending.add(mode, segment, this.sigmaH());
    this.refreshLines();
    this.refreshIndicator();
    if (this.pending.complete) this.requestPreview();
  }

  async requestPreview() {
    const seq = ++this.previewSeq;
    const drawn = this.pending.toDrawn();
    try {
      const p = await api.interpret(drawn);
      if (seq !== this.previewSeq) return; // the pair changed meanwhile
      this.preview = p;
      if (p.accepted) {
        const n = (b64) => api.decodeIndices(b64).length;
        this.ui.show(
          `${p.mode}: ${n(p.s_a)} + ${n(p.s_b)} points selected; p or Apply corrects, Esc cancels`,
          "info",
        );
      } else {
        this.ui.show(`rejected: ${p.reason}`, "rejected");
      }
      this.refreshHighlights();
      this.refreshLines();
      this.refreshIndicator();
    } catch (e) {
      if (seq === this.previewSeq) this.error(e);
    }
  }

  clearPreview() {
    this.previewSeq++;
    this.preview = null;
    this.refreshHighlights();
  }

  /** S_a / S_b of the preview (global point indices), placed by the poses on screen. */
  refreshHighlights() {
    const p = this.preview;
    let a = new Float32Array(0);
    let b = new Float32Array(0);
    if (p && p.accepted && this.scans && this.poses) {
      const { points } = this.scans;
      const poses = this.poses;
      const gather = (b64) => placeIndexed(points, this.owner, poses, api.decodeIndices(b64));
      a = gather(p.s_a);
      b = gather(p.s_b);
    }
    this.highlights = { a: a.length / 2, b: b.length / 2 };
    this.view.setHighlights(a, b);
    this.requestRender();
  }

  // -- loop closures -------------------------------------------------------------------------

  /** The set of rejected loop closures the latest state names. */
  rejectedLoops() {
    const lc = this.state && this.state.loop_closures;
    return new Set(lc ? lc.rejected : []);
  }

  /**
   * Whether the latest state says the map is aligned with its scans: the alignment's own loop
   * closures then replaced the map's, which are drawn faded and cannot be rejected or reinstated
   * until the alignment is undone.
   */
  aligned() {
    return Boolean(this.state && this.state.aligned);
  }

  /** Places the loop closures on the poses on screen with the latest state's rejections. */
  refreshLoops() {
    if (!this.loops) return;
    this.placedLoops = placeLoops(this.loops, this.rejectedLoops(), this.poses, this.aligned());
    this.ui.setLoops(this.loopSummary());
    this.refreshLines();
  }

  /** What the status bar says about the loop closures (and the selected one). */
  loopSummary() {
    if (!this.loops) return null;
    const count = this.loops.pairs.length;
    const rejected = this.rejectedLoops().size;
    const aligned = this.aligned();
    let text = aligned
      ? `loop closures: the map's ${count} replaced (aligned)`
      : `loop closures ${count - rejected}/${count} in the solve`;
    if (!this.loopsVisible) text += " (hidden: c)";
    const k = this.selectedLoop;
    if (k !== null && k < count) {
      const [i, j] = this.loops.pairs[k];
      let state = this.rejectedLoops().has(k) ? "rejected" : "in the solve";
      if (aligned) state = "replaced (aligned)";
      text = `loop closure ${k}: poses ${i}\u2013${j}, trust ${this.loops.weight[k].toFixed(2)}, ${state} \u00b7 ${text}`;
    }
    return { text, selected: k, rejected: k !== null && this.rejectedLoops().has(k), aligned };
  }

  /** A click at screen (x, y): selects the loop closure under it, or clears the selection. */
  click(x, y) {
    if (!this.loops || !this.loopsVisible) return;
    this.selectLoop(pickLoop(this.placedLoops, this.camera, x, y));
  }

  selectLoop(k) {
    this.selectedLoop = k;
    this.refreshLoops();
    if (k !== null) {
      const s = this.loopSummary();
      const then = s.aligned ? ALIGNED_LOOPS : `x ${s.rejected ? "reinstates" : "rejects"} it`;
      this.ui.show(`${s.text.split(" \u00b7 ")[0]}; ${then}`, "info");
    }
  }

  /**
   * Keys n / N: select the next (previous) loop closure and bring it into view, whole and clear
   * of the legend and the other overlays on the map (loops.js frameLoop): centred, unless an
   * overlay or the edge is in the way; zoomed out only when it must be.
   */
  stepLoop(direction) {
    if (!this.loops || this.loops.pairs.length === 0) {
      this.hint("this map has no loop closures (only a map the front end built has them)");
      return;
    }
    const count = this.loops.pairs.length;
    const k = this.selectedLoop === null ? (direction > 0 ? 0 : count - 1) : (this.selectedLoop + direction + count) % count;
    if (!this.loopsVisible) this.toggleLoops();
    this.selectLoop(k);
    const c = this.placedLoops.find((p) => p.index === k);
    if (c) {
      const { cx, cy, scale } = frameLoop(this.camera, c.p0, c.p1, this.overlayRects());
      this.camera.cx = cx;
      this.camera.cy = cy;
      this.camera.scale = scale;
      this.refreshIndicator(); // sigma_h follows the zoom
      this.requestRender();
    }
  }

  /** The boxes of what lies over the map (legend, hint, message, indicator, help) as shown,
   *  in canvas CSS px. */
  overlayRects() {
    const canvas = this.canvas.getBoundingClientRect();
    return ["legend", "hint", "message", "indicator", "help"]
      .map((id) => document.getElementById(id))
      .filter((el) => el && !el.hidden && el.getClientRects().length > 0)
      .map((el) => {
        const r = el.getBoundingClientRect();
        return {
          left: r.left - canvas.left,
          top: r.top - canvas.top,
          right: r.right - canvas.left,
          bottom: r.bottom - canvas.top,
        };
      });
  }

  /** Key c: show or hide the loop closures. */
  toggleLoops() {
    if (!this.loops) {
      this.hint("this map has no loop closures (only a map the front end built has them)");
      return;
    }
    this.loopsVisible = !this.loopsVisible;
    this.ui.setLoopsVisible(this.loopsVisible);
    this.refreshLoops();
  }

  /** Key x: reject the selected loop closure, or reinstate it; the map re-solves at once. */
  toggleSelectedLoop() {
    const k = this.selectedLoop;
    if (k === null || !this.loops) {
      this.hint("select a loop closure first: click its line, or n / N");
      return Promise.resolve();
    }
    if (this.aligned()) {
      this.hint(ALIGNED_LOOPS);
      return Promise.resolve();
    }
    const reject = !this.rejectedLoops().has(k);
    return this.command(async () => {
      const s = await api.setLoopClosure(k, reject);
      const last = s.last;
      const ms = last ? ` in ${last.time_ms.toFixed(0)} ms` : "";
      this.ui.show(`loop closure ${k} ${reject ? "rejected" : "reinstated"}; the map re-solved${ms}`, "ok");
      this.setState(s);
    });
  }

  // -- the front end's doubtful stretches ------------------------------------------------------

  /** Places the doubtful stretches on the poses on screen (they move with the map). */
  refreshDoubtful() {
    if (!this.info || this.info.front_end_doubtful.length === 0) return;
    this.placedDoubtful = placeStretches(this.info.front_end_doubtful, this.poses);
    this.refreshLines();
  }

  /** Rebuilds the overlay (lines and labels) from the corrections, the pair and the preview. */
  refreshLines() {
    const { under, over, labels } = overlay({
      applied: this.applied,
      pending: this.pending.segments,
      pendingComplete: this.pending.complete,
      pendingMode: this.pending.mode,
      draft: this.draft,
      preview: this.preview,
    });
    this.labels = labels;
    if (this.loops && this.loopsVisible) under.unshift(...loopLines(this.placedLoops, this.selectedLoop));
    // Beneath everything else drawn: a band along the poses, not a line of the map.
    if (this.placedDoubtful.length > 0) under.unshift(...stretchLines(this.placedDoubtful));
    this.view.setLines(under, over);
    this.requestRender();
  }

  // -- commands ------------------------------------------------------------------------------

  /** Key p: enter correction mode; with a pair drawn, apply it; otherwise leave. */
  togglePOrApply() {
    if (!this.correcting) {
      this.correcting = true;
      this.refreshIndicator();
    } else if (this.pending.complete) {
      this.apply();
    } else {
      this.leaveCorrecting();
    }
  }

  leaveCorrecting() {
    this.correcting = false;
    this.selectedMode = null;
    this.ui.setSelectedMode(null);
    this.cancel(false);
  }

  /** Esc: close the help if it is open; else drop the pending segments and preview. */
  escape() {
    if (this.ui.helpVisible()) this.ui.toggleHelp(false);
    else this.cancel();
  }

  /** Drop the pending segments and preview (correction mode stays on). */
  cancel(say = true) {
    const had = !this.pending.empty || this.draft;
    this.pending.clear();
    this.draft = null;
    this.clearPreview();
    this.refreshLines();
    this.refreshIndicator();
    if (say && had) this.ui.show("correction cancelled", "info");
    else if (this.ui.message.kind === "rejected") this.ui.clearMessage();
  }

  async apply() {
    if (!this.pending.complete) {
      this.ui.show("draw two segments first: a, then b, with the same modifiers", "error");
      return;
    }
    if (this.preview && !this.preview.accepted) {
      this.ui.show(`rejected: ${this.preview.reason} (draw again)`, "rejected");
      return;
    }
    const drawn = this.pending.toDrawn();
    await this.command(async () => {
      const t0 = performance.now();
      const r = await api.applyCorrection(drawn);
      const t1 = performance.now();
      if (!r.accepted) {
        this.ui.show(`rejected: ${r.reason}`, "rejected");
        this.setState(r.state);
        return;
      }
      this.measure = { t0, t1, solveMs: r.solve_ms, version: r.state.version };
      this.leaveCorrecting();
      const last = r.state.last;
      this.ui.show(`applied ${drawn.mode} in ${r.solve_ms.toFixed(0)} ms (${last ? last.iterations : "?"} iterations)`, "ok");
      this.setState(r.state);
    }, "correction");
  }

  undo() {
    return this.command(async () => {
      this.setState(await api.undo());
      this.ui.show("undone", "info");
    }, "undo");
  }

  redo() {
    return this.command(async () => {
      this.setState(await api.redo());
      this.ui.show("redone", "info");
    }, "redo");
  }

  /**
   * Shift+A: align the map with its scans (the server matches them again from the current poses
   * and keeps every correction; seconds to a minute). A refusal (the aligned map would
   * contradict the odometry too often, or the map has no scans) is shown as a refused
   * correction is, the map unchanged; undo returns to the map before an alignment.
   */
  align() {
    return this.command(async () => {
      this.busyText = "aligning the map with its scans\u2026 (up to a minute on a big map)";
      this.ui.show(this.busyText, "busy");
      let s;
      try {
        s = await api.align();
      } catch (e) {
        if (e instanceof api.ApiError && (e.status === 409 || e.status === 400)) {
          this.ui.show(`alignment refused: ${e.detail}`, "rejected");
          return;
        }
        throw e;
      }
      const last = s.last;
      const a = last && last.alignment;
      const took = last ? ` in ${(last.time_ms / 1000).toFixed(1)} s` : "";
      const figures = a
        ? ` (${a.poses_moved} poses moved, at most ${a.max_move_m.toFixed(2)} m; ` +
          `${a.loop_closures} loop closure${a.loop_closures === 1 ? "" : "s"}; ` +
          `${a.contradicted} of ${a.steps} odometry steps contradicted; ` +
          `inconsistency ${a.inconsistency[0].toFixed(0)} \u2192 ${a.inconsistency[1].toFixed(0)} m\u00b2` +
          (a.statements === "none"
            ? ")"
            : `; your statements ${a.statements === "yield" ? "yield to the scans" : "held firm"}, ` +
              "the more consistent way)")
        : "";
      this.ui.show(`aligned with the scans${took}${figures}; u returns to the map before`, "ok");
      this.setState(s);
    }, "align");
  }

  journalStep() {
    return this.command(async () => {
      const r = await api.journalStep();
      const j = r.state.journal;
      if (r.accepted) this.ui.show(`journal: applied correction ${j.next} of ${j.loaded}`, "ok");
      else this.ui.show(`journal correction ${j.next} of ${j.loaded} rejected: ${r.reason}`, "rejected");
      this.setState(r.state);
    });
  }

  save() {
    return this.command(async () => {
      const r = await api.save();
      this.ui.show(`saved ${r.files.join(", ")}`, "ok");
    }, "save");
  }

  /**
   * Runs one server command (named `what`) at a time; its errors go to #message. A command asked
   * for while another is in flight (a key pressed during a long correction) is not dropped: it
   * waits in the queue, says so, and runs when the one before it ends, in the order asked.
   */
  async command(f, what = "command") {
    if (this.busy) {
      this.queue.push({ f, what });
      const waiting = this.queue.map((q) => q.what).join(", then ");
      const running = this.running === "align" ? "the alignment" : `the ${this.running}`;
      const text = `queued: ${waiting} (after ${running})`;
      // While aligning, the banner says what runs (and must not fade): the queue joins it.
      if (this.ui.message.kind === "busy") this.ui.show(`${this.busyText} — ${text}`, "busy");
      else this.ui.show(text, "busy");
      return;
    }
    this.busy = true;
    this.running = what;
    this.ui.setBusy(what);
    try {
      await f();
    } catch (e) {
      this.error(e);
    } finally {
      this.busy = false;
      this.running = null;
      this.ui.setBusy(null);
    }
    const next = this.queue.shift();
    if (next) await this.command(next.f, next.what);
  }

  error(e) {
    this.ui.show(e instanceof api.ApiError ? e.message : `error: ${e.message || e}`, "error");
    if (!(e instanceof api.ApiError)) console.error(e);
  }

  hint(text) {
    this.ui.show(text, "info");
  }

  fit() {
    // A wider margin than the default keeps the map clear of the message banner at the top.
    if (this.state) this.camera.fit(this.state.bounds, 50);
    this.requestRender();
  }

  toggleHelp() {
    this.ui.toggleHelp();
  }

  setCursor([x, y]) {
    this.ui.setCursor(x, y);
  }

  resize() {
    const [w, h] = this.view.resize();
    this.camera.resize(w, h);
    this.requestRender();
  }

  // -- frames --------------------------------------------------------------------------------

  requestRender() {
    if (this.frameScheduled) return;
    this.frameScheduled = true;
    requestAnimationFrame((ts) => this.frame(ts));
  }

  frame(ts) {
    this.frameScheduled = false;
    if (this.lastFrameTs !== null && ts - this.lastFrameTs < 100) {
      this.rafs.push(ts - this.lastFrameTs);
      if (this.rafs.length > 600) this.rafs.splice(0, this.rafs.length - 600);
    }
    this.lastFrameTs = ts;
    const [w, h] = this.view.resize();
    this.camera.resize(w, h);
    if (this.poses === null) return;
    const drawMs = this.view.render(this.camera);
    this.ui.setScale(this.camera.scale);
    this.ui.setLabels(
      this.labels.map((l) => {
        const [x, y] = this.camera.toScreen((l.at[0][0] + l.at[1][0]) / 2, (l.at[0][1] + l.at[1][1]) / 2);
        return { text: l.text, side: l.side, x, y };
      }),
    );
    if (this.correcting) this.refreshIndicator(); // sigma_h follows the zoom
    const m = this.measure;
    if (m && this.version >= m.version) {
      const load = this.lastLoad && this.lastLoad.version >= m.version ? this.lastLoad : {};
      this.lastRedraw = {
        version: this.version,
        totalMs: performance.now() - m.t0,
        requestMs: m.t1 - m.t0,
        solveMs: m.solveMs,
        fetchMs: load.fetchMs ?? null,
        uploadMs: load.uploadMs ?? null,
        drawMs,
        bytes: load.bytes ?? null,
      };
      this.measure = null;
    }
    if (this.version >= 0) this.resolveReady();
  }
}

// Built here, so that a browser without WebGL gets a message rather than a blank page.
function boot() {
  try {
    return new App();
  } catch (e) {
    const el = document.getElementById("message");
    el.textContent = `hitl-slam cannot start: ${e.message}`;
    el.className = "error";
    el.hidden = false;
    throw e;
  }
}

const app = boot();
installHooks(app);
app.start().catch((e) => app.error(e));
