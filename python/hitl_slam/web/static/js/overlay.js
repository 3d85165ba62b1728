// What is drawn over the laser points besides the poses: the applied corrections' fitted lines
// P_a / P_b (dashed, numbered "1a", "1b", ...), the segments of the pending pair and the one
// being drawn (wide, translucent), and the preview's fitted lines. Also keeps the applied
// corrections' lines on their features as the map moves. Pure functions over plain data.

import { COLOURS } from "./view.js";

const DRAWN_ALPHA = 0.6;
const DRAWN_WIDTH = 5; // [CSS px]
const FITTED_WIDTH = 2;

const withAlpha = (c, a) => [c[0], c[1], c[2], a];

/**
 * The overlay for view.setLines and the labels: {under, over, labels}. `tracked` maps a history
 * index to its current {a, b} lines; `pending` holds the drawn segments (0 to 2); `draft` is
 * {mode, segment} while dragging; `preview` the /api/interpret answer or null.
 */
export function overlay({ tracked, pending, pendingComplete, pendingMode, draft, preview }) {
  const under = [];
  const over = [];
  const labels = [];
  const fitted = (seg, colour) => {
    if (seg) over.push({ p0: seg[0], p1: seg[1], colour, width: FITTED_WIDTH, dashed: true });
  };
  const drawn = (seg, colour) => {
    if (!seg) return;
    const c = withAlpha(colour, DRAWN_ALPHA);
    under.push({ p0: seg[0], p1: seg[1], colour: c, width: DRAWN_WIDTH, dashed: false });
  };
  let k = 0;
  for (const [, t] of tracked) {
    k++;
    fitted(t.a, COLOURS.fittedA);
    fitted(t.b, COLOURS.fittedB);
    labels.push({ text: `${k}a`, side: "a", at: t.a }, { text: `${k}b`, side: "b", at: t.b });
  }
  const [a, b] = pending;
  drawn(a, COLOURS.a);
  drawn(b, COLOURS.b);
  if (draft) {
    const second = a && !pendingComplete && pendingMode === draft.mode;
    drawn(draft.segment, second ? COLOURS.b : COLOURS.a);
  }
  if (preview && preview.accepted) {
    fitted(preview.line_a, COLOURS.fittedA);
    fitted(preview.line_b, COLOURS.fittedB);
  }
  return { under, over, labels };
}

/**
 * The applied corrections' lines on the new map (a new Map, history index -> {a, b}).
 *
 * The server gives P_a / P_b where they were fitted, on the map before the correction; S_a and
 * S_b move with their poses, so each line moves rigidly with the middle pose of X_a (or X_b)
 * from `previousPoses` (the map on screen) to `poses` (the new one). Lines of corrections
 * applied before the page loaded are shown where they were fitted.
 */
export function followPoses(tracked, state, previousPoses, poses) {
  const history = state ? state.history : [];
  const same = previousPoses && previousPoses.length === poses.length;
  const move = (seg, i) => {
    if (!same || i === undefined || 3 * i + 2 >= poses.length) return seg;
    const [ox, oy, ot] = [previousPoses[3 * i], previousPoses[3 * i + 1], previousPoses[3 * i + 2]];
    const [nx, ny, nt] = [poses[3 * i], poses[3 * i + 1], poses[3 * i + 2]];
    const c = Math.cos(nt - ot);
    const s = Math.sin(nt - ot);
    return seg.map(([x, y]) => [nx + c * (x - ox) - s * (y - oy), ny + s * (x - ox) + c * (y - oy)]);
  };
  const middle = (xs) => (xs && xs.length ? xs[xs.length >> 1] : undefined);
  const next = new Map();
  for (const h of history) {
    if (h.status !== "applied" || !h.line_a || !h.line_b) continue;
    const old = tracked.get(h.index);
    next.set(h.index, {
      a: move(old ? old.a : h.line_a, middle(h.x_a)),
      b: move(old ? old.b : h.line_b, middle(h.x_b)),
    });
  }
  return next;
}
