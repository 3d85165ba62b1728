// The view transform between world metres and the canvas: a centre and a scale (CSS pixels per
// metre), y up in the world and down on screen. Pan, zoom about a point, fit to bounds. Pure
// arithmetic: the renderer turns it into one uniform, so moving the view never touches buffers.

export class Camera {
  constructor() {
    this.cx = 0; // world point at the canvas centre [m]
    this.cy = 0;
    this.scale = 50; // CSS pixels per metre
    this.width = 1; // canvas size in CSS pixels
    this.height = 1;
  }

  resize(width, height) {
    this.width = Math.max(1, width);
    this.height = Math.max(1, height);
  }

  /** Canvas-relative CSS pixels of world point (x, y). */
  toScreen(x, y) {
    return [
      this.width / 2 + (x - this.cx) * this.scale,
      this.height / 2 - (y - this.cy) * this.scale,
    ];
  }

  /** World point under canvas-relative CSS pixels (sx, sy). */
  toWorld(sx, sy) {
    return [
      this.cx + (sx - this.width / 2) / this.scale,
      this.cy - (sy - this.height / 2) / this.scale,
    ];
  }

  /** Moves the view by a drag of (dx, dy) CSS pixels: the map follows the mouse. */
  pan(dx, dy) {
    this.cx -= dx / this.scale;
    this.cy += dy / this.scale;
  }

  /** Zooms by `factor` keeping the world point under (sx, sy) where it is on screen. */
  zoomAt(sx, sy, factor) {
    const [wx, wy] = this.toWorld(sx, sy);
    this.scale = Math.min(1e5, Math.max(1e-3, this.scale * factor));
    const [nx, ny] = this.toWorld(sx, sy);
    this.cx += wx - nx;
    this.cy += wy - ny;
  }

  /** Shows the box [xmin, ymin, xmax, ymax] whole, with a margin of `pad` CSS pixels. */
  fit(bounds, pad = 30) {
    const [x0, y0, x1, y1] = bounds;
    if (![x0, y0, x1, y1].every(Number.isFinite)) return;
    const w = Math.max(x1 - x0, 1e-3);
    const h = Math.max(y1 - y0, 1e-3);
    this.cx = (x0 + x1) / 2;
    this.cy = (y0 + y1) / 2;
    this.scale = Math.min(
      Math.max(this.width - 2 * pad, 10) / w,
      Math.max(this.height - 2 * pad, 10) / h,
    );
  }

  /** The world-to-clip transform as (centre, scale) for the shaders: clip = (p - c) * s. */
  uniforms() {
    return {
      center: [this.cx, this.cy],
      scale: [(2 * this.scale) / this.width, (2 * this.scale) / this.height],
    };
  }
}
