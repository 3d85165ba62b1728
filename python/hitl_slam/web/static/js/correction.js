// The correction being drawn: which mode a drag draws in (from its modifier keys or the selected
// mode button), the pending pair of segments a and b, and the request body sent to
// /api/interpret and /api/corrections. No drawing or networking here.

export const MODES = ["colocation", "collinear", "perpendicular", "parallel"];

/**
 * The mode of a drag started with these modifiers (the paper's key bindings), or null for a
 * plain drag: Ctrl = colocation, Shift = collinear, Shift+Alt = perpendicular,
 * Shift+Ctrl = parallel. Cmd counts as Ctrl, so Mac users get the same bindings.
 */
export function modeFromModifiers({ shiftKey, ctrlKey, altKey, metaKey }) {
  const ctrl = ctrlKey || metaKey;
  if (shiftKey && ctrl) return "parallel";
  if (shiftKey && altKey) return "perpendicular";
  if (shiftKey) return "collinear";
  if (ctrl) return "colocation";
  return null;
}

// A person points to within a few screen pixels, so their accuracy in metres (sigma_h, the
// width of the band searched for S_a / S_b) shrinks as they zoom in, as the paper's users zoom
// in to separate two copies of a wall. Clamped to the library's default (0.10 m) above and to
// 2 cm, about laser noise plus wall roughness, below.
export const POINTING_PX = 4;
export const SIGMA_H_MIN = 0.02;
export const SIGMA_H_MAX = 0.1;

export function sigmaForScale(pixelsPerMetre) {
  return Math.min(SIGMA_H_MAX, Math.max(SIGMA_H_MIN, POINTING_PX / pixelsPerMetre));
}

/** Two segments of one mode; `add` of a segment in another mode starts the pair over. */
export class PendingPair {
  constructor() {
    this.clear();
  }

  clear() {
    this.mode = null;
    this.segments = []; // [[[x, y], [x, y]], ...], at most two
    this.sigmaH = null; // the finer of the two segments' pointing accuracies [m]
  }

  get complete() {
    return this.segments.length === 2;
  }

  get empty() {
    return this.segments.length === 0;
  }

  /** Adds a drawn segment; returns "a" or "b" (which one it became). */
  add(mode, segment, sigmaH) {
    if (mode !== this.mode || this.complete) this.clear();
    this.mode = mode;
    this.segments.push(segment);
    this.sigmaH = this.sigmaH === null ? sigmaH : Math.min(this.sigmaH, sigmaH);
    return this.segments.length === 1 ? "a" : "b";
  }

  /** The Drawn body of the API: {mode, a, b, sigma_h}. */
  toDrawn() {
    if (!this.complete) throw new Error("a correction needs two segments");
    const [a, b] = this.segments;
    return { mode: this.mode, a, b, sigma_h: this.sigmaH };
  }
}
