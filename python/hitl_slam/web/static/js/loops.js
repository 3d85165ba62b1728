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
