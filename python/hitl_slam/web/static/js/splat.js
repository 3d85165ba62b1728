// Laser points drawn on the CPU: each point, placed by its pose's frame (the points are kept in
// the robot frame, so a new map only brings new poses), adds one to the count of the pixel it
// falls on (a one-byte-per-pixel image, saturating at 255), the counts go to the GPU as a
// texture, and a shader turns counts into orange of the same opacity as blended GL points. On a
// software WebGL (SwiftShader, llvmpipe: machines without a GPU, remote desktops, headless CI)
// this is some 20 times faster than GL_POINTS, whose per-vertex cost there is about 0.6 us; with
// a GPU the view draws GL_POINTS instead (view.js picks).

import { frames } from "./se2.js";
import { SPLAT_FS, SPLAT_VS, bindExactTexture, compile } from "./shaders.js";

const TILE = 32; // [device px] only tiles with points are shaded

export class PointSplatter {
  constructor(gl) {
    this.gl = gl;
    this.program = compile(gl, SPLAT_VS, SPLAT_FS);
    this.texture = gl.createTexture();
    this.quads = gl.createBuffer();
    this.points = new Float32Array(0); // robot-frame x, y pairs, pose by pose
    this.offsets = null; // (N + 1) per-pose offsets into the points
    this.reach = null; // (N) each scan's farthest point from its robot [m]
    this.frames = null; // (N, 4) each pose's x, y, cos theta, sin theta
    this.width = 0;
    this.height = 0;
    this.lastCpuMs = 0;
    bindExactTexture(gl, this.texture);
  }

  /**
   * The map's scans, once: every point in its robot's frame (x, y pairs) and `offsets` (pose i's
   * points are points[2 offsets[i] .. 2 offsets[i + 1]]). Each scan's reach (its farthest point
   * from the robot) is kept so that a view skips the scans it cannot see.
   */
  setScans(points, offsets) {
    const n = offsets.length - 1;
    if (n < 0 || offsets[n] * 2 !== points.length) {
      throw new Error(`the scans do not match their offsets (${points.length / 2} points, ${offsets[n]} indexed)`);
    }
    this.points = points;
    this.offsets = offsets;
    const reach = new Float32Array(n);
    for (let p = 0; p < n; p++) {
      let r2 = 0;
      for (let i = 2 * offsets[p]; i < 2 * offsets[p + 1]; i += 2) {
        const d = points[i] * points[i] + points[i + 1] * points[i + 1];
        if (d > r2) r2 = d;
      }
      reach[p] = Math.sqrt(r2);
    }
    this.reach = reach;
    this.frames = null;
  }

  /** A new map version: the poses (x, y, theta per pose), whose frames place the scans. */
  setPoses(poses) {
    this.frames = frames(poses); // x, y, cos, sin per pose
  }

  _resize(w, h) {
    if (w === this.width && h === this.height) return;
    const gl = this.gl;
    this.width = w;
    this.height = h;
    // Rows padded to whole 4-byte words, so the tile scan reads 4 pixels at a time; the
    // texture is that wide too (the padding is never shown).
    this.stride = (w + 3) & ~3;
    this.counts = new Uint8ClampedArray(this.stride * h);
    this.words = new Uint32Array(this.counts.buffer);
    this.tilesX = Math.ceil(w / TILE);
    this.tilesY = Math.ceil(h / TILE);
    this.tiles = new Uint8Array(this.tilesX * this.tilesY);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.LUMINANCE, this.stride, h, 0, gl.LUMINANCE, gl.UNSIGNED_BYTE, null);
  }

  /** Counts the points per pixel for the view (centre, device px per metre, point size). */
  _splat(cx, cy, k, size) {
    const { width: w, height: h, counts, frames, reach, offsets } = this;
    counts.fill(0);
    if (frames && offsets && frames.length === 4 * (offsets.length - 1)) {
      // Only the scans whose reach around their pose meets the view (with a point's margin).
      const margin = size / k;
      const vx0 = cx - w / 2 / k - margin;
      const vx1 = cx + w / 2 / k + margin;
      const vy0 = cy - h / 2 / k - margin;
      const vy1 = cy + h / 2 / k + margin;
      const n = offsets.length - 1;
      for (let p = 0; p < n; p++) {
        if (offsets[p] === offsets[p + 1]) continue;
        const x = frames[4 * p];
        const y = frames[4 * p + 1];
        const r = reach[p];
        if (x - r > vx1 || x + r < vx0 || y - r > vy1 || y + r < vy0) continue;
        this._count(2 * offsets[p], 2 * offsets[p + 1], frames, 4 * p, cx, cy, k, size);
      }
    }
    this._markTiles();
  }

  /**
   * Adds points[from .. to) (robot-frame x, y pairs of one scan, whose frame is at
   * frames[f .. f + 4): x, y, cos, sin) to the counts.
   */
  _count(from, to, frames, f, cx, cy, k, size) {
    const { width: w, height: h, stride, counts, points } = this;
    // The scan's frame and the view as one affine map from robot metres to device pixels.
    const a = frames[f + 2] * k;
    const b = frames[f + 3] * k;
    const ex = (frames[f] - cx) * k + w / 2;
    const ey = (frames[f + 1] - cy) * k + h / 2;
    if (size <= 1) {
      // The hot loop (a pass over every visible point each frame): no writes but the count.
      for (let i = from; i < to; i += 2) {
        const lx = points[i];
        const ly = points[i + 1];
        const x = a * lx - b * ly + ex;
        const y = b * lx + a * ly + ey;
        if (x >= 0 && x < w && y >= 0 && y < h) counts[(y | 0) * stride + (x | 0)]++;
      }
      return;
    }
    const back = (size - 1) / 2;
    for (let i = from; i < to; i += 2) {
      const lx = points[i];
      const ly = points[i + 1];
      const x0 = Math.floor(a * lx - b * ly + ex - back);
      const y0 = Math.floor(b * lx + a * ly + ey - back);
      if (x0 + size <= 0 || x0 >= w || y0 + size <= 0 || y0 >= h) continue;
      const x1 = Math.min(w, x0 + size);
      const y1 = Math.min(h, y0 + size);
      for (let y = Math.max(0, y0); y < y1; y++) {
        for (let x = Math.max(0, x0); x < x1; x++) counts[y * stride + x]++;
      }
    }
  }

  /** Which TILE x TILE tiles have any points, reading the counts a word (4 pixels) at a time. */
  _markTiles() {
    const { words, tiles, tilesX, stride, height: h } = this;
    tiles.fill(0);
    const perRow = stride >> 2;
    const perTile = TILE >> 2;
    for (let y = 0; y < h; y++) {
      const row = y * perRow;
      const t = ((y / TILE) | 0) * tilesX;
      for (let q = 0; q < perRow; q++) {
        if (words[row + q] !== 0) {
          tiles[t + ((q / perTile) | 0)] = 1;
          q = ((q / perTile) | 0) * perTile + perTile - 1; // the rest of this tile's row is moot
        }
      }
    }
  }

  /** Clip-space quads over the runs of tiles that have points, 6 vertices each. */
  _tileQuads() {
    const { tiles, tilesX, tilesY, width: w, height: h } = this;
    const out = [];
    const cx = (px) => (2 * Math.min(px, w)) / w - 1;
    const cy = (py) => (2 * Math.min(py, h)) / h - 1;
    for (let ty = 0; ty < tilesY; ty++) {
      let tx = 0;
      while (tx < tilesX) {
        if (!tiles[ty * tilesX + tx]) {
          tx++;
          continue;
        }
        const start = tx;
        while (tx < tilesX && tiles[ty * tilesX + tx]) tx++;
        const x0 = cx(start * TILE);
        const x1 = cx(tx * TILE);
        const y0 = cy(ty * TILE);
        const y1 = cy((ty + 1) * TILE);
        out.push(x0, y0, x1, y0, x1, y1, x0, y0, x1, y1, x0, y1);
      }
    }
    return new Float32Array(out);
  }

  /**
   * Draws the points for the camera into the current framebuffer. `k` is device pixels per
   * metre, `size` the point size in device pixels, `colour` the premultiplied-ready RGBA.
   */
  draw(cx, cy, k, size, colour, width, height) {
    const gl = this.gl;
    this._resize(width, height);
    const t0 = performance.now();
    this._splat(cx, cy, k, Math.max(1, Math.round(size)));
    const quads = this._tileQuads();
    this.lastCpuMs = performance.now() - t0; // counting on the CPU, for the benchmark's split
    if (quads.length === 0) return;
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, this.stride, height, gl.LUMINANCE, gl.UNSIGNED_BYTE, this.counts);
    const p = this.program;
    gl.useProgram(p.program);
    gl.uniform1i(p.uniform.u_counts, 0);
    gl.uniform4fv(p.uniform.u_color, colour);
    gl.uniform1f(p.uniform.u_uscale, width / this.stride);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.quads);
    gl.bufferData(gl.ARRAY_BUFFER, quads, gl.STREAM_DRAW);
    const loc = p.attrib.a_pos;
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
    gl.drawArrays(gl.TRIANGLES, 0, quads.length / 2);
    gl.disableVertexAttribArray(loc);
  }
}
