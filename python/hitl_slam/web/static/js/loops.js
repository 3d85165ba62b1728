// The loop closures of a map the front end built: each drawn as a line between the two poses it
// joins (placed by the poses on screen, so it moves with the map), coloured by the front end's
// trust in it (its robust weight): green trusted, amber down-weighted, orange one the front end
// rejected but the person reinstated, red dashed rejected (left out of the solve); all of them
// faded while the map is aligned with its scans (the alignment's own loop closures replaced the
// map's, which are then out of the solve). Picking the one nearest a click. Pure functions over
// plain data.

const TRUSTED = 0.9; // weight from which a loop closure counts as trusted
const KEPT = 0.5; // below it the front end rejected it
const WIDTH = 1.5; // [CSS px]
const SELECTED_WIDTH = 4;
const PICK_PX = 10; // a click selects the nearest loop closure within this many pixels
const DIMMED = 0.3; // the opacity of the map's loop closures, relative, while it is aligned

/** Why the map's loop closures cannot be rejected or reinstated while it is aligned. */
export const ALIGNED_LOOPS =
  "the map is aligned with its scans; undo the alignment to reject or reinstate loop closures";

export const LOOP_COLOURS = {
  trusted: [0x2b / 255, 0x8a / 255, 0x3e / 255, 0.85],
  downWeighted: [0xe0 / 255, 0xa0 / 255, 0x00 / 255, 0.9],
  untrusted: [0xe8 / 255, 0x64 / 255, 0x10 / 255, 0.9],
  rejected: [0xc0 / 255, 0x1c / 255, 0x1c / 255, 0.8],
  selected: [0x11 / 255, 0x11 / 255, 0x11 / 255, 0.9],
};

/** How a loop closure is shown: "rejected", or by its weight "trusted" / "down-weighted" /
 *  "untrusted" (the front end rejected it, the person put it back). */
export function loopStyle(weight, rejected) {
  if (rejected) return "rejected";
  if (weight >= TRUSTED) return "trusted";
  return weight >= KEPT ? "down-weighted" : "untrusted";
}

const COLOUR_OF = {
  trusted: LOOP_COLOURS.trusted,
  "down-weighted": LOOP_COLOURS.downWeighted,
  untrusted: LOOP_COLOURS.untrusted,
  rejected: LOOP_COLOURS.rejected,
  selected: LOOP_COLOURS.selected,
};

/**
 * Every loop closure as drawn: [{index, pair, weight, rejected, style, dimmed, p0, p1}], the ends
 * at the poses on screen (`poses`, N*3). `loops` is the /api/loop_closures answer, `rejected` a
 * Set of indices, `aligned` the State's (the map's loop closures are then out of the solve, drawn
 * faded: `dimmed`).
 */
export function placeLoops(loops, rejected, poses, aligned = false) {
  const out = [];
  if (!loops || !poses) return out;
  const n = poses.length / 3;
  loops.pairs.forEach(([i, j], k) => {
    if (i >= n || j >= n) return;
    const weight = loops.weight[k];
    const off = rejected.has(k);
    out.push({
      index: k,
      pair: [i, j],
      weight,
      rejected: off,
      style: loopStyle(weight, off),
      dimmed: aligned,
      p0: [poses[3 * i], poses[3 * i + 1]],
      p1: [poses[3 * j], poses[3 * j + 1]],
    });
  });
  return out;
}

/** The colour of a loop closure drawn in `style`, faded when `dimmed`. */
function colourOf(style, dimmed) {
  const [r, g, b, a] = COLOUR_OF[style];
  return dimmed ? [r, g, b, a * DIMMED] : [r, g, b, a];
}

/** The overlay lines of `placed` (placeLoops), the selected one wider and outlined in black. */
export function loopLines(placed, selected) {
  const lines = [];
  let chosen = null;
  for (const c of placed) {
    if (c.index === selected) {
      chosen = c;
      continue;
    }
    lines.push({ p0: c.p0, p1: c.p1, colour: colourOf(c.style, c.dimmed), width: WIDTH, dashed: c.rejected });
  }
  if (chosen) {
    // Drawn last (on top): a dark band with the loop closure's own colour inside.
    const { p0, p1, dimmed } = chosen;
    const band = colourOf("selected", dimmed);
    lines.push({ p0, p1, colour: band, width: SELECTED_WIDTH + 2, dashed: false });
    lines.push({ p0, p1, colour: colourOf(chosen.style, dimmed), width: SELECTED_WIDTH, dashed: chosen.rejected });
  }
  return lines;
}

/** The loop closure whose line passes nearest the screen point (x, y), within PICK_PX; or null. */
export function pickLoop(placed, camera, x, y) {
  let best = null;
  let bestD = PICK_PX;
  for (const c of placed) {
    const [ax, ay] = camera.toScreen(c.p0[0], c.p0[1]);
    const [bx, by] = camera.toScreen(c.p1[0], c.p1[1]);
    const dx = bx - ax;
    const dy = by - ay;
    const len2 = dx * dx + dy * dy;
    const t = len2 > 0 ? Math.max(0, Math.min(1, ((x - ax) * dx + (y - ay) * dy) / len2)) : 0;
    const d = Math.hypot(ax + t * dx - x, ay + t * dy - y);
    if (d <= bestD) {
      bestD = d;
      best = c.index;
    }
  }
  return best;
}

const FRAME_PAD = 24; // [CSS px] kept between a framed loop closure and an overlay or the edge

/** Whether the segment a-b (screen px) passes through the rectangle r ({left, top, right,
 *  bottom}) grown by `pad` (Liang-Barsky clipping). */
function crosses([ax, ay], [bx, by], r, pad) {
  let t0 = 0;
  let t1 = 1;
  const dx = bx - ax;
  const dy = by - ay;
  for (const [p, q] of [
    [-dx, ax - (r.left - pad)],
    [dx, r.right + pad - ax],
    [-dy, ay - (r.top - pad)],
    [dy, r.bottom + pad - ay],
  ]) {
    if (p === 0) {
      if (q < 0) return false;
    } else {
      const t = q / p;
      if (p < 0) t0 = Math.max(t0, t);
      else t1 = Math.min(t1, t);
      if (t0 > t1) return false;
    }
  }
  return true;
}

/**
 * Where the view goes to show the loop closure p0-p1 (world) clear of the overlays on the map
 * (`obstacles`: the legend, the hint, the message, the indicator as {left, top, right, bottom}
 * in canvas CSS px): {cx, cy, scale} for the camera. Centred on the canvas at the present zoom
 * when that leaves it whole and clear; otherwise in the middle of the free rectangle of the
 * canvas (beside or between the overlays) that shows it at the largest scale, zoomed out only
 * as far as it must be to fit there (never in).
 */
export function frameLoop(camera, p0, p1, obstacles, pad = FRAME_PAD) {
  const { width: w, height: h, scale } = camera;
  const mx = (p0[0] + p1[0]) / 2;
  const my = (p0[1] + p1[1]) / 2;
  const wx = Math.abs(p1[0] - p0[0]);
  const wy = Math.abs(p1[1] - p0[1]);
  // Centred on the canvas, as before: the ends relative to the centre.
  const ex = ((p1[0] - p0[0]) / 2) * scale;
  const ey = (-(p1[1] - p0[1]) / 2) * scale;
  const a = [w / 2 - ex, h / 2 - ey];
  const b = [w / 2 + ex, h / 2 + ey];
  const inside = (p) => p[0] >= pad && p[0] <= w - pad && p[1] >= pad && p[1] <= h - pad;
  if (inside(a) && inside(b) && !obstacles.some((r) => crosses(a, b, r, pad))) {
    return { cx: mx, cy: my, scale };
  }
  // The free rectangles: bounded by the canvas edges and the overlays' edges, meeting none.
  const clampX = (x) => Math.min(w, Math.max(0, x));
  const clampY = (y) => Math.min(h, Math.max(0, y));
  const xs = [...new Set([0, w, ...obstacles.flatMap((r) => [clampX(r.left), clampX(r.right)])])].sort((p, q) => p - q);
  const ys = [...new Set([0, h, ...obstacles.flatMap((r) => [clampY(r.top), clampY(r.bottom)])])].sort((p, q) => p - q);
  let best = null;
  for (let i = 0; i < xs.length; i++) {
    for (let j = i + 1; j < xs.length; j++) {
      for (let k = 0; k < ys.length; k++) {
        for (let l = k + 1; l < ys.length; l++) {
          const [x0, x1, y0, y1] = [xs[i], xs[j], ys[k], ys[l]];
          const free = (x1 - x0 - 2 * pad) > 0 && (y1 - y0 - 2 * pad) > 0;
          if (!free) continue;
          if (obstacles.some((r) => r.left < x1 && r.right > x0 && r.top < y1 && r.bottom > y0)) continue;
          const s = Math.min(
            scale,
            wx > 0 ? (x1 - x0 - 2 * pad) / wx : Infinity,
            wy > 0 ? (y1 - y0 - 2 * pad) / wy : Infinity,
          );
          const area = (x1 - x0) * (y1 - y0);
          if (!best || s > best.s * (1 + 1e-9) || (s >= best.s * (1 - 1e-9) && area > best.area)) {
            best = { s, area, x: (x0 + x1) / 2, y: (y0 + y1) / 2 };
          }
        }
      }
    }
  }
  if (!best) return { cx: mx, cy: my, scale };
  return { cx: mx - (best.x - w / 2) / best.s, cy: my + (best.y - h / 2) / best.s, scale: best.s };
}
