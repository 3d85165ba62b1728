// The HTML around the map: the status bar, the #message banner, the correction-mode indicator,
// the mode buttons' selection, the help panel and the scale bar. Only reads and writes the DOM;
// the app decides what to show.

import { ALIGNED_LOOPS } from "./loops.js";

const $ = (id) => document.getElementById(id);

function fmtMs(ms) {
  return ms >= 1000 ? `${(ms / 1000).toFixed(2)} s` : `${ms.toFixed(ms < 10 ? 1 : 0)} ms`;
}

function fmtCost(c) {
  if (!Number.isFinite(c)) return "-";
  return Math.abs(c) >= 1e4 || (Math.abs(c) < 1e-2 && c !== 0) ? c.toExponential(2) : c.toFixed(2);
}

export class Ui {
  constructor() {
    this.message = { text: "", kind: "" };
    this.messageTimer = null;
  }

  /**
   * Shows `text` in #message; kinds "info" and "ok" fade, the others ("rejected", "error",
   * "busy") stay until replaced.
   */
  show(text, kind = "info") {
    const el = $("message");
    this.message = { text, kind };
    el.textContent = text;
    el.className = kind;
    el.hidden = false;
    clearTimeout(this.messageTimer);
    if (kind === "info" || kind === "ok") {
      this.messageTimer = setTimeout(() => this.clearMessage(), 6000);
    }
  }

  clearMessage() {
    clearTimeout(this.messageTimer);
    this.message = { text: "", kind: "" };
    const el = $("message");
    el.hidden = true;
    el.className = "";
    el.textContent = "";
  }

  /** The map's name in the top bar; its tooltip holds it whole (a long one ends in an ellipsis)
   *  and what the served poses are (setMapInfo). */
  setName(name, session) {
    const el = $("map-name");
    el.textContent = session ? `${name} - ${session}` : name;
    el.title = [el.textContent, el.dataset.description].filter(Boolean).join("\n");
    document.title = `hitl-slam: ${name}`;
  }

  /** The server's State in the status bar and the buttons' enabled state. */
  setState(s) {
    $("st-version").textContent = `v${s.version}`;
    $("st-applied").textContent = `${s.applied} correction${s.applied === 1 ? "" : "s"}`;
    const last = s.last;
    if (last && last.kind !== "reject") {
      $("st-solve").textContent = `${last.kind.replace("_", " ")} ${fmtMs(last.time_ms)}`;
      $("st-cost").textContent = `cost ${fmtCost(last.initial_cost)} \u2192 ${fmtCost(last.cost)}`;
      $("st-iter").textContent = `${last.iterations} it`;
    } else if (!last) {
      $("st-solve").textContent = "solve -";
      $("st-cost").textContent = "cost -";
      $("st-iter").textContent = "it -";
    }
    const inc = s.inconsistency_m2;
    $("st-inc").textContent =
      inc === null || inc === undefined ? "inconsistency \u2026" : `inconsistency ${inc.toFixed(2)} m\u00b2`;
    $("st-size").textContent =
      `${s.num_poses.toLocaleString("en")} poses, ${s.num_points.toLocaleString("en")} points`;
    $("btn-undo").disabled = !s.can_undo;
    $("btn-redo").disabled = !s.can_redo;
    const j = s.journal || { loaded: 0, next: 0, source: null };
    const hasJournal = j.loaded > 0;
    $("btn-journal").hidden = !hasJournal;
    $("btn-journal").disabled = j.next >= j.loaded;
    $("st-journal").hidden = !hasJournal;
    $("st-journal").textContent = `journal ${j.next}/${j.loaded}`;
    $("st-aligned").hidden = !s.aligned;
  }

  /**
   * The loop closures' part of the status bar and the buttons (null: the map has none). While
   * the map is aligned with its scans (`summary.aligned`) the Reject / Reinstate button is
   * disabled, its tooltip saying why.
   */
  setLoops(summary) {
    const has = summary !== null;
    $("st-loops").hidden = !has;
    $("loop-buttons").hidden = !has;
    $("legend-loops").hidden = !has;
    if (!has) return;
    const status = $("st-loops");
    if (status.dataset.title === undefined) status.dataset.title = status.title;
    status.textContent = summary.text;
    status.title = `${status.dataset.title}\n${summary.text}`; // all of it, when it is cut
    const button = $("btn-loop-toggle");
    if (button.dataset.title === undefined) button.dataset.title = button.title;
    button.disabled = summary.selected === null || summary.aligned;
    button.title = summary.aligned ? ALIGNED_LOOPS : button.dataset.title;
    button.textContent = summary.selected !== null && summary.rejected ? "Reinstate" : "Reject";
  }

  /**
   * What the served map is: its poses in words (the map name's tooltip), the front end's verdict
   * and a comparison with a bag's own SLAM trajectory in the status bar (null: not shown), and
   * the doubtful stretches, one a line (the verdict's tooltip; "": none, no legend entry).
   */
  setMapInfo(description, verdict, comparison, stretches) {
    const name = $("map-name");
    name.dataset.description = description || "";
    name.title = [name.textContent, description].filter(Boolean).join("\n");
    for (const [id, text] of [
      ["st-verdict", verdict],
      ["st-compare", comparison],
    ]) {
      const el = $(id);
      if (el.dataset.title === undefined) el.dataset.title = el.title;
      el.hidden = !text;
      el.textContent = text || "";
      el.title = text ? `${el.dataset.title}\n${text}` : el.dataset.title;
    }
    if (stretches) $("st-verdict").title += `\n${stretches}`;
    $("st-verdict").classList.toggle("doubtful", Boolean(verdict) && Boolean(stretches));
    $("legend-doubtful").hidden = !stretches;
  }

  setLoopsVisible(visible) {
    $("btn-loops").classList.toggle("selected", visible);
    $("btn-loops").setAttribute("aria-pressed", String(visible));
  }

  setCursor(x, y) {
    $("st-cursor").textContent = `x ${x.toFixed(2)}  y ${y.toFixed(2)} m`;
  }

  /** The indicator: "view", or "correcting" with the pending mode and sigma_h. */
  setIndicator(correcting, text) {
    const el = $("indicator");
    el.classList.toggle("correcting", correcting);
    el.textContent = text;
  }

  setSelectedMode(mode) {
    for (const b of document.querySelectorAll("button.mode")) {
      const on = b.dataset.mode === mode;
      b.classList.toggle("selected", on);
      b.setAttribute("aria-pressed", String(on));
    }
  }

  /**
   * The first-use hint (how to start a correction) shows until a correction has been made in
   * this session: while no history entry was ever applied (applied, undone or discarded).
   */
  setHint(s) {
    const made = s.history.some((h) => ["applied", "undone", "discarded"].includes(h.status));
    $("hint").hidden = made;
  }

  hintVisible() {
    return !$("hint").hidden;
  }

  /**
   * While a command is in flight (`what`: its name, null when none is): the align button is
   * disabled, and says so while the alignment itself runs (it takes seconds to a minute).
   */
  setBusy(what) {
    const button = $("btn-align");
    const aligning = what === "align";
    button.disabled = what !== null;
    button.classList.toggle("busy", aligning);
    button.setAttribute("aria-busy", String(aligning));
    button.textContent = aligning ? "Aligning\u2026" : "Align with scans";
    document.body.classList.toggle("aligning", aligning);
  }

  setApplyReady(ready) {
    $("btn-apply").classList.toggle("ready", ready);
  }

  helpVisible() {
    return !$("help").hidden;
  }

  toggleHelp(force) {
    const el = $("help");
    el.hidden = force === undefined ? !el.hidden : !force;
    return !el.hidden;
  }

  /** A scale bar of a round length, 60 to 150 CSS pixels long. */
  setScale(pixelsPerMetre) {
    const target = 100 / pixelsPerMetre;
    const p = 10 ** Math.floor(Math.log10(target));
    const metres = [1, 2, 5, 10].map((k) => k * p).find((m) => m * pixelsPerMetre >= 60) || 10 * p;
    const bar = document.querySelector("#scalebar .bar");
    bar.style.width = `${Math.round(metres * pixelsPerMetre)}px`;
    const label = metres >= 1000 ? `${metres / 1000} km` : metres >= 1 ? `${metres} m` : `${Math.round(metres * 100)} cm`;
    document.querySelector("#scalebar .label").textContent = label;
  }

  /** "1a"/"1b" labels of the applied corrections at their lines' midpoints (screen px). */
  setLabels(labels) {
    const box = $("labels");
    while (box.children.length > labels.length) box.lastChild.remove();
    while (box.children.length < labels.length) box.appendChild(document.createElement("span"));
    labels.forEach((l, k) => {
      const span = box.children[k];
      span.textContent = l.text;
      span.className = l.side;
      span.style.left = `${l.x}px`;
      span.style.top = `${l.y}px`;
    });
  }
}
