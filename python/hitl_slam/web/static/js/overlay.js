// What is drawn over the laser points besides the poses: the applied corrections' solved lines
// P_a / P_b (dashed, numbered "1a", "1b", ...) exactly as the server's State.lines gives them,
// the segments of the pending pair and the one being drawn (wide, translucent), and the
// preview's fitted lines. Pure functions over plain data.

import { COLOURS } from "./view.js";

const DRAWN_ALPHA = 0.6;
const DRAWN_WIDTH = 5; // [CSS px]
const FITTED_WIDTH = 2;

const withAlpha = (c, a) => [c[0], c[1], c[2], a];

/**
 * The overlay for view.setLines and the labels: {under, over, labels}. `applied` is the State's
 * `lines` (each correction in effect with its solved lines a and b and their segments);
 * `pending` holds the drawn segments (0 to 2); `draft` is {mode, segment} while dragging;
 * `preview` the /api/interpret answer or null.
 */
export function overlay({ applied, pending, pendingComplete, pendingMode, draft, preview }) {
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
  for (const c of applied) {
    k++;
    const [a, b] = [c.a.segment, c.b.segment];
    fitted(a, COLOURS.fittedA);
    fitted(b, COLOURS.fittedB);
    labels.push({ text: `${k}a`, side: "a", at: a }, { text: `${k}b`, side: "b", at: b });
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
