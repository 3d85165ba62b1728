// The stretches of the trajectory the front end doubts (GET /api/map/info, front_end_doubtful:
// 0-based inclusive scan ranges with a reason), drawn as a wide purple band along the poses on
// screen (so it moves with the map), and what the status bar says about the served map: the front
// end's verdict, and beside a bag's own SLAM trajectory both maps' inconsistency. Pure functions
// over plain data.

export const DOUBTFUL_COLOUR = [0x8e / 255, 0x24 / 255, 0xaa / 255, 0.45];
const WIDTH = 7; // [CSS px]
const MAX_SEGMENTS = 400; // per stretch: a long one is drawn through every k-th pose

/**
 * Every doubtful stretch as drawn: [{first, last, reason, path}], `path` the world positions
 * [[x, y], ...] of its poses on screen (`poses`, N*3), every k-th of a long stretch and its last.
 */
export function placeStretches(stretches, poses) {
  const out = [];
  if (!stretches || !poses) return out;
  const n = poses.length / 3;
  for (const s of stretches) {
    const first = Math.max(0, s.first);
    const last = Math.min(n - 1, s.last);
    if (first > last) continue;
    const step = Math.max(1, Math.ceil((last - first) / MAX_SEGMENTS));
    const path = [];
    for (let i = first; i < last; i += step) path.push([poses[3 * i], poses[3 * i + 1]]);
    path.push([poses[3 * last], poses[3 * last + 1]]);
    out.push({ first: s.first, last: s.last, reason: s.reason, path });
  }
  return out;
}

/** The overlay lines of `placed` (placeStretches): one wide segment per step of each path; a
 *  stretch of one scan is a short mark across its pose. */
export function stretchLines(placed) {
  const lines = [];
  for (const s of placed) {
    const p = s.path;
    if (p.length === 1) {
      const [x, y] = p[0];
      lines.push({ p0: [x - 0.05, y], p1: [x + 0.05, y], colour: DOUBTFUL_COLOUR, width: WIDTH, dashed: false });
      continue;
    }
    for (let k = 0; k + 1 < p.length; k++) {
      lines.push({ p0: p[k], p1: p[k + 1], colour: DOUBTFUL_COLOUR, width: WIDTH, dashed: false });
    }
  }
  return lines;
}

const SHOWN = 3; // stretches named in the status bar; its tooltip lists every one with its reason

/**
 * The status bar's line on the front end's verdict ("front end: doubtful map: 3 stretches, scans
 * 1200-1260, 1400-1410, 2000-2100"), or null when it gave none.
 */
export function verdictText(info) {
  const verdict = info && info.front_end_verdict;
  const stretches = (info && info.front_end_doubtful) || [];
  if (!verdict && stretches.length === 0) return null;
  let text = `front end: ${verdict || "doubtful"} map`;
  const n = stretches.length;
  if (n > 0) {
    const shown = stretches.slice(0, SHOWN).map((s) => `${s.first}-${s.last}`).join(", ");
    text += `: ${n} stretch${n === 1 ? "" : "es"}, scans ${shown}${n > SHOWN ? `, \u2026 ${n - SHOWN} more` : ""}`;
  }
  return text;
}

/** Every doubtful stretch on a line of its own ("scans 1200-1260: match failed"), for a tooltip. */
export function stretchList(info) {
  const stretches = (info && info.front_end_doubtful) || [];
  return stretches.map((s) => `scans ${s.first}-${s.last}${s.reason ? `: ${s.reason}` : ""}`).join("\n");
}

/** The status bar's comparison of a bag's own SLAM trajectory with the front end's map, or null. */
export function comparisonText(info) {
  const c = info && info.comparison;
  if (!c) return null;
  const lower = c.front_end_m2 < c.bag_slam_m2 ? "front end" : c.front_end_m2 > c.bag_slam_m2 ? "bag's SLAM" : null;
  return (
    `at start: bag's SLAM ${c.bag_slam_m2.toFixed(2)} \u00b7 front end ${c.front_end_m2.toFixed(2)} m\u00b2` +
    (lower ? ` (${lower} lower)` : "")
  );
}
